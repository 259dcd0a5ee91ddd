"""The wide box of a slab specimen (indreg.forward.wide_box): its width against the closed form, adjoint identities on
it, a parallelepiped whose projections are known analytically, the data term on the detector's pixels only,
padding and cropping, and bad input."""
import math

import pytest
import torch

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform
from indreg.forward import FanBeamGeometry, TiltSeriesGeometry, TiltSeriesTransform, sirt
from indreg.alignment.operator import AlignedOperator
from indreg.forward.wide_box import MAX_WIDTH, WideBox, slab_thickness, specimen_box, wide_box

TILTS = [-60.0, -37.0, -12.0, 0.0, 8.0, 33.0, 55.0]
SLAB = ImageDomain((40, 12), (-10.0, -3.0), (10.0, 3.0))       # a slab 20 wide, 6 thick, cells 0.5


def tilt_series_2d(domain=SLAB, tilts=TILTS):
    """Parallel beam, a detector exactly as wide as the box."""
    g = ParallelBeamGeometry(det_count=domain.shape[0], det_min=domain.min_pt[0], det_max=domain.max_pt[0],
                             angles=tilts, angle_unit="deg")
    return RayTransform(domain, g)


def test_width_is_the_closed_form_of_the_widest_tilt():
    """u reaches (W / 2 + (t / 2) |sin theta|) / |cos theta| at the widest tilt, rounded up to whole cells."""
    T = tilt_series_2d()
    box = wide_box(T)
    reach = max((10.0 + 3.0 * abs(math.sin(math.radians(a)))) / math.cos(math.radians(a)) for a in TILTS)
    h = SLAB.cell_sides[0]
    assert box.pad == ((math.ceil((reach - 10.0) / h),) * 2, (0, 0))
    assert box.domain.cell_sides == pytest.approx(SLAB.cell_sides, rel=1e-12)
    assert box.domain.max_pt[0] >= reach > box.domain.max_pt[0] - h
    assert not box.capped and box.thickness == pytest.approx(6.0)
    thin = wide_box(T, thickness=2.0)   # a thinner specimen needs less
    assert thin.pad[0][0] == math.ceil(((10.0 + abs(math.sin(math.radians(-60)))) / 0.5 - 10.0) / h - 1e-6)


def test_no_widening_for_an_object_inside_the_field_of_view():
    """A specimen whose extent is the detector's at tilt 0 only: its thickness and extent keep it in the box."""
    T = tilt_series_2d(tilts=[0.0])
    assert not wide_box(T).widened
    dom = ImageDomain((32, 32), (-8.0, -8.0), (8.0, 8.0))
    full = RayTransform(dom, ParallelBeamGeometry(det_count=48, det_min=-12.0, det_max=12.0, num_angles=18))
    assert not wide_box(full, extent=16.0).widened   # a square inside the detector's disc


def test_full_angle_scan_is_capped_or_bounded_by_the_extent():
    dom = ImageDomain((32, 32), (-8.0, -8.0), (8.0, 8.0))
    T = RayTransform(dom, ParallelBeamGeometry(det_count=32, det_min=-8.0, det_max=8.0, num_angles=18))
    capped = wide_box(T)
    assert capped.capped and capped.domain.extent[0] == pytest.approx(MAX_WIDTH * 16.0)
    disc = wide_box(T, thickness=24.0, extent=24.0)   # a 24 x 24 specimen: widened to it along both axes
    assert not disc.capped and disc.domain.extent == pytest.approx((24.0, 24.0))


