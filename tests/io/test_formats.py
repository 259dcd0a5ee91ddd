"""indreg.io.formats: the registry of file formats. The built-ins in their order; a FileFormat's checks; a suffix held
by one format; plug-in formats of each kind (a container, sections stored (z, y, x) with a voxel size, a picture, a
write-only one) through every reader and writer; a plug-in's errors as one line; the deprecated suffix tuples."""
import subprocess
import sys
import warnings

import numpy as np
import pytest

import indreg
from indreg import io
from indreg.io import DataFileError, FileFormat, register_format
from indreg.io.formats import FILE_FORMATS, get_format, split_path, suffixes


@pytest.fixture
def registry():
    """What a test registers goes with it."""
    saved = dict(FILE_FORMATS)
    yield
    FILE_FORMATS.clear()
    FILE_FORMATS.update(saved)


def test_the_builtin_formats_and_their_suffixes():
    assert suffixes() == (".npy", ".npz", ".h5", ".hdf5", ".hspy", ".mrc", ".st", ".ali", ".png", ".tif", ".tiff")
    assert suffixes("container") == (".npz", ".h5", ".hdf5", ".hspy")
    assert suffixes("picture") == (".png", ".tif", ".tiff")
    assert suffixes("sections") == suffixes("read_voxel_size") == (".mrc", ".st", ".ali")
    assert suffixes("write") == (".npy", ".mrc", ".st", ".ali")
    assert get_format(".TIFF").name == "TIFF" and get_format(".xyz") is None and get_format("") is None
    assert get_format(".mrc").volume_order == "zyx" and get_format(".npy").volume_order == "xyz"


@pytest.mark.parametrize("kwargs, error, message", [
    ({"suffixes": "grid"}, ValueError, r"suffixes must be like '\.ext'"),
    ({"suffixes": ".tar.gz"}, ValueError, r"suffixes must be like '\.ext'"),
    ({"suffixes": ()}, ValueError, r"suffixes must be like '\.ext'"),
    ({"suffixes": (".a", 3)}, ValueError, r"suffixes must be like '\.ext'"),
    ({"read": None}, ValueError, "needs a read or a write function"),
    ({"read": "np.load"}, TypeError, "read must be callable or None, got str"),
    ({"signature": "GRID"}, TypeError, "signature must be bytes, got str"),
    ({"volume_order": "yxz"}, ValueError, "volume_order must be one of xyz, zyx, got 'yxz'"),
    ({"name": ""}, TypeError, "name must be a non-empty str"),
])
def test_a_bad_format_is_refused_in_one_line(kwargs, error, message):
    with pytest.raises(error, match=message):
        FileFormat(**{"name": "x", "suffixes": ".x", "read": np.load, **kwargs})


def test_suffixes_are_lower_case_and_one_format_holds_each(registry):
    fmt = FileFormat("Mine", (".MINE", ".mine"), read=np.load)
    assert fmt.suffixes == (".mine",)
    with pytest.raises(TypeError, match="register_format takes an indreg.io.formats.FileFormat, got dict"):
        register_format({"name": "Mine"})
    with pytest.raises(ValueError, match=r"suffix \.tif is format 'TIFF''s; register a FileFormat named 'TIFF'"):
        register_format(FileFormat("my TIFF", ".tif", read=np.load))
    assert get_format(".tif").name == "TIFF"                     # nothing registered by the refused call
    other = register_format(FileFormat("TIFF", (".tif", ".tiff"), read=lambda path: (np.load(path), False),
                                       picture=True))
    assert get_format(".tiff") is other and list(FILE_FORMATS).index("TIFF") == 5   # replaced in its place


def _plugins():
    """A container (``.arrs``: numpy's zip under another suffix), a stack of sections stored (z, y, x) with a voxel
    size in its header (``.sec``), a picture (``.pix``: 8-bit grey levels) and a write-only format (``.out``)."""
    def read_arrs(path, key):
        with np.load(path) as f:
            return f[key or "a"]

    def write_sec(path, array, voxel_size=None, origin=None):
        with open(path, "wb") as f:
            np.savez(f, data=array, voxel_size=np.asarray(voxel_size if voxel_size is not None else (1, 1, 1)),
                     origin=np.asarray(origin if origin is not None else (0, 0, 0)))

    def read_sec(path):
        with np.load(path) as f:
            return f["data"]

    def sec_voxel_size(path):
        with np.load(path) as f:
            return tuple(f["voxel_size"])

    register_format(FileFormat("Arrays", ".arrs", read=read_arrs, container=True))
    register_format(FileFormat("Sections", ".sec", read=read_sec, write=write_sec, volume_order="zyx", sections=True,
                               read_voxel_size=sec_voxel_size))
    register_format(FileFormat("Pix", ".pix", read=lambda path: (np.load(path), False), picture=True))
    register_format(FileFormat("Out", ".out", write=lambda path, array: np.save(open(path, "wb"), array)))


def test_a_plugin_container_takes_keys(registry, tmp_path):
    _plugins()
    a, b = np.arange(12.0).reshape(3, 4), np.arange(20.0).reshape(4, 5)
    np.savez(tmp_path / "f.npz", a=a, b=b)
    (tmp_path / "f.npz").rename(tmp_path / "f.arrs")
    assert split_path(f"{tmp_path / 'f.arrs'}:b") == (tmp_path / "f.arrs", "b")
    np.testing.assert_array_equal(io.read_image(f"{tmp_path / 'f.arrs'}:b"), b)
    np.testing.assert_array_equal(io.read_sinogram(tmp_path / "f.arrs"), a)        # key None: the reader's choice
    with pytest.raises(DataFileError, match=r"a ':KEY' suffix is only for \.npz, \.h5, \.hdf5, \.hspy, \.arrs files"):
        io.read_image(f"{tmp_path / 'x.npy'}:k")


