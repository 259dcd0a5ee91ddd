"""Slab specimens (wider than the detector): the stretched cross-correlation, leave-one-out projection matching
through the wide box and the common-line search of the tilt axis, on slabs made without indreg
(``slab_series``); ``indreg-align`` on them: the specimen found, a shift at its bound warned and recorded."""
import json
import logging
import math

import mrcfile
import numpy as np
import pytest

from indreg.alignment.axis_search import common_line_score, search_axis_angle
from indreg.alignment.slab import gauge_fix, slab_projection_matching
from indreg.alignment.xcorr import axis_frame, coarse_alignment, correlate, stretch, taper_window
from slab_series import axis_frame_shifts, gauge_rms, slab_series


def _lines(series):
    return -np.log(np.maximum(series["intensities"], 0.5) / series["dose"])


def test_correlate_finds_a_known_shift():
    """A band-passed random image moved by (3.4, -2.6) px (Fourier shift): the peak at that shift to 0.1 px, its
    coefficient near 1."""
    rng = np.random.default_rng(1)
    a = rng.normal(size=(64, 80))
    fy, fx = np.fft.fftfreq(64)[:, None], np.fft.rfftfreq(80)[None, :]
    b = np.fft.irfft2(np.fft.rfft2(a) * np.exp(-2j * np.pi * (fx * 3.4 + fy * -2.6)), a.shape)
    w = taper_window(64, 80, 0.1)
    shift, peak = correlate(a * w, b * w, (10, 10))
    assert np.abs(shift - [3.4, -2.6]).max() < 0.1 and peak > 0.8


def test_stretch_maps_x_to_factor_x():
    """``stretch(image, c)(x) = image(x / c)`` about the middle: a line at column offset 10 lands at 10 c."""
    img = np.zeros((8, 65))
    img[:, 32 + 10] = 1.0
    out = stretch(img, 1.5)
    assert abs(float((out[4] * (np.arange(65) - 32)).sum() / out[4].sum()) - 15.0) < 0.05


def test_coarse_alignment_and_projection_matching_recover_a_slab():
    """A 64 x 48 slab series (15 tilts, shifts up to 8 px, tilt axis 4 degrees, 400 counts a pixel: the fast
    stand-in of the slow test's cryo-ET dose): the stretched cross-correlation within 1 px RMS, projection
    matching through the wide box within 0.4 px (in the gauge)."""
    s = slab_series(tilts=15, dose=400.0)
    lines, theta = _lines(s), -np.radians(s["deg"])
    truth = axis_frame_shifts(s["shifts"], s["alpha"])
    coarse = coarse_alignment(axis_frame(lines, s["alpha"]), theta)
    assert max(gauge_rms(gauge_fix(coarse.shifts, theta), truth, s["deg"])) < 1.0
    assert not coarse.at_bound.any()
    result = slab_projection_matching(lines, theta, s["alpha"], [1], [2])
    across, along = gauge_rms(result.shifts, truth, s["deg"])
    assert across < 0.4 and along < 0.4, (across, along)
    assert not result.at_bound.any() and result.thickness > 0


def test_common_line_score_is_best_at_the_true_axis():
    """On the slab above aligned by its true shifts, the common-line score at the true angle beats 2 degrees
    off on either side."""
    s = slab_series()
    lines, theta = _lines(s), -np.radians(s["deg"])
    v = axis_frame_shifts(s["shifts"], s["alpha"])
    from indreg.alignment.axis_search import view_profiles

    scores = [common_line_score(view_profiles(lines, theta, s["alpha"] + d, v)) for d in (-2.0, 0.0, 2.0)]
    assert scores[1] > max(scores[0], scores[2])


def test_search_axis_reports_not_determined_on_a_flat_scan():
    """A stack of pure noise: the search says the angle is not determined, with the reason."""
    rng = np.random.default_rng(0)
    lines = rng.normal(size=(11, 32, 40))
    found = search_axis_angle(lines, np.radians(np.linspace(-50, 50, 11)), 0.0, np.zeros((11, 2)), span=1.0,
                              step=0.5)
    assert not found.determined and found.reason
    assert "not determined" in found.describe()


def _write(tmp_path, s):
    with mrcfile.new(tmp_path / "slab.mrc") as m:
        m.set_data(s["intensities"].astype(np.float32))
    np.savetxt(tmp_path / "slab.tlt", -s["deg"], fmt="%.3f")   # IMOD's sign
    return tmp_path / "slab.mrc", tmp_path / "slab.tlt"


