"""Tests of indreg.io: round trips of every format, display orientation, path syntax, MRC stacks,
one-line errors naming the file and the problem, angle files, and the skimage radon convention."""
import math
import warnings

import h5py
import imageio.v3 as iio
import mrcfile
import numpy as np
import pytest
import tifffile
import torch

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.io import (DataFileError, read_angles, read_image, read_sinogram, read_stack, read_tilt_series,
                       read_volume, read_voxel_size, tilt_angles_for, write_image, write_tilt_series, write_volume)


def picture(rows=5, cols=7, dtype=np.uint8):
    """An asymmetric displayed picture (rows top to bottom, columns left to right), integer grey levels."""
    return (np.arange(rows * cols).reshape(rows, cols) * 3 + 1).astype(dtype)


def array(shape=(6, 4)):
    """An asymmetric float64 array with non-integer values."""
    return np.arange(math.prod(shape), dtype=np.float64).reshape(shape) * 0.25 - 1.5


def one_line_error(func, *args, contains=(), **kwargs):
    """Call ``func`` expecting a DataFileError; check it is one line holding every string in ``contains``."""
    with pytest.raises(DataFileError) as info:
        func(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    for text in contains:
        assert str(text) in message, (text, message)
    return message


# --- round trips of the array formats (layout kept as is) ---------------------------------------------

def test_npy_round_trip_image_and_sinogram(tmp_path):
    a = array()
    write_image(tmp_path / "a.npy", a)
    for reader in (read_image, read_sinogram):
        out = reader(tmp_path / "a.npy")
        assert out.dtype == np.float64 and out.flags.c_contiguous
        np.testing.assert_array_equal(out, a)


def test_write_image_accepts_torch_and_str_path(tmp_path):
    a = array()
    write_image(str(tmp_path / "t.npy"), torch.from_numpy(a))
    np.testing.assert_array_equal(read_image(tmp_path / "t.npy"), a)


def test_npz_single_array_and_key_syntax(tmp_path):
    a, b = array(), array((3, 5))
    np.savez(tmp_path / "one.npz", image=a)
    np.testing.assert_array_equal(read_image(tmp_path / "one.npz"), a)
    np.savez(tmp_path / "two.npz", image=a, sino=b)
    np.testing.assert_array_equal(read_image(f"{tmp_path / 'two.npz'}:image"), a)
    np.testing.assert_array_equal(read_sinogram(f"{tmp_path / 'two.npz'}:sino"), b)


def test_h5_dataset_syntax_and_single_dataset(tmp_path):
    a, b = array(), array((3, 5))
    with h5py.File(tmp_path / "one.h5", "w") as f:
        f.create_dataset("/deep/group/img", data=a)
    np.testing.assert_array_equal(read_image(tmp_path / "one.h5"), a)
    with h5py.File(tmp_path / "two.hdf5", "w") as f:
        f.create_dataset("/group/img", data=a.astype(np.float32))
        f.create_dataset("/sino", data=b)
    np.testing.assert_array_equal(read_image(f"{tmp_path / 'two.hdf5'}:/group/img"), a)
    np.testing.assert_array_equal(read_sinogram(f"{tmp_path / 'two.hdf5'}:sino"), b)


def test_hspy_is_hdf5_with_the_signal_named(tmp_path):
    """HyperSpy's .hspy (etspy's aligned stacks): the signal array at /Experiments/__unnamed__/data, read as
    stored; without the key the metadata arrays make the dataset ambiguous (one-line error)."""
    stack = np.arange(3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5)
    path = tmp_path / "stack.hspy"
    with h5py.File(path, "w") as f:
        f.create_dataset("/Experiments/__unnamed__/data", data=stack)
        f.create_dataset("/Experiments/__unnamed__/metadata/tilts", data=np.zeros(3))
    np.testing.assert_array_equal(read_stack(f"{path}:/Experiments/__unnamed__/data"), stack)
    with pytest.raises(DataFileError, match="holds 2 datasets"):
        read_stack(path)


def test_mrc_round_trip_and_image_section(tmp_path):
    a = array()
    write_image(tmp_path / "a.mrc", a)
    np.testing.assert_array_equal(read_image(tmp_path / "a.mrc"), a)   # values exact in float32
    with mrcfile.new(tmp_path / "section.mrc") as mrc:
        mrc.set_data(a[None].astype(np.float32))
    np.testing.assert_array_equal(read_image(tmp_path / "section.mrc"), a)


@pytest.mark.parametrize("ext", [".mrc", ".st", ".ali"])
@pytest.mark.parametrize("stack", ["row", "column", "flat"])
def test_mrc_tilt_series_shapes(tmp_path, ext, stack):
    sino = array((7, 5)).astype(np.float32)          # 7 tilts, 5 detector bins
    data = {"row": sino[:, None, :], "column": sino[:, :, None], "flat": sino}[stack]
    path = tmp_path / f"series{ext}"
    with mrcfile.new(path) as mrc:
        mrc.set_data(np.ascontiguousarray(data))
    np.testing.assert_array_equal(read_sinogram(path), sino)


def test_mrc_bad_header_read_permissively_with_warning(tmp_path):
    a = array().astype(np.float32)
    path = tmp_path / "broken.mrc"
    with mrcfile.new(path) as mrc:
        mrc.set_data(a)
    raw = bytearray(path.read_bytes())
    raw[208:212] = b"XXXX"                            # the MRC map ID "MAP " at byte 208
    path.write_bytes(bytes(raw))
    with pytest.warns(UserWarning, match="permissive"):
        np.testing.assert_array_equal(read_image(path), a)


# --- picture formats: display orientation -------------------------------------------------------------

@pytest.mark.parametrize("ext", [".png", ".tif", ".tiff"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_picture_image_is_upright_under_rot90(tmp_path, ext, dtype):
    shown = picture(dtype=dtype)
    path = tmp_path / f"pic{ext}"
    (iio.imwrite if ext == ".png" else tifffile.imwrite)(path, shown)
    f = read_image(path, integer_scale="raw")
    assert f.shape == (7, 5) and f.dtype == np.float64          # (nx, ny): columns are x
    np.testing.assert_array_equal(np.rot90(f), shown)             # shown upright, values not rescaled
    # top-left pixel of the picture is at the smallest x and the largest y
    assert f[0, -1] == shown[0, 0] and f[-1, 0] == shown[-1, -1]


@pytest.mark.parametrize("ext", [".png", ".tif"])
def test_picture_sinogram_is_taken_as_displayed(tmp_path, ext):
    shown = picture(dtype=np.uint16)
    path = tmp_path / f"sino{ext}"
    (iio.imwrite if ext == ".png" else tifffile.imwrite)(path, shown)
    np.testing.assert_array_equal(read_sinogram(path, integer_scale="raw"), shown)    # rows = angles, columns = bins


@pytest.mark.parametrize("ext", [".png", ".tif"])
@pytest.mark.parametrize("channels", [3, 4])
def test_rgb_picture_to_grey_by_luminance(tmp_path, ext, channels):
    rgb = np.stack([picture(), picture()[::-1], picture()[:, ::-1]], axis=-1)
    if channels == 4:
        rgb = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 7, np.uint8)], axis=-1)
    path = tmp_path / f"rgb{ext}"
    if ext == ".png":
        iio.imwrite(path, rgb)
    else:
        tifffile.imwrite(path, rgb, photometric="rgb")
    expected = rgb[..., :3].astype(np.float64) @ np.array([0.2125, 0.7154, 0.0721])
    np.testing.assert_allclose(np.rot90(read_image(path)), expected / 255, rtol=0, atol=1e-12)


