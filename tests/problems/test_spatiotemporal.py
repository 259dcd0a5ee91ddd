"""Spatiotemporal registration (model="spatiotemporal", TimeSeriesOperator): reductions, gradients, errors."""
import math

import pytest
import torch

import indreg
from indreg import dynamic, phantoms
from indreg.forward import TimeSeriesOperator
from indreg.solvers import Algorithm1, SpatiotemporalRegistration
from indreg.forward.operator import adjointness
from indreg.problems.spatiotemporal import FramesOfTemplate, time_indices
from indreg.solvers.spatiotemporal import IntertwinedSolver


def _ops(domain, frames, per_frame=3, det=24):
    return [indreg.RayTransform(domain, indreg.ParallelBeamGeometry(
        angles=dynamic.frame_angles(k, frames, per_frame), det_count=det, det_min=-24.0, det_max=24.0))
        for k in range(frames)]


@pytest.fixture(scope="module")
def small():
    """16^2, K = 2 frames at t = 1/2, 1 (N = 4), a warped J."""
    domain = indreg.ImageDomain.paper(16)
    ops = _ops(domain, 2)
    template = phantoms.get("j", domain)
    frames = torch.stack([template.roll(1, 0), template.roll(2, 0)])
    data = torch.stack([T(f) for T, f in zip(ops, frames)])
    return domain, ops, template, data


def _problem(small, backward="autograd", known=True, n=4, tv=0.0):
    domain, ops, template, data = small
    W = indreg.LDDMMDeformation(domain, n, backward=backward)
    return SpatiotemporalRegistration(TimeSeriesOperator(ops), W, indreg.GaussianKernel(domain, 3.0),
                                      template if known else None, data, [0.5, 1.0], 1e-3, tv_weight=tv,
                                      template_tv_weight=tv, initial_template=None if known else 0.5 * template)


# ---------------------------------------------------------------------------------------------------- the operator
def test_time_series_operator_adjoints_and_shapes():
    domain = indreg.ImageDomain.paper(16)
    T = TimeSeriesOperator(_ops(domain, 4))
    assert T.range_shape == (4, 3, 24) and len(T) == 4
    assert T.adjointness_test() < 1e-12 and T.frames_adjointness_test() < 1e-12
    f = torch.randn(2, 4, 16, 16, dtype=torch.float64)
    assert T.frames(f).shape == (2, 4, 3, 24) and T.frames_adjoint(T.frames(f)).shape == f.shape
    assert torch.allclose(T(f[0, 0]), T.frames(f[0, 0].expand(4, 16, 16)))   # static = every frame the same
    coarse = T.on_domain(indreg.ImageDomain.paper(8))
    assert coarse.domain.shape == (8, 8) and coarse.range_shape == T.range_shape


def test_time_series_operator_errors():
    domain = indreg.ImageDomain.paper(16)
    ops = _ops(domain, 2)
    with pytest.raises(ValueError, match="non-empty list"):
        TimeSeriesOperator([])
    with pytest.raises(ValueError, match=r"operators\[1\].range_shape"):
        TimeSeriesOperator([ops[0], indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(4, 24))])
    with pytest.raises(TypeError, match=r"operators\[1\]"):
        TimeSeriesOperator([ops[0], "not an operator"])


# ---------------------------------------------------------------------------------------------------- reductions
@pytest.mark.parametrize("backward", ["autograd", "exact"])
def test_one_frame_at_t1_is_ordinary_registration(backward):
    """K = 1, t_1 = 1: the same iterates, objectives and result as model='lddmm' (to float64 rounding)."""
    domain = indreg.ImageDomain.paper(24)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(8, 36))
    template, data = phantoms.get("j", domain), T(phantoms.get("v", domain))
    common = dict(num_steps=4, max_iter=6, backward=backward, sigma=4.0)
    a = indreg.register(template, data, T, **common)
    b = indreg.register(template, [data], [T], model="spatiotemporal", times=[1.0], **common)
    assert [h["objective"] for h in b.history] == pytest.approx([h["objective"] for h in a.history], rel=1e-12)
    assert torch.allclose(a.momentum, b.momentum, rtol=0, atol=1e-12 * float(a.momentum.abs().max()))
    assert torch.allclose(a.deformed, b.deformed, atol=1e-12) and torch.allclose(b.frames[0], b.deformed)
    assert b.residual == pytest.approx(a.residual, rel=1e-10)


