"""Tests of indreg.io.conventions and ``indreg.load(convention=...)``: every convention round-trips and reproduces
indreg's data from its own export; scikit-image's radon checked numerically against indreg's operator (arrays,
.npy and .tif files), ASTRA's and ODL's where installed, TomoPy's ray geometry (from its source) on Gaussian
blobs, IMOD's MRC section against the tilt-series reading; the orientation warning names the convention; bad values
are one-line errors (scripts/verify_conventions.py prints the same checks)."""
import logging
import warnings

import numpy as np
import pytest
import tifffile
import torch

import indreg
from indreg.io import conventions
from indreg.io.conventions import CONVENTIONS
from indreg.io import DataFileError
from indreg.metrics import ssim

N, THETA = 64, np.linspace(0.0, 180.0, 20, endpoint=False)     # degrees, as skimage takes them


def picture(n=N):
    """scikit-image's Shepp-Logan phantom as displayed, plus an off-centre blob (no mirror symmetry)."""
    from skimage.data import shepp_logan_phantom
    from skimage.transform import resize

    r, c = np.mgrid[:n, :n]
    blob = np.exp(-((r - 0.3 * n) ** 2 + (c - 0.65 * n) ** 2) / (2 * (n / 12) ** 2))
    return resize(shepp_logan_phantom(), (n, n), anti_aliasing=True) + blob


def warped(pic):
    """The picture warped with scipy-backed ``skimage.transform.warp`` (a smooth known deformation)."""
    from skimage.transform import warp

    r, c = np.mgrid[:pic.shape[0], :pic.shape[1]].astype(float)
    return warp(pic, np.array([r + 2.5 * np.sin(c / 9), c + 1.5]), order=1)


def radon(pic, circle=True):
    from skimage.transform import radon as sk_radon

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # skimage: the blob's tail reaches beyond the inscribed circle
        return sk_radon(pic, theta=THETA, circle=circle)


def relative(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


# --- each convention: round trips and its own export ---------------------------------------------------------

@pytest.mark.parametrize("name", list(CONVENTIONS))
def test_round_trips(name):
    rng = np.random.default_rng(0)
    image, sino, angles = rng.normal(size=(5, 5)), rng.normal(size=(7, 9)), rng.uniform(-3, 3, 7)
    np.testing.assert_array_equal(conventions.image_from_indreg(conventions.image_to_indreg(image, name), name), image)
    np.testing.assert_array_equal(conventions.image_to_indreg(conventions.image_from_indreg(image, name), name), image)
    back = conventions.sinogram_from_indreg(conventions.sinogram_to_indreg(sino, name, 0.25), name, 0.25)
    np.testing.assert_allclose(back, sino, rtol=1e-15)
    np.testing.assert_allclose(conventions.angles_from_indreg(conventions.angles_to_indreg(angles, name), name),
                               angles, rtol=0, atol=1e-15)


@pytest.mark.parametrize("name", list(CONVENTIONS))
@pytest.mark.parametrize("n", [16, 17])
def test_own_export_loads_as_indreg_data(tmp_path, name, n):
    """Data of indreg's operator on the convention's domain and detector, exported in the tool's layout, angles and
    units (``*_from_indreg``) and saved as .npy, load back to the same template, data, angles and detector."""
    c = CONVENTIONS[name]
    h, det_count = 2.0, 23
    domain = conventions.domain_for(c, n, n * h / 2)
    det_min, det_max = conventions.detector_for(c, det_count, h)
    radians = np.deg2rad(THETA[:7] + 3.0)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=torch.from_numpy(radians), det_count=det_count,
                                                                det_min=det_min, det_max=det_max))
    f = np.random.default_rng(1).uniform(size=(n, n))
    g = T(torch.from_numpy(f)).numpy()
    np.save(tmp_path / "t.npy", conventions.image_from_indreg(f, c))
    np.save(tmp_path / "s.npy", conventions.sinogram_from_indreg(g, c, h))
    d = indreg.load(tmp_path / "t.npy", tmp_path / "s.npy", angles=conventions.angles_from_indreg(radians, c),
                    angle_unit="rad", half_width=n * h / 2, convention=name)
    np.testing.assert_array_equal(d.template.numpy(), f)
    np.testing.assert_allclose(d.data.numpy(), g, rtol=1e-12, atol=1e-12 * np.abs(g).max())
    np.testing.assert_allclose(d.geometry.angles.numpy(), radians, rtol=0, atol=1e-14)
    assert d.domain.min_pt == domain.min_pt and d.domain.max_pt == domain.max_pt
    np.testing.assert_allclose(d.operator(d.template).numpy(), g, rtol=1e-12, atol=1e-12 * np.abs(g).max())


