"""examples/real_data_haadf.py (docs/real_data.md) on a synthetic stand-in of the HAADF series, and on the real
files when ``INDREG_HAADF_DIR`` names a folder holding them (``HAADF.mrc``, ``HAADF.rawtlt``,
``HAADF_Aligned.hspy``; see the example's docstring for where to get them)."""
import importlib.util
import json
import os
import subprocess
from pathlib import Path

import h5py
import mrcfile
import numpy as np
import pytest
import torch

from indreg import phantoms
from indreg.domain import ImageDomain

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "real_data_haadf.py"
OFFSET = -31886          # the raw stack's int16 level outside the specimen
SCALE = 400.0            # counts per unit line integral
RNG = np.random.default_rng(7)
SHIFTS = np.stack([RNG.integers(-3, 4, 31), RNG.integers(-1, 2, 31)], axis=1).astype(float)   # etspy's (row, col)


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("real_data_haadf", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def rod_series(example, angles_deg: np.ndarray, pixels: int = 32) -> np.ndarray:
    """Projections ``(tilts, rows, cols)`` of a 3D rod along y with a bright segment, on a ``pixels^3`` grid of
    unit cells, in indreg's layout (tilt axis along the rows' index)."""
    domain = ImageDomain((pixels,) * 3, (-pixels / 2,) * 3, (pixels / 2,) * 3)
    rod = [(1.0, 0.3, 0.8, 0.3, 0.05, -0.1, 0.0, 0, 0, 0), (2.0, 0.25, 0.2, 0.25, 0.05, 0.3, 0.05, 0, 0, 0),
           (1.0, 0.1, 0.1, 0.1, 0.4, -0.5, 0.3, 0, 0, 0)]                   # off-centre: the axis is decided
    volume = phantoms.ellipsoid_phantom(domain, rod)
    return example.operator(domain, np.radians(angles_deg))(volume).numpy()


@pytest.fixture(scope="module")
def stand_in(tmp_path_factory, example):
    """A folder like the etspy one: an int16 raw stack with the tilt axis along X, an offset and the drift
    ``-SHIFTS`` (raw(p) = aligned(p + s), etspy's convention), its .rawtlt, and an "aligned" .hspy (float32,
    minimum moved to 0, as etspy's) with ``SHIFTS`` recorded."""
    from scipy import ndimage

    folder = tmp_path_factory.mktemp("haadf")
    angles = np.arange(-60.0, 61.0, 4.0)                                    # 31 tilts
    series = rod_series(example, angles)
    ideal = np.rot90(series, k=-1, axes=(1, 2))                             # axis along X, as the raw stack
    drifted = np.stack([ndimage.shift(im, -s, order=0) for im, s in zip(ideal, SHIFTS)])
    counts = np.round(SCALE * drifted + OFFSET).astype(np.int16)
    with mrcfile.new(folder / "HAADF.mrc") as m:
        m.set_data(counts)
    (folder / "HAADF.rawtlt").write_text("".join(f"{a:8.2f}\n" for a in angles))
    aligned = SCALE * ideal + OFFSET
    with h5py.File(folder / "HAADF_Aligned.hspy", "w") as f:
        f.create_dataset(example.ALIGNED_KEY, data=(aligned - aligned.min()).astype(np.float32))
        f.create_dataset("/Experiments/__unnamed__/metadata/Tomography/tilts", data=angles)
        f.create_dataset(example.SHIFTS_KEY, data=SHIFTS)
    return folder


def test_split_tilts_disjoint_and_in_range(example):
    angles = np.radians(np.arange(-76.0, 77.0, 2.0))
    t = example.split_tilts(angles, fit_every=2, max_angle=40.0)
    assert t["template"].tolist() == list(range(0, 77, 2))
    used = np.concatenate([t["fit"], t["validation"], t["test"]])
    assert sorted(used.tolist()) == list(range(1, 77, 2))                   # every odd tilt once
    assert np.abs(np.degrees(angles[np.concatenate([t["fit"], t["validation"]])])).max() <= 40.0 + 1e-9
    assert len(t["fit"]) == len(t["validation"]) == 10 and len(t["test"]) == 18


def test_bin_stack_keeps_counts_per_pixel(example):
    stack = np.arange(2 * 8 * 8, dtype=float).reshape(2, 8, 8)
    binned = example.bin_stack(stack, 4)
    assert binned.shape == (2, 4, 4)
    assert binned[1, 2, 3] == stack[1, 4:6, 6:8].mean()
    with pytest.raises(ValueError, match="--size"):
        example.bin_stack(stack, 3)


def test_handedness_negated_angles_mirror_the_volume(example):
    """Negating every angle fits the data equally and mirrors the reconstruction along the beam (z)."""
    angles = np.arange(-60.0, 61.0, 10.0)
    data = rod_series(example, angles, pixels=16)
    domain = example.volume_domain(16, 16, 1.0)
    out = example.handedness(data, np.radians(angles), domain, iters=5)
    assert out["residual_as_given"] == pytest.approx(out["residual_negated"], rel=1e-10)
    assert out["mirror_difference"] < 1e-10


def test_compare_shifts_ignores_offset_and_object_translation(example):
    angles = np.arange(-60.0, 61.0, 10.0)
    T = example.operator(example.volume_domain(8, 8, 1.0), np.radians(angles))
    theta = np.radians(angles)
    translation = np.stack([2.0 - 3.0 * np.cos(theta) + 0.5 * np.sin(theta), np.full_like(theta, 4.0)], axis=1)
    out = example.compare_shifts(translation, np.zeros_like(translation), T, factor=4)
    assert out["rms_px_gauge_removed"] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert out["rms_px_offset_removed"][1] == pytest.approx(0.0, abs=1e-12) and out["rms_px_offset_removed"][0] > 1.0
    jitter = np.zeros_like(translation)
    jitter[::2, 1] = 1.0
    rms = example.compare_shifts(jitter, 0 * jitter, T, factor=4)["rms_px_offset_removed"][1]
    assert rms == pytest.approx(4 * np.sqrt(7 * 6) / 13)                    # 7 ones, 6 zeros


@pytest.mark.slow
def rescored(out: Path, m: dict, monkeypatch, capsys) -> None:
    """``indreg-score`` on the files the walk-through wrote (``m["score_command"]``) prints its scores again, to the
    4 digits of its table: one implementation (indreg.evaluation.score)."""
    import shlex

    from indreg.evaluation import score_app

    monkeypatch.chdir(out)
    capsys.readouterr()
    assert score_app.main(shlex.split(m["score_command"])[1:]) == 0
    rows = {line.split("|")[1].strip(): line.split("|")[2:-2] for line in capsys.readouterr().out.splitlines()[2:]}
    for name, s in m["scores"].items():
        cells = rows[f"{name.lower()}.mrc"]
        assert [c.strip() for c in cells] == [f"{s[f'{k}_residual']:.4f}" for k in ("test", "validation", "fit")]


def test_raw_stack_aligned_in_the_fit(example, stand_in, tmp_path, monkeypatch, capsys):
    """--stack raw: the template's tilts aligned by projection matching, the data by the registration; both
    recover the recorded drift (2 raw pixels per binned one) in the gauge."""
    m = example.run(stand_in, tmp_path / "raw", size=16, depth=16, iters=10, sigma_cells=2.0, num_steps=4,
                    misalign=3.0, max_angle=30.0, align="shifts+axis", align_rounds=2, baselines_too=False, quick=True)
    assert m["stack"] == "raw" and m["alignment"]["mode"] == "shifts+axis"
    assert m["registration"]["background"] == pytest.approx(OFFSET, abs=2)
    for key in ("template_shifts_vs_etspy", "shifts_vs_etspy"):
        rms, drift = m[key]["rms_px_gauge_removed"], m[key]["rms_px_reference_in_gauge"]
        assert drift[0] > 1.0 and max(rms) < 0.5, (key, rms, drift)
    assert set(m["scores"]) == {"template", "registered"}
    assert m["scores"]["registered"]["fit_residual"] < m["scores"]["template"]["fit_residual"]
    assert m["alignment"]["gauge"] == "none" and (tmp_path / "raw" / "alignment.png").stat().st_size > 0
    rescored(tmp_path / "raw", m, monkeypatch, capsys)   # through the alignment's record


def test_pipeline_on_the_stand_in(example, stand_in, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    m = example.run(stand_in, out, size=16, depth=16, iters=4, sigma_cells=2.0, num_steps=4, misalign=3.0,
                    max_angle=30.0, stack="aligned", quick=True)
    rescored(out, m, monkeypatch, capsys)
    ev = m["evaluation"]   # the split, the uncertainty and its flagged voxels (docs/evaluation.md)
    assert ev["split_check"]["range"]["split_projection_difference"] <= 1.01e-3 and ev["uncertainty_seconds"] > 0
    assert set(ev["flagged"]) >= {"as_is", "flagged_replaced", "random_replaced_mean", "flagged_refitted"}
    assert (out / "evaluation.png").stat().st_size > 0
    assert json.loads((out / "metrics.json").read_text())["num_tilts"] == 31
    assert (out / "figure.png").stat().st_size > 0
    for name in ("registered", "template", "fbp", "sirt", "tv"):
        assert np.load(out / f"{name}.npy").shape == (16, 16, 16)
        assert (out / f"{name}.mrc").exists()
    # the raw stack: its offset found, its tilt axis along X (with the offset removed)
    assert m["background_raw"]["border_level"] == pytest.approx(OFFSET, abs=1)
    assert m["tilt_axis_as_stored"]["raw"]["tilt_axis_direction"] == "columns"
    assert m["tilt_axis_turned"]["tilt_axis_direction"] == "rows"
    assert m["load"]["tilt_axis_angle"] == 90.0
    # the template is per voxel length (pixel 3.36 * 32 / 16 nm), the data per nm: template_scale ~ 1 / cell
    cell = example.PIXEL_NM * 32 / 16
    reg = m["registration"]
    assert 0.5 / cell < reg["template_scale"] < 2.0 / cell
    assert reg["background"] == pytest.approx(0.0, abs=1.0)                # the aligned stack starts at ~0
    assert reg["residual"] <= m["scores"]["template"]["fit_residual"] + 1e-9
    assert set(m["scores"]) == {"template", "registered", "FBP", "SIRT", "TV"}
    assert all(np.isfinite(s["test_residual"]) for s in m["scores"].values())
    assert set(m["cpu_seconds_by_part"]) >= {"registration (the alignment and the model's finish included)",
                                             "baselines (FBP, SIRT, TV, parameters chosen on the validation tilts)"}
    assert set(m["wall_seconds_by_part"]) == set(m["cpu_seconds_by_part"]) and m["threads"] >= 1
    assert sum(m["wall_seconds_by_part"].values()) <= m["wall_seconds"] + 1e-6
    # docs/real_data.md's table (--table): a row per volume, both stacks' test and validation residuals, the ratios
    lines = example.table({"raw": m, "aligned": m}).splitlines()
    n = {k: len(m["tilts_deg"][k]) for k in ("test", "validation")}
    assert lines[0] == "| volume | " + " | ".join(f"{s}: {k} ({n[k]})" for s in ("raw", "aligned") for k in n) + " |"
    tv = m["scores"]["TV"]
    assert lines[2 + list(m["scores"]).index("TV")].startswith(
        f"| TV | {tv['test_residual']:.4f} | {tv['validation_residual']:.4f} |")
    reg = m["scores"]["registered"]
    assert lines[-3].startswith(f"raw: registered / TV {reg['test_residual'] / tv['test_residual']:.2f} on the test "
                                "tilts") and lines[-3].endswith(f"TV mu = {tv['mu_relative']:g} x u")
    assert lines[-1] == "registered, raw / aligned stack on the test tilts: 1.00"


REAL = os.environ.get("INDREG_HAADF_DIR")


@pytest.mark.skipif(not REAL, reason="INDREG_HAADF_DIR not set (the etspy HAADF files; docs/real_data.md)")
def test_real_haadf_files(example):
    """The numbers docs/real_data.md quotes for the reading and the checks of the real series."""
    folder = Path(REAL)
    with pytest.warns(UserWarning, match="invalid MRC header"):
        raw, angles = example.read_raw(folder)
    assert raw.shape == (77, 256, 256) and np.degrees(angles[[0, -1]]).tolist() == pytest.approx([-76, 76])
    aligned = example.read_aligned(folder)
    assert aligned.shape == raw.shape
    checks = example.axis_checks(raw, aligned)
    assert checks["raw"]["tilt_axis_direction"] == "columns"
    level = example.background_report(raw, "raw")["border_level"]
    assert -31890 < level < -31875
    turned = example.align_tilt_axis(example.bin_stack(aligned, 32), example.TILT_AXIS_ANGLE)
    out = example.handedness(turned - np.median(turned), angles, example.volume_domain(32, 32, 26.88), iters=3)
    assert out["mirror_difference"] < 1e-10


def test_fetch_unpacks_the_wheel_once(example, stand_in, tmp_path, monkeypatch):
    """Without --data: ``pip download`` (faked here: no network in CI) into a temporary folder, then the
    ``etspy/tests/test_data/HAADF*`` members and the licence are unpacked into the cache; a second call reuses it."""
    import zipfile
    calls = []

    def fake_pip(command, check):
        calls.append(command)
        wheel = Path(command[command.index("-d") + 1]) / "etspy-1.3.0-py3-none-any.whl"
        with zipfile.ZipFile(wheel, "w") as z:
            for f in ("HAADF.mrc", "HAADF.rawtlt"):
                z.write(stand_in / f, f"etspy/tests/test_data/{f}")
            z.writestr("etspy/__init__.py", "")
            z.writestr("etspy-1.3.0.dist-info/LICENSE", "NIST")

    monkeypatch.setattr(subprocess, "run", fake_pip)                       # fetch's (examples/haadf_files.py)
    cache = tmp_path / "cache"
    assert example.fetch(cache) == cache and example.fetch(cache) == cache
    assert len(calls) == 1 and example.WHEEL in calls[0] and "--no-deps" in calls[0]
    assert sorted(p.name for p in cache.iterdir()) == ["HAADF.mrc", "HAADF.rawtlt", "LICENSE"]
    assert example.read_raw(cache)[0].shape == (31, 32, 32)


def test_scale_bar_is_round_and_at_most_a_third_of_the_width(example):
    assert example.scale_bar_nm(64 * 3.36) == 50        # 215 nm wide: 50 nm
    assert example.scale_bar_nm(30.0) == 10 and example.scale_bar_nm(3.0) == 1 and example.scale_bar_nm(1.4) == 0.2


def test_bad_dtype_is_refused(example, stand_in, tmp_path):
    with pytest.raises(ValueError, match="dtype must be 'float32' or 'float64', got 'float16'"):
        example.run(stand_in, tmp_path, dtype="float16")


def test_bad_thread_count_is_one_line(stand_in):
    """``--threads 0``: the script's one-line error, no traceback."""
    import sys
    run = subprocess.run([sys.executable, str(EXAMPLE), "--data", str(stand_in), "--threads", "0"],
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(EXAMPLE.parents[1])})
    assert run.returncode != 0 and run.stderr.strip().splitlines() == [
        "real_data_haadf.py: error: --threads must be >= 1, got 0"]


def test_missing_data_is_one_line_with_the_fetch_before_any_import(tmp_path, error_without_torch):
    """``--data`` a folder without the files: one line naming them and how to get them, before torch is imported (a
    ``torch`` that cannot be imported first on the path shows it)."""
    line = error_without_torch(EXAMPLE, "--data", tmp_path / "empty")
    assert line.startswith(f"real_data_haadf.py: error: {tmp_path / 'empty'} has no HAADF.mrc or HAADF.rawtlt: ")
    assert "pip download etspy==1.3.0 --no-deps" in line and "leave --data out to download" in line


def test_fetch_once_names_the_missing_files(example, tmp_path):
    import argparse
    (tmp_path / "HAADF.mrc").write_bytes(b"")
    with pytest.raises(FileNotFoundError, match=r"has no HAADF.rawtlt: pass --data a folder"):
        example.fetch_once(argparse.Namespace(data=tmp_path, cache=tmp_path / "cache"))


DOCS = EXAMPLE.parents[1] / "docs"


def test_the_pages_figure_shows_the_numbers_of_its_table():
    """docs/real_data.md's figure is the default run's ``figure.png``; its sidecar ``real_data_haadf.json``, written
    with it, holds its SHA-256 and the test-tilt residuals its titles print. They must be the page's: the raw-stack
    test column of the table of the walk-through's defaults and the paragraph under the figure (a figure
    regenerated without its sidecar, or a table rerun without the figure, fails here)."""
    import hashlib
    import re
    side = json.loads((DOCS / "real_data_haadf.json").read_text())
    assert hashlib.sha256((DOCS / "real_data_haadf.png").read_bytes()).hexdigest() == side["sha256"]
    shown = side["test_residual"]
    assert sorted(shown) == ["FBP", "SIRT", "TV", "registered", "template"]
    page = (DOCS / "real_data.md").read_text()
    after = page[page.index("**With the walk-through's defaults as they are now**"):]
    block = after[after.index("| volume |"):].split("\n\n", 1)[0].splitlines()[2:]
    table = {row.split("|")[1].strip().split(" (")[0]: row.split("|")[2].strip() for row in block}
    assert {name: table[name] for name in shown} == shown
    words = re.search(r"no\s+method\s+used:\s+template\s+([0-9.]+),\s+registered\s+([0-9.]+),\s+FBP\s+([0-9.]+),"
                      r"\s+SIRT\s+([0-9.]+),\s+TV\s+([0-9.]+);", page)
    assert words and list(words.groups()) == [shown[k] for k in ("template", "registered", "FBP", "SIRT", "TV")]


def test_the_refit_measure_finds_the_voxels_that_hold_the_error(example):
    """``evaluation_steps.refitted``: the voxels that hold an error fitted alone take the residual to nearly 0, as
    many voxels far from it hardly move it, all voxels fit it; ``flagged_voxels`` reports both measures for a map
    that points at the error (the replacement being the truth here)."""
    import indreg
    from indreg.evaluation.score import relative_residual
    from evaluation_steps import flagged_voxels, refitted   # on sys.path once the example is loaded

    d = indreg.ImageDomain.paper(32)
    T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(12, 46))
    V, x = phantoms.get("v", d).double(), d.points()
    blob = torch.exp(-((x[0] - 3.0) ** 2 + (x[1] + 4.0) ** 2) / 4.0).double()
    f, y = V + 0.5 * blob, T(V)
    as_is = relative_residual(T, f, y)
    far = torch.topk((-(x[0] - 10) ** 2 - (x[1] - 10) ** 2).reshape(-1), 60).indices
    assert refitted(T, f, y, torch.topk(blob.reshape(-1), 60).indices) < 0.01 * as_is
    assert refitted(T, f, y, far) > 0.95 * as_is
    assert refitted(T, f, y, torch.arange(f.numel())) < 0.01 * as_is
    out = flagged_voxels(f, blob, V, T, y)
    assert out["flagged_refitted"] < 0.02 * out["random_refitted_min"]
    assert out["flagged_replaced"] < 0.02 * out["random_replaced_min"]