def test_a_plugin_of_sections_is_transposed_and_carries_a_voxel_size(registry, tmp_path):
    _plugins()
    rng = np.random.default_rng(0)
    volume = rng.standard_normal((4, 5, 3))
    domain = indreg.ImageDomain((4, 5, 3), (-2.0, -5.0, 0.0), (2.0, 5.0, 6.0))
    io.write_volume(tmp_path / "v.sec", volume, domain)
    with np.load(tmp_path / "v.sec") as f:   # as stored: sections (z, y, x), the domain's cells and first centre
        np.testing.assert_array_equal(f["data"], volume.transpose(2, 1, 0))
        np.testing.assert_allclose(f["origin"], [-1.5, -4.0, 1.0])
    np.testing.assert_array_equal(io.read_volume(tmp_path / "v.sec"), volume)
    assert io.read_voxel_size(tmp_path / "v.sec") == pytest.approx((1.0, 2.0, 2.0))
    section = rng.standard_normal((1, 6, 7))
    io.write_image(tmp_path / "one.sec", section)                                  # one section (1, nx, ny)
    np.testing.assert_array_equal(io.read_image(tmp_path / "one.sec"), section[0])
    stack, angles = rng.standard_normal((5, 1, 8)), np.linspace(-1.0, 1.0, 5)
    io.write_tilt_series(tmp_path / "ts.sec", stack, angles, pixel_size=2.0)
    assert io.read_voxel_size(tmp_path / "ts.sec") == (2.0, 2.0, 1.0)
    data, radians = io.read_tilt_series(tmp_path / "ts.sec")                       # its angles from ts.tlt
    np.testing.assert_array_equal(data, stack)
    np.testing.assert_allclose(radians, angles, atol=1e-7)
    np.testing.assert_array_equal(io.read_sinogram(tmp_path / "ts.sec"), stack[:, 0, :])   # one-row projections
    with pytest.raises(DataFileError, match=r"a tilt series is written as MRC or Sections \(\.mrc, \.st, \.ali, \.sec\)$"):
        io.write_tilt_series(tmp_path / "ts.npy", stack, angles)
    with pytest.raises(DataFileError, match=r"only MRC or Sections files \(\.mrc, \.st, \.ali, \.sec\) carry a voxel"):
        io.read_voxel_size(tmp_path / "x.npy")


def test_a_plugin_picture_is_turned_upright_and_is_no_volume(registry, tmp_path):
    _plugins()
    displayed = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    np.save(open(tmp_path / "p.pix", "wb"), displayed)
    np.testing.assert_allclose(io.read_image(tmp_path / "p.pix"), np.rot90(displayed / 255.0, k=-1))
    np.testing.assert_array_equal(io.read_image(tmp_path / "p.pix", integer_scale="raw"), np.rot90(displayed, k=-1))
    with pytest.raises(DataFileError, match=r"a volume must be \.npy, \.npz, .*\.ali, \.arrs, \.sec, not a picture$"):
        io.read_volume(tmp_path / "p.pix")


def test_read_only_and_write_only_formats_are_refused_the_other_way(registry, tmp_path):
    _plugins()
    io.write_image(tmp_path / "r.out", np.ones((2, 2)))
    with pytest.raises(DataFileError, match=r"format Out is written only, not read: '\.out'; supported: \.npy, .*\.sec, "
                                            r"\.pix$"):
        io.read_image(tmp_path / "r.out")
    with pytest.raises(DataFileError, match=r"cannot write format '\.pix'; use \.npy, \.mrc, \.st, \.ali, \.sec, \.out$"):
        io.write_image(tmp_path / "w.pix", np.ones((2, 2)))


def test_a_plugins_own_errors_are_one_line_naming_the_file(registry, tmp_path):
    def broken(*args, **kwargs):
        raise RuntimeError("boom\n  at line 2")

    register_format(FileFormat("Broken", ".brk", read=broken, write=broken))
    (tmp_path / "b.brk").write_text("x")
    with pytest.raises(DataFileError, match=r"^template file .*b\.brk: unreadable as \.brk \(RuntimeError: boom at line "
                                            r"2\)$"):
        io.read_image(tmp_path / "b.brk")
    with pytest.raises(DataFileError, match=r"^output file .*c\.brk: cannot be written \(RuntimeError: boom at line 2\)$"):
        io.write_volume(tmp_path / "c.brk", np.ones((2, 2, 2)))


def test_the_old_suffix_tuples_warn_and_come_from_the_registry(registry):
    _plugins()
    for old, new in (("FORMATS", "read"), ("PICTURE", "picture"), ("MRC", "sections"), ("CONTAINER", "container"),
                     ("WRITE_FORMATS", "write")):
        with pytest.warns(DeprecationWarning, match=rf"^indreg\.io\.{old} is deprecated and will be removed in indreg "
                                                    rf"0\.2\.0: use indreg\.io\.formats\.suffixes\('{new}'\)"):
            assert getattr(io, old) == suffixes(new)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ".pix" in suffixes("picture") and ".sec" in suffixes("sections")
    with pytest.raises(AttributeError, match="module 'indreg.io' has no attribute 'FORMAT'"):
        io.FORMAT


def test_the_registry_loads_no_torch():
    code = ("import sys\nfrom indreg.io import FileFormat, register_format, read_image, write_volume\n"
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
