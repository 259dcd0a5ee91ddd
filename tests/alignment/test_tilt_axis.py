"""The tilt axis in the detector image: rotation into indreg's layout (exact and interpolated), the consistency
check, the .mdoc's angle, and ``indreg.load(..., tilt_axis_angle=...)``."""
import logging
import re

import numpy as np
import pytest

import indreg
from indreg import ImageDomain, phantoms
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.io import DataFileError, read_tilt_axis_angle, write_tilt_series
from indreg.alignment.tilt_axis import align_tilt_axis, check_tilt_axis, rotate_images

DOMAIN = ImageDomain((16, 12, 16), (-8.0, -6.0, -8.0), (8.0, 6.0, 8.0))   # 1-unit voxels, half_width 8
ANGLES = np.arange(-60.0, 61.0, 10.0)


@pytest.fixture(scope="module")
def series():
    """A template slab and the aligned tilt series (13 tilts, 12 rows along the axis y, 20 columns) of a deformed
    phantom: indreg's layout."""
    full = ImageDomain.paper(16, ndim=3)
    template = phantoms.get("shepp_logan_3d", full)[:, 2:14, :].numpy()
    target = phantoms.get("shepp_logan_3d_swirl", full)[:, 2:14, :]
    T = TiltSeriesTransform(DOMAIN, TiltSeriesGeometry(ANGLES, 20, -10.0, 10.0, angle_unit="deg"))
    return template, T(target).numpy()


def load(template, stack, **kw):
    return indreg.load(template, stack, "tilt_series", angles=ANGLES, half_width=8.0, det_min=-10.0,
                       det_max=10.0, **kw)


def test_rotation_conventions():
    """The interpolated rotation by +-90 and 180 degrees is the exact one (np.rot90): one convention; a general
    angle rotates as the formula says."""
    a = np.random.default_rng(0).random((2, 9, 9))
    for angle, k in ((90, 1), (-90, -1), (180, 2)):
        np.testing.assert_allclose(rotate_images(a, angle), np.rot90(a, k, axes=(1, 2)), atol=1e-12)
        np.testing.assert_array_equal(align_tilt_axis(a, angle), np.rot90(a, k, axes=(1, 2)))
    # an axis 90 degrees counterclockwise from Y points along -X: a line along X becomes one along Y
    line = np.zeros((1, 5, 7))
    line[0, 2, :] = 1.0
    aligned = align_tilt_axis(line, 90)
    assert aligned.shape == (1, 7, 5) and np.array_equal(aligned[0, :, 2], np.ones(7))
    # a general angle: out(p) = image(R(angle) p), p = (x, y) centred, x along the columns, y along the rows
    y, x = np.meshgrid(np.arange(41) - 20.0, np.arange(41) - 20.0, indexing="ij")
    bump = lambda x, y: np.exp(-((x - 4) ** 2 + y ** 2) / 60.0)              # noqa: E731, off-centre along x
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    rotated = rotate_images(bump(x, y)[None], 30.0)[0]
    assert np.abs(rotated - bump(c * x - s * y, s * x + c * y)).max() < 0.02          # bilinear error
    assert np.abs(rotated - bump(c * x + s * y, -s * x + c * y)).max() > 0.3      # not the other way round


def test_check_says_which_way_the_axis_runs(series):
    _, y = series
    aligned = check_tilt_axis(y)
    assert aligned.direction == "rows" and aligned.row_inconsistency < 0.01 < 0.05 < aligned.column_inconsistency
    for raw in (np.rot90(y, -1, axes=(1, 2)), y.swapaxes(1, 2)):          # axis along X: rotated or transposed
        check = check_tilt_axis(raw)
        assert check.direction == "columns"
        assert check.row_inconsistency == pytest.approx(aligned.column_inconsistency)
    # one scale per tilt (exposure) changes nothing; a misaligned stack (rows shifted per tilt) is inconsistent
    scaled = y * np.linspace(0.5, 2.0, len(ANGLES))[:, None, None]
    assert check_tilt_axis(scaled).row_inconsistency == pytest.approx(aligned.row_inconsistency, rel=1e-9)
    shifted = np.stack([np.roll(t, k % 3 - 1, axis=0) for k, t in enumerate(y)])
    assert check_tilt_axis(shifted).row_inconsistency > 10 * aligned.row_inconsistency
    ball = np.ones((5, 8, 8))
    assert check_tilt_axis(ball).direction == "undetermined"


def test_check_ignores_an_offset(series):
    """An int16-style offset (the empty border at -31 900) is the frame's level: the check's numbers are those of
    the clean stack (without the subtraction they shrink 3-5x on measured data)."""
    _, y = series
    clean, offset = check_tilt_axis(y), check_tilt_axis(y - 31900.0)
    assert offset.direction == clean.direction == "rows"
    assert offset.row_inconsistency == pytest.approx(clean.row_inconsistency, rel=1e-6)
    assert offset.column_inconsistency == pytest.approx(clean.column_inconsistency, rel=1e-6)


