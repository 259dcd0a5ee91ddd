"""``indreg-align`` on a raw stack made by IMOD's formula (scipy) from known shifts and a tilt axis at 93 degrees:
the .xf it writes recovers them (in the gauge), the residual falls, the outputs carry their pixel sizes."""
import json
import logging
import math
import subprocess
import sys

import mrcfile
import numpy as np
import pytest
import torch
from scipy.ndimage import affine_transform

from indreg import ImageDomain
from indreg.alignment.app import _slab_sirt, choose_binning, levels, main, parse_bytes, slab_rows, working_set
from indreg.alignment.files import read_aln, read_xf
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.io import write_tilt_series

N, AXIS = 32, 93.0


def _raw_series(tmp_path):
    domain = ImageDomain((N, N, N // 2), (-N / 2, -N / 2, -N / 4), (N / 2, N / 2, N / 4))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 6, det_count=N, det_min=-N / 2,
                                                               det_max=N / 2))
    gen = np.random.default_rng(5)
    x, y, z = torch.meshgrid(*(torch.arange(n, dtype=torch.float64) - (n - 1) / 2 for n in domain.shape),
                             indexing="ij")
    f = sum(gen.uniform(0.5, 1) * torch.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / 6)
            for c in gen.uniform(-5, 5, (6, 3)) * [1, 1, 0.5])
    ideal = T(f).numpy()
    K = len(ideal)
    t = np.radians(-AXIS)
    A = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    D = gen.uniform(-2, 2, (K, 2))
    c = np.full(2, (N - 1) / 2)
    m = np.array([[A[1, 1], A[1, 0]], [A[0, 1], A[0, 0]]])
    raw = np.stack([affine_transform(ideal[k], m, D[k, ::-1] + c - m @ c, order=1, mode="nearest")
                    for k in range(K)])   # raw(u) = aligned(A u + D), IMOD's formula
    write_tilt_series(tmp_path / "raw.mrc", raw, T.geometry.angles, pixel_size=2.5)
    return T.geometry.angles.numpy(), D


def _gauge(D, theta):
    """Across the axis without a cos + b sin, along it without its mean (projection matching's gauge)."""
    basis = np.stack([np.cos(theta), np.sin(theta)], 1)
    across = D[:, 0] - basis @ np.linalg.lstsq(basis, D[:, 0], rcond=None)[0]
    return np.stack([across, D[:, 1] - D[:, 1].mean()], 1)


@pytest.mark.slow
def test_recovers_the_shifts_and_writes_the_outputs(tmp_path, capsys):
    theta, D = _raw_series(tmp_path)
    out = tmp_path / "out"
    assert main([str(tmp_path / "raw.mrc"), "--tilt-axis-angle", str(AXIS), "--out", str(out), "--rounds", "3",
                 "--iters", "20", "--thickness", "16", "--bin", "1"]) == 0
    line = capsys.readouterr().out
    assert line.startswith("indreg-align: residual") and line.count("\n") == 1
    s = json.loads((out / "align.json").read_text())
    assert s["residual_after"] < 0.5 * s["residual_before"], s
    xf = np.loadtxt(out / "alignment.xf")
    rotation = np.degrees(np.arctan2(xf[:, 2] - xf[:, 1], xf[:, 0] + xf[:, 3]))
    np.testing.assert_allclose(rotation, -AXIS, atol=1e-3)   # the axis given, not refined
    error = _gauge(xf[:, 4:], theta) - _gauge(D, theta)
    assert np.sqrt((error ** 2).mean()) < 0.2, error
    a = read_xf(out / "alignment.xf")
    b = read_aln(out / "alignment.aln")
    np.testing.assert_allclose(a.shifts, b.shifts, atol=1e-3)
    np.testing.assert_allclose(a.tilt_angles_deg, np.degrees(theta), atol=1e-3)
    with mrcfile.open(out / "aligned.mrc") as mrc:
        assert mrc.data.shape == (len(theta), N, N) and abs(float(mrc.voxel_size.x) - 2.5) < 1e-6
    with mrcfile.open(out / "reconstruction.mrc") as mrc:
        assert mrc.data.shape == (16, N, N) and abs(float(mrc.voxel_size.z) - 2.5) < 1e-6
        assert abs(float(mrc.header.origin.x) + (N - 1) / 2 * 2.5) < 1e-4
    by_path = {o["path"]: o for o in s["outputs"]}
    assert set(by_path) == {"align.json", "aligned.mrc", "reconstruction.mrc", "alignment.xf", "alignment.tlt",
                            "alignment.aln", "alignment.json", "aligned.tlt"}
    assert by_path["aligned.mrc"]["writer"] == by_path["reconstruction.mrc"]["writer"] == "mrcfile"
    assert by_path["reconstruction.mrc"]["version"] == mrcfile.__version__
    assert by_path["alignment.xf"]["writer"] == "indreg" and by_path["alignment.xf"]["format"] == "IMOD .xf"
    assert by_path["alignment.xf"]["conventions"]["xf"].startswith("IMOD")
    assert by_path["alignment.tlt"]["units"] == "degree"
    np.testing.assert_allclose(by_path["reconstruction.mrc"]["voxel_size_A"], 2.5, rtol=1e-6)   # read back
    assert by_path["reconstruction.mrc"]["shape_zyx"] == [16, N, N]
    assert by_path["aligned.mrc"]["pixel_size_A"] == 2.5 and "tilt axis along Y" in by_path["aligned.mrc"]["axis_order"]


