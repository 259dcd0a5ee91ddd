"""Indirect metamorphosis: objective terms, L2 gradients by finite differences, descent, torch.optim, errors
(2D; the objective's terms, gradients and descent also in 3D with a tilt series on an 8^3 volume)."""
import math

import pytest
import torch

from indreg import ImageDomain, phantoms
from indreg.deform import GaussianKernel, MetamorphosisDeformation
from indreg.forward import ParallelBeamGeometry, RayTransform, TiltSeriesGeometry, TiltSeriesTransform
from indreg.solvers import (Algorithm1, IndirectRegistration, MetamorphosisDescent, MetamorphosisRegistration,
                            MetamorphosisState, MetamorphosisTorchOptim, SolverState)
from indreg.problems.metamorphosis import data_support, noise_std, opened, template_support


def make_problem(n=24, num_steps=4, gamma=1e-5, tau=1e-3, interpolation="reinterpolate", source_sigma=None,
                 mask=False, ndim=2):
    """J -> V with the target's grey values scaled and offset (an intensity change LDDMM cannot make);
    ``ndim=3``: ``make_problem_3d``."""
    if ndim == 3:
        return make_problem_3d(num_steps=num_steps - 1, gamma=gamma, tau=tau, interpolation=interpolation,
                               source_sigma=source_sigma, mask=mask)
    dom = ImageDomain.paper(n)
    T = RayTransform(dom, ParallelBeamGeometry.paper(10, int(round(n * 92 / 64))))
    target = 0.6 * phantoms.get("v", dom).double() + 0.3 * (phantoms.get("v", dom).double() > 0.5)
    M = MetamorphosisDeformation(dom, num_steps, interpolation=interpolation)
    source_kernel = None if source_sigma is None else GaussianKernel(dom, source_sigma)
    template = phantoms.get("j", dom).double()
    return MetamorphosisRegistration(T, M, GaussianKernel(dom, 6.0), template, T(target), gamma, tau,
                                     source_kernel=source_kernel, **masks(template, dom, mask)), target


def masks(template, domain, mask) -> dict:
    """``mask`` True: the template's support dilated by 2 units; ``"uniform"`` / ``"early"``: a uniform source
    outside it (``"early"``: the problem is then put before the source's start)."""
    support = template_support(template, domain, 2.0)
    return {"source_mask": support if mask is True else None,
            "uniform_region": 1 - support if mask in ("uniform", "early") else None}


def blob(domain, centre, widths):
    return torch.exp(-sum(((p - c) / w) ** 2 for p, c, w in zip(domain.points(), centre, widths)) / 2)


def make_problem_3d(n=8, num_steps=3, gamma=1e-5, tau=1e-3, interpolation="reinterpolate", source_sigma=None,
                    mask=False):
    """A blob -> a shifted blob of another grey value, a tilt series about y (-60..60, 7 tilts) of an ``n^3``
    volume on [-8, 8]^3."""
    dom = ImageDomain((n,) * 3, (-8.0,) * 3, (8.0,) * 3)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 20, det_count=n, det_min=-8.0, det_max=8.0))
    template = blob(dom, (0.0, 0.0, 0.0), (3.0, 2.5, 2.5)).double()
    target = 1.5 * blob(dom, (1.0, -0.5, 0.5), (3.0, 2.5, 2.5)).double()
    M = MetamorphosisDeformation(dom, num_steps, interpolation=interpolation)
    source_kernel = None if source_sigma is None else GaussianKernel(dom, source_sigma)
    return MetamorphosisRegistration(T, M, GaussianKernel(dom, 4.0), template, T(target), gamma, tau,
                                     source_kernel=source_kernel, **masks(template, dom, mask)), target