def test_static_object_gives_static_reconstruction():
    """Noise-free data of a static object: with the object as template nothing moves (zero gradient); with the
    template unknown and the momentum held at 0, the template steps are Landweber on all data at once."""
    domain = indreg.ImageDomain.paper(16)
    ops = _ops(domain, 3)
    f = phantoms.get("j", domain)
    T = TimeSeriesOperator(ops)
    data = T(f)
    W = indreg.LDDMMDeformation(domain, 3, backward="autograd")
    K = indreg.GaussianKernel(domain, 3.0)
    known = SpatiotemporalRegistration(T, W, K, f, data, None, 1e-3)
    terms, h, _ = known.gradient(known.zero_iterate())
    assert terms["data_fit"] < 1e-20 and float(h[0].abs().max()) < 1e-12
    unknown = SpatiotemporalRegistration(T, W, K, None, data, None, 1e-3)
    solver = Algorithm1(unknown, cycle=((("template",), 1),), max_iter=5)
    state = indreg.SolverState.initial(unknown)
    solver.run(state)
    step, x = solver.step_sizes[1], torch.zeros_like(f)
    for _ in range(5):
        x = x - step * T.adjoint(T(x) - data)      # the L2 gradient of (1/2)||T x - g||^2
    assert float(state.momentum.abs().max()) == 0
    assert torch.allclose(state.template, x, atol=1e-12)
    frames = unknown.outputs(state.iterate)["frames"]
    assert all(torch.equal(frames[k], frames[0]) for k in range(3))


# ---------------------------------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("backward", ["autograd", "exact"])
def test_gradcheck_momentum_and_template(backward):
    """gradcheck of E(m, I) (float64; 8^2, N = 2, K = 2 frames, TV on the frames and the template; its smoothing
    0.1: with 1e-3 its curvature, ~1e6, puts central differences with eps 1e-6 off by ~1e-6)."""
    domain = indreg.ImageDomain.paper(8)
    ops = _ops(domain, 2, per_frame=2, det=12)
    gen = torch.Generator().manual_seed(0)
    data = 0.1 * torch.randn(2, 2, 12, generator=gen, dtype=torch.float64)
    W = indreg.LDDMMDeformation(domain, 2, backward=backward)
    p = SpatiotemporalRegistration(TimeSeriesOperator(ops), W, indreg.GaussianKernel(domain, 6.0), None, data,
                                   [0.5, 1.0], 1e-3, tv_weight=0.01, template_tv_weight=0.01, tv_smoothing=0.1)
    # steps of a few cells: near the identity the points sit near nodes, on bilinear interpolation's kinks
    m = (0.2 * torch.randn(p.momentum_shape, generator=gen, dtype=torch.float64)).requires_grad_(True)
    template = torch.rand(domain.shape, generator=gen, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: p.terms((a, b))["objective"], (m, template), eps=1e-6,
                                    atol=1e-6, rtol=1e-4)


def test_central_differences_of_the_descent_directions(small):
    """``gradient()``'s h: ``<dE/dm, dm> = (cell_volume / N) <K h_nu, dm>`` (h_nu's definition, nu = K m) and
    ``<dE/dI, dI> = cell_volume <h_I, dI>``, against central differences of E."""
    p = _problem(small, "autograd", known=False)
    gen = torch.Generator().manual_seed(1)
    m = 0.3 * torch.randn(p.momentum_shape, generator=gen, dtype=torch.float64)
    x = (m, p.zero_iterate()[1])
    _, h, _ = p.gradient(x)
    dm = torch.randn(p.momentum_shape, generator=gen, dtype=torch.float64)
    dI = torch.randn(p.domain.shape, generator=gen, dtype=torch.float64)
    eps = 1e-5

    def E(a, b):
        return p.evaluate_iterate((a, b))["objective"]
    fd_m = (E(m + eps * dm, x[1]) - E(m - eps * dm, x[1])) / (2 * eps)
    fd_i = (E(m, x[1] + eps * dI) - E(m, x[1] - eps * dI)) / (2 * eps)
    assert fd_m == pytest.approx(p.time_weight * float((p.kernel.apply(h[0]) * dm).sum()), rel=1e-6)
    assert fd_i == pytest.approx(p.domain.cell_volume * float((h[1] * dI).sum()), rel=1e-6)


