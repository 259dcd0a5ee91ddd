"""Vacuum or specimen at the detector's border (indreg.units.border): the slab law, the decision on vacuum, slab and
region-of-interest frames, the background 'auto' takes, the refusal of a background that makes most data negative and
the offset advice that never names a specimen's border."""
import logging
import math

import numpy as np
import pytest
import torch

import indreg
from indreg import ImageDomain, ParallelBeamGeometry, RayTransform, phantoms
from indreg.units.border import MOST, background_level, check_border, negative_fraction, slab_law
from indreg.forward.wide_box import wide_box
from indreg.units import check_offset

TILTS = np.arange(-60.0, 60.1, 3.0)


def compact(offset=0.0, snr_db=None):
    """The paper's V in [-16, 16]^2 seen by a detector [-24, 24] over 10 angles: vacuum at the border."""
    domain = ImageDomain.paper(32)
    T = RayTransform(domain, ParallelBeamGeometry.paper(10, 46))
    g = T(phantoms.get("v", domain).double())
    if snr_db is not None:
        g, _ = indreg.noise.add_white_noise(g, snr_db=snr_db, seed=0)
    return g + offset, T


def slab(offset=0.0, sigma=0.0, seed=0):
    """A slab 2 thick (value 1) with blobs, three times wider than the detector, tilts -60..60: specimen at the
    border. Returns (data, narrow operator, wide box, truth on the wide box)."""
    domain = ImageDomain((48, 16), (-12.0, -4.0), (12.0, 4.0))
    T = RayTransform(domain, ParallelBeamGeometry(det_count=48, det_min=-12.0, det_max=12.0, angles=TILTS,
                                                  angle_unit="deg"))
    box = wide_box(T, thickness=4.0)
    x, y = box.domain.points()
    gen = torch.Generator().manual_seed(seed)
    truth = (y.abs() <= 2.0).double()
    for cx in torch.linspace(-30, 30, 9):
        cx = float(cx) + float(torch.rand(1, generator=gen)) * 3
        truth = truth + 0.6 * (((x - cx) / 2.5) ** 2 + (y / 1.2) ** 2 <= 1).double()
    g = box.widen(T)(truth)
    g = g + sigma * torch.randn(g.shape, generator=gen, dtype=g.dtype)
    return g + offset, T, box, truth


def test_slab_law_recovers_a_b_theta0():
    theta = np.radians(TILTS)
    levels = 0.7 / np.cos(theta - math.radians(2.5)) - 0.3
    law = slab_law(levels, theta)
    assert law.a == pytest.approx(0.7, rel=1e-9) and law.b == pytest.approx(-0.3, abs=1e-9)
    assert math.degrees(law.theta0) == pytest.approx(2.5, abs=1e-9) and law.r2 == pytest.approx(1.0)
    assert slab_law(levels[:3], theta[:3]) is None                        # too few tilts
    assert slab_law(np.ones(8), np.radians(np.linspace(0, 170, 8))) is None   # tilts near 90: no law


@pytest.mark.parametrize("offset,snr", [(0.0, None), (3.0, None), (-3.0, 15.0)])
def test_compact_object_border_is_vacuum(offset, snr):
    g, T = compact(offset, snr)
    c = check_border(g, T.geometry.angles.numpy())
    assert c.kind == "vacuum", c.describe()
    level, _, how = background_level(g, T.geometry.angles.numpy(), c)
    assert level == pytest.approx(offset, abs=0.05 * float(g.std()) + 1e-12) and "vacuum" in how


def test_exposure_drift_over_tilts_is_still_vacuum():
    """Each projection's border is compared with its own: a level that drifts with the tilt is not specimen."""
    g, T = compact()
    drift = torch.log(torch.cos(T.geometry.angles * 0.5))[:, None]
    assert check_border(g + drift, T.geometry.angles.numpy()).kind == "vacuum"


@pytest.mark.parametrize("sigma", [0.0, 0.3])
def test_slab_border_is_specimen_and_auto_background_is_the_slab_laws_intercept(sigma):
    """Noise-free the position and the law both say so; at a noise far above the blobs' contrast the law does."""
    g, T, _, _ = slab(offset=1.5, sigma=sigma)
    theta = T.geometry.angles.numpy()
    c = check_border(g, theta)
    assert c.kind == "specimen" and any("a / cos" in r for r in c.reasons), c.describe()
    level, _, how = background_level(g, theta, c)
    assert level == pytest.approx(1.5, abs=0.2) and "slab law" in how   # the blobs in and out of view: 3 % of <g>
    assert negative_fraction(g, c.level, c.sigma) > 0.0           # the border's level is not the bottom
    assert negative_fraction(g, level, c.sigma) < 0.05


def test_region_of_interest_border_is_specimen():
    """A full-angle scan of a disc wider than the detector (no tilt law): its border is structured material."""
    domain = ImageDomain((64, 64), (-16.0, -16.0), (16.0, 16.0))
    T = RayTransform(domain, ParallelBeamGeometry(det_count=32, det_min=-8.0, det_max=8.0, num_angles=60))
    x, y = domain.points()
    f = ((x ** 2 + y ** 2) <= 14 ** 2).double() + 0.8 * (((x - 9) / 3) ** 2 + (y / 2) ** 2 <= 1).double()
    c = check_border(T(f), T.geometry.angles.numpy())
    assert c.kind == "specimen", c.describe()
    assert background_level(T(f), T.geometry.angles.numpy(), c)[0] == 0.0   # no vacuum, no slab law: nothing


def test_auto_background_never_makes_most_data_negative():
    g, T, _, _ = slab()
    c = check_border(g, None)    # no angles: no law; the border is specimen by its position
    level, _, how = background_level(g, None, c)
    assert level == 0.0 and c.kind == "specimen" and "none" in how


def test_a_background_that_makes_most_data_negative_is_refused_naming_it():
    g, T, _, _ = slab()
    template = torch.zeros(T.domain.shape, dtype=torch.float64) + 1.0
    level = float(g.median()) + 1.0
    assert negative_fraction(g, level) > MOST
    with pytest.raises(ValueError, match=r"^background=.* would make \d+ % of the data negative beyond their noise"):
        indreg.register(template, g, T, background=level, max_iter=0, wide_box=False)


def warnings_of(caplog):
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def test_offset_advice_never_names_a_specimens_border(caplog):
    """A slab offset by 2: the warning points at the slab law's intercept, not at the border's level; a vacuum offset
    keeps the advice to subtract the border's level."""
    caplog.set_level(logging.INFO, logger="indreg")
    g, T, _, _ = slab(offset=2.0)
    check_offset(g, "background", T.geometry.angles.numpy())
    (message,) = warnings_of(caplog)
    assert "a slab's line integrals have no such intercept" in message and "not the border's level" in message
    caplog.clear()
    check_offset(g - 2.0, "background", T.geometry.angles.numpy())
    assert warnings_of(caplog) == []
    g, T = compact(offset=3.0)
    check_offset(g, "background", T.geometry.angles.numpy())
    (message,) = warnings_of(caplog)
    assert "pass background='auto' to subtract the border level" in message


def test_check_border_describes_itself():
    g, T, _, _ = slab()
    c = check_border(g, T.geometry.angles.numpy())
    d = c.as_dict()
    assert d["border"] == "specimen" and d["border_law_a"] > 0 and c.describe().startswith(
        "the detector's outermost columns look like specimen (")
