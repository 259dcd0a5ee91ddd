"""``indreg-align`` refuses in one line, before it writes anything: option values that used to crash or silently
mean the default, a planted link in the output directory (or the default directory being one), a constant stack,
a stack whose object is darker than its background (unless ``--invert``); a shift that ends at its bound is warned
about and recorded."""
import json
import logging
import os

import numpy as np
import pytest

from indreg.alignment.app import main
from indreg.alignment.app_checks import at_bound
from indreg.alignment.files import read_xf, write_alignment
from indreg.io import write_tilt_series

from test_align_app import AXIS, _raw_series


@pytest.fixture()
def stack(tmp_path):
    """A small stack (6 tilts of 24 x 24 px, a blob) and its .tlt."""
    y, x = np.mgrid[:24, :24] - 11.5
    image = np.exp(-(x ** 2 + y ** 2) / 20.0)
    write_tilt_series(tmp_path / "s.mrc", np.stack([image] * 6), np.radians(np.linspace(-50, 50, 6)), pixel_size=1.0)
    return tmp_path / "s.mrc"


def _refused(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("indreg-align: error: "), err
    return err


@pytest.mark.parametrize("option, message", [
    (["--max-memory", "1e999"], "--max-memory must be a finite size > 0, got '1e999'"),
    (["--tilt-axis-angle", "inf"], "--tilt-axis-angle must be a finite number, got inf"),
    (["--tilt-axis-angle", "nan"], "--tilt-axis-angle must be a finite number, got nan"),
    (["--rounds", "0"], "--rounds must be an integer >= 1, got 0"),
    (["--iters", "0"], "--iters must be an integer >= 1, got 0"),
    (["--threads", "-1"], "--threads must be an integer in [1, "),
    (["--threads", "100000"], "--threads must be an integer in [1, "),
    (["--thickness", "-5"], "--thickness must be an integer >= 1, got -5"),
    (["--thickness", "0"], "--thickness must be an integer >= 1, got 0"),
    (["--bin", "0"], "--bin must be an integer >= 1, got 0"),
    (["--pixel-size", "0"], "--pixel-size must be a finite number > 0, got 0.0"),
    (["--recon-bin", "1000"], "--recon-bin 1000 leaves less than 8 pixels of the 24 x 24 images: at most 3"),
    (["--bin", "64"], "--bin 64 leaves less than 8 pixels"),
    (["--thickness", "1000"], "--thickness 1000 is more than 4 times the images' width (24 px)"),
    (["--angles", "missing.tlt"], "--angles missing.tlt: no such file, and not a comma list of angles"),
])
def test_option_values_are_refused_before_anything_is_written(tmp_path, capsys, stack, option, message):
    err = _refused(capsys, [str(stack), "--out", str(tmp_path / "out")] + option)
    assert message in err, err
    assert not (tmp_path / "out").exists()


OUTPUTS = ("alignment.xf", "alignment.tlt", "alignment.aln", "alignment.json", "aligned.mrc", "aligned.tlt",
           "reconstruction.mrc", "reconstruction.zarr", "align.json")


@pytest.mark.parametrize("name", OUTPUTS)
def test_a_link_in_the_output_directory_is_refused_and_nothing_is_touched(tmp_path, capsys, stack, name):
    out, victim = tmp_path / "out", tmp_path / "victim"
    out.mkdir()
    victim.write_text("precious")
    (out / name).symlink_to(victim)
    err = _refused(capsys, [str(stack), "--out", str(out), "--zarr"])
    assert f"output directory {out}: {name} is a symbolic link" in err
    assert victim.read_text() == "precious" and sorted(os.listdir(out)) == [name]


def test_the_default_output_directory_may_not_be_a_planted_link(tmp_path, capsys, stack):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "s_align").symlink_to(elsewhere, target_is_directory=True)
    err = _refused(capsys, [str(stack)])
    assert "the default output directory" in err and "is a symbolic link" in err
    assert os.listdir(elsewhere) == []