def test_masked_frames_match_the_trajectory(small):
    """The batched masked-velocity frames (backward "exact") equal the trajectory's (autograd), gradients too."""
    a, b = _problem(small, "autograd"), _problem(small, "exact")
    m = 0.3 * torch.randn(a.momentum_shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    assert torch.allclose(a.all_frames((m,)), b.all_frames((m,)), atol=1e-12)
    ga, gb = a.gradient((m,))[1][0], b.gradient((m,))[1][0]
    assert torch.allclose(ga, gb, atol=1e-9 * float(ga.abs().max()))


def test_template_step_is_a_tv_reconstruction_through_the_motion(small):
    """The intertwined scheme's template step: TV (Chambolle-Pock) on I -> (T_k W(phi_{0,t_k}, I))_k, whose
    adjoint (by autograd) is the L2 adjoint; at m = 0 it is the static TV reconstruction from all data."""
    p = _problem(small, "autograd", known=False)
    m = 0.3 * torch.randn(p.momentum_shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert adjointness(FramesOfTemplate(p, p.velocity(m))) < 1e-12
    solver = IntertwinedSolver(Algorithm1(p, cycle=((("momentum",), 1),)), template_steps=20, template_tv_weight=0.05)
    zero = torch.zeros_like(m)
    static = indreg.forward.tv_reconstruction(p.ray_transform, p.data, 0.1, 20, x0=p.template, opnorm_iter=20,
                                              balanced=False)[0]
    assert torch.allclose(solver.reconstruct_template((zero, p.template)), static, atol=1e-6)
    with pytest.raises(ValueError, match="moves only the momentum"):
        IntertwinedSolver(Algorithm1(p))


# ---------------------------------------------------------------------------------------------------- errors
def test_time_indices():
    assert time_indices(None, 12, 3) == [4, 8, 12]
    assert time_indices([0.0, 0.25, 1.0], 4, 3) == [0, 1, 4]


@pytest.mark.parametrize("times, match", [
    ([1.0, 0.5], "strictly increasing"), ([0.5, 1.5], r"in \[0, 1\]"), ([-0.5, 1.0], r"in \[0, 1\]"),
    ([0.3, 1.0], "time grid"), ([1.0], "one time per frame"), ("late", "list of 2 numbers"),
])
def test_bad_times_one_line(small, times, match):
    domain, ops, template, data = small
    with pytest.raises(ValueError, match=match) as e:
        indreg.register(template, list(data), ops, model="spatiotemporal", times=times, num_steps=4, max_iter=1)
    assert "\n" not in str(e.value)


def test_bad_inputs_one_line(small):
    domain, ops, template, data = small
    run = dict(model="spatiotemporal", num_steps=4, max_iter=1)
    cases = [
        (lambda: indreg.register(template, list(data), ops[:1], **run), ValueError, "2 frames but the operators 1"),
        (lambda: indreg.register(template, [data[0], data[1, :, :5]], ops, **run), ValueError, r"data\[1\] has shape"),
        (lambda: indreg.register(template[:8], list(data), ops, **run), ValueError, "template has shape"),
        (lambda: indreg.register(template, data[0], ops[0], **run), TypeError, "TimeSeriesOperator"),
        (lambda: indreg.register(None, data[0], ops[0]), TypeError, "None .*only with model='spatiotemporal'"),
        (lambda: indreg.register(None, list(data), ops, solver="adam", lr=0.1, template_update="intertwined", **run),
         ValueError, "template_update"),
        (lambda: indreg.register(template, list(data), ops, holdout=2, **run), ValueError, "holdout"),
    ]
    for call, kind, match in cases:
        with pytest.raises(kind, match=match) as e:
            call()
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="cycle must name"):
        Algorithm1(_problem(small), cycle=((("source",), 2),))


def test_data_sets_of_mixed_dtypes_are_not_truncated(small):
    """An integer first frame (read from an integer file) does not truncate the others: the common dtype."""
    from indreg.forward.time_series import as_time_series

    domain, ops, template, data = small
    frames = [torch.round(data[0] * 10).to(torch.int32), data[1] * 10 + 0.4]
    _, stacked = as_time_series(ops, frames)
    assert stacked.dtype == torch.float64
    torch.testing.assert_close(stacked[1], frames[1])


# ---------------------------------------------------------------------------------------------------- runs
def test_known_template_recovers_motion():
    """The breathing phantom at 32^2 (6 frames, 4 angles each, noise-free): the frames get closer to the truth
    than the template, the recovered phi_{t_k,0} closer to the true motion than the identity."""
    d = dynamic.acquisition(32, frames=6, per_frame=4, det_count=46, snr_db=60.0)
    r = indreg.register(d.template, list(d.data), d.operators, model="spatiotemporal", times=d.times, num_steps=6,
                        max_iter=40, sigma=3.0, gamma=1e-5, step_size=0.05)
    err = lambda frames: float(sum((f - g).norm() for f, g in zip(frames, d.frames)))   # noqa: E731
    assert r.status == "completed" and r.frames.shape == (6, 32, 32)
    assert err(r.frames) < 0.8 * err(d.template.expand(6, 32, 32))
    p = r.problem
    est = torch.stack([p.deformation_field(p.velocity(r.momentum) * (torch.arange(7) <= j).reshape(-1, 1, 1, 1))
                       for j in p.indices]) - p.domain.points(torch.float64)
    assert float((est - d.motion).norm(dim=1).mean()) < 0.8 * float(d.motion.norm(dim=1).mean())


@pytest.mark.parametrize("update", ["intertwined", "joint"])
def test_unknown_template_runs(small, update):
    domain, ops, template, data = small
    r = indreg.register(None, list(data), ops, model="spatiotemporal", times=[0.5, 1.0], num_steps=4, max_iter=10,
                        template_update=update, template_steps=3, registration_steps=2, sigma=3.0)
    assert r.template.shape == template.shape and r.frames.shape == (2, 16, 16)
    assert r.objective < 0.5 * r.history[0]["objective"] and r.history[0]["template_step_size"] > 0
