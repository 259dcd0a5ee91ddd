"""The tilt-axis angle from the stack's moment conditions (indreg.alignment.moments): the conditions hold to rounding on
an exact series at its true angle, the estimate on series turned and shifted by scipy, the warning on a specimen
that looks alike at every turn, one-line errors."""
import math

import numpy as np
import pytest
from scipy import ndimage

from indreg.alignment.moments import MAX_SE_DEG, binned, condition_misfit, estimate_axis_angle

SIZE = 32
THETA = np.radians(np.arange(-60, 60.1, 6.0))


def blobs(count: int, seed: int, reach: float = 8.0, widths: tuple = (1.5, 2.5)) -> tuple:
    """``count`` Gaussian blobs: centres ``(x, y, z)`` (px; x across the axis, y along it, z along the beam at tilt
    0) within ``reach`` px of the axis' point, widths within ``widths`` px, heights 0.5 - 1."""
    gen = np.random.default_rng(seed)
    return gen.uniform(-reach, reach, (count, 3)), gen.uniform(*widths, count), gen.uniform(0.5, 1, count)


def exact_series(specimen: tuple, alpha_deg: float, shifts: np.ndarray, size: int = SIZE) -> np.ndarray:
    """The blobs' projections ``(tilts, rows, columns)``, analytic: blob ``j`` at tilt ``theta`` is a 2D Gaussian at
    ``(x cos theta + z sin theta, y)``, seen at the detector point ``R(alpha) q + shift`` (``shifts`` ``(tilts,
    2)``: across, along, in the detector's frame)."""
    centres, widths, heights = specimen
    r = np.arange(size) - (size - 1) / 2
    t, s = np.meshgrid(r, r, indexing="ij")
    a = math.radians(alpha_deg)
    out = np.zeros((len(THETA), size, size))
    for k, th in enumerate(THETA):
        ps, pt = s - shifts[k, 0], t - shifts[k, 1]
        u, v = math.cos(a) * ps + math.sin(a) * pt, -math.sin(a) * ps + math.cos(a) * pt
        for (x, y, z), w, h in zip(centres, widths, heights):
            uj = x * math.cos(th) + z * math.sin(th)
            out[k] += h * w * np.exp(-((u - uj) ** 2 + (v - y) ** 2) / (2 * w * w))
    return out


def turned_by_scipy(stack: np.ndarray, alpha_deg: float, shifts: np.ndarray, noise: float, seed: int) -> np.ndarray:
    """Every image turned about its centre so that the axis lies at ``alpha_deg`` (indreg's angle:
    ``scipy.ndimage.rotate`` by ``-alpha_deg``), shifted (cubic), plus Gaussian noise of ``noise`` times the largest
    datum: a series indreg's operators did not make."""
    out = np.stack([ndimage.shift(ndimage.rotate(img, -alpha_deg, reshape=False, order=3), (d[1], d[0]), order=3)
                    for img, d in zip(stack, shifts)])
    return out + noise * np.abs(out).max() * np.random.default_rng(seed).standard_normal(out.shape)


def random_shifts(seed: int, largest: float = 2.0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-largest, largest, (len(THETA), 2))


def test_conditions_hold_to_rounding_at_the_true_angle():
    """Blobs whose every projection lies within the detector and within the flat part of the window along the axis
    (7 widths), sampled finely enough that the pixel sums are the integrals."""
    specimen, shifts, alpha = blobs(6, 0, reach=6.0, widths=(1.5, 1.5)), random_shifts(1), 2.0
    stack = exact_series(specimen, alpha, shifts, size=64)
    a = math.radians(alpha)
    frame = np.stack([math.cos(a) * shifts[:, 0] + math.sin(a) * shifts[:, 1],
                      -math.sin(a) * shifts[:, 0] + math.cos(a) * shifts[:, 1]], 1)   # the shifts in the axis' frame
    exact = condition_misfit(stack, THETA, alpha, frame)
    assert exact < 1e-10
    assert condition_misfit(stack, THETA, alpha + 1.0, frame) > 1e4 * exact
    assert condition_misfit(stack, THETA, alpha, frame + [0.3, 0.0]) > 1e4 * exact