@pytest.mark.slow
def test_coarse_to_fine_and_a_slabwise_reconstruction(tmp_path, caplog):
    """Rounds binned by 2, then one at full size, the shifts carried up; the reconstruction made from the aligned
    stack slab by slab: the shifts still within 0.3 px in the gauge, the record names both levels."""
    caplog.set_level(logging.INFO, logger="indreg.align")
    theta, D = _raw_series(tmp_path)
    out = tmp_path / "out"
    assert main([str(tmp_path / "raw.mrc"), "--tilt-axis-angle", str(AXIS), "--out", str(out), "--rounds", "3",
                 "--iters", "20", "--thickness", "16", "--bin", "1", "--coarse-bin", "2", "--recon-bin", "1"]) == 0
    s = json.loads((out / "align.json").read_text())
    assert [level["bin"] for level in s["levels"]] == [2, 1] and [len(lv["rounds"]) for lv in s["levels"]] == [3, 1]
    assert s["recon_binning"] == 1 and s["residual_after"] < 0.5 * s["residual_before"], s
    xf = np.loadtxt(out / "alignment.xf")
    error = _gauge(xf[:, 4:], theta) - _gauge(D, theta)
    assert np.sqrt((error ** 2).mean()) < 0.3, error
    with mrcfile.open(out / "reconstruction.mrc") as mrc:
        assert mrc.data.shape == (16, N, N) and abs(float(mrc.voxel_size.x) - 2.5) < 1e-6
    assert "level 2/2: binned by 1" in caplog.text and "reconstruction: rows 0-31 of 32" in caplog.text


def test_levels_and_slabs():
    assert levels(1024, 1024, 4) == [8, 4] and levels(256, 200, 1) == [1] and levels(256, 256, 1) == [2, 1]
    assert levels(1024, 1024, 4, 16) == [16, 8, 4] and levels(64, 64, 2, 2) == [2] and levels(64, 64, 3, 6) == [6, 3]
    assert levels(768, 768, 3) == [6, 3]
    for fine, coarse in ((4, 2), (2, 6), (3, 9)):
        with pytest.raises(ValueError, match="must be --bin .* times a power of 2"):
            levels(64, 64, fine, coarse)
    rows = [slab_rows(1024, 1024, 512, 61, budget) for budget in (6 * 2**30, 8 * 2**30, 64 * 2**30)]
    assert 1 <= rows[0] < rows[1] < rows[2] == 1024
    assert slab_rows(1024, 1024, 512, 61, 1) == 1


