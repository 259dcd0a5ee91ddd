"""Damaged or crafted alignment files: refused in one line naming the file (and the line or byte), never a raw
UnicodeDecodeError, ``int()`` / ``float()`` error, a minutes-long parse of a huge file, or an index overflow."""
import time

import numpy as np
import pytest

import indreg
from indreg.alignment.files import read_aln, read_xf
from indreg.io import DataFileError, write_tilt_series
from indreg.io._files import MAX_TEXT_BYTES


def _xf(tmp_path, text=b"1 0 0 1 0 0\n", tlt=b"0\n"):
    (tmp_path / "a.xf").write_bytes(text)
    (tmp_path / "a.tlt").write_bytes(tlt)
    return tmp_path / "a.xf"


@pytest.mark.parametrize("which", ["xf", "tlt", "xtilt"])
def test_bytes_that_are_not_utf8_name_the_file_and_byte(tmp_path, which):
    path = _xf(tmp_path)
    bad = {"xf": path, "tlt": tmp_path / "a.tlt", "xtilt": tmp_path / "a.xtilt"}[which]
    bad.write_bytes(b"1 0 0 1 0 0\n\xfe\xff\n" if which == "xf" else b"0\n\xfe\n")
    with pytest.raises(DataFileError, match=rf"a\.{which}: is not UTF-8 text: byte 0xfe at offset \d+ \(line 2\)"):
        read_xf(path)


@pytest.mark.parametrize("line, message", [
    (b"# RawSize = x y z\n", r"line 1: RawSize must be three integers >= 1 \(nx ny sections\), got 'x y z'"),
    (b"# RawSize = 8 8\n", "line 1: RawSize must be three integers"),
    (b"# DarkFrame = 0 nan 0\n", "line 1: DarkFrame has a non-finite number"),
    (b"# DarkFrame = 0 zero 0\n", "line 1: DarkFrame is not numbers"),
    (b"0 0 1 nan 0 1 1 1 0 0\n", "line 1: the row has a non-finite number"),
    (b"\xff\n", r"is not UTF-8 text: byte 0xff at offset 0 \(line 1\)"),
])
def test_aln_fields(tmp_path, line, message):
    (tmp_path / "a.aln").write_bytes(line + b"0 0 1 0 0 1 1 1 0 0\n")
    with pytest.raises(DataFileError, match=message) as e:
        read_aln(tmp_path / "a.aln")
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("suffix", [".xf", ".aln"])
def test_a_huge_file_is_refused_before_it_is_read(tmp_path, suffix):
    path = tmp_path / f"a{suffix}"
    with open(path, "wb") as f:                 # 10^7 lines would be ~700 MB; sparse, no disk used
        f.truncate(MAX_TEXT_BYTES + 1)
    t0 = time.perf_counter()
    with pytest.raises(DataFileError, match="more than the 16777216 indreg reads"):
        read_xf(path, [0.0]) if suffix == ".xf" else read_aln(path)
    assert time.perf_counter() - t0 < 1.0


def test_a_shift_beyond_the_images_is_refused_by_load(tmp_path):
    """``data.alignment=`` with a 1e300 shift used to end in ``RuntimeError: index -9223372036854775808``."""
    n = 8
    write_tilt_series(tmp_path / "s.mrc", np.ones((2, n, n)), np.radians([-10.0, 10.0]), pixel_size=1.0)
    np.save(tmp_path / "t.npy", np.ones((n, n, n)))
    np.savetxt(tmp_path / "s.xf", [[1, 0, 0, 1, 0, 0], [1, 0, 0, 1, 1e300, 0]])
    np.savetxt(tmp_path / "s.tlt", [-10.0, 10.0])
    with pytest.raises(DataFileError, match=r"s\.xf: tilt 1's shift \(-1e\+300, -0\) px is beyond the stack's "
                                            r"8 x 8 px images"):
        indreg.load(tmp_path / "t.npy", tmp_path / "s.mrc", "tilt_series", alignment=tmp_path / "s.xf",
                    half_width=n / 2)
