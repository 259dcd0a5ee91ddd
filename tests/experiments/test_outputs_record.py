"""The registration app's ``outputs.json``: every file of the run directory with its format, the tool that wrote it
and its version, the arrays' axis order and voxel size, and the MRC's voxel size read back from its header."""
import json

import mrcfile
import numpy as np

from experiment_helpers import run_app
from test_et_3d import TINY_3D


def test_outputs_json_lists_every_file_with_its_writer(tmp_path):
    out = tmp_path / "run"
    run_app(TINY_3D + ["baseline=none", "logging.figure=false", "logging.tensorboard=false"], out)
    record = json.loads((out / "outputs.json").read_text())
    entries = {e["path"]: e for e in record["outputs"]}
    on_disk = {p.name for p in out.iterdir()}
    assert set(entries) == on_disk, on_disk ^ set(entries)
    assert record["run"] == "indreg-register" and record["writer"] == "indreg"
    final = entries["final.npy"]
    assert (final["writer"], final["version"], final["dtype"]) == ("numpy", np.__version__, "float64")
    assert final["axis_order"].startswith("(nx, ny, nz)") and final["shape"] == list(np.load(out / "final.npy").shape)
    h = final["voxel_size"]
    assert len(h) == 3 and min(h) > 0 and len(final["origin"]) == 3
    assert entries["velocity.npy"]["axis_order"].startswith("(N + 1, d components")
    assert entries["data.npy"]["axis_order"] == "(tilts, rows, columns)"
    mrc = entries["final.mrc"]
    assert (mrc["writer"], mrc["version"]) == ("mrcfile", mrcfile.__version__)
    np.testing.assert_allclose(mrc["voxel_size_A"], h, rtol=1e-6)   # read back from the header
    np.testing.assert_allclose(mrc["origin_A"], final["origin"], rtol=1e-6)   # the centre of voxel 0, both
    assert entries["checkpoint.pt"]["writer"] == "torch" and entries["metrics.json"]["writer"] == "indreg"


def test_a_fifo_and_a_corrupt_npy_in_the_run_dir_neither_hang_nor_end_the_run(tmp_path):
    """A FIFO named ``*.npy`` (a reader waits for a writer forever) and a foreign ``notes.npy`` of one byte in the
    run directory: the run completes, ``outputs.json`` lists the run's own files only."""
    import os

    import pytest
    from experiment_helpers import FAST

    if not hasattr(os, "mkfifo"):
        pytest.skip("needs FIFOs (POSIX)")
    out = tmp_path / "run"
    out.mkdir()
    os.mkfifo(out / "pipe.npy")
    (out / "notes.npy").write_bytes(b"x")
    result = run_app(FAST + ["solver.max_iter=2"], out)
    assert result["status"] == "completed"
    paths = {e["path"] for e in json.loads((out / "outputs.json").read_text())["outputs"]}
    assert "final.npy" in paths and "metrics.json" in paths and not paths & {"pipe.npy", "notes.npy"}