def test_tables_say_what_differs():
    """The conventions as documented (docs/file_formats.md): layouts, angle origin, units, detector centre."""
    sk, astra, tomopy, imod = (CONVENTIONS[k] for k in ("skimage", "astra", "tomopy", "imod"))
    assert (sk.image, sk.sinogram, sk.pixel_units, sk.bins) == ("displayed", "bin_angle", True, "index")
    assert (astra.image, astra.sinogram, astra.angle_offset, astra.bins) == ("displayed", "angle_bin", 0.0, "middle")
    assert (tomopy.image, tomopy.sinogram, tomopy.angle_offset, tomopy.pixel_units, tomopy.bins) == \
        (astra.image, astra.sinogram, astra.angle_offset, astra.pixel_units, astra.bins)      # TomoPy reads as ASTRA
    assert (imod.image, imod.angle_sense, imod.pixel_units, imod.bins) == ("yx", -1.0, True, "middle")
    odl, own = CONVENTIONS["odl"], CONVENTIONS["indreg"]
    assert (odl.image, odl.sinogram, odl.angle_offset, odl.pixel_units, odl.bins) == \
        (own.image, own.sinogram, own.angle_offset, own.pixel_units, own.bins)
    # skimage's rotation centre: pixel n // 2 of the displayed picture, at the origin
    dom = conventions.domain_for("skimage", 4, 2.0)
    assert dom.min_pt == (-2.5, -1.5) and dom.max_pt == (1.5, 2.5)
    assert conventions.detector_for("skimage", 5, 1.0) == (-2.5, 2.5)
    assert conventions.detector_for("skimage", 6, 1.0) == (-3.5, 2.5)
    assert conventions.detector_for("astra", 6, 0.5) == (-1.5, 1.5)
    assert conventions.detector_for("indreg", 6, 0.5) == (None, None)
    assert conventions.detector_for("skimage", 6, 1.0, -4.0, 4.0) == (-4.0, 4.0)     # given: kept


# --- scikit-image's radon, numerically ----------------------------------------------------------------------------

@pytest.mark.parametrize("n", [64, 65])
@pytest.mark.parametrize("circle", [True, False])
def test_skimage_radon_is_indreg_operator(n, circle):
    """``convention="skimage"``: skimage's picture and ``radon`` sinogram, as they come, are indreg's template and
    the data of indreg's operator on it, up to discretisation (rotate-and-sum vs Joseph: below 1 %; a flipped
    detector, a wrong angle sign or pixel units would give tens of percent)."""
    pic = picture(n)
    d = indreg.load(pic, radon(pic, circle), angles=THETA, convention="skimage")
    assert relative(d.operator(d.template), d.data) < 0.01
    np.testing.assert_array_equal(np.rot90(d.template.numpy()), pic)
    wrong = indreg.load(pic, radon(pic, circle)[::-1].copy(), angles=THETA, convention="skimage")
    assert relative(wrong.operator(wrong.template), wrong.data) > 0.2