def test_palette_png_to_grey(tmp_path):
    from PIL import Image

    Image.fromarray(picture()).convert("P", palette=Image.ADAPTIVE, colors=8).save(tmp_path / "p.png")
    rgb = np.asarray(Image.open(tmp_path / "p.png").convert("RGB"), dtype=np.float64)
    assert len(np.unique(rgb)) > 1
    expected = rgb @ np.array([0.2125, 0.7154, 0.0721])
    np.testing.assert_allclose(np.rot90(read_image(tmp_path / "p.png", integer_scale="raw")), expected, rtol=0,
                               atol=1e-12)


def test_grey_alpha_png_drops_alpha(tmp_path):
    la = np.stack([picture(), np.full((5, 7), 9, np.uint8)], axis=-1)
    iio.imwrite(tmp_path / "la.png", la)
    np.testing.assert_array_equal(np.rot90(read_image(tmp_path / "la.png", integer_scale="raw")), picture())


# --- 8- and 16-bit pictures as fractions of their full scale ------------------------------------------

@pytest.mark.parametrize("ext", [".png", ".tif"])
@pytest.mark.parametrize("dtype, full", [(np.uint8, 255), (np.uint16, 65535)])
def test_integer_picture_read_as_fraction_of_full_scale(tmp_path, caplog, ext, dtype, full):
    """As ``skimage.util.img_as_float``: 8-bit / 255, 16-bit / 65535, the log says so; ``raw`` keeps values."""
    from skimage.util import img_as_float

    shown = picture(dtype=dtype)
    shown[0, 0] = np.iinfo(dtype).max                            # full scale reads as 1
    path = tmp_path / f"pic{ext}"
    (iio.imwrite if ext == ".png" else tifffile.imwrite)(path, shown)
    with caplog.at_level("INFO", logger="indreg"):
        f = read_image(path)
    np.testing.assert_allclose(np.rot90(f), img_as_float(shown), rtol=0, atol=1e-15)
    assert f[0, -1] == 1.0 and f.max() == 1.0
    assert f"{8 * np.dtype(dtype).itemsize}-bit grey levels as fractions of {full}" in caplog.text
    np.testing.assert_array_equal(np.rot90(read_image(path, integer_scale="raw")), shown)
    np.testing.assert_allclose(read_sinogram(path), shown / full, rtol=0, atol=1e-15)