def test_fan_beam_box_holds_every_crossing_of_the_specimen():
    dom = ImageDomain((32, 32), (-8.0, -8.0), (8.0, 8.0))
    g = FanBeamGeometry(24, 40, src_radius=40.0, det_radius=20.0, det_min=-15.0, det_max=15.0)
    T = RayTransform(dom, g)
    box = wide_box(T, thickness=20.0, extent=30.0)
    (u_lo, u_hi), (v_lo, v_hi), _ = specimen_box(T.geometry, dom, 20.0, 30.0)
    # brute force: points of the specimen on a ray reaching the detector, at one angle after another
    u, v = torch.meshgrid(torch.linspace(-15, 15, 301, dtype=torch.float64),
                          torch.linspace(-10, 10, 201, dtype=torch.float64), indexing="ij")
    seen_u, seen_v = [], []
    for beta in g.angles.tolist():
        c, s = math.cos(beta), math.sin(beta)
        depth = -s * u + c * v + g.src_radius
        along = (g.src_radius + g.det_radius) * (c * u + s * v) / depth
        hit = (depth > 0) & (along >= g.det_min) & (along <= g.det_max)
        seen_u.append(u[hit])
        seen_v.append(v[hit])
    su, sv = torch.cat(seen_u), torch.cat(seen_v)
    assert float(su.min()) >= u_lo - 1e-9 and float(su.max()) <= u_hi + 1e-9
    assert float(su.min()) - u_lo < 0.2 and u_hi - float(su.max()) < 0.2      # tight (grid step 0.1)
    assert float(sv.min()) >= v_lo - 1e-9 and float(sv.max()) <= v_hi + 1e-9
    assert box.domain.min_pt[0] <= u_lo + 1e-9 and box.domain.max_pt[1] >= v_hi - 1e-9


def _operators():
    dom = ImageDomain((16, 16), (-4.0, -4.0), (4.0, 4.0))
    fan = RayTransform(dom, FanBeamGeometry(20, 24, src_radius=20.0, det_radius=10.0, det_min=-6.0, det_max=6.0))
    vol = ImageDomain((12, 5, 4), (-3.0, -1.25, -1.0), (3.0, 1.25, 1.0))
    tilt = TiltSeriesTransform(vol, TiltSeriesGeometry(TILTS, 12, -3.0, 3.0, angle_unit="deg"))
    return {"parallel": (tilt_series_2d(), {}), "fan": (fan, {"thickness": 10.0, "extent": 12.0}),
            "tilt_series": (tilt, {})}


@pytest.mark.parametrize("kind", ["parallel", "fan", "tilt_series"])
def test_adjoint_identity_on_the_wide_box(kind):
    T, kw = _operators()[kind]
    box = wide_box(T, **kw)
    assert box.widened
    Tw = box.widen(T)
    assert tuple(Tw.range_shape) == tuple(T.range_shape)     # the detector's pixels, nothing more
    assert Tw.adjointness_test() < 1e-13
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(box.domain.shape, generator=gen, dtype=torch.float64)
    y = torch.randn(T.range_shape, generator=gen, dtype=torch.float64)
    lhs, rhs = Tw.inner_data(Tw(x), y), box.domain.inner(x, Tw.adjoint(y))
    assert float((lhs - rhs).abs()) <= 1e-12 * float(Tw.norm_data(Tw(x)) * Tw.norm_data(y))