def test_skimage_files_npy_and_tif_are_the_same_object(tmp_path, caplog):
    """The same picture saved as .npy and as a float .tif is one template under ``convention=skimage``; the log
    names each file's orientation."""
    pic, sino = picture(), radon(warped(picture()))
    np.save(tmp_path / "t.npy", pic)
    tifffile.imwrite(tmp_path / "t.tif", pic.astype(np.float32))
    np.save(tmp_path / "s.npy", sino)
    with caplog.at_level(logging.INFO, logger="indreg"):
        a = indreg.load(tmp_path / "t.npy", tmp_path / "s.npy", angles=THETA, convention="skimage")
        b = indreg.load(tmp_path / "t.tif", tmp_path / "s.npy", angles=THETA, convention="skimage")
    np.testing.assert_allclose(a.template.numpy(), b.template.numpy(), rtol=1e-6)
    assert ".npy read as displayed (rows = y top-down, columns = x), converted to axis 0 = x" in caplog.text
    assert ".npy read as (bins, angles), transposed" in caplog.text
    assert "WARNING" not in [r.levelname for r in caplog.records]


def test_skimage_files_without_the_convention_name_it(tmp_path, caplog):
    """As they come: the (bins, angles) sinogram is an error naming ``convention=skimage``; transposed by hand, the
    template's orientation warning names skimage."""
    pic, sino = picture(), radon(warped(picture()))
    np.save(tmp_path / "t.npy", pic)
    np.save(tmp_path / "s.npy", sino)
    np.save(tmp_path / "st.npy", sino.T)
    with pytest.raises(DataFileError, match=r"64 rows .* 20 angles; .* give convention=skimage") as err:
        indreg.load(tmp_path / "t.npy", tmp_path / "s.npy", angles=THETA)
    assert "\n" not in str(err.value)
    with caplog.at_level(logging.WARNING, logger="indreg"):
        indreg.load(tmp_path / "t.npy", tmp_path / "st.npy", angles=THETA)
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "probably follow skimage" in warned[0]
    assert "with the sinogram's axes swapped" in warned[0]


def test_orientation_warning_names_imod(tmp_path, caplog):
    """IMOD's files (an MRC-like section (Z, X), rows = z, and data in IMOD's sense of rotation, pixel sums) read as
    indreg's: the warning names imod (with astra and tomopy: the same reading here); read as imod, no warning."""
    domain = indreg.ImageDomain.paper(32)
    h = domain.cell_sides[0]
    f = indreg.phantoms.get("shepp_logan", domain).numpy() + np.where(np.arange(32)[:, None] < 8, 0.5, 0.0)
    T_imod = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=torch.from_numpy(-np.deg2rad(THETA)),
                                                                     det_count=46, det_min=-23 * h, det_max=23 * h))
    np.save(tmp_path / "t.npy", f.T)
    np.save(tmp_path / "s.npy", T_imod(torch.from_numpy(f)).numpy() / h)
    with caplog.at_level(logging.WARNING, logger="indreg"):
        indreg.load(tmp_path / "t.npy", tmp_path / "s.npy", angles=THETA)
        assert "imod" in caplog.text.split("probably follow")[1] and "set convention accordingly" in caplog.text
        caplog.clear()
        d = indreg.load(tmp_path / "t.npy", tmp_path / "s.npy", angles=THETA, convention="imod")
    assert caplog.text == ""
    assert relative(d.operator(d.template), d.data) < 1e-6


# --- the other tools, numerically ---------------------------------------------------------------------------------

