"""MultilevelSolver (``solver=fast``): transfer operators, descent over levels, fine-grid momentum, checkpoints."""
import copy

import pytest
import torch

from indreg import ImageDomain
from indreg.deform.kernel import GaussianKernel
from indreg.solvers import MultilevelSolver, SolverState
from indreg.problems.grids import prolong, resample_time, restrict

from solver_problems import make_problem

LEVELS = {"levels": (4, 2), "level_steps": (3, 4), "level_iter": (3, 3), "min_size": 8}


def test_restrict_is_area_average_and_prolong_its_right_inverse():
    gen = torch.Generator().manual_seed(0)
    f = torch.randn(3, 2, 8, 8, generator=gen, dtype=torch.float64)
    coarse = restrict(f, (4, 4))
    assert coarse.shape == (3, 2, 4, 4)
    torch.testing.assert_close(coarse[..., 1, 2], f[..., 2:4, 4:6].mean(dim=(-2, -1)))
    up = prolong(coarse, (8, 8))
    torch.testing.assert_close(up[..., 2:4, 4:6], coarse[..., 1, 2, None, None].expand(3, 2, 2, 2))
    torch.testing.assert_close(restrict(up, (4, 4)), coarse)
    # the integral (L2 pairing with constants) is kept by both transfers
    torch.testing.assert_close(coarse.sum() * 4, f.sum())


def test_prolonged_momentum_keeps_the_velocity():
    """nu = K m of a piecewise-constant density equals K of the coarse one up to the finer quadrature."""
    fine, coarse = ImageDomain.paper(64), ImageDomain.paper(32)
    gen = torch.Generator().manual_seed(1)
    m = torch.randn(2, 32, 32, generator=gen, dtype=torch.float64)
    nu_coarse = GaussianKernel(coarse, 6.0)(m)
    nu_fine = GaussianKernel(fine, 6.0)(prolong(m, (64, 64)))
    err = (restrict(nu_fine, (32, 32)) - nu_coarse).norm() / nu_coarse.norm()
    assert err < 0.01


def test_resample_time_is_linear_and_keeps_the_ends():
    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    m = (2 * t + 1).view(6, 1, 1, 1).expand(6, 2, 3, 3)
    out = resample_time(m, 10)
    torch.testing.assert_close(out[:, 0, 0, 0], 2 * torch.linspace(0, 1, 11, dtype=torch.float64) + 1)
    assert resample_time(m, 5) is m


def test_coarse_problem_is_the_same_problem_on_a_coarser_grid():
    p = make_problem(n=32)
    c = p.coarsened((16, 16), 3, "autograd")
    assert c.domain.shape == (16, 16) and c.domain.min_pt == p.domain.min_pt and c.num_steps == 3
    assert c.data is p.data and c.gamma == p.gamma and c.kernel.sigma == p.kernel.sigma
    assert c.ray_transform.geometry == p.ray_transform.geometry and c.deformation.backward == "autograd"
    torch.testing.assert_close(c.template, restrict(p.template, (16, 16)))
    # the same sinogram of the same image, up to discretisation
    f = p.template
    r = c.ray_transform(restrict(f, (16, 16))) - p.ray_transform(f)
    assert float(r.norm() / p.ray_transform(f).norm()) < 0.1


@pytest.mark.parametrize("inner", ["lbfgs", "algorithm1"])
def test_fast_decreases_the_objective_and_ends_on_the_fine_grid(inner):
    problem = make_problem(n=32)
    solver = MultilevelSolver(problem, max_iter=9, inner=inner, **LEVELS)
    state = SolverState(problem.zero_momentum())
    infos = []
    info = solver.run(state, callback=lambda s, i: infos.append(i))
    assert info["status"] == "completed" and state.iteration == 9
    assert [i["level"] for i in infos] == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert [i["grid"] for i in infos] == [8] * 3 + [16] * 3 + [32] * 3
    assert [i["iteration"] for i in infos] == list(range(1, 10))
    assert all(b > a for a, b in zip([i["evaluations"] for i in infos], [i["evaluations"] for i in infos[1:]]))
    assert state.momentum.shape == problem.momentum_shape
    start = problem.evaluate(problem.zero_momentum())["objective"]
    final = problem.evaluate(state.momentum)["objective"]
    assert final < 0.6 * start
    # on the fine grid the report is the problem's objective at state.momentum
    assert info["objective"] == pytest.approx(final, rel=1e-10)
    for level in range(3):  # descent within each level
        e = [i["objective"] for i in infos if i["level"] == level]
        assert all(b <= a for a, b in zip(e, e[1:])), (level, e)