@pytest.mark.parametrize("alpha", [-3.0, 1.5])
def test_estimate_on_a_series_turned_by_scipy(alpha):
    shifts = random_shifts(2)
    clean = exact_series(blobs(12, 3), 0.0, np.zeros_like(shifts))
    e = estimate_axis_angle(turned_by_scipy(clean, alpha, shifts, 0.01, 4), THETA)
    assert abs(e.angle_deg - alpha) < 0.2
    assert e.determined and e.se_deg <= MAX_SE_DEG


def test_estimate_with_a_scale_per_tilt():
    """Every tilt's intensity scaled (an exposure that grows with the path length, and 10 % at random): the scales
    are fitted with the shifts, so the angle stays right and the scales come back; with every scale held at 1 the
    conditions misfit (chi-square per degree of freedom)."""
    alpha, shifts = -3.0, random_shifts(2)
    exposure = np.random.default_rng(7).uniform(0.9, 1.1, len(THETA)) / np.cos(THETA) ** 0.5
    clean = exact_series(blobs(12, 3), 0.0, np.zeros_like(shifts)) * exposure[:, None, None]
    stack = turned_by_scipy(clean, alpha, shifts, 0.01, 4)
    e = estimate_axis_angle(stack, THETA)
    assert abs(e.angle_deg - alpha) < 0.2 and e.determined
    used = e.tilts_used
    assert np.abs(e.scales[used] - exposure[used] / exposure[used].mean()).max() < 0.03
    held = estimate_axis_angle(stack, THETA, scales=False)
    assert held.scales is None and held.chi2_per_dof > 3 * e.chi2_per_dof


def test_binned_keeps_the_centre_and_the_counts_per_pixel():
    stack = np.random.default_rng(0).standard_normal((3, 11, 9))
    b = binned(stack, 2)
    assert b.shape == (3, 5, 4)
    assert np.allclose(b[:, 0, 0], stack[:, 0:2, 0:2].mean(axis=(1, 2)))       # one row and one column left out at
    assert np.allclose(b[:, -1, -1], stack[:, 8:10, 6:8].mean(axis=(1, 2)))     # the end: (11 - 10) // 2 = 0 before
    assert binned(stack, 1) is stack


def test_a_large_stack_is_binned_for_the_estimate():
    """A 64-pixel series estimated within a 32-pixel bound: binned by 2, the angle as from the full stack's
    specimen, the shifts given back in the stack's own pixels."""
    alpha, shifts = -3.0, 2 * random_shifts(2)
    specimen = blobs(12, 3, reach=16.0, widths=(3.0, 5.0))
    stack = turned_by_scipy(exact_series(specimen, 0.0, np.zeros_like(shifts), size=64), alpha, shifts, 0.01, 4)
    e = estimate_axis_angle(stack, THETA, max_pixels=32)
    assert e.binning == 2 and "binned by 2" in e.describe()
    assert abs(e.angle_deg - alpha) < 0.2 and e.determined
    a = math.radians(alpha)
    frame = np.stack([math.cos(a) * shifts[:, 0] + math.sin(a) * shifts[:, 1],
                      -math.sin(a) * shifts[:, 0] + math.cos(a) * shifts[:, 1]], 1)
    along = e.shifts_px[e.tilts_used, 1] - frame[e.tilts_used, 1]
    assert np.sqrt(((along - along.mean()) ** 2).mean()) < 0.1      # along the axis, less the common offset (px)


