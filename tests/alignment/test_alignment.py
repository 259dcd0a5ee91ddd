"""Alignment in the fit: the shifted / rotated data model T_s (adjoint, derivatives, analytic shifts), the
estimation of shifts and the tilt-axis angle on exact data, the joint fit through indreg.register, and errors."""
import math

import numpy as np
import pytest
import torch

import indreg
from indreg import ImageDomain, phantoms
from indreg.alignment import (MAX_ANGLE_SE_DEG, aligned, angle_uncertainty, coarse_shifts, estimate, fit_scale, gauge,
                              plot_shifts, projection_matching)
from indreg.forward import (FanBeamGeometry, ParallelBeamGeometry, RayTransform, TiltSeriesGeometry,
                            TiltSeriesTransform)
from indreg.forward.operator import adjointness
from indreg.alignment.operator import AlignedOperator

F64 = torch.float64


@pytest.fixture(scope="module")
def series():
    domain = ImageDomain.paper(24, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 3, det_count=24, det_min=-16., det_max=16.))
    return T, phantoms.get("shepp_logan_3d", domain).double()


def _sinogram(n=48, angles=60):
    domain = ImageDomain.paper(n)
    return RayTransform(domain, ParallelBeamGeometry.paper(angles, n))


def _random_shifts(T, scale, seed):
    """Random shifts in the gauge, at most ``scale`` px per component."""
    op = AlignedOperator(T)
    gen = torch.Generator().manual_seed(seed)
    s = gauge(op, torch.rand(op.shifts.shape, generator=gen, dtype=F64) * 2 - 1)
    return s * (scale / s.abs().amax(dim=0))


@pytest.mark.parametrize("interpolation,edge", [("cubic", "nearest"), ("cubic", "zero"), ("linear", "nearest"),
                                                ("linear", "zero")])
def test_adjointness_2d_and_3d(series, interpolation, edge):
    for T in (series[0], _sinogram(16, 10)):
        tilt = len(T.range_shape) == 3
        op = AlignedOperator(T, _random_shifts(T, 3.0, 1), 0.04 if tilt else 0.0, interpolation, edge)
        y = torch.randn(T.range_shape, dtype=F64)
        assert not torch.allclose(op.warp(y, op.shifts, op.angle), y)   # the model does move the data
        assert adjointness(op) < 1e-13
        assert adjointness(op, seed=3) < 1e-13


def test_integer_shift_moves_columns_and_rows(series):
    """An integer shift moves the image exactly with either interpolation; beyond the detector the nearest edge
    pixel (edge='nearest', the default) or zero."""
    T = series[0]
    y = torch.randn(T.range_shape, dtype=F64)
    s = torch.zeros(T.geometry.num_tilts, 2, dtype=F64)
    zero = torch.tensor(0.0, dtype=F64)
    for interpolation in ("cubic", "linear"):
        op, zeros = AlignedOperator(T, interpolation=interpolation), AlignedOperator(T, interpolation=interpolation,
                                                                                     edge="zero")
        assert torch.allclose(op.warp(y, s, zero), y, atol=1e-12)
        moved = s.clone()
        moved[:, 0], moved[:, 1] = 2, -1            # content moves +2 columns, -1 row
        out, out0 = op.warp(y, moved, zero), zeros.warp(y, moved, zero)
        for o in (out, out0):
            assert torch.allclose(o[:, :-1, 2:], y[:, 1:, :-2], atol=1e-12)
        assert torch.allclose(out[:, :-1, :2], y[:, 1:, :1].expand(-1, -1, 2), atol=1e-12)   # the edge column
        assert torch.allclose(out[:, -1, 2:], y[:, -1, :-2], atol=1e-12)                     # the edge row
        assert float(out0[:, :, :2].abs().max()) < 1e-12 and float(out0[:, -1].abs().max()) < 1e-12


