"""Intensities in, line integrals out (indreg.units.transmission): the -ln round trip, I0 from the frames' vacuum (exposure
per frame) and from the slab law on a synthetic stack, an exposure cos^-n found where the data say so, a given
exposure, bad input, and a registration given intensities against one given line integrals."""
import math

import numpy as np
import pytest
import torch

import indreg
from indreg import ImageDomain, ParallelBeamGeometry, RayTransform, phantoms
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.forward.wide_box import wide_box
from indreg.units.transmission import NONPOSITIVE, line_integrals

TILTS = np.arange(-60.0, 60.1, 3.0)


def compact_lines():
    domain = ImageDomain.paper(32)
    T = RayTransform(domain, ParallelBeamGeometry(det_count=48, det_min=-24.0, det_max=24.0, angles=TILTS,
                                                  angle_unit="deg"))
    return 0.05 * T(phantoms.get("v", domain).double()), T


def slab_stack(mu=0.05, seed=0):
    """Line integrals ``(tilts, rows, columns)`` of a slab 6 thick, three times wider than the detector, with blobs
    (a 3D tilt series, tilt axis y, through indreg's wide box)."""
    domain = ImageDomain((32, 4, 12), (-8.0, -0.5, -3.0), (8.0, 0.5, 3.0))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry(TILTS, 32, -8.0, 8.0, angle_unit="deg"))
    box = wide_box(T)
    x, _, z = box.domain.points()
    gen = torch.Generator().manual_seed(seed)
    f = torch.ones(box.domain.shape, dtype=torch.float64)
    for cx in torch.linspace(-20, 20, 7):
        cx = float(cx) + 2 * float(torch.rand(1, generator=gen))
        f = f + 0.5 * (((x - cx) / 1.5) ** 2 + (z / 1.0) ** 2 <= 1).double()
    return mu * box.widen(T)(f), T


def test_round_trip_with_a_given_i0():
    p, _ = compact_lines()
    I = 250.0 * torch.exp(-p)
    q, t = line_integrals(I, None, 250.0)
    torch.testing.assert_close(q, p, rtol=0, atol=1e-12)
    assert t.how.startswith("given") and t.raised == 0
    torch.testing.assert_close(-torch.log(I / torch.as_tensor(t.i0)[:, None]), q)


def test_i0_from_the_frames_vacuum_follows_the_exposure_frame_by_frame():
    p, T = compact_lines()
    theta = T.geometry.angles
    exposure = (1.0 / torch.cos(theta))[:, None]          # SerialEM's exposure scaled with 1 / cos
    I = 300.0 * exposure * torch.exp(-p)
    q, t = line_integrals(I, theta.numpy())
    torch.testing.assert_close(q, p, rtol=0, atol=1e-4)     # a border with a trace of the object at a few tilts
    assert "vacuum" in t.how and t.i0 == pytest.approx(300.0 / np.cos(theta.numpy()), rel=1e-4)


def test_i0_from_the_slab_law_on_a_synthetic_stack():
    """No vacuum in the frame: I0 from -ln<I> = a / cos(theta - theta0) + b, to 1 % (noise-free) and 2 % (counted at
    400 per pixel, Poisson, 128 pixels a frame; 4 % at 40)."""
    p, T = slab_stack()
    theta = T.geometry.angles.numpy()
    for counts, tol in ((None, 0.01), (400.0, 0.02)):
        lam = 500.0 * torch.exp(-p) if counts is None else counts * torch.exp(-p)
        I = lam if counts is None else torch.poisson(lam, generator=torch.Generator().manual_seed(1))
        q, t = line_integrals(I, theta)
        assert "slab law" in t.how and t.exposure_power is None
        assert float(np.median(t.i0)) == pytest.approx(500.0 if counts is None else counts, rel=tol)
        assert t.law.a == pytest.approx(float(p.mean(dim=(1, 2))[len(theta) // 2]), rel=0.1)   # mu t at 0 degrees


def test_an_exposure_cos_power_is_found_where_the_data_say_so():
    """The slab recorded with exposure cos^-1: the plain law cannot fit (the means fall with the tilt), the one with
    the exposure finds n (roughly: 1 / cos and ln cos are nearly collinear) and I0; given, the exposure is exact."""
    p, T = slab_stack()
    theta = T.geometry.angles.numpy()
    exposure = torch.from_numpy(1.0 / np.cos(theta))[:, None, None]
    I = 200.0 * exposure * torch.exp(-p)
    q, t = line_integrals(I, theta)
    assert t.exposure_power == pytest.approx(1.0, abs=0.15) and "exposure cos^-n" in t.how
    assert float(np.median(t.i0 * np.cos(theta))) == pytest.approx(200.0, rel=0.1)
    with pytest.raises(ValueError, match=r"transmission='auto': the frames show no vacuum"):
        line_integrals(I, theta, exposure=None)
    q, t = line_integrals(I, theta, exposure=exposure.reshape(-1).numpy())   # the acquisition's exposure, given
    assert t.exposure_power is None and "given exposure" in t.how
    assert float(np.median(t.i0 * np.cos(theta))) == pytest.approx(200.0, rel=0.01)


def test_bad_input_is_one_line_naming_the_option():
    p, T = compact_lines()
    I = torch.exp(-p)
    I[0, :30] = -1.0   # 1.5 %
    with pytest.raises(ValueError, match=r"^transmission: .* % of the data are <= 0, which intensities cannot be"):
        line_integrals(I, None, label="transmission")
    few = torch.exp(-p)
    few[0, 0] = 0.0                        # a counted frame's empty pixel: raised, counted
    assert few.numel() * NONPOSITIVE > 1
    _, t = line_integrals(few, None, 1.0)
    assert t.raised == 1 and t.floor > 0
    with pytest.raises(ValueError, match=r"transmission must be None, 'auto' or a positive number"):
        line_integrals(I.abs() + 1, None, -2.0)
    lines, _ = slab_stack()
    with pytest.raises(ValueError, match=r"transmission='auto' needs vacuum at the detector's border or the tilt"):
        line_integrals(torch.exp(-lines), None)
    with pytest.raises(ValueError, match=r"exposure must be 41 positive numbers"):
        line_integrals(torch.exp(-lines), TILTS * math.pi / 180, exposure=[1.0, 2.0])


def test_register_given_intensities_matches_the_run_on_line_integrals():
    domain = ImageDomain.paper(32)
    T = RayTransform(domain, ParallelBeamGeometry.paper(10, 46))
    template, target = phantoms.get("j", domain).double(), phantoms.get("v", domain).double()
    p = T(target)
    options = dict(max_iter=4, num_steps=4, sigma=6.0)
    ref = indreg.register(template, p, T, **options)
    run = indreg.register(template, 80.0 * torch.exp(-p), T, transmission="auto", **options)
    assert run.units.transmission.startswith("the vacuum") and run.units.i0 == pytest.approx([80.0] * 10, rel=1e-9)
    torch.testing.assert_close(run.deformed, ref.deformed, rtol=0, atol=1e-8)
    assert run.units.apply(None, 80.0 * torch.exp(-p))[1] == pytest.approx(p, abs=1e-10)
    with pytest.raises(ValueError, match="transmission must be None, 'auto' or a finite number > 0"):
        indreg.register(template, p, T, transmission="yes", max_iter=0)
