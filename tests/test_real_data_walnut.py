"""examples/real_data_walnut.py (docs/real_data_walnut.md) on a synthetic stand-in of the walnut sinogram, and on
the real file when ``INDREG_WALNUT_DIR`` names a folder holding ``walnut_sinogram.png`` (see the example's
docstring for where to get it)."""
import importlib.util
import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from indreg import phantoms

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "real_data_walnut.py"
SHIFT_MM = 0.3           # the stand-in's detector shift (the real one: 0.27 mm)
LEVEL = 0.02             # the stand-in's level outside the object (the real one: 0.0203)
WALNUT = [(1.0, 0.75, 0.65, 0.0, 0.0, 10.0), (-0.8, 0.68, 0.58, 0.0, 0.0, 10.0),     # a shell
          (1.2, 0.35, 0.45, -0.05, 0.05, 0.0), (0.6, 0.15, 0.2, 0.3, -0.2, 30.0)]    # the kernel, off-centre


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("real_data_walnut", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def write_png(folder: Path, sino: np.ndarray) -> None:
    """``sino`` ``(angles, bins)`` in [0, 1] as gratopy stores it: 16-bit, detector x angle."""
    Image.fromarray(np.round(sino.T * 65535).astype(np.uint16)).save(folder / "walnut_sinogram.png")


@pytest.fixture(scope="module")
def stand_in(tmp_path_factory, example):
    """A folder like the unpacked sdist: a 16-bit PNG of an off-centre shell-and-kernel phantom's fan-beam
    sinogram (120 angles, 328 bins) with the detector shifted by ``SHIFT_MM`` and a level ``LEVEL`` outside."""
    folder = tmp_path_factory.mktemp("walnut")
    domain = example.square_domain(96, 40.0)
    angles = np.radians(example.STEP_DEG * np.arange(120))
    T = example.operator(domain, angles, 328, SHIFT_MM)
    sino = T(phantoms.ellipse_phantom(domain, WALNUT)).numpy()
    write_png(folder, LEVEL + 0.9 * sino / sino.max())
    return folder


def test_split_angles_full_turn(example):
    angles = np.radians(3.0 * np.arange(120))
    t = example.split_angles(angles, max_angle=45.0, fit_every=2)
    deg = np.degrees(angles)
    assert t["template"].tolist() == list(range(0, 120, 2))
    fitted = np.concatenate([t["fit"], t["validation"]])
    assert len(t["fit"]) == len(t["validation"]) == 8 and len(t["test"]) == 28
    assert len(np.intersect1d(fitted, t["test"])) == 0 and np.all(np.concatenate([fitted, t["test"]]) % 2 == 1)
    assert np.abs((deg[fitted] + 180) % 360 - 180).max() <= 45.0
    assert np.abs((deg[t["test"]] + 90) % 180 - 90).min() > 45.0                # directions outside the range
    unused = np.setdiff1d(np.arange(1, 120, 2), np.concatenate([fitted, t["test"]]))
    assert np.all(np.abs(deg[unused] - 180.0) <= 45.0) and len(unused) == 16    # the opposite side: used by none
    order = fitted[np.argsort((deg[fitted] + 180) % 360 - 180)]               # -45 .. 45 degrees
    assert set(order[::2]) == set(t["fit"]) and set(order[1::2]) == set(t["validation"])


def test_bin_detector_keeps_the_mean(example):
    sino = np.arange(2 * 12, dtype=float).reshape(2, 12)
    assert example.bin_detector(sino, 4)[1, 2] == sino[1, 8:12].mean()
    with pytest.raises(ValueError, match="--bin must divide"):
        example.bin_detector(sino, 5)


def test_read_sinogram_layout_and_errors(example, stand_in, tmp_path):
    sino, angles = example.read_sinogram(stand_in)
    assert sino.shape == (120, 328) and np.degrees(angles[[0, -1]]).tolist() == pytest.approx([0.0, 357.0])
    assert sino.min() == pytest.approx(LEVEL, abs=1e-4) and sino.max() <= 1.0
    with pytest.raises(FileNotFoundError, match="walnut_sinogram.png"):
        example.read_sinogram(tmp_path)
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "walnut_sinogram.png")
    with pytest.raises(ValueError, match="16-bit"):
        example.read_sinogram(tmp_path)