def test_big_endian_and_signed_tiffs(tmp_path):
    """A big-endian 16-bit TIFF is a 16-bit picture (/ 65535); a signed one keeps its values (no full scale)."""
    shown = picture(dtype=np.uint16)
    tifffile.imwrite(tmp_path / "be.tif", shown.astype(">u2"), byteorder=">")
    np.testing.assert_allclose(np.rot90(read_image(tmp_path / "be.tif")), shown / 65535, rtol=0, atol=1e-15)
    tifffile.imwrite(tmp_path / "s.tif", shown.astype(np.int16) - 50)
    np.testing.assert_array_equal(np.rot90(read_image(tmp_path / "s.tif")), shown.astype(np.int16) - 50)


def test_integer_arrays_and_float_pictures_keep_their_values(tmp_path):
    """Counts in ``.npy`` are physical: an integer array is not rescaled; nor is a float TIFF."""
    counts = picture(dtype=np.uint16)
    np.save(tmp_path / "c.npy", counts)
    np.testing.assert_array_equal(read_image(tmp_path / "c.npy"), counts)
    tifffile.imwrite(tmp_path / "f.tif", counts.astype(np.float32) * 0.5)
    np.testing.assert_array_equal(np.rot90(read_image(tmp_path / "f.tif")), counts * 0.5)


def test_bad_integer_scale_is_one_line(tmp_path):
    iio.imwrite(tmp_path / "p.png", picture())
    with pytest.raises(ValueError, match=r"^integer_scale must be one of fraction, raw, got 'scaled'$"):
        read_image(tmp_path / "p.png", integer_scale="scaled")


# --- errors: one line, naming the file and the problem ------------------------------------------------

def test_missing_file_and_unknown_format(tmp_path):
    one_line_error(read_image, tmp_path / "nope.npy", contains=("template file", "nope.npy", "no such file"))
    (tmp_path / "a.xyz").write_text("1")
    one_line_error(read_sinogram, tmp_path / "a.xyz", contains=("sinogram file", "a.xyz", "unknown format"))
    (tmp_path / "dir.npy").mkdir()
    one_line_error(read_image, tmp_path / "dir.npy", contains=("dir.npy", "is not a file"))