def test_the_shifts_derivatives_are_the_transforms_finite_differences():
    """The Gauss-Newton step's ``dG/dc`` and ``dG/dd`` (one phase for every tilt, the tilt's shift along the axis a
    factor of its own) against central differences of ``G``; the noise's standard deviations against the direct
    sums ``sigma^2 sum (u^n w)^2 cos^2 / sin^2``."""
    from indreg.alignment.moments import _prepare, _transforms, _window

    stack = turned_by_scipy(exact_series(blobs(12, 3), 0.0, np.zeros((len(THETA), 2))), 1.0, random_shifts(2), 0.01, 4)
    S, _ = _prepare(stack, THETA, 0.25, 1.0, 10.0, None, 2)
    gen = np.random.default_rng(1)
    c, d, alpha, h = gen.uniform(-1, 1, len(S.theta)), gen.uniform(-1, 1, len(S.theta)), 0.02, 1e-5
    G, sd, dG_dc, dG_dd = _transforms(S, alpha, c, d, derivatives=True)
    for k in (0, 7, len(c) - 1):
        e = np.zeros_like(c)
        e[k] = h
        fd_c = (_transforms(S, alpha, c + e, d)[0] - _transforms(S, alpha, c - e, d)[0]) / (2 * h)
        fd_d = (_transforms(S, alpha, c, d + e)[0] - _transforms(S, alpha, c, d - e)[0]) / (2 * h)
        assert np.abs(fd_c[k] - dG_dc[k]).max() < 1e-6 * np.abs(dG_dc[k]).max()
        assert np.abs(fd_d[k] - dG_dd[k]).max() < 1e-6 * np.abs(dG_dd[k]).max()
    u = (math.cos(alpha) * S.s + math.sin(alpha) * S.t)[None] - c[:, None]
    v = (-math.sin(alpha) * S.s + math.cos(alpha) * S.t)[None] - d[:, None]
    w = _window(v, S.half, S.taper)[0] * S.mask
    x = -2 * np.pi * v[..., None] * S.freqs
    for n in range(3):
        basis2 = (u ** n * w)[..., None] ** 2
        assert np.allclose(sd[0, :, n], S.sigma * np.sqrt((basis2 * np.cos(x) ** 2).sum(1)), rtol=1e-9)
        assert np.allclose(sd[1, :, n], S.sigma * np.sqrt((basis2 * np.sin(x) ** 2).sum(1)), rtol=1e-9, atol=1e-12)


def test_a_round_specimen_is_not_determined():
    """A ball on the axis looks alike at every turn of the axis: the criterion is flat."""
    ball = (np.zeros((1, 3)), np.array([4.0]), np.array([1.0]))
    stack = turned_by_scipy(exact_series(ball, 0.0, np.zeros((len(THETA), 2))), 2.0, random_shifts(5), 0.01, 6)
    e = estimate_axis_angle(stack, THETA)
    assert not e.determined and e.se_deg > MAX_SE_DEG
    assert "not determined" in e.describe()


def test_bad_input_is_one_line():
    with pytest.raises(ValueError, match="stack must be"):
        estimate_axis_angle(np.zeros((4, 8)), THETA[:4])
    with pytest.raises(ValueError, match="tilt_angles has"):
        estimate_axis_angle(np.zeros((5, 16, 16)), THETA[:4])
    with pytest.raises(ValueError, match="at least 6 tilts"):
        estimate_axis_angle(np.ones((len(THETA), 16, 16)), THETA)


def register_turned(specimen: tuple, alpha: float, caplog, **options):
    """``indreg.register(..., align="shifts+axis")`` (one iteration) on the volume of ``specimen``'s blobs
    projected by indreg's ``TiltSeriesTransform`` (32^3, the tilts of ``THETA``), every image turned by scipy so that
    the axis lies at ``alpha``, shifted and with 1 % noise; the template is the volume itself."""
    import torch

    import indreg
    from indreg import ImageDomain
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform

    domain = ImageDomain.paper(SIZE, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 6, det_count=SIZE, det_min=-16., det_max=16.))
    assert np.allclose(T.geometry.angles.numpy(), THETA)
    x, y, z = torch.meshgrid(*domain.axes(), indexing="ij")
    f = sum(h * torch.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (2 * w * w))
            for c, w, h in zip(*specimen))
    g = torch.from_numpy(turned_by_scipy(T(f).numpy(), alpha, random_shifts(2), 0.01, 4))
    with caplog.at_level("INFO", logger="indreg"):
        return indreg.register(f, g, T, align="shifts+axis", num_steps=2, max_iter=1, sigma=3.0, **options)