def test_the_alignment_files_replace_links_never_follow_them(tmp_path):
    """The writers themselves (``write_alignment``): a link planted after the app's check is replaced."""
    a = read_xf(_xf(tmp_path))
    out, victim = tmp_path / "out", tmp_path / "victim"
    out.mkdir()
    victim.write_text("precious")
    for name in ("alignment.xf", "alignment.tlt", "alignment.aln", "alignment.json"):
        (out / name).symlink_to(victim)
    write_alignment(out, a)
    assert victim.read_text() == "precious" and not any((out / n).is_symlink() for n in os.listdir(out))


def _xf(tmp_path):
    np.savetxt(tmp_path / "a.xf", [[1, 0, 0, 1, 0.5, 0]] * 3)
    np.savetxt(tmp_path / "a.tlt", [-10.0, 0.0, 10.0])
    return tmp_path / "a.xf"


@pytest.mark.parametrize("value", [0.0, 3.5])
def test_a_constant_stack_is_refused(tmp_path, capsys, value):
    write_tilt_series(tmp_path / "c.mrc", np.full((4, 16, 16), value), np.radians([-30, -10, 10, 30]))
    err = _refused(capsys, [str(tmp_path / "c.mrc"), "--out", str(tmp_path / "out")])
    assert f"the stack is constant (every value {value:.6g}): there is nothing to align" in err
    assert not (tmp_path / "out").exists()


def test_a_darker_object_needs_invert(tmp_path, capsys, stack):
    from indreg.io import read_tilt_series

    data, radians = read_tilt_series(stack)
    write_tilt_series(tmp_path / "bf.mrc", 5.0 - data, radians)     # bright field: the object darker
    err = _refused(capsys, [str(tmp_path / "bf.mrc"), "--out", str(tmp_path / "out")])
    assert "the object is darker than the background" in err and "give --invert" in err
    err = _refused(capsys, [str(stack), "--invert", "--out", str(tmp_path / "out")])
    assert "drop --invert" in err


@pytest.mark.slow   # two small alignments: ~10 s
def test_an_inverted_stack_aligns_with_invert_as_the_plain_one(tmp_path):
    theta, _ = _raw_series(tmp_path)
    from indreg.io import read_tilt_series

    raw, radians = read_tilt_series(tmp_path / "raw.mrc")
    write_tilt_series(tmp_path / "bf.mrc", 3.0 * raw.max() - raw, radians, pixel_size=2.5)
    args = ["--tilt-axis-angle", str(AXIS), "--rounds", "2", "--iters", "10", "--thickness", "16", "--bin", "1"]
    assert main([str(tmp_path / "raw.mrc"), "--out", str(tmp_path / "plain")] + args) == 0
    assert main([str(tmp_path / "bf.mrc"), "--invert", "--out", str(tmp_path / "inv")] + args) == 0
    plain, inverted = (json.loads((tmp_path / d / "align.json").read_text()) for d in ("plain", "inv"))
    assert inverted["inverted"] and inverted["residual_after"] < 0.5 * inverted["residual_before"]
    np.testing.assert_allclose(np.loadtxt(tmp_path / "inv/alignment.xf"), np.loadtxt(tmp_path / "plain/alignment.xf"),
                               atol=0.05)


def test_shifts_at_their_bound_are_named(caplog):
    shifts = np.array([[0.0, 1.0], [8.0, 0.0], [-2.0, -8.0], [7.9, 7.9]])
    with caplog.at_level(logging.WARNING, logger="indreg.align"):
        assert at_bound(shifts, np.array([8.0, 8.0]), 2) == [1, 2]
    assert "2 tilt(s) ended with a shift at its bound (16, 16 px of the stack" in caplog.text
    assert at_bound(shifts[:1], np.array([8.0, 8.0])) == []