@pytest.mark.parametrize("ext", [".npy", ".npz", ".h5", ".png", ".tif", ".mrc"])
def test_unreadable_file(tmp_path, ext):
    path = tmp_path / f"junk{ext}"
    path.write_bytes(b"this is not a real file\nsecond line\n" * 3)
    one_line_error(read_image, path, name="target", contains=("target file", f"junk{ext}", "unreadable"))


def test_name_appears_in_message(tmp_path):
    one_line_error(read_image, tmp_path / "x.png", name="template", contains=("template file", "x.png"))


@pytest.mark.parametrize("shape", [(2, 3, 4), (5,), ()])
def test_wrong_dimensionality_names_shape(tmp_path, shape):
    np.save(tmp_path / "a.npy", np.ones(shape))
    one_line_error(read_image, tmp_path / "a.npy", contains=("a.npy", "2D", str(shape)))


def test_mrc_volume_is_not_a_sinogram(tmp_path):
    with mrcfile.new(tmp_path / "vol.mrc") as mrc:
        mrc.set_data(np.ones((4, 3, 5), np.float32))
    one_line_error(read_sinogram, tmp_path / "vol.mrc", contains=("vol.mrc", "(4, 3, 5)"))
    one_line_error(read_image, tmp_path / "vol.mrc", contains=("vol.mrc", "(4, 3, 5)"))


def test_empty_array(tmp_path):
    np.save(tmp_path / "e.npy", np.ones((0, 4)))
    one_line_error(read_image, tmp_path / "e.npy", contains=("e.npy", "empty"))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values(tmp_path, bad):
    a = array()
    a[2, 1] = bad
    np.save(tmp_path / "n.npy", a)
    one_line_error(read_sinogram, tmp_path / "n.npy", contains=("n.npy", "non-finite", "NaN or Inf"))


def test_complex_and_non_numeric_dtype(tmp_path):
    np.save(tmp_path / "c.npy", array() + 1j)
    one_line_error(read_image, tmp_path / "c.npy", contains=("c.npy", "complex"))
    np.save(tmp_path / "s.npy", np.array([["a", "b"], ["c", "d"]]))
    one_line_error(read_image, tmp_path / "s.npy", contains=("s.npy", "non-numeric", "<U1"))
    np.save(tmp_path / "o.npy", np.array([[1, None]], dtype=object))
    one_line_error(read_image, tmp_path / "o.npy", contains=("o.npy", "Python objects"))
    np.savez(tmp_path / "o.npz", a=np.array([[1, None]], dtype=object))
    one_line_error(read_image, tmp_path / "o.npz", contains=("o.npz", "Python objects"))
    with h5py.File(tmp_path / "s.h5", "w") as f:
        f.create_dataset("names", data=np.array([b"ab", b"cd"]))
    one_line_error(read_image, tmp_path / "s.h5", contains=("s.h5", "non-numeric"))


def test_npz_missing_or_ambiguous_key(tmp_path):
    np.savez(tmp_path / "two.npz", image=array(), sino=array())
    np.save(tmp_path / "a.npy", array())
    one_line_error(read_image, f"{tmp_path / 'a.npy'}:k", contains=("a.npy:k", "only for .npz"))
    one_line_error(read_image, tmp_path / "two.npz", contains=("two.npz", "2 arrays", "image", "sino"))
    one_line_error(read_image, f"{tmp_path / 'two.npz'}:other", contains=("two.npz", "'other'", "keys"))


def test_h5_missing_group_or_ambiguous_dataset(tmp_path):
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f.create_dataset("/g/a", data=array())
        f.create_dataset("/b", data=array())
    one_line_error(read_image, tmp_path / "d.h5", contains=("d.h5", "2 datasets", "/g/a", "/b"))
    one_line_error(read_image, f"{tmp_path / 'd.h5'}:/g/zz", contains=("d.h5", "/g/zz", "missing"))
    one_line_error(read_image, f"{tmp_path / 'd.h5'}:/g", contains=("d.h5", "group"))