@pytest.mark.slow
@pytest.mark.parametrize("options", [{}, {"template_scale": "auto"}], ids=["plain", "scale-fitted"])
def test_register_holds_the_angle_from_the_stack(caplog, options):
    """``align="shifts+axis"`` takes the angle from the stack before the fit and holds it (a series turned by
    scipy, as a microscope's tilted axis is), also through the template's scale fitted with the alignment (which
    comes first and must not fit the angle itself); the summary says where it came from."""
    r = register_turned(blobs(12, 3), -3.0, caplog, **options)
    assert r.alignment["axis_angle_source"] == "stack" and r.alignment["axis_angle_determined"] is True
    assert abs(r.alignment["axis_angle_deg"] + 3.0) < 0.2
    held, stack = r.alignment["axis_angle_deg"], r.alignment["axis_angle_stack_deg"]
    assert held == pytest.approx(stack, rel=0, abs=1e-9)        # held through degrees -> radians -> degrees
    assert any("moment conditions" in m for m in caplog.messages)
    assert any(m.startswith("tilt-axis angle from the stack's moment conditions: estimating (") for m in caplog.messages)


@pytest.mark.slow
def test_register_warns_when_the_stack_does_not_determine_the_angle(caplog):
    """A ball on the axis: the stack cannot tell the angle, the run says so in the words of the issue, holds the
    stack's estimate with its standard error (the fit would wander along the valley) and reports it as not
    determined."""
    r = register_turned((np.zeros((1, 3)), np.array([4.0]), np.array([1.0])), 2.0, caplog)
    a = r.alignment
    assert a["axis_angle_determined"] is False
    if a["axis_angle_stack_se_deg"] is None:        # a flat criterion: the given angle, s.e. inf
        assert a["axis_angle_source"] == "given" and a["axis_angle_deg"] == 0.0 and a["axis_angle_se_deg"] is None
    else:
        assert a["axis_angle_source"] == "stack (not determined)"
        assert a["axis_angle_deg"] == pytest.approx(a["axis_angle_stack_deg"], abs=1e-12)
        assert a["axis_angle_se_deg"] == a["axis_angle_stack_se_deg"] > 0.2
    assert any("tilt-axis angle not determined by the data (s.e." in m for m in caplog.messages)


def test_register_warns_when_too_few_tilts_tell_the_angle(caplog):
    """Five tilts (fewer than ``MIN_TILTS``): the stack's conditions cannot be used, the run says why in the same
    words as for a flat criterion, and the angle the fit ends at is reported as not determined, whatever its own
    standard error."""
    import torch

    import indreg
    from indreg import ImageDomain
    from indreg.alignment.moments import MIN_TILTS
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform

    domain = ImageDomain.paper(SIZE, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-24, 24, 12, det_count=SIZE, det_min=-16., det_max=16.))
    assert T.range_shape[0] < MIN_TILTS
    x, y, z = torch.meshgrid(*domain.axes(), indexing="ij")
    f = sum(h * torch.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (2 * w * w))
            for c, w, h in zip(*blobs(12, 3)))
    g = torch.from_numpy(turned_by_scipy(T(f).numpy(), -2.0, random_shifts(2)[:T.range_shape[0]], 0.01, 4))
    with caplog.at_level("INFO", logger="indreg"):
        r = indreg.register(f, g, T, align="shifts+axis", num_steps=2, max_iter=1, sigma=3.0)
    assert r.alignment["axis_angle_source"] == "given" and r.alignment["axis_angle_determined"] is False
    assert r.alignment["axis_angle_deg"] == 0.0 and r.alignment["axis_angle_se_deg"] is None   # held, s.e. inf
    assert r.alignment["axis_angle_stack_deg"] is None
    assert any(f"tilt-axis angle not determined by the data (the tilt-axis angle needs at least {MIN_TILTS} tilts"
               in m for m in caplog.messages)