def test_every_coarse_iterate_is_a_fine_momentum():
    """state.momentum after a coarse step is the coarse momentum prolongated (the app evaluates it)."""
    problem = make_problem(n=32)
    solver = MultilevelSolver(problem, max_iter=9, **LEVELS)
    state = SolverState(problem.zero_momentum())
    solver.step(state)
    coarse = solver.state_dict()["momentum"]
    assert coarse.shape == (4, 2, 8, 8) and state.momentum.shape == problem.momentum_shape
    torch.testing.assert_close(state.momentum, prolong(resample_time(coarse, 5), (32, 32)))


def test_state_dict_round_trip_resumes_identically():
    """Stop on each level, rebuild solver and state from the checkpoint: the same iterates as one run."""
    problem = make_problem(n=32)
    reference = SolverState(problem.zero_momentum())
    solver = MultilevelSolver(problem, max_iter=9, **LEVELS)
    ref_infos = [solver.step(reference) for _ in range(9)]
    for stop in (2, 3, 5, 7):
        solver = MultilevelSolver(problem, max_iter=9, **LEVELS)
        state = SolverState(problem.zero_momentum())
        for _ in range(stop):
            solver.step(state)
        saved = copy.deepcopy({"state": state.state_dict(), "solver": solver.state_dict()})
        resumed = MultilevelSolver(problem, max_iter=9, **LEVELS)
        resumed.load_state_dict(saved["solver"])
        state = SolverState.from_state_dict(saved["state"])
        infos = [resumed.step(state) for _ in range(9 - stop)]
        assert torch.equal(state.momentum, reference.momentum), stop
        for a, b in zip(infos, ref_infos[stop:]):
            assert a["objective"] == b["objective"] and a["evaluations"] == b["evaluations"], stop


def test_rtol_ends_levels_and_converges():
    problem = make_problem(n=32)
    solver = MultilevelSolver(problem, levels=(2,), level_steps=(3,), level_iter=(50,), max_iter=200,
                              rtol=0.05, window=2)
    state = SolverState(problem.zero_momentum())
    info = solver.run(state)
    assert info["status"] == "converged" and info["level"] == 1 and state.iteration < 100


def test_fast_bad_input():
    problem = make_problem(n=32)
    with pytest.raises(ValueError, match="levels, level_steps and level_iter"):
        MultilevelSolver(problem, levels=(4, 2), level_iter=(3,))
    with pytest.raises(ValueError, match="levels must be coarsening factors"):
        MultilevelSolver(problem, levels=(2, 4), level_iter=(3, 3))
    with pytest.raises(ValueError, match="backward must be"):
        MultilevelSolver(problem, inner="lbfgs", backward="paper")
    with pytest.raises(ValueError, match="inner must be"):
        MultilevelSolver(problem, inner="adam")
    with pytest.raises(TypeError, match="problem must be"):
        MultilevelSolver(object())
    solver = MultilevelSolver(problem, **LEVELS)
    state = SolverState(problem.zero_momentum())
    solver.step(state)
    state.momentum = state.momentum + 1
    with pytest.raises(ValueError, match="not the iterate of this MultilevelSolver"):
        solver.step(state)


def test_levels_below_min_size_are_skipped():
    problem = make_problem(n=32)
    solver = MultilevelSolver(problem, levels=(8, 4, 2), level_steps=(2, 3, 4), level_iter=(1, 1, 1), min_size=8)
    assert [s[0] for s in solver.schedule] == [(8, 8), (16, 16), (32, 32)]


def test_coarse_budgets_that_use_up_max_iter_are_scaled_to_half_of_it(caplog):
    """The problem's grid always gets iterations: coarse budgets summing to max_iter or more are scaled to half."""
    problem = make_problem(n=32)
    with caplog.at_level("INFO", logger="indreg"):
        solver = MultilevelSolver(problem, max_iter=6, **LEVELS)
    assert "would use up max_iter=6" in caplog.text
    assert sum(it for _, _, it in solver.schedule[:-1]) <= 3 and all(it >= 1 for _, _, it in solver.schedule[:-1])
    kept = MultilevelSolver(problem, max_iter=7, **LEVELS)
    assert [it for _, _, it in kept.schedule[:-1]] == list(LEVELS["level_iter"])