def test_axis_along_x_detected_and_the_angle_gives_the_aligned_result(series, caplog):
    """Must-show: a stack with its tilt axis along X is detected, and with ``tilt_axis_angle=90`` gives the same
    data and the same registration as the stack turned by hand (np.rot90)."""
    template, y = series
    raw = np.rot90(y, -1, axes=(1, 2)).copy()                               # (13, 20, 12): the axis along X
    with caplog.at_level(logging.WARNING, logger="indreg"):
        with pytest.raises(DataFileError):          # unrotated, its 12 columns do not fit the 12 x ... slab rows
            load(template, raw)
    assert "runs along the image's X" in caplog.text and "give tilt_axis_angle" in caplog.text
    d = load(template, raw, tilt_axis_angle=90)
    by_hand = load(template, np.rot90(raw, 1, axes=(1, 2)).copy())
    np.testing.assert_array_equal(d.data.numpy(), y)
    np.testing.assert_array_equal(by_hand.data.numpy(), y)
    assert d.tilt_axis.direction == "rows" and d.report()["tilt_axis_angle"] == 90
    options = dict(num_steps=3, max_iter=3, sigma=3.0)
    a = indreg.register(d.template, d.data, d.operator, **options)
    b = indreg.register(by_hand.template, by_hand.data, by_hand.operator, **options)
    np.testing.assert_array_equal(a.deformed.numpy(), b.deformed.numpy())


def test_general_angle_by_interpolation(series):
    template, y = series
    raw = align_tilt_axis(y, -87.2)                 # the axis 87.2 degrees counterclockwise from Y
    d = load(template, raw, tilt_axis_angle=87.2)
    assert d.data.shape == y.shape and d.tilt_axis.direction == "rows"
    inner = (slice(None), slice(3, 9), slice(6, 14))          # away from the extrapolated corners
    error = np.linalg.norm(d.data.numpy()[inner] - y[inner]) / np.linalg.norm(y[inner])
    assert error < 0.05                     # two bilinear interpolations of a 16-voxel phantom's projections


@pytest.mark.parametrize("angle", [0.0, -2.8, 177.2])
def test_a_contradicting_angle_is_one_line(series, angle):
    template, y = series
    raw = align_tilt_axis(y, -87.2)
    turned = "as stored" if angle == 0 else f"turned by {-angle:g} degrees"
    with pytest.raises(DataFileError, match=rf"^data: tilt_axis_angle={angle:g} contradicts the data: {turned}, the "
                                            r"tilt axis runs along the image's X .* \(e\.g\. ") as e:
        load(template, raw, tilt_axis_angle=angle)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("angle, message", [
    (float("nan"), "tilt_axis_angle must be a finite number of degrees in [-180, 180] or None, got nan"),
    ("90", "tilt_axis_angle must be a finite number of degrees in [-180, 180] or None, got '90'"),
    (1e300, "tilt_axis_angle must be a finite number of degrees in [-180, 180] or None, got 1e+300"),
])
def test_bad_angle_values(series, angle, message):
    template, y = series
    with pytest.raises(ValueError, match=re.escape(message)):
        load(template, y, tilt_axis_angle=angle)
    with pytest.raises(ValueError, match="tilt_axis_angle applies to a tilt series"):
        indreg.load(np.zeros((8, 8)), np.zeros((4, 11)), angles=[0, 45, 90, 135], tilt_axis_angle=90)


def test_mdoc_angle(series, tmp_path):
    template, y = series
    raw = np.rot90(y, 1, axes=(1, 2)).copy()                  # the axis at -90 degrees
    path = tmp_path / "series.mrc"
    write_tilt_series(path, raw, np.deg2rad(ANGLES), pixel_size=1.0)
    mdoc = tmp_path / "series.mrc.mdoc"
    mdoc.write_text("PixelSpacing = 1.0\nImageFile = series.mrc\n\n"
                    "[T = SerialEM: Digitized on EMBL Krios   11-Jan-24  10:01:02]\n\n"
                    "[T =     Tilt axis angle = -90.0, binning = 1  spot = 8  camera = 0]\n\n"
                    "[ZValue = 0]\nTiltAngle = -60.0\n")
    assert read_tilt_axis_angle(mdoc) == -90.0
    d = indreg.load(template, str(path), "tilt_series", half_width=8.0, det_min=-10.0, det_max=10.0)
    np.testing.assert_allclose(d.data.numpy(), y, rtol=1e-6, atol=1e-6 * np.abs(y).max())   # float32 MRC
    assert d.tilt_axis_angle == -90.0
    mdoc.write_text("TiltAxisAngle = 0.0\n")                 # a wrong record: an error naming the .mdoc
    with pytest.raises(DataFileError, match=r"the tilt axis angle 0 of .*series\.mrc\.mdoc contradicts the data"):
        indreg.load(template, str(path), "tilt_series", half_width=8.0, det_min=-10.0, det_max=10.0)
    # the argument overrides the record
    d = indreg.load(template, str(path), "tilt_series", half_width=8.0, det_min=-10.0, det_max=10.0,
                    tilt_axis_angle=-90)
    assert d.tilt_axis.direction == "rows"
    mdoc.write_text("PixelSpacing = 1.0\n")
    assert read_tilt_axis_angle(mdoc) is None