def test_astra_parallel_is_indreg_operator(tmp_path):
    """``convention="astra"``: ASTRA's default volume (one unit a pixel) and its CPU 'linear' projector's sinogram, as
    they come, are indreg's template and data up to float32 (a reversed detector: 60 %)."""
    astra = pytest.importorskip("astra")
    for n, det_count in ((64, 64), (65, 91)):
        pic = picture(n)
        vol = astra.create_vol_geom(n, n)
        proj = astra.create_proj_geom("parallel", 1.0, det_count, np.deg2rad(THETA + 7))
        pid = astra.create_projector("linear", proj, vol)
        sid, g = astra.create_sino(pic.astype(np.float32), pid)
        astra.data2d.delete(sid)
        astra.projector.delete(pid)
        d = indreg.load(pic, g, angles=THETA + 7, convention="astra")
        assert relative(d.operator(d.template), d.data) < 1e-5
        wrong = indreg.load(pic, g[:, ::-1].copy(), angles=THETA + 7, convention="astra")
        assert relative(wrong.operator(wrong.template), wrong.data) > 0.2


def test_odl_ray_transform_is_indreg_operator():
    """``convention="odl"``: ODL's element (axis 0 = x) and ``RayTransform`` data on ``parallel_beam_geometry``,
    with indreg fitting the detector itself, are indreg's template and data up to float32."""
    odl = pytest.importorskip("odl")
    pytest.importorskip("astra")
    from odl.applications import tomo

    space = odl.uniform_discr([-10.0, -10.0], [10.0, 10.0], (65, 65), dtype="float32")
    geometry = tomo.parallel_beam_geometry(space, num_angles=20)
    f = np.rot90(picture(65), k=-1).copy()
    g = tomo.RayTransform(space, geometry, impl="astra_cpu")(space.element(f.astype(np.float32))).asarray()
    d = indreg.load(f, np.asarray(g), angles=np.asarray(geometry.angles), angle_unit="rad", half_width=10.0,
                    convention="odl")
    assert relative(d.operator(d.template), d.data) < 1e-5


def tomopy_blobs(n: int, theta_rad: np.ndarray, offset: float = 0.0) -> tuple:
    """Gaussian blobs ``(x_t, y_t, std, amplitude)`` in TomoPy's slice coordinates (pixels, ``x_t`` along the slice's
    axis 0, ``y_t`` along axis 1, centred) sampled on the slice, and their exact line integrals in the geometry of
    TomoPy's source (libtomo ``calc_coords``: rays along ``(cos t, sin t)``, bin ``d`` at ``d - (n - 1) / 2`` along
    ``(-sin t, cos t)``, ``t`` = the angle + ``offset``)."""
    blobs = ((-9.0, 5.0, 3.0, 1.0), (6.0, 10.0, 2.0, 0.7), (4.0, -7.0, 4.0, 0.5))
    c = np.arange(n) - (n - 1) / 2
    xt, yt = np.meshgrid(c, c, indexing="ij")
    image = sum(a * np.exp(-((xt - x) ** 2 + (yt - y) ** 2) / (2 * s ** 2)) for x, y, s, a in blobs)
    t = theta_rad + offset
    data = sum(a * np.sqrt(2 * np.pi) * s * np.exp(-(c[None, :] - (y * np.cos(t) - x * np.sin(t))[:, None]) ** 2
                                                    / (2 * s ** 2)) for x, y, s, a in blobs)
    return image, data


@pytest.mark.parametrize("n", [64, 65])
def test_tomopy_geometry_is_indreg_operator(n):
    """``convention="tomopy"``: a slice and its projections in TomoPy's ray geometry are indreg's template and data
    up to sampling (0.6 %); the 90-degree offset the table once had gives 64 %."""
    image, g = tomopy_blobs(n, np.deg2rad(THETA))
    d = indreg.load(image, g, angles=THETA, convention="tomopy", half_width=16.0)
    assert relative(d.operator(d.template), d.data) < 0.01
    image, g = tomopy_blobs(n, np.deg2rad(THETA), offset=np.pi / 2)
    d = indreg.load(image, g, angles=THETA, convention="tomopy", half_width=16.0)
    assert relative(d.operator(d.template), d.data) > 0.3


