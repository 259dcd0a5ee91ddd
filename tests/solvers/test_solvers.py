"""Algorithm1 and TorchOptimSolver: descent, reports, step halving, checkpoints, bad input."""
import math

import pytest
import torch

from indreg.solvers import Algorithm1, SolverState, TorchOptimSolver

from solver_problems import make_problem


def _run(solver, state, k):
    return [solver.step(state) for _ in range(k)]


def test_algorithm1_descends_and_reports(problem):
    state = SolverState(problem.zero_momentum())
    solver = Algorithm1(problem, step_size=0.02, max_iter=4)
    infos = []
    info = solver.run(state, callback=lambda s, i: infos.append(i))
    assert state.iteration == 4 and len(infos) == 4 and info["status"] == "completed"
    assert not solver.converged(info) and not solver.failed(info)
    assert info == dict(infos[-1], status="completed")
    start = problem.evaluate(problem.zero_momentum())["objective"]
    objectives = [i["objective"] for i in infos]
    assert objectives[0] < start and all(b < a for a, b in zip(objectives, objectives[1:]))
    assert [i["evaluations"] for i in infos] == [2, 3, 4, 5]       # one evaluation per iteration
    assert info["objective"] == pytest.approx(problem.evaluate(state.momentum)["objective"], rel=1e-12)
    assert 0 < info["min_jacobian"] <= 1.5 and info["warning"] == "" and not info["rejected"]
    assert info["grad_norm"] > 0 and info["step_size"] == 0.02
    assert set(info) >= {"objective", "data_fit", "regulariser", "grad_norm", "min_jacobian", "step_size",
                         "evaluations", "rejected", "warning"}


def test_algorithm1_grad_tol_stops(problem):
    solver = Algorithm1(problem, step_size=0.02, max_iter=50, grad_tol=1e30)
    state = SolverState(problem.zero_momentum())
    info = solver.run(state)
    assert state.iteration == 1 and info["status"] == "converged" and solver.converged(info)


def _solver(kind, problem, **kwargs):
    if kind == "algorithm1":
        return Algorithm1(problem, step_size=kwargs.pop("step_size", 0.02), **kwargs)
    return TorchOptimSolver(problem, "lbfgs", **kwargs)


@pytest.mark.parametrize("kind", ["algorithm1", "lbfgs"])
def test_run_without_iterations_reports_the_current_iterate(problem, kind):
    """max_iter = 0, or a state already at max_iter: the report of state.momentum, not None."""
    from solver_problems import smooth_momentum

    m = smooth_momentum(problem)
    for max_iter, iteration in ((0, 0), (3, 3), (3, 5)):
        state = SolverState(m.clone(), iteration)
        solver = _solver(kind, problem, max_iter=max_iter)
        info = solver.run(state)
        terms = problem.evaluate(m)
        assert info["iteration"] == iteration and state.iteration == iteration and torch.equal(state.momentum, m)
        assert info["status"] == "completed" and info["evaluations"] == 1
        for key in ("objective", "data_fit", "regulariser"):
            assert info[key] == pytest.approx(terms[key], rel=1e-10), key
        assert info["grad_norm"] > 0 and 0 < info["min_jacobian"] < 2 and info["warning"] == ""


@pytest.mark.parametrize("kind", ["algorithm1", "lbfgs"])
def test_non_finite_objective_is_a_failure_not_convergence(problem, kind):
    """A step of 1e300 overflows the regulariser: status "failed" at once, grad_tol or not."""
    for grad_tol in (0.0, 1e-3):
        state = SolverState(problem.zero_momentum())
        solver = (Algorithm1(problem, step_size=1e300, max_iter=5, grad_tol=grad_tol) if kind == "algorithm1"
                  else TorchOptimSolver(problem, "sgd", lr=1e300, max_iter=5, grad_tol=grad_tol))
        info = solver.run(state)
        assert state.iteration == 1 and info["status"] == "failed"
        assert not math.isfinite(info["objective"]) and "non-finite objective" in info["warning"]
        assert solver.failed(info) and not solver.converged(info) and solver.status(info) == "failed"


def test_step_halving_rejects_bad_steps(problem):
    state = SolverState(problem.zero_momentum())
    info = Algorithm1(problem, step_size=50.0).step(state)
    assert info["warning"]                                   # too large: increase and/or folding reported
    state = SolverState(problem.zero_momentum())
    solver = Algorithm1(problem, step_size=50.0, step_halving=True)
    start = problem.evaluate(state.momentum)["objective"]
    info = solver.step(state)
    assert not info["rejected"] and info["warning"] == ""
    assert info["step_size"] < 50.0 and solver.step_size == info["step_size"]
    assert info["objective"] < start and info["min_jacobian"] > 0


def test_step_halving_gives_up_after_bounded_retries(problem):
    state = SolverState(problem.zero_momentum())
    solver = Algorithm1(problem, step_size=1e6, step_halving=True, max_halvings=2)
    info = solver.step(state)
    assert info["rejected"] and "rejected" in info["warning"]
    assert torch.equal(state.momentum, problem.zero_momentum()) and solver.step_size == 1e6 / 4


def test_mass_preserving_descends():
    p = make_problem(action="mass_preserving")
    state = SolverState(p.zero_momentum())
    infos = _run(Algorithm1(p, step_size=0.02), state, 3)
    start = p.evaluate(p.zero_momentum())["objective"]
    assert infos[0]["objective"] < start and infos[2]["objective"] < infos[0]["objective"]