def test_slabwise_sirt_equals_the_whole_volume_s():
    """A tilt series' rows are independent: SIRT slab by slab (2 rows, and 4 leaving a remainder) is SIRT of the
    whole stack."""
    stack = np.random.default_rng(3).random((5, 6, 8)).astype(np.float32)
    theta = np.radians(np.linspace(-60, 60, 5))
    whole, r_whole = _slab_sirt(stack, theta, 4, 10, 6)
    for rows in (2, 4):
        parts, r_parts = _slab_sirt(stack, theta, 4, 10, rows)
        torch.testing.assert_close(parts, whole, rtol=1e-5, atol=1e-6)
        assert abs(r_parts - r_whole) < 1e-5 * r_whole
    assert 0 < r_whole < 1


@pytest.mark.slow
def test_refine_axis_warns_that_it_is_not_validated(tmp_path, caplog):
    """--refine-axis runs, and says that its angle is not validated (docs/alignment.md: it stays near its start)."""
    _raw_series(tmp_path)
    with caplog.at_level("WARNING", logger="indreg.align"):
        assert main([str(tmp_path / "raw.mrc"), "--tilt-axis-angle", "91.5", "--refine-axis", "--out",
                     str(tmp_path / "out"), "--rounds", "1", "--iters", "5", "--thickness", "16", "--bin", "1"]) == 0
    assert any("refined tilt-axis angle is not validated" in m for m in caplog.messages)


def test_memory_budget_and_errors(tmp_path, capsys):
    assert parse_bytes("8GiB") == 8 * 2**30 and parse_bytes("512M") == 512 * 2**20
    with pytest.raises(ValueError, match="--max-memory must be a size"):
        parse_bytes("lots")
    full = working_set(1024, 1024, 512, 61)
    b = choose_binning(1024, 1024, 512, 61, 8 * 2**30, 3 * 61 * 1024 ** 2 * 4, "linear")
    assert working_set(1024 // b, 1024 // b, 512 // b, 61) < 8 * 2**30 < full or b == 1
    assert main([str(tmp_path / "missing.mrc")]) == 2
    assert "indreg-align: error: " in capsys.readouterr().err
    for bad in (["--recon-bin", "0"], ["--recon-bin", "2", "--recon", "tv"]):
        assert main([str(tmp_path / "missing.mrc")] + bad) == 2
        err = capsys.readouterr().err
        assert err.startswith("indreg-align: error: --recon-bin must be") and err.count("\n") == 1


def test_help_is_fast():
    r = subprocess.run([sys.executable, "-m", "indreg.alignment.app", "--help"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and "--max-memory" in r.stdout


@pytest.mark.slow
def test_axis_from_stack_finds_the_axis(tmp_path, caplog):
    """The axis given 1.5 degrees off (91.5 for 93): --axis-from-stack takes the rest from the stack's moment
    conditions, so the .xf's rotation is the true axis' and the record says where it came from."""
    theta, D = _raw_series(tmp_path)
    out = tmp_path / "out"
    with caplog.at_level("INFO", logger="indreg.align"):
        assert main([str(tmp_path / "raw.mrc"), "--tilt-axis-angle", "91.5", "--axis-from-stack", "--out", str(out),
                     "--rounds", "3", "--iters", "20", "--thickness", "16", "--bin", "1"]) == 0
    s = json.loads((out / "align.json").read_text())
    assert s["axis_from_stack"]["determined"] is True and s["axis_from_stack"]["given_rest_deg"] == 1.5
    xf = np.loadtxt(out / "alignment.xf")
    rotation = np.degrees(np.arctan2(xf[:, 2] - xf[:, 1], xf[:, 0] + xf[:, 3]))
    np.testing.assert_allclose(rotation, -AXIS, atol=0.2)
    assert abs(s["axis_angle_deg"] - AXIS) < 0.2
    error = _gauge(xf[:, 4:], theta) - _gauge(D, theta)
    assert np.sqrt((error ** 2).mean()) < 0.2, error
    assert any("--axis-from-stack: tilt-axis angle from the stack's moment conditions" in m for m in caplog.messages)
