"""IndirectRegistration with the velocity on a coarser grid (CoarseVelocityDeformation, ``velocity_factor``): the
L2 gradient on the coarse grid, the solvers on it, coarse levels keeping the factor."""
import pytest
import torch

from indreg import ImageDomain
from indreg.deform import CoarseVelocityDeformation, GaussianKernel, coarse_domain
from indreg.solvers import Algorithm1, IndirectRegistration, MultilevelSolver, SolverState, TorchOptimSolver

from solver_problems import make_problem, smooth_momentum


def coarse_problem(n=32, factor=2, backward="exact", gamma=0.05, tv_weight=0.0):
    """``make_problem`` with the velocity on the grid ``factor`` times coarser (same operator, template, data)."""
    p = make_problem(n=n, gamma=gamma, tv_weight=tv_weight)
    vdom = coarse_domain(p.domain, factor)
    W = CoarseVelocityDeformation(p.domain, vdom, p.num_steps, backward=backward)
    return IndirectRegistration(p.ray_transform, W, GaussianKernel(vdom, p.kernel.sigma), p.template, p.data,
                                p.gamma, tv_weight=tv_weight)


def test_grids_of_the_problem():
    p = coarse_problem()
    assert p.domain.shape == (16, 16) and p.image_domain.shape == (32, 32)
    assert p.momentum_shape == (6, 2, 16, 16) and p.time_weight == p.domain.cell_volume / p.num_steps
    m = smooth_momentum(p)
    assert p.reconstruction((m,)).shape == (32, 32) and p.image_trajectory((m,)).shape == (6, 32, 32)
    assert p.deformation_field(p.velocity(m)).shape == (2, 32, 32)


@pytest.mark.parametrize("backward", ["exact", "autograd"])
def test_l2_gradient_matches_central_differences(backward):
    """dE along dm = time_weight <h, K dm> with h = gamma m + (N / coarse cell_volume) dL/dnu (TV term included)."""
    p = coarse_problem(backward=backward, tv_weight=0.1)
    m = smooth_momentum(p, seed=3)
    terms, h, _ = p.l2_gradient(m)
    direction = smooth_momentum(p, seed=4)
    eps = 1e-5
    fd = (p.evaluate(m + eps * direction)["objective"] - p.evaluate(m - eps * direction)["objective"]) / (2 * eps)
    analytic = p.time_weight * float((h * p.velocity(direction)).sum())
    assert analytic == pytest.approx(fd, rel=1e-6)
    assert terms["objective"] == pytest.approx(p.evaluate(m)["objective"], rel=1e-14)


def test_autograd_gradient_of_the_parametrisation_is_the_v_gradient():
    """TorchOptimSolver's scale s = N / coarse cell_volume: dE/dp = K h on the coarse grid."""
    p = coarse_problem()
    m = smooth_momentum(p, seed=2)
    s = p.num_steps / p.domain.cell_volume
    param = (m / s).requires_grad_(True)
    p.terms(s * param)["objective"].backward()
    v_grad = p.v_gradient(m)
    assert float((param.grad - v_grad).abs().max()) <= 1e-11 * float(v_grad.abs().max())


def test_the_solvers_descend():
    p = coarse_problem(gamma=1e-6)
    start = p.evaluate(p.zero_momentum())["objective"]
    for solver in (Algorithm1(p, step_size=0.02, max_iter=4, step_halving=True),
                   TorchOptimSolver(p, "lbfgs", max_iter=3)):
        info = solver.run(SolverState(p.zero_momentum()))
        assert info["status"] == "completed" and info["objective"] < 0.9 * start and info["min_jacobian"] > 0


def test_coarse_levels_keep_the_factor():
    p = coarse_problem(n=32)
    c = p.coarsened((8, 8), 3, "autograd")
    assert c.domain.shape == (8, 8) and c.image_domain.shape == (16, 16) and c.kernel.domain == c.domain
    assert isinstance(c.deformation, CoarseVelocityDeformation) and c.deformation.velocity_domain == c.domain
    assert c.deformation.backward == "autograd" and c.num_steps == 3
    assert c.ray_transform.domain == c.image_domain and c.template.shape == (16, 16)
    solver = MultilevelSolver(p, levels=(2,), level_steps=(3,), level_iter=(2,), max_iter=4, min_size=8)
    state = SolverState(p.zero_momentum())
    infos = [solver.step(state) for _ in range(4)]
    assert [i["level"] for i in infos] == [0, 0, 1, 1] and state.momentum.shape == p.momentum_shape
    assert infos[-1]["objective"] < infos[0]["objective"]


def test_the_kernel_must_live_on_the_velocity_grid():
    p = coarse_problem()
    with pytest.raises(ValueError, match="kernel.domain .* differs from the deformation's velocity_domain"):
        IndirectRegistration(p.ray_transform, p.deformation, GaussianKernel(p.image_domain, 6.0), p.template, p.data,
                             1e-6)
    W = CoarseVelocityDeformation(ImageDomain.paper(16), ImageDomain.paper(8), 5)
    with pytest.raises(ValueError, match="ray_transform.domain .* differs from deformation.domain"):
        IndirectRegistration(p.ray_transform, W, GaussianKernel(ImageDomain.paper(8), 6.0), p.template, p.data, 1e-6)
    with pytest.raises(ValueError, match=r"momentum must have shape \(\.\.\., 6, 2, 16, 16\)"):
        p.evaluate(torch.zeros(6, 2, 32, 32, dtype=torch.float64))
