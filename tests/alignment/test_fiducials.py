"""Alignment by gold fiducials (``indreg.alignment.fiducials``): beads found to a tenth of a pixel, the rigid model
solved exactly, a slab with gold beads made without indreg (``slab_series``) recovered from shifts it does not
know, a stack without beads reported as not determined, and ``indreg-align --fiducials`` on the slab path."""
import json
import logging
import math

import mrcfile
import numpy as np
import pytest

from indreg.alignment.fiducials import _solve, bead_scale, detect_beads, fiducial_alignment
from slab_series import GOLD, axis_frame_shifts, gauge_rms, slab_series


def _spots(centres, width, shape=(64, 80), noise=0.0, seed=0):
    """Gaussian spots of amplitude 1 at ``centres`` (x, y from the image's centre) on white noise."""
    ny, nx = shape
    y, x = np.mgrid[:ny, :nx]
    x, y = x - (nx - 1) / 2, y - (ny - 1) / 2
    image = sum(np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * width ** 2)) for cx, cy in centres)
    return image + noise * np.random.default_rng(seed).standard_normal(shape)


def _lines(series):
    return -np.log(np.maximum(series["intensities"], 0.5) / series["dose"])


def test_detect_beads_finds_spots_to_a_tenth_of_a_pixel():
    """Gaussian spots 2.5 px wide: exact without noise (within 0.01 px, the three-point fit of the logarithms is
    exact for a Gaussian); with white noise of 1/20 of their peak, within 0.1 px RMS over 10 draws (measured
    0.063 at the scale 3, the largest 0.13)."""
    centres = np.array([[-20.3, -12.7], [5.45, 3.2], [18.9, -20.05], [-8.6, 17.75]])
    found = detect_beads(_spots(centres, 2.5), 3.0)
    assert len(found) == len(centres)
    assert max(np.linalg.norm(found[:, :2] - c, axis=1).min() for c in centres) < 0.01
    errors = []
    for seed in range(10):
        found = detect_beads(_spots(centres, 2.5, noise=0.05, seed=seed), 3.0)
        assert len(found) == len(centres)
        errors += [np.linalg.norm(found[:, :2] - c, axis=1).min() for c in centres]
    assert np.sqrt(np.mean(np.square(errors))) < 0.1


def test_bead_scale_grows_with_the_beads():
    rng = np.random.default_rng(1)
    centres = rng.uniform(-25, 25, (8, 2)) * [1.0, 0.7]
    small, large = bead_scale(_spots(centres, 1.2, noise=0.02)), bead_scale(_spots(centres, 3.5, noise=0.02))
    assert small < large and 2.5 <= large <= 5.0, (small, large)


def test_the_rigid_model_is_solved_exactly():
    """Observations made by the model itself (module Notes): zero residual, the shifts recovered in the gauge."""
    rng = np.random.default_rng(2)
    theta = np.radians(np.linspace(-60, 60, 21))
    X, Y, Z = rng.uniform(-50, 50, 12), rng.uniform(-40, 40, 12), rng.uniform(-15, 15, 12)
    v = rng.uniform(-10, 10, (21, 2))
    rows = [(k, j, X[j] * math.cos(t) + Z[j] * math.sin(t) + v[k, 0], Y[j] + v[k, 1], j)
            for k, t in enumerate(theta) for j in range(12) if rng.random() < 0.9]
    Xs, Zs, Ys, vs, res = _solve(np.array(rows, dtype=np.float64), theta, 12)
    assert np.abs(res).max() < 1e-9
    assert max(gauge_rms(vs, v, np.degrees(theta))) < 1e-9


@pytest.fixture(scope="module")
def gold_slab():
    """The slab of the docs' measurement with a fifth of its specimen blobs (they cost the time to make it)."""
    return slab_series(width=128, rows=96, tilts=41, thickness=40.0, max_shift=20.0, seed=3, blobs_per_px=0.02,
                       **GOLD)


def _recovered(s, alpha_off):
    theta = -np.radians(s["deg"])
    truth = axis_frame_shifts(s["shifts"], s["alpha"])
    found = fiducial_alignment(_lines(s), theta, s["alpha"] + alpha_off, np.zeros_like(truth), search_axis=True)
    assert found.determined, found.reason
    assert len(found.beads) >= 4 and found.per_view.min() >= 2
    return abs(found.angle_deg - s["alpha"]), gauge_rms(found.shifts, truth, s["deg"]), found


@pytest.mark.parametrize("alpha_off", [0.0, 1.0])
def test_a_slab_with_gold_beads_recovered(gold_slab, alpha_off):
    """128 x 96, 41 tilts over +-60, shifts up to 20 px, tilt axis 4 degrees, 40 counts a pixel; started from no
    shifts and the axis 0 or 1 degree off: shifts within 0.3 px RMS in the gauge, the angle within 0.2 degree."""
    angle, shifts, found = _recovered(gold_slab, alpha_off)
    assert angle < 0.2 and max(shifts) < 0.3, found.describe()


@pytest.fixture(scope="module")
def cluttered_gold_slab():
    return slab_series(width=128, rows=96, tilts=41, thickness=40.0, max_shift=20.0, seed=3, **GOLD)


