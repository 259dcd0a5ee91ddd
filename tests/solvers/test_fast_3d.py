"""``solver="fast"`` (MultilevelSolver) in 3D: the coarse tilt-series problem and coarse-to-fine runs on a volume."""
import pytest
import torch

import indreg
from indreg import ImageDomain
from indreg.deform import GaussianKernel, LDDMMDeformation
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.solvers import IndirectRegistration, MultilevelSolver, SolverState
from indreg.problems.grids import prolong, resample_time, restrict

FINE, COARSE = (32, 32, 32), (16, 16, 16)


def blob(domain, centre, widths):
    return torch.exp(-sum(((p - c) / w) ** 2 for p, c, w in zip(domain.points(), centre, widths)) / 2)


def tilt_series(shape=FINE, tilt_axis="y"):
    """A tilt series (-60..60 in 10-degree steps, a detector as wide as the volume) of a volume on [-8, 8]^3."""
    dom = ImageDomain(shape, (-8.0,) * 3, (8.0,) * 3)
    return TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 10, det_count=32, det_min=-8.0, det_max=8.0,
                                                               tilt_axis=tilt_axis))


def make_problem(num_steps=4):
    T = tilt_series()
    dom = T.domain
    template = blob(dom, (0.0, 0.0, 0.0), (2.5, 2.0, 2.0)).double()
    target = blob(dom, (1.0, -0.5, 0.5), (2.5, 2.0, 2.0)).double()
    W = LDDMMDeformation(dom, num_steps, backward="exact", interpolation="compose")
    return IndirectRegistration(T, W, GaussianKernel(dom, 3.0), template, T(target), gamma=1e-4), target


@pytest.mark.parametrize("tilt_axis", ("x", "y", "z"))
def test_coarse_tilt_series_is_the_row_average_of_the_fine_one(tilt_axis):
    """A coarse slice (orthogonal to the tilt axis) is the average of its fine slices, so it projects to the
    average of their detector rows: restrict(T_fine f, coarse rows) ~ T_coarse(restrict f) for a smooth f, up
    to the in-plane discretisation (measured 1.3-2.1 %; taking every other row instead: 7-12 %)."""
    T = tilt_series(tilt_axis=tilt_axis)
    T_coarse = T.on_domain(ImageDomain(COARSE, T.domain.min_pt, T.domain.max_pt))
    assert T_coarse.range_shape == (13, 16, 32)  # the tilts and columns kept, one row per coarse slice
    f = blob(T.domain, (1.0, -0.5, 0.5), (2.5, 2.0, 1.5)).double()
    data = T(f)
    reference = T_coarse(restrict(f, COARSE))
    averaged = restrict(data, T_coarse.range_shape[-2:])
    error = float((averaged - reference).norm() / reference.norm())
    subsampled = float((data[:, ::2] - reference).norm() / reference.norm())
    assert error < 0.03 and error < 0.3 * subsampled


def test_coarse_objective_approximates_the_fine_one():
    """``coarsened`` in 3D: template and data cell-averaged, the same box, kernel width and gamma; the objective
    at restricted momenta is the fine one up to discretisation (measured 2.7 % at 0, 0.7 % at a smooth m)."""
    problem, _ = make_problem()
    coarse = problem.coarsened(COARSE, 4, "exact")
    assert coarse.domain.shape == COARSE and coarse.domain.min_pt == problem.domain.min_pt
    assert coarse.kernel.sigma == problem.kernel.sigma and coarse.gamma == problem.gamma
    torch.testing.assert_close(coarse.template, restrict(problem.template, COARSE))
    torch.testing.assert_close(coarse.data, restrict(problem.data, (16, 32)))
    assert coarse.momentum_shape == (5, 3, *COARSE)
    g = torch.Generator().manual_seed(0)
    m = problem.kernel.apply(torch.randn(problem.momentum_shape, generator=g, dtype=torch.float64))
    m *= 1.0 / float(problem.velocity(m).abs().max())  # moves points by up to 1 unit (half a cell)
    for x in (problem.zero_momentum(), m):
        fine, approx = problem.evaluate(x)["objective"], coarse.evaluate(restrict(x, COARSE))["objective"]
        assert approx == pytest.approx(fine, rel=0.05)


def test_every_coarse_iterate_is_a_fine_momentum_3d():
    problem, _ = make_problem()
    solver = MultilevelSolver(problem, levels=(2,), level_steps=(3,), level_iter=(2,), min_size=8, max_iter=4)
    assert [s[0] for s in solver.schedule] == [COARSE, FINE]
    state = SolverState(problem.zero_momentum())
    solver.step(state)
    coarse = solver.state_dict()["momentum"]
    assert coarse.shape == (4, 3, *COARSE) and state.momentum.shape == problem.momentum_shape
    torch.testing.assert_close(state.momentum, prolong(resample_time(coarse, 4), FINE))


def test_register_fast_3d_runs_both_levels_and_decreases_the_objective():
    problem, target = make_problem()
    T = problem.ray_transform
    r = indreg.register(problem.template, problem.data, T, solver="fast", sigma=3.0, gamma=1e-4, num_steps=4,
                        max_iter=6, target=target,
                        optimizer_kwargs={"levels": (2,), "level_steps": (4,), "level_iter": (3,), "min_size": 8})
    assert [h["level"] for h in r.history] == [0, 0, 0, 1, 1, 1]
    assert [h["grid"] for h in r.history] == [16] * 3 + [32] * 3
    assert r.momentum.shape == (5, 3, *FINE) and r.deformed.shape == FINE and r.status == "completed"
    assert r.problem.deformation.interpolation == "compose" and r.min_jacobian > 0
    start = problem.evaluate(problem.zero_momentum())["objective"]
    assert r.objective < 0.05 * start  # measured 62.5 -> 0.62
    for level in (0, 1):  # descent within each level
        e = [h["objective"] for h in r.history if h["level"] == level]
        assert all(b <= a for a, b in zip(e, e[1:])), (level, e)
    assert r.ssim > indreg.metrics.ssim(problem.template, target)
