"""Indirect registration in 3D: objective, Algorithm 1, L-BFGS, ``indreg.register`` and checkpoints on a
3D domain, with a small exact operator (integrals along z, i.e. a single projection direction)."""
import pytest
import torch

import indreg
from indreg import ImageDomain
from indreg.deform import GaussianKernel, LDDMMDeformation
from indreg.experiments import checkpoint
from indreg.forward.operator import adjointness, check_operator
from indreg.solvers import Algorithm1, IndirectRegistration, SolverState, TorchOptimSolver


class ProjectZ:
    """``T f (x, y) = int f(x, y, z) dz`` (the Riemann sum ``hz sum_k``), data ``(nx, ny)`` with the weight
    ``hx hy``; adjoint ``T^* g (x, y, z) = g(x, y)`` (constant along z)."""

    def __init__(self, domain):
        self.domain = domain
        self.range_shape = domain.shape[:2]

    def __call__(self, f):
        return f.sum(dim=-1) * self.domain.cell_sides[2]

    def adjoint(self, g):
        return g.unsqueeze(-1).expand(*g.shape, self.domain.shape[2]).contiguous()

    def inner_data(self, y1, y2):
        hx, hy, _ = self.domain.cell_sides
        return hx * hy * (y1 * y2).sum(dim=(-2, -1))


def blob(domain, centre, widths):
    return torch.exp(-sum(((p - c) / w) ** 2 for p, c, w in zip(domain.points(), centre, widths)) / 2)


def make_problem(n=12, num_steps=4, backward="paper", dtype=torch.float64):
    dom = ImageDomain((n, n, n), (-8.0,) * 3, (8.0,) * 3)
    T = ProjectZ(dom)
    template = blob(dom, (0.0, 0.0, 0.0), (2.5, 2.0, 2.0)).to(dtype)
    target = blob(dom, (1.0, -0.5, 0.5), (2.5, 2.0, 2.0)).to(dtype)
    W = LDDMMDeformation(dom, num_steps, backward=backward)
    return IndirectRegistration(T, W, GaussianKernel(dom, 3.0), template, T(target), gamma=1e-4), target


def test_the_toy_operator_is_exact():
    dom = ImageDomain((6, 5, 4), (-3.0, -2.0, -1.0), (3.0, 3.0, 1.0))
    T = check_operator(ProjectZ(dom))
    assert adjointness(T) < 1e-14


def test_objective_3d_shapes_and_gradient_scale():
    """``h = gamma m + (N / cell_volume) dL/dnu``: its inner product with a direction is the directional derivative
    of E in the discrete ``L2([0,1], L2)`` pairing (``backward="exact"``: the derivative of the discrete map)."""
    problem, _ = make_problem(backward="exact")
    assert problem.momentum_shape == (5, 3, 12, 12, 12)
    g = torch.Generator().manual_seed(0)
    m = problem.kernel.apply(torch.randn(problem.momentum_shape, dtype=torch.float64, generator=g)) * 0.05
    d = problem.kernel.apply(torch.randn(problem.momentum_shape, dtype=torch.float64, generator=g)) * 0.05
    terms, h, nu = problem.l2_gradient(m)
    assert h.shape == nu.shape == problem.momentum_shape
    # E as a function of nu (the regulariser (gamma/2) <m, K m> = (gamma/2) <K^-1 nu, nu>: use nu = K m, d = K e)
    eps = 1e-6
    plus, minus = (problem.evaluate(m + s * eps * d)["objective"] for s in (1, -1))
    fd = (plus - minus) / (2 * eps)
    assert abs(problem.time_weight * float((h * problem.kernel.apply(d)).sum()) - fd) < 1e-6 * abs(fd)


def test_tv_term_in_3d_gradient():
    """With the TV term (3D isotropic TV of the deformed volume): the L2 gradient still gives the directional
    derivative of E (``backward="exact"``)."""
    base, _ = make_problem(n=8, num_steps=3, backward="exact")
    problem = IndirectRegistration(base.ray_transform, base.deformation, base.kernel, base.template, base.data,
                                   gamma=1e-4, tv_weight=0.05, tv_smoothing=0.1)
    g = torch.Generator().manual_seed(1)
    m, d = (problem.kernel.apply(torch.randn(problem.momentum_shape, dtype=torch.float64, generator=g)) * 0.05
            for _ in range(2))
    terms, h, _ = problem.l2_gradient(m)
    assert terms["tv"] > 0
    eps = 1e-6
    fd = (problem.evaluate(m + eps * d)["objective"] - problem.evaluate(m - eps * d)["objective"]) / (2 * eps)
    assert abs(problem.time_weight * float((h * problem.kernel.apply(d)).sum()) - fd) < 1e-6 * abs(fd)


def test_algorithm1_decreases_the_objective_3d():
    problem, target = make_problem()
    solver = Algorithm1(problem, step_size=0.02, max_iter=6, step_halving=True)
    state = SolverState(problem.zero_momentum())
    start = problem.evaluate(state.momentum)["objective"]
    info = solver.run(state)
    assert info["status"] == "completed" and info["objective"] < 0.5 * start
    assert info["min_jacobian"] > 0
    deformed = problem.deformed(state.momentum)
    assert float((deformed - target).norm()) < float((problem.template - target).norm())