def test_write_image_errors(tmp_path):
    one_line_error(write_image, tmp_path / "a.png", array(), contains=("a.png", "cannot write"))
    one_line_error(write_image, tmp_path / "a.npy", np.array([np.nan]), contains=("a.npy", "non-finite"))
    one_line_error(write_image, tmp_path / "a.mrc", np.ones(3), contains=("a.mrc", "(3,)"))
    one_line_error(write_image, tmp_path / "no" / "dir" / "a.npy", array(), contains=("a.npy", "cannot be written"))


# --- angles -------------------------------------------------------------------------------------------

def test_angle_file_with_comments_and_blank_lines(tmp_path):
    path = tmp_path / "series.tlt"
    path.write_text("# tilt angles\n  -60.0\n\n-30   # comment\n0\n 30.5\n\t\n60\n")
    np.testing.assert_allclose(read_angles(path), np.deg2rad([-60, -30, 0, 30.5, 60]), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(read_angles(str(path), "rad"), [-60, -30, 0, 30.5, 60])
    theta = np.array([0.1, 1.2, 2.9])
    np.savetxt(tmp_path / "exported.tlt", np.rad2deg(theta))         # the export recipe of the docs
    np.testing.assert_allclose(read_angles(tmp_path / "exported.tlt"), theta, rtol=1e-14)


@pytest.mark.parametrize("junk,line", [("abc", 3), ("1.0 2.0", 3), ("nan", 3), ("1,5", 3)])
def test_angle_file_junk_line_is_named(tmp_path, junk, line):
    path = tmp_path / "bad.rawtlt"
    path.write_text(f"0\n# ok\n{junk}\n10\n")
    one_line_error(read_angles, path, contains=("angles file", "bad.rawtlt", f"line {line}"))


def test_angle_file_missing_or_empty(tmp_path):
    one_line_error(read_angles, tmp_path / "none.tlt", contains=("none.tlt", "no such file"))
    (tmp_path / "empty.tlt").write_text("# nothing\n\n")
    one_line_error(read_angles, tmp_path / "empty.tlt", contains=("empty.tlt", "no angles"))
    (tmp_path / "bin.tlt").write_bytes(b"\xff\xfe\x00\x81")
    one_line_error(read_angles, tmp_path / "bin.tlt", contains=("bin.tlt", "text"))


def test_inline_angles_deg_and_rad():
    np.testing.assert_allclose(read_angles([0, 90, 180]), [0, math.pi / 2, math.pi], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(read_angles((0.0, 1.5), unit="rad"), [0.0, 1.5])
    out = read_angles(np.array([45.0]))
    assert out.dtype == np.float64 and out.shape == (1,) and out[0] == pytest.approx(math.pi / 4)


@pytest.mark.parametrize("values", [[], [[1, 2]], [1, float("nan")], ["a", 1]])
def test_inline_angles_errors(values):
    with pytest.raises(ValueError, match="angles") as info:
        read_angles(values)
    assert "\n" not in str(info.value)


def test_angle_unit_must_be_deg_or_rad():
    with pytest.raises(ValueError, match="angle_unit"):
        read_angles([1.0], unit="grad")


def test_tilt_angles_for_prefers_tlt_then_rawtlt(tmp_path):
    sino = tmp_path / "series.st"
    assert tilt_angles_for(sino) is None
    (tmp_path / "series.rawtlt").write_text("0\n")
    assert tilt_angles_for(sino) == tmp_path / "series.rawtlt"
    (tmp_path / "series.tlt").write_text("0\n")
    assert tilt_angles_for(str(sino)) == tmp_path / "series.tlt"
    (tmp_path / "data.tlt").write_text("0\n")
    assert tilt_angles_for(f"{tmp_path / 'data.h5'}:/sino") == tmp_path / "data.tlt"


# --- skimage's radon in indreg's convention (docs/file_formats.md) -------------------------------------

@pytest.mark.parametrize("n", [31, 32])
@pytest.mark.parametrize("circle", [True, False])
def test_skimage_radon_matches_ray_transform(n, circle):
    """``radon(np.rot90(f), theta_deg).T * h`` is indreg's data of ``f`` on the domain centred on skimage's
    rotation centre (pixel ``n // 2``), angles ``deg2rad(theta_deg)``, ``det_min = -(D // 2 + 1/2) h``."""
    from skimage.transform import radon

    h, c = 0.5, n // 2
    dom = ImageDomain((n, n), (-(c + 0.5) * h, -(n - c - 0.5) * h), ((n - c - 0.5) * h, (c + 0.5) * h))
    X, Y = torch.meshgrid(*dom.axes(), indexing="ij")
    f = (torch.exp(-((X - 2.5) ** 2 + (Y - 1.0) ** 2) / 2) + 0.5 * torch.exp(-((X + 1) ** 2 + (Y + 3) ** 2))).numpy()
    theta = np.array([0.0, 20.0, 50.0, 90.0, 130.0, 170.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # skimage: tails of the blobs reach beyond the inscribed circle
        sk = radon(np.rot90(f), theta=theta, circle=circle)
    D = sk.shape[0]
    det_min = -(D // 2 + 0.5) * h
    geometry = ParallelBeamGeometry(angles=np.deg2rad(theta), det_count=D, det_min=det_min, det_max=det_min + D * h)
    g = RayTransform(dom, geometry)(torch.from_numpy(f.copy())).numpy()
    err = np.abs(sk.T * h - g).max() / np.abs(g).max()
    assert err < 0.02                                          # two interpolation schemes, same line integrals
    flipped = np.abs(sk.T[:, ::-1] * h - g).max() / np.abs(g).max()
    assert flipped > 0.3                                       # the test would see a detector flip


# --- 3D: volumes and tilt series ----------------------------------------------------------------------------

VOLUME_DOMAIN = ImageDomain((6, 5, 4), (-3.0, -2.0, 0.0), (3.0, 0.5, 6.0))   # cell sides (1, 0.5, 1.5)


def volume():
    return np.random.default_rng(1).random(VOLUME_DOMAIN.shape).astype(np.float32).astype(np.float64)


def test_mrc_volume_round_trip_axis_order_and_voxel_size(tmp_path):
    v = volume()
    write_volume(tmp_path / "v.mrc", torch.from_numpy(v), VOLUME_DOMAIN)
    np.testing.assert_array_equal(read_volume(tmp_path / "v.mrc"), v)
    np.testing.assert_array_equal(read_image(tmp_path / "v.mrc", ndim=3), v)
    assert read_voxel_size(tmp_path / "v.mrc") == pytest.approx((1.0, 0.5, 1.5))
    with mrcfile.open(tmp_path / "v.mrc") as mrc:   # MRC's own view: nx, ny, nz columns, rows, sections
        assert (int(mrc.header.nx), int(mrc.header.ny), int(mrc.header.nz)) == (6, 5, 4)
        assert (int(mrc.header.mapc), int(mrc.header.mapr), int(mrc.header.maps)) == (1, 2, 3)
        assert float(mrc.data[3, 2, 1]) == v[1, 2, 3]                       # data[z, y, x]


@pytest.mark.parametrize("ext", [".npy", ".h5"])
def test_volume_arrays_read_as_stored(tmp_path, ext):
    v = volume()
    if ext == ".npy":
        write_volume(tmp_path / "v.npy", v, VOLUME_DOMAIN)
    else:
        with h5py.File(tmp_path / "v.h5", "w") as f:
            f["/vol"] = v
    np.testing.assert_array_equal(read_volume(tmp_path / f"v{ext}"), v)


def test_tilt_series_round_trip_with_tlt(tmp_path):
    """A simulated tilt series written as an MRC stack + .tlt is read back as the operator's data."""
    dom = ImageDomain.paper(8, 3)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 15, det_count=12))
    y = T(torch.rand(dom.shape, dtype=torch.float64)).float().double()
    write_tilt_series(tmp_path / "ts.mrc", y, T.geometry.angles, pixel_size=T.geometry.det_cell)
    assert (tmp_path / "ts.tlt").read_text().splitlines()[0] == "-60.000000"
    data, angles = read_tilt_series(tmp_path / "ts.mrc")
    np.testing.assert_array_equal(data, y.numpy())
    np.testing.assert_allclose(angles, T.geometry.angles.numpy(), rtol=0, atol=1e-8)
    assert read_voxel_size(tmp_path / "ts.mrc")[0] == pytest.approx(T.geometry.det_cell, rel=1e-6)
    (tmp_path / "ts.tlt").rename(tmp_path / "ts.rawtlt")
    assert read_tilt_series(tmp_path / "ts.mrc")[1].shape == (9,)
    np.testing.assert_allclose(read_tilt_series(tmp_path / "ts.mrc", angles=np.arange(9) * 0.1, unit="rad")[1],
                               np.arange(9) * 0.1)


def test_3d_bad_input_one_line_errors(tmp_path):
    v = volume()
    write_volume(tmp_path / "v.mrc", v)
    with pytest.raises(DataFileError, match=r"template file .*v.mrc: must hold a 2D array, got shape \(4, 5, 6\)"):
        read_image(tmp_path / "v.mrc")
    np.save(tmp_path / "flat.npy", v[0])
    with pytest.raises(DataFileError, match=r"flat.npy: must hold a 3D array, got shape \(5, 4\)"):
        read_volume(tmp_path / "flat.npy")
    with pytest.raises(DataFileError, match="a volume must be .*not a picture"):
        read_volume(tmp_path / "v.png")
    with pytest.raises(DataFileError, match="volume has shape"):
        write_volume(tmp_path / "w.mrc", v[:, :, :2], VOLUME_DOMAIN)
    with pytest.raises(DataFileError, match="non-finite"):
        write_volume(tmp_path / "w.mrc", np.full((2, 2, 2), np.nan))
    with pytest.raises(DataFileError, match="must be a non-empty real 3D array"):
        write_volume(tmp_path / "w.npy", v[0])
    write_tilt_series(tmp_path / "ts.mrc", np.ones((3, 2, 4)), np.zeros(3))
    (tmp_path / "ts.tlt").unlink()
    with pytest.raises(DataFileError, match=r"ts.mrc: no tilt angles: give angles= or put ts.tlt"):
        read_tilt_series(tmp_path / "ts.mrc")
    with pytest.raises(DataFileError, match="3 tilts .* but angles gives 2 angles"):
        read_tilt_series(tmp_path / "ts.mrc", angles=[0.0, 1.0])
    with pytest.raises(ValueError, match="angle_unit must be 'deg' or 'rad'"):
        read_tilt_series(tmp_path / "ts.mrc", angles=[0, 1, 2], unit="degree")
    with pytest.raises(DataFileError, match="needs 3 finite angles"):
        write_tilt_series(tmp_path / "ts.mrc", np.ones((3, 2, 4)), [0.0, 1.0])
    with pytest.raises(DataFileError, match="only MRC files"):
        read_voxel_size(tmp_path / "flat.npy")
    with pytest.raises(ValueError, match="ndim must be 2 or 3"):
        read_image(tmp_path / "v.mrc", ndim=4)


def test_paths_and_scalar_arguments_are_type_checked(tmp_path):
    # Path(None) raised pathlib's TypeError; pixel_size "1.5", True or nan went into the MRC header
    v = volume()
    for call, name in ((lambda p: read_image(p), "template"), (lambda p: read_volume(p), "template"),
                       (lambda p: read_sinogram(p), "sinogram"), (lambda p: read_voxel_size(p), "volume"),
                       (lambda p: tilt_angles_for(p), "sinogram"), (lambda p: write_image(p, v), "output"),
                       (lambda p: write_volume(p, v), "output"), (lambda p: write_tilt_series(p, v, np.zeros(len(v))),
                                                                   "output")):
        for bad in (None, 3, True, ["a.npy"]):
            with pytest.raises(DataFileError, match=f"^{name} path must be a str or os.PathLike, got "):
                call(bad)
    for bad, error in (("1.5", TypeError), (True, TypeError), (math.nan, ValueError), (0.0, ValueError)):
        with pytest.raises(error, match="^pixel_size must be a "):
            write_tilt_series(tmp_path / "ts.mrc", v, np.zeros(len(v)), pixel_size=bad)
    with pytest.raises(TypeError, match="^domain must be an ImageDomain or None, got tuple"):
        write_volume(tmp_path / "w.mrc", v, domain=v.shape)