def test_cubic_interpolation_is_exact_for_quadratics_and_sharper_than_linear():
    """Keys' kernel reproduces a quadratic profile at any fractional shift (linear interpolation does not), and
    shifts a sinusoid of 6 pixels a period by half a pixel to within 3 % of its amplitude (bilinear: 13 %)."""
    domain = ImageDomain((8, 8, 8), (-4., -4., -4.), (4., 4., 4.))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-30, 30, 30, det_count=16, det_min=-8., det_max=8.))
    cubic, linear = AlignedOperator(T, interpolation="cubic"), AlignedOperator(T)
    col = torch.arange(16, dtype=F64)
    y = (0.3 * col ** 2 - 2 * col + 1).expand(T.range_shape).clone()
    s = torch.tensor([[0.37, 0.0], [-0.5, 0.0], [1.25, 0.0]], dtype=F64)
    zero = torch.tensor(0.0, dtype=F64)
    expected = 0.3 * (col - s[:, :1]) ** 2 - 2 * (col - s[:, :1]) + 1          # y(p - s), rows alike
    inner = slice(3, -3)                                                          # off the edges
    assert torch.allclose(cubic.warp(y, s, zero)[..., inner], expected.unsqueeze(1).expand(3, 8, 16)[..., inner])
    assert not torch.allclose(linear.warp(y, s, zero)[..., inner], expected.unsqueeze(1).expand(3, 8, 16)[..., inner])
    wave = torch.sin(2 * math.pi * col / 6).expand(T.range_shape).clone()     # 6 pixels a period
    half = torch.tensor([[0.5, 0.0]] * 3, dtype=F64)
    moved = torch.sin(2 * math.pi * (col - 0.5) / 6)
    errors = [float((op.warp(wave, half, zero) - moved)[..., inner].abs().max()) for op in (cubic, linear)]
    assert errors[0] < 0.03 and errors[1] > 0.1, errors    # bilinear: the average of two neighbours, a blur
    with pytest.raises(ValueError, match="interpolation must be one of"):
        AlignedOperator(T, interpolation="spline")
    with pytest.raises(ValueError, match="edge must be one of"):
        AlignedOperator(T, edge="wrap")


def test_quarter_turn_rotates_square_detector():
    domain = ImageDomain((8, 8, 8), (-4., -4., -4.), (4., 4., 4.))   # unit cells, detector centred on the axis
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-30, 30, 30, det_count=8, det_min=-4., det_max=4.))
    op = AlignedOperator(T)
    y = torch.randn(T.range_shape, dtype=F64)
    out = op.warp(y, op.shifts, torch.tensor(math.pi / 2, dtype=F64))
    # (S y)(s, t) = y(R(-90deg)(s, t)) = y(t, -s): the image turned a quarter counter-clockwise in (s, t)
    assert torch.allclose(out, y.transpose(-1, -2).flip(-1), atol=1e-12)


@pytest.mark.parametrize("interpolation,edge", [pytest.param("cubic", "nearest", marks=pytest.mark.slow),
                                                ("linear", "zero")])