# IMOD's projection, written from its formula (flib/tilt/tilt.f90 of IMOD: the point (x, z) of a section, in pixels
# from the centre, lands on detector column x cos b - z sin b; the datum is a pixel sum), independent of indreg: the
# analytic line integrals of Gaussian blobs in pixel lengths.
BLOBS = ((0.31, -0.18, 0.05, 1.0), (-0.22, 0.27, -0.1, 0.7), (0.05, 0.12, 0.2, 0.5))   # (x, z, y) / n, amplitude


def imod_blobs(n: int, tilts_deg: np.ndarray, width: float = 2.5) -> tuple:
    """``(volume (x, y, z), tilt series (tilt, Y, X))`` in pixels: Gaussian blobs of ``width`` pixels sampled at the
    pixel centres, and their projections by IMOD's formula in pixel sums (``sqrt(2 pi) width`` per unit of
    amplitude along a ray), the tilt axis along Y, centres at ``(n - 1) / 2``."""
    c = np.arange(n) - (n - 1) / 2
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    b = np.deg2rad(tilts_deg)[:, None, None]
    rows, cols = np.meshgrid(c, c, indexing="ij")
    f, g = np.zeros((n, n, n)), np.zeros((b.size, n, n))
    for bx, bz, by, a in BLOBS:
        x0, y0, z0 = bx * n, by * n, bz * n
        f += a * np.exp(-((x - x0) ** 2 + (y - y0) ** 2 + (z - z0) ** 2) / (2 * width ** 2))
        p0 = x0 * np.cos(b) - z0 * np.sin(b)                                    # IMOD: x cos b - z sin b
        g += a * np.sqrt(2 * np.pi) * width * np.exp(-((cols - p0) ** 2 + (rows - y0) ** 2) / (2 * width ** 2))
    return f, g


def test_imod_convention_matches_imods_formula(tmp_path):
    """``convention="imod"`` against the independent projector above: a section of IMOD's unrotated reconstruction
    (MRC ``(Y, Z, X)``: the slice ``(Z, X)``, Z up) and the matching row of the tilt series load as a template and
    data that indreg's operator reproduces (to the blobs' sampling), in the domain's length unit (pixel sums times
    the pixel side ``h = 0.25``); the angles' sense or the units left as indreg's do not; the 3D reading of the whole
    series agrees with the 2D one."""
    import mrcfile

    n, tilts = 48, np.arange(-60.0, 61.0, 3.0)
    f, g = imod_blobs(n, tilts)
    j = int(round(BLOBS[0][2] * n + (n - 1) / 2))                 # the row through the first blob
    with mrcfile.new(tmp_path / "rec.mrc") as mrc:
        mrc.set_data(np.ascontiguousarray(f.transpose(1, 2, 0)[j:j + 1]).astype(np.float32))   # (Y, Z, X): section j
    with mrcfile.new(tmp_path / "row.mrc") as mrc:
        mrc.set_data(np.ascontiguousarray(g[:, j:j + 1]).astype(np.float32))                    # (tilt, 1, X)
    half_width = n * 0.25 / 2
    d = indreg.load(tmp_path / "rec.mrc", tmp_path / "row.mrc", angles=tilts, half_width=half_width,
                    convention="imod")
    np.testing.assert_array_equal(d.template.numpy(), f[:, j].astype(np.float32))
    np.testing.assert_allclose(d.data.numpy(), 0.25 * g[:, j].astype(np.float32), rtol=1e-6)
    assert relative(d.operator(d.template), d.data) < 0.02
    sense = indreg.load(f[:, j], 0.25 * g[:, j], angles=tilts, half_width=half_width)          # indreg's sense
    assert relative(sense.operator(sense.template), sense.data) > 0.3
    astra = indreg.load(tmp_path / "rec.mrc", tmp_path / "row.mrc", angles=tilts, half_width=half_width,
                        convention="astra")       # the same reading: the section as displayed is it mirrored in z
    assert relative(astra.operator(astra.template), astra.data) < 0.02
    three = indreg.load(f, g, "tilt_series", angles=tilts, half_width=half_width, convention="imod")
    assert relative(three.operator(three.template), three.data) < 0.02
    np.testing.assert_allclose(three.data[:, j].numpy(), d.data.numpy(), rtol=1e-6)
    own = indreg.load(f, g, "tilt_series", angles=tilts, half_width=half_width)
    assert relative(own.operator(own.template), own.data) > 0.3