def random_point(problem, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = torch.randn(problem.momentum_shape, generator=g, dtype=torch.float64)
    m *= 0.5 * problem.domain.cell_sides[0] / float(problem.velocity(m).abs().max())
    return m, 0.3 * torch.randn(problem.source_shape, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("ndim", (2, 3))
def test_terms_at_zero_are_lddmm_terms(ndim):
    problem, _ = make_problem(ndim=ndim)
    terms = problem.evaluate(problem.zero_momentum(), problem.zero_source())
    lddmm = problem.lddmm.evaluate(problem.zero_momentum())
    assert terms["source_regulariser"] == 0 and terms["regulariser"] == 0
    assert terms["objective"] == pytest.approx(lddmm["objective"], rel=1e-14)
    m, z = random_point(problem)
    terms = problem.evaluate(m, z)
    # zeta = 0: the data fit is LDDMM's (the geometric action W(K m, I))
    assert problem.evaluate(m, 0 * z)["data_fit"] == pytest.approx(problem.lddmm.evaluate(m)["data_fit"], rel=1e-12)
    n = problem.num_steps
    expected = 0.5 * problem.tau * sum(float(problem.domain.norm(z[i]) ** 2) / n for i in range(n + 1))
    assert terms["source_regulariser"] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("interpolation,source_sigma,mask,ndim", (
    ("reinterpolate", None, False, 2), ("compose", None, False, 2), ("reinterpolate", 2.0, False, 2),
    ("reinterpolate", None, True, 2), ("compose", 2.0, True, 2),
    ("reinterpolate", None, False, 3), ("compose", None, False, 3), ("compose", 2.0, True, 3),
    ("reinterpolate", 2.0, "uniform", 2), ("compose", None, "uniform", 2), ("reinterpolate", 2.0, "uniform", 3),
    ("reinterpolate", 2.0, "early", 2), ("compose", None, "early", 2), ("reinterpolate", 2.0, "early", 3)))
def test_l2_gradients_match_finite_differences(interpolation, source_sigma, mask, ndim):
    """dE(m + e dm, s + e ds)/de = time_weight (<K h_nu, dm> + <K_s h_s, ds>) (E in m and s; nu = K m, zeta = K_s s;
    K_s = identity for the L2 source); with a uniform region also before the source's start (its part only)."""
    problem, _ = make_problem(interpolation=interpolation, source_sigma=source_sigma, tau=0.1, mask=mask,
                              ndim=ndim)
    problem.source_start = 1
    early = mask == "early"
    assert problem.at_iteration(0 if early else 1) == early and problem.early == early
    m, z = random_point(problem)
    _, h_nu, h_zeta, _ = problem.l2_gradient(m, z)
    dm, dz = random_point(problem, seed=1)
    w = problem.time_weight
    for direction in ((dm, 0 * dz), (0 * dm, dz)):
        eps = 1e-6  # a velocity component near 0 puts a point near a node: an interpolation kink ~1e-4 away
        numeric = (problem.evaluate(m + eps * direction[0], z + eps * direction[1])["objective"]
                   - problem.evaluate(m - eps * direction[0], z - eps * direction[1])["objective"]) / (2 * eps)
        analytic = w * float((problem.kernel.apply(h_nu) * direction[0]).sum()
                             + (problem.unmasked_source(h_zeta) * direction[1]).sum())
        assert numeric == pytest.approx(analytic, rel=1e-6)


def test_descent_decreases_the_objective_and_changes_intensities():
    problem, target = make_problem()
    state = MetamorphosisState.zeros(problem)
    solver = MetamorphosisDescent(problem, step_size=0.02, max_iter=15)
    infos = []
    info = solver.run(state, callback=lambda s, i: infos.append(i))
    objectives = [problem.evaluate(problem.zero_momentum(), problem.zero_source())["objective"]]
    objectives += [i["objective"] for i in infos]
    assert info["status"] == "completed" and solver.evaluations == 16
    assert all(b < a for a, b in zip(objectives, objectives[1:]))
    assert info["source_regulariser"] > 0 and info["regulariser"] > 0
    assert info["grad_norm"] == pytest.approx(math.hypot(info["velocity_grad_norm"], info["source_grad_norm"]))
    # the source changes the grey values: LDDMM with the same velocity step size fits the data worse
    lddmm_state = SolverState(problem.lddmm.zero_momentum())
    lddmm = Algorithm1(problem.lddmm, step_size=0.02, max_iter=15).run(lddmm_state)
    assert info["data_fit"] < 0.5 * lddmm["data_fit"]
    deformed, intensity = problem.parts(state.momentum, state.source)
    torch.testing.assert_close(deformed + intensity, problem.image(state.momentum, state.source))
    torch.testing.assert_close(deformed, problem.lddmm.deformed(state.momentum))


def test_large_tau_is_lddmm():
    """tau -> infinity freezes the source: the first step is Algorithm 1's (whose paper gradient agrees with the
    exact one at nu = 0, except at t_0, which the discrete map does not use)."""
    problem, _ = make_problem(tau=1e12)
    state = MetamorphosisState.zeros(problem)
    MetamorphosisDescent(problem, step_size=0.02, max_iter=1).run(state)
    lddmm_state = SolverState(problem.lddmm.zero_momentum())
    Algorithm1(problem.lddmm, step_size=0.02, max_iter=1).run(lddmm_state)
    assert float(state.source.abs().max()) < 1e-9
    torch.testing.assert_close(state.momentum[1:], lddmm_state.momentum[1:], rtol=1e-8, atol=1e-12)


def test_step_halving_rejects_an_increase():
    problem, _ = make_problem()
    solver = MetamorphosisDescent(problem, step_size=1e3, source_step_size=1e3, max_iter=2, step_halving=True,
                                  max_halvings=30)
    state = MetamorphosisState.zeros(problem)
    start = solver.report(state)["objective"]
    info = solver.run(state)
    assert info["objective"] <= start and solver.step_size < 1e3 and solver.source_step_size < 1e3


@pytest.mark.parametrize("optimizer,kwargs,source_sigma,mask", (("adam", {"lr": 1e-3, "source_lr": 2e-2}, None, False),
                                                               ("lbfgs", {}, None, False), ("lbfgs", {}, 2.0, False),
                                                               ("lbfgs", {}, 2.0, True)))
def test_torch_optim_decreases_and_its_gradients_are_the_l2_gradients(optimizer, kwargs, source_sigma, mask):
    problem, _ = make_problem(source_sigma=source_sigma, mask=mask)
    solver = MetamorphosisTorchOptim(problem, optimizer, max_iter=5, **kwargs)
    state = MetamorphosisState.zeros(problem)
    start = solver.report(state)["objective"]
    info = solver.run(state)
    assert info["objective"] < 0.9 * start
    _, (grad_p, grad_q), *_ = solver._evaluate()
    _, h_nu, h_zeta, _ = problem.l2_gradient(state.momentum, state.source)
    torch.testing.assert_close(grad_p, problem.kernel.apply(h_nu), rtol=1e-8, atol=1e-12)
    torch.testing.assert_close(grad_q, problem.unmasked_source(h_zeta), rtol=1e-8, atol=1e-12)


def test_rkhs_source_is_smooth_and_its_regulariser_is_the_rkhs_norm():
    problem, _ = make_problem(source_sigma=2.0, tau=0.1)
    state = MetamorphosisState.zeros(problem)
    MetamorphosisDescent(problem, step_size=0.02, max_iter=5).run(state)
    zeta = problem.source(state.source)
    expected = 0.5 * 0.1 * problem.time_weight * float((state.source * zeta).sum())
    assert problem.evaluate(state.momentum, state.source)["source_regulariser"] == pytest.approx(expected, rel=1e-12)
    rough = lambda z: float((z[..., 1:, :] - z[..., :-1, :]).norm() / z.norm())  # noqa: E731
    l2, _ = make_problem(tau=0.1)
    l2_state = MetamorphosisState.zeros(l2)
    MetamorphosisDescent(l2, step_size=0.02, max_iter=5).run(l2_state)
    assert rough(zeta) < 0.75 * rough(l2_state.source)  # measured 0.32 vs 0.52


def test_source_mask_confines_the_intensity_change():
    problem, _ = make_problem(mask=True, tau=0.1)
    mask = problem.source_mask
    assert 0 < float(mask.mean()) < 1 and bool((mask[problem.template > 0.01] == 1).all())
    state = MetamorphosisState.zeros(problem)
    MetamorphosisDescent(problem, step_size=0.02, max_iter=3).run(state)
    assert float(state.source.abs().max()) > 0
    assert not bool(problem.source(state.source)[:, mask == 0].ne(0).any())
    with pytest.raises(ValueError, match="source_mask must have values in"):
        MetamorphosisRegistration(problem.ray_transform, problem.deformation, problem.kernel, problem.template,
                                  problem.data, 1e-5, 0.1, source_mask=2 * mask)


@pytest.mark.parametrize("early", (False, True))
def test_uniform_region_is_an_orthogonal_projection(early):
    """``restricted`` (B) with a uniform region U: B B u = B u, <B u, v> = <u, B v>; on U the mean of u over U at each
    time, off U u itself (0 before the source's start)."""
    problem, _ = make_problem(mask="uniform")
    problem.early, region = early, problem.uniform_region.bool()
    u, v = random_point(problem, seed=2)[1], random_point(problem, seed=3)[1]
    b = problem.restricted(u)
    torch.testing.assert_close(problem.restricted(b), b, rtol=1e-12, atol=1e-12)
    assert float((b * v).sum()) == pytest.approx(float((u * problem.restricted(v)).sum()), rel=1e-12)
    torch.testing.assert_close(b[:, region], u[:, region].mean(1, keepdim=True).expand(-1, int(region.sum())))
    torch.testing.assert_close(b[:, ~region], 0 * u[:, ~region] if early else u[:, ~region])


def test_staged_source_is_uniform_on_its_region_before_its_start():
    """Algorithm 1 with a uniform region and source_start 3: in the first 3 iterations the source is nonzero only
    on the region, uniform there; from then on elsewhere too. The objective reported after the switch is the full
    problem's, and a run resumed across the switch equals the uninterrupted one."""
    problem, _ = make_problem(mask="uniform", tau=0.1)
    problem.source_start, region = 3, problem.uniform_region.bool()
    state, zetas, infos = MetamorphosisState.zeros(problem), [], []
    solver = MetamorphosisDescent(problem, step_size=0.02, max_iter=6)
    solver.run(state, callback=lambda s, i: (zetas.append(problem.source(s.source)), infos.append(i)))
    for k, zeta in enumerate(zetas, 1):
        on = zeta[1:, region]
        assert float(on.abs().min()) > 0 and float((on - on[:, :1]).abs().max()) <= 1e-12 * float(on.abs().max())
        assert bool(zeta[:, ~region].eq(0).all()) == (k <= 3), k
    assert not problem.early
    assert infos[-1]["objective"] == pytest.approx(problem.evaluate(state.momentum, state.source)["objective"],
                                                   rel=1e-12)
    fresh, _ = make_problem(mask="uniform", tau=0.1)
    fresh.source_start, resumed = 3, MetamorphosisState.zeros(fresh)
    first = MetamorphosisDescent(fresh, step_size=0.02, max_iter=2)
    first.run(resumed)
    again, _ = make_problem(mask="uniform", tau=0.1)
    again.source_start = 3
    second = MetamorphosisDescent(again, step_size=0.02, max_iter=6)
    second.load_state_dict(first.state_dict())
    second.run(resumed)
    torch.testing.assert_close(resumed.source, state.source, rtol=1e-12, atol=1e-14)


def test_state_dict_round_trip():
    problem, _ = make_problem()
    state = MetamorphosisState.zeros(problem)
    solver = MetamorphosisDescent(problem, max_iter=2)
    solver.run(state)
    copy = MetamorphosisState.zeros(problem)
    copy.load_state_dict(state.state_dict())
    assert torch.equal(copy.source, state.source) and copy.iteration == 2
    other = MetamorphosisDescent(problem, max_iter=3)
    other.load_state_dict(solver.state_dict())
    assert other.source_step_size == solver.source_step_size


def test_bad_input():
    problem, _ = make_problem()
    with pytest.raises(TypeError, match="deformation must be a MetamorphosisDeformation"):
        MetamorphosisRegistration(problem.ray_transform, problem.deformation.lddmm, problem.kernel,
                                  problem.template, problem.data, 1e-5, 1e-3)
    with pytest.raises(ValueError, match="tau must be a finite number >= 0"):
        MetamorphosisRegistration(problem.ray_transform, problem.deformation, problem.kernel, problem.template,
                                  problem.data, 1e-5, -1)
    with pytest.raises(TypeError, match="problem must be a MetamorphosisRegistration"):
        MetamorphosisDescent(problem.lddmm)
    with pytest.raises(ValueError, match="source_step_size must be a finite number > 0"):
        MetamorphosisDescent(problem, source_step_size=0)
    with pytest.raises(ValueError, match="iterate must be a tuple of 2 tensors"):
        MetamorphosisDescent(problem, source_step_size=1.0).step(SolverState(problem.zero_momentum()))
    with pytest.raises(ValueError, match="source must have shape"):
        problem.evaluate(problem.zero_momentum(), problem.zero_source()[:2])
    for region in (0.5 * torch.ones_like(problem.template), torch.zeros_like(problem.template)):
        with pytest.raises(ValueError, match="uniform_region must have values 0 or 1, some of them 1"):
            MetamorphosisRegistration(problem.ray_transform, problem.deformation, problem.kernel, problem.template,
                                      problem.data, 1e-5, 0.1, uniform_region=region)
    with pytest.raises(ValueError, match="source_start must be an integer >= 0"):
        MetamorphosisRegistration(problem.ray_transform, problem.deformation, problem.kernel, problem.template,
                                  problem.data, 1e-5, 0.1, source_start=-1)
    with pytest.raises(ValueError, match="L-BFGS takes one parameter group"):
        MetamorphosisTorchOptim(problem, "lbfgs", source_lr=0.1)
    for tau, tau_rel in ((None, None), (1.0, 0.1)):
        with pytest.raises(ValueError, match="give exactly one of tau and tau_rel"):
            MetamorphosisRegistration(problem.ray_transform, problem.deformation, problem.kernel, problem.template,
                                      problem.data, 1e-5, tau, tau_rel=tau_rel)


def test_tau_rel_is_the_share_of_the_smoothest_residual_the_source_leaves():
    """tau = tau_rel ||T||^2 (L2 source): at nu = 0 the source z v / (1 + tau_rel), constant in time, is stationary
    for the residual T v along the top singular vector v of T (T^* T v = ||T||^2 v), i.e. the source alone explains
    1 / (1 + tau_rel) of it (docs/metamorphosis.md); with an RKHS source tau_scale is ||T||^2 ||K_s||."""
    base, _ = make_problem(n=16)
    T, dom = base.ray_transform, base.domain
    v = torch.ones(dom.shape, dtype=torch.float64)
    for _ in range(3000):   # power iteration to the top eigenvector of T^* T
        v = T.adjoint(T(v))
        v = v / dom.norm(v)
    sigma2 = float(dom.inner(v, T.adjoint(T(v))))
    assert float(dom.norm(T.adjoint(T(v)) - sigma2 * v)) < 1e-6 * sigma2
    problem = MetamorphosisRegistration(T, base.deformation, base.kernel, base.template,
                                        T(base.template) + T(v), 1e-5, None, tau_rel=0.5)
    assert problem.tau == pytest.approx(0.5 * sigma2, rel=1e-6)
    s = torch.stack([torch.zeros_like(v)] + [v / 1.5] * base.num_steps)
    _, _, h_s, _ = problem.l2_gradient(problem.zero_momentum(), s)
    assert float(h_s[1:].norm()) < 1e-5 * float((problem.tau * s[1:]).norm())
    rkhs = MetamorphosisRegistration(T, base.deformation, base.kernel, base.template, base.data, 1e-5, None,
                                     source_kernel=GaussianKernel(dom, 2.0), tau_rel=0.5)
    assert rkhs.tau == pytest.approx(0.5 * problem.operator_norm ** 2 * rkhs.source_kernel_norm())
    assert rkhs.hparams() == {"tau": rkhs.tau, "tau_rel": pytest.approx(0.5), "source_sigma": 2.0}


@pytest.mark.parametrize("ndim", (2, 3))
def test_template_support_is_the_dilated_support(ndim):
    """One bright voxel and a margin of one cell side along x, two along the others: a box of 3 x 5 (x 5) ones."""
    dom = ImageDomain((9, 11, 10)[:ndim], (-4.5, -2.75, -5.0)[:ndim], (4.5, 2.75, 5.0)[:ndim])  # cells 1, 0.5, 1
    template = torch.zeros(dom.shape, dtype=torch.float64)
    template[(4, 5, 5)[:ndim]] = 2.0
    template[(0, 0, 0)[:ndim]] = 0.01  # below the threshold (1% of the maximum)
    mask = template_support(template, dom, margin=1.0)
    expected = torch.zeros_like(template)
    expected[(slice(3, 6), slice(3, 8), slice(4, 7))[:ndim]] = 1.0
    assert mask.shape == dom.shape and torch.equal(mask, expected)


@pytest.mark.parametrize("noise_std", (0.0, 0.1))
def test_data_support_is_the_datas_visual_hull(noise_std):
    """A disc of radius 6 seen by 10 parallel-beam angles: the points whose rays all carry mass are the disc and the
    corners of the 10 strips around it, at most R / cos(9 deg) from the centre plus the detector smoothing's reach
    (3 widths of 2 cells of 0.53; measured: 8.9 noise-free, 6.5 with noise); with noise of 10% of the largest
    projection the disc's interior is still inside (measured: nothing within 5.7 is outside)."""
    dom = ImageDomain.paper(64)
    T = RayTransform(dom, ParallelBeamGeometry.paper(10, 90))
    r = sum(p ** 2 for p in dom.points()).sqrt().double()
    data = T((r <= 6.0).double())
    data = data + noise_std * float(data.max()) * torch.randn(data.shape, generator=torch.Generator().manual_seed(0),
                                                              dtype=data.dtype)
    mask = data_support(data, T, dom)
    assert mask.shape == dom.shape and set(mask.unique().tolist()) <= {0.0, 1.0}
    assert bool((mask[r <= 6.0 - dom.cell_sides[0]] == 1).all())
    assert bool((mask[r > 6.0 / math.cos(math.pi / 20) + 3 * 2 * 48 / 90] == 0).all())
    assert float(data_support(data, T, dom, margin=2.0).sum()) > float(mask.sum())   # dilated as template_support


def test_data_support_3d_tilt_series():
    """A ball of radius 4 in a tilt series about y (-60..60 degrees): the ball is inside; along the tilt axis y,
    where every ray's data row is empty, nothing is; 2D and 3D are the same function (the operator's
    back-projection)."""
    dom = ImageDomain((12,) * 3, (-8.0,) * 3, (8.0,) * 3)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 20, det_count=12, det_min=-8.0, det_max=8.0))
    ball = sum(p ** 2 for p in dom.points()).sqrt().double() <= 4.0
    mask = data_support(T(ball.double()), T, dom)
    assert mask.shape == dom.shape and bool((mask[ball] == 1).all())
    assert float(mask[:, :2].sum()) == 0 and float(mask[:, -2:].sum()) == 0


