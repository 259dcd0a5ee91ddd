"""Small text files (angles, ``.mdoc`` metadata; the alignment files in tests/alignment): read only when they are
regular files of a sane size and UTF-8, else refused in one line naming the file; an ``.mdoc``'s tilt axis angle
that is not a finite number is refused, not read as 0 degrees."""
import os

import pytest

from indreg.io import DataFileError
from indreg.io._files import MAX_TEXT_BYTES, read_text
from indreg.io.angle_files import read_angles, read_tilt_axis_angle


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "abc", "1e999", "85.3abc", ""])
def test_mdoc_tilt_axis_angle_that_is_not_a_number_is_refused(tmp_path, value):
    mdoc = tmp_path / "s.mrc.mdoc"
    mdoc.write_text(f"PixelSpacing = 1.0\nTiltAxisAngle = {value}\nTiltAxisAngle = 3\n")
    with pytest.raises(DataFileError, match=r"s\.mrc\.mdoc: line 2: the tilt axis angle is not a finite number") as e:
        read_tilt_axis_angle(mdoc)
    assert "\n" not in str(e.value)


def test_mdoc_angles_in_title_lines_still_read(tmp_path):
    mdoc = tmp_path / "s.mdoc"
    mdoc.write_text("[T = SerialEM: Tilt axis angle = 85.3, binning = 1]\n")
    assert read_tilt_axis_angle(mdoc) == pytest.approx(85.3)


def test_non_utf8_angles_are_refused_naming_the_byte(tmp_path):
    tlt = tmp_path / "a.tlt"
    tlt.write_bytes(b"-60\n0\n\xff60\n")
    with pytest.raises(DataFileError, match=r"a\.tlt: is not UTF-8 text: byte 0xff at offset 6 \(line 3\)"):
        read_angles(tlt)


def test_a_huge_text_file_is_refused_before_it_is_read(tmp_path, monkeypatch):
    big = tmp_path / "big.tlt"
    with open(big, "wb") as f:                 # sparse: no disk used, no time spent
        f.truncate(MAX_TEXT_BYTES + 1)
    monkeypatch.setattr("builtins.open", lambda *a, **k: pytest.fail("the file was opened"))
    with pytest.raises(DataFileError, match=r"big\.tlt: is 16777217 bytes, more than the 16777216"):
        read_text(big, "angles")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs (POSIX)")
def test_a_fifo_is_refused_not_waited_on(tmp_path):
    os.mkfifo(tmp_path / "a.tlt")
    with pytest.raises(DataFileError, match="is not a regular file"):
        read_angles(tmp_path / "a.tlt")