def test_align_app_on_a_slab_warns_and_records_a_shift_at_its_bound(tmp_path, caplog):
    """``indreg-align --intensities`` on the slab with ``--max-shift 0.05`` (3.2 px: the true shifts reach 8):
    the specimen found to be a slab, a warning naming --max-shift, ``at_bound`` in align.json; with the default
    bound none."""
    from indreg.alignment.app import main

    stack, tlt = _write(tmp_path, slab_series())
    common = [str(stack), "--angles", str(tlt), "--tilt-axis-angle", "4", "--intensities", "--rounds", "1",
              "--fine-rounds", "1", "--iters", "5", "--threads", "1"]
    with caplog.at_level(logging.WARNING, logger="indreg.align"):
        assert main(common + ["--out", str(tmp_path / "tight"), "--max-shift", "0.05"]) == 0
    assert "--max-shift 0.05" in caplog.text
    record = json.loads((tmp_path / "tight" / "align.json").read_text())
    assert record["specimen"] == "slab" and len(record["at_bound"]) > 0
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="indreg.align"):
        assert main(common + ["--out", str(tmp_path / "free")]) == 0
    record = json.loads((tmp_path / "free" / "align.json").read_text())
    assert record["at_bound"] == [] and "--max-shift" not in caplog.text
    assert np.allclose(np.loadtxt(tmp_path / "free" / "alignment.tlt"), np.loadtxt(tlt), atol=1e-3)


def test_max_shift_out_of_range_is_one_line(tmp_path, capsys):
    from indreg.alignment.app import main

    stack, tlt = _write(tmp_path, slab_series(width=32, rows=24, tilts=7))
    assert main([str(stack), "--angles", str(tlt), "--max-shift", "0.9", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "indreg-align: error: --max-shift must be a fraction of the detector in (0, 0.5], got 0.9"


@pytest.mark.slow
def test_slab_recovered_to_a_third_of_a_pixel():
    """128 x 96, 41 tilts over +-60, shifts up to 20 px, tilt axis 4 degrees, 40 counts a pixel, bin 2 then bin 1:
    within 0.3 px RMS across and along with the tilt axis' offset also removed; the offset itself is weakly
    determined over +-60 degrees (``c`` against ``a cos``): within 1 px in the gauge that keeps it (measured 0.70 /
    0.28 px with it, 0.17 / 0.28 without, docs/alignment.md)."""
    s = slab_series(width=128, rows=96, tilts=41, thickness=40.0, max_shift=20.0, seed=3)
    lines, theta = _lines(s), -np.radians(s["deg"])
    result = slab_projection_matching(lines, theta, s["alpha"], [2, 1], [6, 2])
    truth = axis_frame_shifts(s["shifts"], s["alpha"])
    across, along = gauge_rms(result.shifts, truth, s["deg"], constant=True)
    assert across < 0.3 and along < 0.3, (across, along)
    assert max(gauge_rms(result.shifts, truth, s["deg"])) < 1.0
    assert math.isfinite(result.thickness)


def test_aligned_slab_operator_is_the_axis_frame_s_operator_moved():
    """``aligned_slab_operator``: identity maps give ``slab_operators``' operator; it is adjoint to its adjoint; and
    its projections, taken into the axis frame by ``axis_frame`` with the same alignment, are the plain
    operator's (the convention is ``axis_frame``'s)."""
    import torch

    from indreg.alignment.slab import aligned_slab_operator, slab_operators

    theta = np.radians(np.linspace(-60, 60, 7))
    nx, ny, depth = 40, 32, 10.0
    plain = slab_operators(theta, nx, ny, depth)[0]
    g = torch.Generator().manual_seed(0)
    x = torch.rand(plain.domain.shape, generator=g, dtype=torch.float64)
    assert torch.allclose(aligned_slab_operator(theta, nx, ny, depth, 0.0, np.zeros((7, 2)))(x), plain(x))
    alpha, v = 3.0, np.random.default_rng(1).uniform(-2, 2, (7, 2))
    moved = aligned_slab_operator(theta, nx, ny, depth, alpha, v, interpolation="cubic")
    assert moved.adjointness_test() < 1e-12
    X, Y, Z = np.meshgrid(*[np.linspace(-1, 1, n) for n in plain.domain.shape], indexing="ij")
    blob = torch.from_numpy(np.exp(-(X ** 2 + Y ** 2 + Z ** 2) / 0.08))
    back = axis_frame(moved(blob).numpy(), alpha, v, order=3)
    inner = (slice(None), slice(6, -6), slice(6, -6))
    want = plain(blob).numpy()
    assert np.abs(back - want)[inner].max() < 0.02 * np.abs(want).max()