def test_gradcheck_in_image_shifts_and_angle(interpolation, edge):
    domain = ImageDomain((6, 5, 6), (-3., -2.5, -3.), (3., 2.5, 3.))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-45, 45, 45, det_count=7))
    op = AlignedOperator(T, interpolation=interpolation, edge=edge)
    gen = torch.Generator().manual_seed(0)
    f = torch.randn(domain.shape, generator=gen, dtype=F64, requires_grad=True)
    s = (torch.rand(op.num_projections, 2, generator=gen, dtype=F64) * 1.6 - 0.8 + 0.1).requires_grad_()
    a = torch.tensor(0.07, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(op.apply, (f, s, a))
    T2 = _sinogram(8, 5)
    op2 = AlignedOperator(T2, interpolation=interpolation, edge=edge)
    f2 = torch.randn(T2.domain.shape, generator=gen, dtype=F64, requires_grad=True)
    s2 = (torch.rand(5, 1, generator=gen, dtype=F64) * 3 - 1.3).requires_grad_()
    assert torch.autograd.gradcheck(lambda f, s: op2.apply(f, s, op2.angle), (f2, s2))


@pytest.mark.parametrize("interpolation", ["linear", pytest.param("cubic", marks=pytest.mark.slow)])
def test_recovers_shifts_and_axis_angle_3d(series, interpolation):
    T, f = series
    op, _ = aligned(T, "shifts+axis", interpolation=interpolation)
    true, angle = _random_shifts(T, 4.0, 0), torch.tensor(math.radians(2.0), dtype=F64)
    g = op.warp(T(f), true, angle)
    P = T(f)
    start = gauge(op, coarse_shifts(op, P, g))
    s, a, at_bound = estimate(op, P, g, start, torch.tensor(0.0, dtype=F64), axis=True, iterations=30)
    assert float((s - true).abs().max()) < 0.05
    assert abs(math.degrees(float(a)) - 2.0) < 0.05 and at_bound == 0


def test_recovers_shifts_2d():
    T = _sinogram()
    f = phantoms.get("shepp_logan", T.domain).double()
    op, _ = aligned(T, "shifts")
    true = _random_shifts(T, 6.0, 2)
    g = op.warp(T(f), true, op.angle)
    P = T(f)
    s, _, at_bound = estimate(op, P, g, gauge(op, coarse_shifts(op, P, g)), op.angle)
    assert float((s - true).abs().max()) < 0.05 and at_bound == 0


def test_axis_offset_over_a_limited_range_recovered_in_its_gauge():
    """A 3D series over +-40 degrees whose axis lies 2 px off the detector's middle, with drift and an object
    translation: on exact data the shifts in gauge 'translation' (the offset kept) and in 'none' (everything kept)
    come back to 0.05 px; the default gauge removes the constant, so over this range it misses the offset's part
    that no translation explains (a(1 - cos theta) and its least-squares share)."""
    domain = ImageDomain.paper(24, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-40, 40, 4, det_count=24, det_min=-16., det_max=16.))
    f = phantoms.get("shepp_logan_3d", domain).double()
    theta, zero = T.geometry.angles.double(), torch.tensor(0.0, dtype=F64)
    drift = _random_shifts(T, 1.5, 5)
    drift[:, 0] += 2.0 + 1.0 * torch.cos(theta) - 0.8 * torch.sin(theta)    # offset 2 px, a translation
    P = T(f)
    for kind in ("none", "translation"):
        op, _ = aligned(T, "shifts", gauge=kind)
        true = gauge(op, drift, kind)
        g = op.warp(P, true, zero)
        s, _, at_bound = estimate(op, P, g, gauge(op, coarse_shifts(op, P, g), kind), zero, iterations=30, kind=kind)
        assert float((s - true).abs().max()) < 0.05 and at_bound == 0, kind
        if kind == "translation":
            default, _ = aligned(T, "shifts")
            s0, _, _ = estimate(default, P, g, gauge(default, coarse_shifts(default, P, g)), zero, iterations=30)
            assert float((s0 - true).abs().max()) > 0.2
    with pytest.raises(ValueError, match="align_gauge must be one of"):
        aligned(T, "shifts", gauge="offset")
    with pytest.raises(ValueError, match="align_interpolation must be one of"):
        aligned(T, "shifts", interpolation="spline")


def test_projection_matching_recovers_shifts_without_a_template():
    """SIRT through the current shifts, re-fitted to its projection: from the misaligned data alone, the shifts
    come back to a fraction of a pixel, and the SIRT residual falls from round to round."""
    T = _sinogram(48, 60)
    f = phantoms.get("shepp_logan", T.domain).double()
    true = _random_shifts(T, 4.0, 3)
    g = AlignedOperator(T).warp(T(f), true, torch.zeros((), dtype=F64))
    op, x, records = projection_matching(T, g, rounds=4, iters=30)
    error = (op.shifts - true).pow(2).mean().sqrt()
    assert float(error) < 0.2 and x.shape == T.domain.shape
    assert records[-1][0] < 0.5 * records[0][0]
    with pytest.raises(ValueError, match="projection_matching needs mode"):
        projection_matching(T, g, mode="none")