def test_orientation_and_centre_found_by_consistency(example, stand_in):
    """The full turn decides the detector's direction and its shift: reversing the detector breaks the pairs of
    rays that measure the same line; the shift is recovered to a tenth of a (0.35 mm) bin."""
    sino, angles = example.read_sinogram(stand_in)
    binned = example.bin_detector(sino, 4) - LEVEL
    domain = example.square_domain(32, 40.0)
    o = example.orientation(binned, angles, domain, iters=10)
    assert not o["reverse"] and o["reversed"] > 1.03 * o["as_stored"]
    assert example.orientation(binned[:, ::-1].copy(), angles, domain, iters=10)["reverse"]
    flipped = torch.from_numpy(binned[:, ::-1].copy())                       # reversed and the angles negated:
    mirrored = example._full_turn_residual(flipped, -angles, domain, 0.0, 10)  # the mirror image, as consistent
    assert mirrored == pytest.approx(o["as_stored"], rel=1e-6)
    c = example.centre_of_rotation(binned, angles, domain, shifts_mm=np.arange(-0.3, 1.0, 0.2), iters=10)
    assert c["shift_mm"] == pytest.approx(SHIFT_MM, abs=0.035)
    assert c["residual"] <= min(c["residuals"]) + 1e-9


def test_pipeline_on_the_stand_in(example, stand_in, tmp_path):
    out = tmp_path / "out"
    m = example.run(stand_in, out, size=24, side_mm=40.0, bin_factor=4, iters=5, num_steps=4, quick=True)
    assert json.loads((out / "metrics.json").read_text())["shape"] == [120, 328]
    assert (out / "figure.png").stat().st_size > 0 and np.load(out / "registered.npy").shape == (24, 24)
    assert m["centre"]["shift_mm"] == pytest.approx(SHIFT_MM, abs=0.1)
    reg = m["registration"]
    cell = 40.0 / 24                                  # the template is per cell length, the data per mm
    assert 0.5 / cell < reg["template_scale"] < 2.0 / cell
    assert reg["background"] == pytest.approx(LEVEL, abs=5e-3)
    assert reg["iterations"] == 5 and reg["options"] == {"max_iter": 5, "num_steps": 4}
    assert reg["residual"] <= m["scores"]["template"]["fit_residual"] + 1e-9
    assert set(m["scores"]) == {"template", "registered", "SIRT", "TV"}
    assert all(np.isfinite(s["test_residual"]) for s in m["scores"].values())


def test_fetch_unpacks_the_sdist_once(example, stand_in, tmp_path, monkeypatch):
    """Without --data: ``pip download`` of the source distribution (faked here: no network in CI) into a
    temporary folder, the sinogram and gratopy's README and LICENSE unpacked into the cache, reused the next time."""
    calls = []

    def fake_pip(command, check):
        calls.append(command)
        sdist = Path(command[command.index("-d") + 1]) / "gratopy-0.1.0.tar.gz"
        with tarfile.open(sdist, "w:gz") as t:
            t.add(stand_in / "walnut_sinogram.png", "gratopy-0.1.0/tests/walnut_sinogram.png")
            for name in ("README.md", "LICENSE", "setup.py"):
                (tmp_path / name).write_text(name)
                t.add(tmp_path / name, f"gratopy-0.1.0/{name}")

    monkeypatch.setattr(subprocess, "run", fake_pip)
    cache = tmp_path / "cache"
    assert example.fetch(cache) == cache and example.fetch(cache) == cache
    assert len(calls) == 1 and calls[0][0] == sys.executable and example.SDIST in calls[0]
    assert "--no-binary" in calls[0] and "--no-deps" in calls[0]
    assert sorted(p.name for p in cache.iterdir()) == ["gratopy_LICENSE", "gratopy_README.md", "walnut_sinogram.png"]
    assert example.read_sinogram(cache)[0].shape == (120, 328)


REAL = os.environ.get("INDREG_WALNUT_DIR")


@pytest.mark.skipif(not REAL, reason="INDREG_WALNUT_DIR not set (gratopy 0.1.0's walnut sinogram; "
                    "docs/real_data_walnut.md)")
def test_real_walnut_file(example):
    """The numbers docs/real_data_walnut.md quotes for the reading and the checks of the real sinogram."""
    sino, angles = example.read_sinogram(Path(REAL))
    assert sino.shape == (120, 328) and len(angles) == 120
    assert example.background_report(sino)["border_level"] == pytest.approx(0.0203, abs=5e-4)
    binned = example.bin_detector(sino, 4) - 0.0203
    domain = example.square_domain(64, 40.0)
    assert not example.orientation(binned, angles, domain, iters=30)["reverse"]
    assert example.centre_of_rotation(binned, angles, domain, iters=30)["shift_mm"] == pytest.approx(0.272, abs=0.01)


def test_missing_data_is_one_line_with_the_fetch_before_any_import(tmp_path, error_without_torch):
    """``--data`` a folder without the sinogram: one line naming it and how to get it, before torch is imported (a
    ``torch`` that cannot be imported first on the path shows it)."""
    line = error_without_torch(EXAMPLE, "--data", tmp_path / "empty")
    assert line.startswith(f"real_data_walnut.py: error: {tmp_path / 'empty'} has no walnut_sinogram.png: ")
    assert "pip download gratopy==0.1.0 --no-deps --no-binary gratopy" in line