def test_noise_std_of_white_noise_on_a_smooth_signal():
    """The std of white noise from neighbouring detector cells' differences: within 5% on 20 x 400 cells of a signal
    whose steps between cells are at most a fifth of the noise (the signal alone reads as less than that)."""
    s = torch.linspace(-3, 3, 400, dtype=torch.float64)
    clean = (5 * torch.exp(-s ** 2)).expand(20, 400)
    noisy = clean + 0.3 * torch.randn(20, 400, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert noise_std(noisy) == pytest.approx(0.3, rel=0.05) and noise_std(clean) < 0.3 / 5


@pytest.mark.parametrize("ndim", (2, 3))
def test_opened_removes_thin_parts_and_keeps_thick_ones(ndim):
    """Opening by half-width 1 (cells of 1): a 9-cell block stays whole, a 2-cell-thick strip attached to it goes."""
    dom = ImageDomain((16,) * ndim, (0.0,) * ndim, (16.0,) * ndim)
    mask = torch.zeros(dom.shape, dtype=torch.float64)
    mask[(slice(2, 11),) * ndim] = 1.0
    strip = mask.clone()
    strip[(slice(11, 16), slice(4, 6), slice(4, 6))[:ndim]] = 1.0
    torch.testing.assert_close(opened(strip, dom, 1.0), mask)
    torch.testing.assert_close(opened(mask, dom, 1.0), mask)


def test_descent_3d_decreases_the_objective_and_changes_intensities():
    """3D (tilt series, 8^3): Algorithm 1 on (m, s) decreases E, moves and creates intensity (measured: E 507 -> 6.1
    in 6 iterations; the 2D step 0.02 overshoots on these data)."""
    problem, target = make_problem_3d(tau=1e-3)
    state = MetamorphosisState.zeros(problem)
    infos = []
    MetamorphosisDescent(problem, step_size=0.005, max_iter=6).run(state, callback=lambda s, i: infos.append(i))
    start = problem.evaluate(problem.zero_momentum(), problem.zero_source())["objective"]
    objectives = [start] + [i["objective"] for i in infos]
    assert all(b < a for a, b in zip(objectives, objectives[1:])) and objectives[-1] < 0.05 * start
    assert infos[-1]["source_regulariser"] > 0 and infos[-1]["regulariser"] > 0 and infos[-1]["min_jacobian"] > 0
    image = problem.image(state.momentum, state.source)
    assert image.shape == (8, 8, 8) and float((image - target).norm()) < float((problem.template - target).norm())