@pytest.mark.slow
def test_register_with_shifts_recovers_them_and_the_unshifted_ssim(tmp_path):
    T = _sinogram(48, 60)
    template = phantoms.get("shepp_logan_template", T.domain).double()
    target = phantoms.get("shepp_logan", T.domain).double()
    true = _random_shifts(T, 5.0, 4)
    data = AlignedOperator(T, true)(target)
    options = dict(num_steps=6, max_iter=100, sigma=3.0, gamma=1e-7, step_size=0.02, target=target,
                   interpolation="reinterpolate")   # as sized (compose: 0.777 aligned, 0.789 unshifted)
    plain = indreg.register(template, T(target), T, **options)
    r = indreg.register(template, data, T, align="shifts", **options)
    shifts = torch.tensor(r.alignment["shifts_px"], dtype=F64)
    rms = float((shifts - true).pow(2).mean().sqrt())
    assert rms < 0.3, rms
    assert r.alignment["estimates"] == 10 and r.alignment["mode"] == "shifts"
    assert r.alignment["gauge"] == "offset+translation" and r.alignment["interpolation"] == "linear"
    assert r.ssim > plain.ssim - 0.01, (r.ssim, plain.ssim)
    unaligned = indreg.register(template, data, T, **options)
    assert unaligned.ssim < r.ssim - 0.01
    plot_shifts(r.alignment, tmp_path / "alignment.png")
    assert (tmp_path / "alignment.png").stat().st_size > 0


def _cost_at(op, P, g, c, s, a) -> float:
    return float((c * op.warp(P, s, a) - g).pow(2).sum())


@pytest.mark.parametrize("kind", ["offset+translation", "none"])
def test_fit_scale_recovers_the_scale_of_drifted_data(kind):
    """A template in other units (x 0.5) and data that drift by up to 6 px: the plain least-squares factor
    <T I, g> / <T I, T I> is biased low by the drift (more than 5 %), the fit through the alignment recovers 2 and
    the shifts; every round lowers ||c S_s T I - g|| (alternating minimisation) and op is left as it was."""
    T = _sinogram(48, 60)
    f = phantoms.get("shepp_logan", T.domain).double()
    op, state = aligned(T, "shifts", gauge=kind)
    true = _random_shifts(T, 6.0, 1)
    g = op.warp(T(f), true, op.angle)
    plain = indreg.units.compare_units(0.5 * f, g, T)[1]
    c, s, a, rounds = fit_scale(op, state, 0.5 * f, g)
    assert plain < 0.95 * 2 and c == pytest.approx(2.0, rel=1e-4), (plain, c)
    assert float((s - true).abs().max()) < 0.01 and 1 <= rounds < 8
    assert float(op.shifts.abs().max()) == 0 and not state.started
    costs = [_cost_at(op, T(0.5 * f), g, *fit_scale(op, state, 0.5 * f, g, rounds=k)[:3]) for k in (0, 1, 2)]
    assert costs[0] > costs[1] >= costs[2], costs


def test_register_fits_template_scale_through_the_alignment():
    """register(template_scale='auto', align='shifts') on drifted data fits the template's factor through the
    alignment (the plain one kept as units.scale_fit_unaligned); without align, or with a given factor, the units
    are as before: the plain fit, no alignment of the scale."""
    T = _sinogram(32, 20)
    target = phantoms.get("shepp_logan", T.domain).double()
    data = AlignedOperator(T, _random_shifts(T, 4.0, 7))(target)
    options = dict(num_steps=2, max_iter=1, sigma=3.0)
    plain = indreg.units.compare_units(0.5 * target, data, T)[1]
    r = indreg.register(0.5 * target, data, T, align="shifts", template_scale="auto", **options)
    assert r.units.template_scale == pytest.approx(2.0, rel=1e-3) and r.units.scale_fit == r.units.template_scale
    assert r.units.scale_fit_unaligned == pytest.approx(plain, rel=1e-12) and plain < 1.9
    off = indreg.register(0.5 * target, data, T, template_scale="auto", **options)
    assert off.units.scale_fit == off.units.template_scale == pytest.approx(plain, rel=1e-12)
    assert math.isnan(off.units.scale_fit_unaligned)
    given = indreg.register(0.5 * target, data, T, align="shifts", template_scale=2.0, **options)
    assert given.units.scale_fit == pytest.approx(plain, rel=1e-12) and math.isnan(given.units.scale_fit_unaligned)