@pytest.mark.parametrize("kind", ["parallel", "fan", "tilt_series"])
def test_data_term_on_the_detector_pixels_only(kind):
    """The field's image padded with zeros projects as on the given box; what lies off every detector ray is not
    seen; the pad and crop are each other's inverse on the field."""
    T, kw = _operators()[kind]
    box = wide_box(T, **kw)
    Tw = box.widen(T)
    gen = torch.Generator().manual_seed(2)
    f = torch.rand(T.domain.shape, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(Tw(box.pad_image(f, "zero")), T(f), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(box.crop(box.pad_image(f, "edge")), f, rtol=0, atol=0)
    seen = Tw.transpose(torch.ones(T.range_shape, dtype=torch.float64)) > 0   # cells some detector ray crosses
    unseen = torch.rand(box.domain.shape, generator=gen, dtype=torch.float64) * (~seen)
    assert float(Tw(unseen).abs().max()) == 0.0


def test_slab_projections_are_thickness_over_cosine_inside_the_field_of_view():
    """A parallelepiped slab of thickness t filling the wide box laterally: every detector pixel sees t / cos theta
    on the wide box; the detector-wide box loses the slab beyond its edges at high tilt."""
    dom = ImageDomain((64, 16), (-16.0, -4.0), (16.0, 4.0))
    T = tilt_series_2d(dom)
    box = wide_box(T)
    Tw = box.widen(T)
    slab = box.domain.zeros() + 1.0
    p = Tw(slab)
    expected = 8.0 / torch.cos(torch.deg2rad(torch.tensor(TILTS, dtype=torch.float64)))[:, None]
    torch.testing.assert_close(p, expected.expand_as(p), rtol=5e-3, atol=0)   # Joseph at the faces
    narrow = T(dom.zeros() + 1.0)
    assert float((narrow[0] / expected[0]).min()) < 0.55   # at -60 degrees the outer pixels see half of it or less


def test_sirt_on_the_wide_box_fits_slab_data():
    """Data of a slab wider than the detector: SIRT fits them on the wide box, not on the detector-wide one."""
    dom = ImageDomain((40, 10), (-10.0, -2.5), (10.0, 2.5))
    T = tilt_series_2d(dom)
    box = wide_box(T)
    Tw = box.widen(T)
    truth = box.domain.zeros() + 1.0
    truth[30:50, 3:6] += 1.5   # a feature outside the field of view, on the slab
    g = Tw(truth)
    _, wide = sirt(Tw, g, 60, nonneg=True)
    _, narrow = sirt(T, g, 60, nonneg=True)
    norm = float(T.norm_data(g))
    assert float(wide["data_residual"][-1]) / norm < 0.5 * float(narrow["data_residual"][-1]) / norm


def test_padding_modes():
    box = wide_box(tilt_series_2d())
    f = torch.arange(float(SLAB.shape[0] * SLAB.shape[1]), dtype=torch.float64).reshape(SLAB.shape)
    a, b = box.pad[0]
    edge, zero, level = (box.pad_image(f, m) for m in ("edge", "zero", "level"))
    torch.testing.assert_close(edge[:a], f[:1].expand(a, -1))
    torch.testing.assert_close(edge[-b:], f[-1:].expand(b, -1))
    assert float(zero[:a].abs().max()) == 0.0
    faces = torch.cat([f[0], f[-1]]).median()
    assert float((level[:a] - faces).abs().max()) == 0.0
    mask = box.field_mask()
    assert float(mask.sum()) == f.numel() and float(box.crop(mask).min()) == 1.0
    with pytest.raises(ValueError, match="template padding must be one of"):
        box.pad_image(f, "mirror")


def test_slab_thickness_from_a_template():
    dom = ImageDomain((20, 16), (-5.0, -4.0), (5.0, 4.0))   # cells 0.5
    f = dom.zeros()
    f[:, 5:11] = 1.0    # v in [-1.5, 1.5]
    assert slab_thickness(f, dom, 1) == pytest.approx(3.0)
    assert slab_thickness(dom.zeros() + 1.0, dom, 1) is None   # fills the box
    assert slab_thickness(dom.zeros(), dom, 1) is None


def test_aligned_operator_keeps_its_alignment_on_the_wide_box():
    vol = ImageDomain((12, 5, 4), (-3.0, -1.25, -1.0), (3.0, 1.25, 1.0))
    T = TiltSeriesTransform(vol, TiltSeriesGeometry(TILTS, 12, -3.0, 3.0, angle_unit="deg"))
    shifts = torch.linspace(-1, 1, 2 * len(TILTS), dtype=torch.float64).reshape(-1, 2)
    A = AlignedOperator(T, shifts, 0.02)
    box = wide_box(A)
    Aw = box.widen(A)
    assert isinstance(Aw, AlignedOperator) and torch.equal(Aw.shifts, A.shifts)
    assert tuple(Aw.domain.shape) == tuple(box.domain.shape)
    f = torch.rand(vol.shape, dtype=torch.float64)
    torch.testing.assert_close(Aw(box.pad_image(f, "zero")), A(f), rtol=1e-12, atol=1e-12)


def test_bad_input():
    T = tilt_series_2d()
    with pytest.raises(ValueError, match="slab thickness"):
        wide_box(T, thickness=-1.0)
    with pytest.raises(ValueError, match="max_width must be >= 1"):
        wide_box(T, max_width=0.5)
    with pytest.raises(TypeError, match="a wide box needs a RayTransform"):
        wide_box(object())
    other = tilt_series_2d(ImageDomain((20, 12), (-10.0, -3.0), (10.0, 3.0)))
    with pytest.raises(ValueError, match="not the box this wide box was made for"):
        wide_box(T).widen(other)
    assert isinstance(wide_box(T), WideBox)
