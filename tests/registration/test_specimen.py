"""The wide box in a registration (indreg.registration.specimen, options wide_box / slab_thickness / slab_extent /
template_padding): chosen where the border is specimen and not otherwise, the template padded, the data term on the
detector's pixels, SSIM on the field of view, the poor-fit message naming an object wider than the box, a tilt series,
the chord law of a full-angle scan, and bad option values."""
import logging

import pytest
import torch

import indreg
from indreg import ImageDomain, ParallelBeamGeometry, RayTransform, phantoms
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.forward.operator import relative_residual
from indreg.forward.wide_box import wide_box
from indreg.registration.run import wider_hint
from indreg.registration.specimen import chord_extent
from indreg.units import Units

QUICK = dict(max_iter=4, num_steps=3, sigma=3.0)


def slab_case(seed=0):
    """A slab 4 thick in a box 8 thick, three times wider than the detector, with blobs; the template: the slab without
    them. Returns (template, data, T, target on the given box, wide box of the truth)."""
    domain = ImageDomain((32, 12), (-8.0, -3.0), (8.0, 3.0))
    T = RayTransform(domain, ParallelBeamGeometry(det_count=32, det_min=-8.0, det_max=8.0,
                                                  angles=torch.arange(-60.0, 60.1, 6.0), angle_unit="deg"))
    box = wide_box(T, thickness=4.0)
    x, y = box.domain.points()
    slab = (y.abs() <= 2.0).double()
    truth = slab.clone()
    gen = torch.Generator().manual_seed(seed)
    for cx in torch.linspace(-20, 20, 7):
        cx = float(cx) + 2 * float(torch.rand(1, generator=gen))
        truth = truth + 0.7 * (((x - cx) / 2.0) ** 2 + (y / 1.0) ** 2 <= 1).double()
    return box.crop(slab), box.widen(T)(truth), T, box.crop(truth), box


def test_wide_box_is_chosen_for_slab_data_and_fits_them_better(caplog):
    caplog.set_level(logging.INFO, logger="indreg")
    template, data, T, target, truth_box = slab_case()
    r = indreg.register(template, data, T, target=target, **QUICK)
    assert r.units.border == "specimen" and r.box is not None and r.box.widened
    assert r.units.slab_thickness == pytest.approx(4.0)          # the template's support along the beam
    assert r.box.domain.shape == truth_box.domain.shape and r.deformed.shape == r.box.domain.shape
    assert r.units.box_width == pytest.approx(r.box.width_factor)
    torch.testing.assert_close(r.trajectory[0], r.box.pad_image(template, "edge"), rtol=0, atol=1e-6)
    # the data term: the detector's pixels only, the residual that of the wide operator on the measured data
    assert r.residual == pytest.approx(relative_residual(r.box.widen(T), r.deformed, data), rel=1e-9)
    assert r.ssim == pytest.approx(indreg.metrics.ssim(r.box.crop(r.deformed), target), rel=1e-12)
    assert any("wide box:" in m.getMessage() and "template padded" in m.getMessage() for m in caplog.records)
    narrow = indreg.register(template, data, T, target=target, wide_box=False, **QUICK)
    assert narrow.box is None and narrow.deformed.shape == T.domain.shape
    assert r.residual < 0.5 * narrow.residual and r.ssim > narrow.ssim


def test_no_wide_box_for_an_object_inside_the_field_of_view():
    domain = ImageDomain.paper(32)
    T = RayTransform(domain, ParallelBeamGeometry.paper(10, 46))
    template, data = phantoms.get("j", domain).double(), T(phantoms.get("v", domain).double())
    auto = indreg.register(template, data, T, **QUICK)
    off = indreg.register(template, data, T, wide_box=False, **QUICK)
    assert auto.units.border == "vacuum" and auto.box is None
    torch.testing.assert_close(auto.deformed, off.deformed, rtol=0, atol=0)
    forced = indreg.register(template, data, T, wide_box=True, max_iter=0)   # the chord law: about the object
    assert forced.box is not None and not forced.box.capped and forced.box.width_factor < 1.3


def test_poor_fit_names_an_object_wider_than_the_box():
    template, data, T, _, _ = slab_case()
    r = indreg.register(template, data, T, wide_box=False, max_iter=11, num_steps=3, sigma=3.0)
    assert "the object is wider than the box" in r.poor_fit and "wide_box=True" in r.poor_fit
    assert wider_hint(Units(border="vacuum"), None) == wider_hint(Units(border="unclear"), None) == ""
    assert "template_padding" in wider_hint(Units(border="specimen"), wide_box(T))


def test_tilt_series_registration_on_the_wide_box():
    domain = ImageDomain((16, 7, 8), (-4.0, -1.75, -2.0), (4.0, 1.75, 2.0))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry(list(range(-60, 61, 15)), 16, -4.0, 4.0, angle_unit="deg"))
    box = wide_box(T, thickness=2.0)
    x, _, z = box.domain.points()
    truth = (z.abs() <= 1.0).double() + 0.8 * ((((x - 2) / 1.5) ** 2 + z ** 2) <= 1).double() \
        + 0.8 * ((((x + 7) / 1.5) ** 2 + z ** 2) <= 1).double()
    data = box.widen(T)(truth)
    template = box.crop((z.abs() <= 1.0).double())
    r = indreg.register(template, data, T, target=box.crop(truth), **QUICK)
    assert r.box is not None and r.box.pad == box.pad and r.ssim is not None
    narrow = indreg.register(template, data, T, wide_box=False, **QUICK)
    assert r.residual < narrow.residual


def test_chord_law_extent_of_a_full_angle_scan():
    domain = ImageDomain((48, 48), (-12.0, -12.0), (12.0, 12.0))
    T = RayTransform(domain, ParallelBeamGeometry(det_count=24, det_min=-6.0, det_max=6.0, num_angles=60))
    x, y = domain.points()
    disc = ((x ** 2 + y ** 2) <= 10.0 ** 2).double()
    assert chord_extent(T(disc), T) == pytest.approx(20.0, rel=0.05)
    inside = ((x ** 2 + y ** 2) <= 4.0 ** 2).double()     # inside the detector
    assert chord_extent(T(inside), T) == pytest.approx(8.0, rel=0.05)
    assert 24.0 <= chord_extent(T(domain.zeros() + 1.0), T) <= 34.0   # a 24 x 24 square: between its sides and diagonal
    limited = RayTransform(domain, ParallelBeamGeometry(det_count=24, det_min=-6.0, det_max=6.0,
                                                        angles=[-60.0, 0.0, 60.0], angle_unit="deg"))
    assert chord_extent(limited(disc), limited) is None


@pytest.mark.parametrize("option,value,match", [
    ("wide_box", "yes", "wide_box must be one of 'auto', True, False"),
    ("slab_thickness", -1.0, "slab_thickness must be"),
    ("slab_extent", 0.0, "slab_extent must be"),
    ("template_padding", "mirror", "template_padding must be one of 'edge', 'zero', 'level'"),
])
def test_bad_option_values_are_one_line(option, value, match):
    template, data, T, _, _ = slab_case()
    with pytest.raises(ValueError, match=match):
        indreg.register(template, data, T, max_iter=0, **{option: value})