def test_lbfgs_decreases_monotonically_and_beats_algorithm1():
    p = make_problem(num_steps=10)
    state = SolverState(p.zero_momentum())
    solver = TorchOptimSolver(p, "lbfgs", max_iter=8)
    infos = _run(solver, state, 8)
    objectives = [p.evaluate(p.zero_momentum())["objective"]] + [i["objective"] for i in infos]
    assert all(b <= a for a, b in zip(objectives, objectives[1:]))
    assert objectives[-1] < 0.5 * objectives[0]
    assert all(i["warning"] == "" for i in infos)
    # Algorithm 1 with the same number of forward/backward evaluations
    a_state, alg = SolverState(p.zero_momentum()), Algorithm1(p, step_size=0.02)
    while alg.evaluations < infos[-1]["evaluations"]:
        a_info = alg.step(a_state)
    assert infos[-1]["objective"] < a_info["objective"]


@pytest.mark.parametrize("name,lr", [("adam", 1e-4), ("sgd", 1e-7)])
def test_first_order_optimizers_run(problem, name, lr):
    state = SolverState(problem.zero_momentum())
    infos = _run(TorchOptimSolver(problem, name, lr=lr, max_iter=3), state, 3)
    assert all(math.isfinite(i["objective"]) for i in infos)
    assert infos[-1]["objective"] < problem.evaluate(problem.zero_momentum())["objective"]
    assert [i["evaluations"] for i in infos] == [2, 3, 4]


def _resume_matches(make_solver, problem, k=3):
    state, solver = SolverState(problem.zero_momentum()), make_solver()
    _run(solver, state, k)
    saved = (state.state_dict(), solver.state_dict())
    reference = _run(solver, state, k)
    resumed_state, resumed = SolverState.from_state_dict(saved[0]), make_solver()
    resumed.load_state_dict(saved[1])
    again = _run(resumed, resumed_state, k)
    assert torch.equal(resumed_state.momentum, state.momentum)
    assert [i["objective"] for i in again] == [i["objective"] for i in reference]
    assert [i["evaluations"] for i in again] == [i["evaluations"] for i in reference]  # no recount on resume
    assert resumed_state.iteration == state.iteration == 2 * k


@pytest.mark.parametrize("kind", ["algorithm1", "halving", "lbfgs", "adam"])
def test_state_dict_round_trip_continues_identically(problem, kind):
    make = {"algorithm1": lambda: Algorithm1(problem, step_size=0.02),
            "halving": lambda: Algorithm1(problem, step_size=20.0, step_halving=True),
            "lbfgs": lambda: TorchOptimSolver(problem, "lbfgs"),
            "adam": lambda: TorchOptimSolver(problem, "adam", lr=1e-4)}[kind]
    _resume_matches(make, problem)


def test_solver_bad_input(problem):
    with pytest.raises(ValueError, match="step_size"):
        Algorithm1(problem, step_size=-0.1)
    with pytest.raises(ValueError, match="step_size"):
        Algorithm1(problem, step_size=0.0)
    with pytest.raises(ValueError, match="grad_tol"):
        Algorithm1(problem, grad_tol=-1.0)
    with pytest.raises(TypeError, match="IndirectRegistration"):
        Algorithm1("problem")
    with pytest.raises(ValueError, match="optimizer must be"):
        TorchOptimSolver(problem, "newton")
    with pytest.raises(ValueError, match="lr is required"):
        TorchOptimSolver(problem, "adam")
    with pytest.raises(ValueError, match="lr"):
        TorchOptimSolver(problem, "lbfgs", lr=-1.0)
    with pytest.raises(ValueError, match="momentum must have shape"):
        Algorithm1(problem).step(SolverState(torch.zeros(2, 2, 32, 32, dtype=torch.float64)))


def test_jacobian_every_skips_the_jacobian(problem):
    state = SolverState(problem.zero_momentum())
    infos = _run(Algorithm1(problem, step_size=0.02, jacobian_every=2), state, 2)
    assert math.isnan(infos[0]["min_jacobian"]) and infos[1]["min_jacobian"] > 0
    assert infos[0]["warning"] == ""


@pytest.mark.parametrize("backward", ["exact", "autograd", "paper"])
def test_torch_optim_backward_rebuilds_the_deformation(problem, backward):
    # default "exact": the line search sees the exact gradient of the discrete map at the paper's cost
    solver = TorchOptimSolver(problem, "lbfgs", max_iter=1, backward=backward)
    assert solver.problem.deformation.backward == backward
    assert TorchOptimSolver(problem, "lbfgs", max_iter=1).problem.deformation.backward == "exact"


def test_torch_optim_exact_and_autograd_take_the_same_steps(problem):
    states = []
    for backward in ("exact", "autograd"):
        solver = TorchOptimSolver(problem, "lbfgs", max_iter=3, backward=backward)
        states.append(SolverState(problem.zero_momentum()))
        solver.run(states[-1])
    assert states[0].iteration == 3
    assert torch.allclose(states[0].momentum, states[1].momentum, rtol=1e-8, atol=1e-12)
    with pytest.raises(ValueError, match="backward must be one of"):
        TorchOptimSolver(problem, "lbfgs", backward="adjoint")