def test_lbfgs_decreases_the_objective_3d():
    problem, _ = make_problem()
    solver = TorchOptimSolver(problem, "lbfgs", max_iter=4)
    state = SolverState(problem.zero_momentum())
    start = problem.evaluate(state.momentum)["objective"]
    objectives = [solver.step(state)["objective"] for _ in range(4)]
    assert objectives[-1] < 0.5 * start
    assert all(b <= a for a, b in zip(objectives, objectives[1:]))


@pytest.mark.parametrize("solver", ("algorithm1", "lbfgs"))
def test_register_3d(solver):
    problem, target = make_problem()
    result = indreg.register(problem.template, problem.data, problem.ray_transform, sigma=3.0, gamma=1e-4,
                             num_steps=4, max_iter=5, solver=solver, target=target)
    assert result.deformed.shape == (12, 12, 12) and result.trajectory.shape == (5, 12, 12, 12)
    assert result.momentum.shape == result.velocity.shape == (5, 3, 12, 12, 12)
    assert result.deformation.shape == (3, 12, 12, 12)
    assert result.min_jacobian > 0 and result.status == "completed"
    assert result.objective < result.history[0]["objective"]
    assert result.residual < 1.0 and 0 < result.ssim <= 1 and result.psnr > 0
    assert float((result.deformed - target).norm()) < float((problem.template - target).norm())


@pytest.mark.parametrize("solver,options", (("algorithm1", {"step_size": 0.02, "source_mask": "template"}),
                                             ("lbfgs", {"source_sigma": None, "source_mask": None})))
def test_register_3d_metamorphosis(solver, options):
    """model="metamorphosis" in 3D through indreg.register: the same code path as 2D, 3D shapes throughout."""
    problem, target = make_problem()
    result = indreg.register(problem.template, 1.3 * problem.data, problem.ray_transform, model="metamorphosis",
                             sigma=3.0, gamma=1e-4, tau=1e-3, num_steps=4, max_iter=4, solver=solver,
                             target=1.3 * target, **options)
    assert result.deformed.shape == (12, 12, 12) and result.trajectory.shape == (5, 12, 12, 12)
    assert result.momentum.shape == (5, 3, 12, 12, 12) and result.source.shape == (5, 12, 12, 12)
    assert result.deformation_part.shape == result.intensity_part.shape == (12, 12, 12)
    torch.testing.assert_close(result.deformation_part + result.intensity_part, result.deformed)
    assert result.status == "completed" and result.objective < 0.5 * result.history[0]["objective"]
    assert result.terms["source_regulariser"] > 0 and float(result.intensity_part.abs().max()) > 0
    if options.get("source_mask"):  # the source is 0 outside the template's dilated support
        mask = result.problem.source_mask
        zeta = result.problem.source(result.source)
        assert 0 < float(mask.mean()) < 1 and not bool(zeta[:, mask == 0].ne(0).any())
        assert float(zeta[:, mask == 1].abs().max()) > 0


@pytest.mark.parametrize("solver_name", ("algorithm1", "lbfgs"))
def test_checkpoint_resume_3d_is_bit_identical(tmp_path, solver_name):
    """Save the state and the solver's state_dict after 2 steps (the app's checkpoint format), resume in a new
    solver: the next 2 steps equal those of the uninterrupted run."""
    def new_solver(problem):
        if solver_name == "algorithm1":
            return Algorithm1(problem, step_size=0.02, max_iter=4, step_halving=True)
        return TorchOptimSolver(problem, "lbfgs", max_iter=4)

    problem, _ = make_problem(n=8, num_steps=3)
    solver, state = new_solver(problem), SolverState(problem.zero_momentum())
    for _ in range(2):
        solver.step(state)
    path = tmp_path / "checkpoint.pt"
    checkpoint.save(path, {"state": state.state_dict(), "solver": solver.state_dict()})
    for _ in range(2):
        solver.step(state)
    saved = checkpoint.load(path)
    resumed, state2 = new_solver(problem), SolverState.from_state_dict(saved["state"])
    resumed.load_state_dict(saved["solver"])
    for _ in range(2):
        info = resumed.step(state2)
    assert torch.equal(state2.momentum, state.momentum) and state2.iteration == state.iteration == 4
    assert info["evaluations"] == solver.evaluations


def test_register_with_a_tilt_series_3d():
    """End to end with the 3D tilt-series projector: the deformed template fits the data better."""
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform

    dom = ImageDomain((12, 12, 12), (-8.0,) * 3, (8.0,) * 3)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 20, det_count=12, det_min=-8.0, det_max=8.0))
    template = blob(dom, (0.0, 0.0, 0.0), (2.5, 2.0, 2.0))
    target = blob(dom, (1.0, -0.5, 0.5), (2.5, 2.0, 2.0))
    result = indreg.register(template, T(target), T, sigma=3.0, gamma=1e-4, num_steps=4, max_iter=6)
    assert result.deformed.shape == dom.shape and result.min_jacobian > 0
    start = float((T(template) - T(target)).norm() / T(target).norm())
    relative = float((T(result.deformed) - T(target)).norm() / T(target).norm())
    assert relative < 0.7 * start