# --- 8-bit pictures through load; bad values ----------------------------------------------------------------------

def test_eight_bit_template_reads_as_fraction(tmp_path):
    import imageio.v3 as iio

    shown = np.round(255 * picture() / picture().max()).astype(np.uint8)
    iio.imwrite(tmp_path / "t.png", shown)
    sino = np.zeros((THETA.size, 64))
    d = indreg.load(tmp_path / "t.png", sino, angles=THETA)
    np.testing.assert_allclose(np.rot90(d.template.numpy()), shown / 255.0, rtol=1e-15)
    raw = indreg.load(tmp_path / "t.png", sino, angles=THETA, integer_scale="raw")
    np.testing.assert_array_equal(np.rot90(raw.template.numpy()), shown)


@pytest.mark.parametrize("kwargs, message", [
    (dict(convention="matlab"), r"^convention must be one of indreg, odl, skimage, astra, tomopy, imod, got 'matlab'$"),
    (dict(integer_scale="bits"), r"^integer_scale must be one of fraction, raw, got 'bits'$"),
    (dict(convention="skimage", geometry="fan_flat", src_radius=100.0),
     r"^convention=skimage is for 2D parallel-beam data; with geometry=fan_flat use indreg or odl$"),
])
def test_bad_values_are_one_line(kwargs, message):
    with pytest.raises(ValueError, match=message):
        indreg.load(np.zeros((8, 8)), np.zeros((4, 12)), angles=THETA[:4], **kwargs)


def test_tilt_series_takes_indreg_or_imod():
    with pytest.raises(ValueError, match=r"^convention=astra is for 2D parallel-beam data; with geometry=tilt_series "
                                         r"use indreg or imod$"):
        indreg.load(np.zeros((8, 8, 8)), np.zeros((4, 8, 12)), "tilt_series", angles=THETA[:4], convention="astra")


# --- end to end -----------------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_skimage_case_registers_as_indreg_data():
    """The new user's case: skimage phantom, warped, skimage's radon at 20 angles. With ``convention="skimage"``
    the registration reaches the SSIM of the same problem with data made by indreg's own operator (within 0.01)."""
    pic = picture()
    target = warped(pic)
    d = indreg.load(pic, radon(target), angles=THETA, convention="skimage", target=target)
    own = d.operator(d.target)
    scores = [ssim(indreg.register(d.template, data, d.operator, sigma=2.0, max_iter=60).deformed, d.target)
              for data in (d.data, own)]
    assert scores[0] > ssim(d.template, d.target) + 0.2
    assert abs(scores[0] - scores[1]) < 0.01


def test_upside_down_picture_is_warned(tmp_path, caplog):
    """A picture saved upside down (no convention reads it so): the warning says the template fits flipped."""
    import imageio.v3 as iio

    pic = picture()
    iio.imwrite(tmp_path / "t.png", np.round(255 * pic[::-1] / pic.max()).astype(np.uint8))
    with caplog.at_level(logging.WARNING, logger="indreg"):
        indreg.load(tmp_path / "t.png", radon(warped(pic)), angles=THETA, convention="skimage")
        assert "flipped along y (np.flip(f, 1): a picture upside down?)" in caplog.text
        caplog.clear()
        iio.imwrite(tmp_path / "t.png", np.round(255 * pic / pic.max()).astype(np.uint8))
        indreg.load(tmp_path / "t.png", radon(warped(pic)), angles=THETA, convention="skimage")
    assert caplog.text == ""