def test_errors(series):
    T = _sinogram(16, 10)
    data, template = torch.ones(T.range_shape), torch.zeros(T.domain.shape)
    with pytest.raises(ValueError, match="align must be one of 'none', 'shifts', 'shifts\\+axis', got 'axis'"):
        indreg.register(template, data, T, align="axis")
    with pytest.raises(ValueError, match="needs a 3D tilt series"):
        aligned(T, "shifts+axis")
    fan = RayTransform(T.domain, FanBeamGeometry.paper(10, 16) if hasattr(FanBeamGeometry, "paper") else
                       FanBeamGeometry(num_angles=10, det_count=16, src_radius=40.0, det_radius=40.0))
    with pytest.raises(TypeError, match="align='shifts': alignment needs a parallel-beam RayTransform"):
        aligned(fan, "shifts")
    with pytest.raises(ValueError, match="at least 4 projections, the data have 3"):
        aligned(_sinogram(16, 3), "shifts")
    with pytest.raises(ValueError, match="not 'fast'"):
        indreg.register(template, data, T, align="shifts", solver="fast", max_iter=1)


def test_app_writes_alignment_to_metrics_and_a_plot(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parents[1] / "experiments"))
    from experiment_helpers import FAST, run_app

    out = tmp_path / "run"
    m = run_app(FAST + ["data.align=shifts", "data.align_gauge=translation", "data.align_interpolation=cubic"], out)
    a = m["alignment"]
    assert a["mode"] == "shifts" and a["gauge"] == "translation" and a["interpolation"] == "cubic"
    assert a["estimates"] == 1
    assert len(a["shifts_px"]) == len(a["tilt_angles_deg"]) == 10
    assert (out / "alignment.png").stat().st_size > 0
    assert "alignment" not in run_app(FAST, tmp_path / "plain")


@pytest.mark.slow
def test_app_resume_continues_the_alignment(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parents[1] / "experiments"))
    from experiment_helpers import FAST, run_app

    base = [o for o in FAST if not o.startswith("solver.max_iter")] + ["solver.max_iter=15", "data.align=shifts",
                                                                          "dtype=float64"]
    ref = run_app(base, tmp_path / "ref")
    out = tmp_path / "run"
    assert run_app(base + ["stop_after=12"], out)["status"] == "stopped"
    again = run_app(base + ["resume=true"], out)
    assert again["alignment"]["estimates"] == ref["alignment"]["estimates"] == 2
    assert torch.allclose(torch.tensor(again["alignment"]["shifts_px"]), torch.tensor(ref["alignment"]["shifts_px"]),
                          atol=1e-10)
    assert again["objective"] == pytest.approx(ref["objective"], rel=1e-10)


def test_holdout_and_lbfgs_with_alignment():
    T = _sinogram(32, 20)
    template = phantoms.get("shepp_logan_template", T.domain).double()
    target = phantoms.get("shepp_logan", T.domain).double()
    data = AlignedOperator(T, _random_shifts(T, 3.0, 5))(target)
    r = indreg.register(template, data, T, align="shifts", holdout=4, num_steps=4, max_iter=12, sigma=3.0)
    assert len(r.alignment["shifts_px"]) == 20 and r.alignment["estimates"] == 2 and r.holdout
    r = indreg.register(template, data, T, align="shifts", solver="lbfgs", num_steps=4, max_iter=12, sigma=3.0)
    assert r.status in ("completed", "converged") and r.alignment["estimates"] == 2