@pytest.mark.slow
@pytest.mark.parametrize("alpha_off", [0.0, 1.0])
def test_a_cluttered_slab_with_gold_beads_recovered(cluttered_gold_slab, alpha_off):
    """The same with all the specimen's blobs (docs/alignment.md: measured 0.16 / 0.16 px, the angle 3.95 and
    4.02 degrees)."""
    angle, shifts, found = _recovered(cluttered_gold_slab, alpha_off)
    assert angle < 0.2 and max(shifts) < 0.3, found.describe()


def test_a_stack_without_beads_is_not_determined():
    """The default slab's 'beads' are faint texture (1.5 px, below the noise): no fit, the reason given, the
    starting shifts kept."""
    s = slab_series(width=64, rows=48, tilts=21)
    start = np.full((21, 2), 0.5)
    found = fiducial_alignment(_lines(s), -np.radians(s["deg"]), s["alpha"], start)
    assert not found.determined and found.reason
    assert np.array_equal(found.shifts, start)
    assert "not determined" in found.describe()


def test_align_app_takes_the_beads_and_records_them(tmp_path, caplog):
    """``indreg-align --intensities --axis-from-stack`` on the gold slab: the beads' fit logged and recorded
    (``slab.fiducials``), its shifts and angle the ones written; ``--fiducials off`` runs projection matching only."""
    from indreg.alignment.app import main

    s = slab_series(width=128, rows=96, tilts=21, thickness=40.0, max_shift=8.0, seed=3, blobs_per_px=0.02, **GOLD)
    with mrcfile.new(tmp_path / "slab.mrc") as m:
        m.set_data(s["intensities"].astype(np.float32))
    np.savetxt(tmp_path / "slab.tlt", -s["deg"], fmt="%.3f")   # IMOD's sign
    common = [str(tmp_path / "slab.mrc"), "--angles", str(tmp_path / "slab.tlt"), "--tilt-axis-angle", "4.5",
              "--intensities", "--specimen", "slab", "--rounds", "1", "--iters", "3", "--threads", "1"]
    with caplog.at_level(logging.INFO, logger="indreg.align"):
        assert main(common + ["--axis-from-stack", "--out", str(tmp_path / "beads")]) == 0
    assert any(m.startswith("fiducials: ") for m in caplog.messages)
    record = json.loads((tmp_path / "beads" / "align.json").read_text())
    beads = record["slab"]["fiducials"]
    assert beads["determined"] and beads["beads"] >= 4
    assert abs(record["axis_angle_deg"] - beads["angle_deg"]) < 1e-9 and abs(beads["angle_deg"] - 4.0) < 0.3
    truth = axis_frame_shifts(s["shifts"], s["alpha"])
    assert max(gauge_rms(np.array(record["slab"]["shifts_axis_frame_px"]), truth, s["deg"])) < 0.5
    assert main(common + ["--fiducials", "off", "--out", str(tmp_path / "off")]) == 0
    assert json.loads((tmp_path / "off" / "align.json").read_text())["slab"]["fiducials"] is None


def test_bead_residual_of_the_fit_and_of_other_shifts(gold_slab):
    """The fit's own shifts give its residual; the true shifts moved by a translation of the specimen (``a cos + b
    sin`` across, a constant along) about as little; shifts 3 px off at random far more."""
    from indreg.alignment.fiducials import bead_residual

    s = gold_slab
    theta = -np.radians(s["deg"])
    truth = axis_frame_shifts(s["shifts"], s["alpha"])
    found = fiducial_alignment(_lines(s), theta, s["alpha"], np.zeros_like(truth))
    own = bead_residual(found, theta, s["alpha"], found.shifts)
    assert np.allclose(own, found.residual_px, atol=1e-6)
    moved = truth + np.stack([5.0 * np.cos(theta) + 3.0 * np.sin(theta), np.full_like(theta, 7.0)], 1)
    assert max(bead_residual(found, theta, s["alpha"], moved)) < max(own) + 0.2
    off = truth + np.random.default_rng(0).normal(0.0, 3.0, truth.shape)
    assert min(bead_residual(found, theta, s["alpha"], off)) > 2.0


def test_fiducials_on_the_compact_path_is_a_warning(tmp_path, caplog):
    """No ignored option: ``--fiducials`` given where the compact path runs says that it is not used."""
    from indreg.alignment.app import main

    s = slab_series(width=32, rows=24, tilts=7)
    with mrcfile.new(tmp_path / "s.mrc") as m:
        m.set_data(s["intensities"].astype(np.float32))
    np.savetxt(tmp_path / "s.tlt", -s["deg"], fmt="%.3f")
    args = [str(tmp_path / "s.mrc"), "--angles", str(tmp_path / "s.tlt"), "--intensities", "--specimen", "compact",
            "--rounds", "1", "--iters", "2", "--threads", "1"]
    with caplog.at_level(logging.WARNING, logger="indreg.align"):
        assert main(args + ["--fiducials", "off", "--out", str(tmp_path / "a")]) == 0
    assert "--fiducials off is not used" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="indreg.align"):
        assert main(args + ["--out", str(tmp_path / "b")]) == 0
    assert "--fiducials" not in caplog.text