def test_shifts_beyond_the_bound_warn(caplog):
    T = _sinogram(32, 20)                       # bound: 0.25 * 32 = 8 px
    target = phantoms.get("shepp_logan", T.domain).double()
    data = AlignedOperator(T, _random_shifts(T, 12.0, 6))(target)
    with caplog.at_level("WARNING", logger="indreg"):
        r = indreg.register(target, data, T, align="shifts", num_steps=2, max_iter=1)
    assert r.alignment["at_bound"] > 0
    assert max(abs(s[0]) for s in r.alignment["shifts_px"]) == pytest.approx(8.0)
    assert any("at their bound" in m for m in caplog.messages)


@pytest.fixture(scope="module")
def band_limited():
    """A 32^3 Shepp-Logan blurred by one voxel (a band-limited specimen: a pixel-sharp one is aliased, and its
    turned images are not those of any interpolation, docs/alignment.md) and its tilt series over +-60 degrees."""
    from scipy import ndimage

    domain = ImageDomain.paper(32, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 6, det_count=32, det_min=-16., det_max=16.))
    f = torch.from_numpy(ndimage.gaussian_filter(phantoms.get("shepp_logan_3d", domain).double().numpy(), 1.0))
    return T, f


def _turned_by_scipy(P: torch.Tensor, angle: float, shifts: torch.Tensor, seed: int) -> torch.Tensor:
    """Every image of ``P`` turned about its centre as a microscope's tilted axis does (the axis at ``angle``
    degrees, indreg's convention: ``scipy.ndimage.rotate`` by ``-angle``), shifted (cubic), 2 % noise."""
    from scipy import ndimage

    out = torch.from_numpy(np.stack([ndimage.shift(ndimage.rotate(p, -angle, reshape=False, order=3),
                                                   (float(s[1]), float(s[0])), order=3)
                                     for p, s in zip(P.numpy(), shifts)]))
    gen = torch.Generator().manual_seed(seed)
    return out + 0.02 * out.abs().max() * torch.randn(out.shape, generator=gen, dtype=F64)


@pytest.mark.slow
@pytest.mark.parametrize("angle", [1.0, -3.0, 5.0])
def test_recovers_an_axis_turned_by_scipy(band_limited, angle):
    """Images turned and shifted by scipy, not by indreg's model: against the object's own projection the angle
    comes back within 0.2 degree (0.12 measured at +1 on these 21 tilts) and the shifts within 0.05 px RMS, and its
    standard error is below the limit."""
    T, f = band_limited
    true = _random_shifts(T, 3.0, 7)
    g = _turned_by_scipy(T(f), angle, true, 0)
    (op, _), P = aligned(T, "shifts+axis"), T(f)
    op.shifts, op.angle, at_bound = estimate(op, P, g, gauge(op, coarse_shifts(op, P, g)), op.angle, axis=True)
    assert abs(math.degrees(float(op.angle)) - angle) < 0.2 and at_bound == 0
    assert float((op.shifts - true).pow(2).mean().sqrt()) < 0.05
    assert angle_uncertainty(op, f, g) < MAX_ANGLE_SE_DEG


@pytest.mark.slow
def test_undetermined_axis_angle_warns(caplog):
    """A Gaussian ball on the tilt axis looks alike at every turn: the angle's standard error is above the limit,
    the summary says so and a warning names it."""
    domain = ImageDomain.paper(16, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 10, det_count=16, det_min=-16., det_max=16.))
    x, y, z = torch.meshgrid(*domain.axes(), indexing="ij")
    ball = torch.exp(-(x ** 2 + y ** 2 + z ** 2) / 30)
    g = _turned_by_scipy(T(ball), 3.0, _random_shifts(T, 2.0, 8), 1)
    with caplog.at_level("WARNING", logger="indreg"):
        r = indreg.register(ball, g, T, align="shifts+axis", num_steps=2, max_iter=1, sigma=3.0)
    assert r.alignment["axis_angle_determined"] is False
    assert r.alignment["axis_angle_se_deg"] is None or r.alignment["axis_angle_se_deg"] > MAX_ANGLE_SE_DEG
    assert any("not determined by the data" in m for m in caplog.messages)
