"""``indreg.io.provenance``: each output file listed with its format, the tool that wrote it and its version, and
what the file says of itself read back from it (an .npy's header, an MRC's voxel size and origin, an OME-Zarr's
scale); files it does not know are listed too."""
import json
from importlib import metadata

import mrcfile
import numpy as np
import pytest

from indreg.io.provenance import describe, record, version, write_record
from indreg.io.volume_files import ome_zarr_available, write_mrc, write_ome_zarr


def test_files_are_read_back_and_credited_to_their_writer(tmp_path):
    gen = np.random.default_rng(0)
    np.save(tmp_path / "final.npy", gen.random((5, 4, 3)))
    write_mrc(tmp_path / "final.mrc", gen.random((5, 4, 3)), (2.0, 2.5, 3.0), (-4.0, -3.75, -3.0))
    (tmp_path / "notes.xyz").write_text("?")
    (tmp_path / "foreign.npy").write_text("?")
    entries = {e["path"]: e for e in record(tmp_path, ["final.npy", "final.mrc", "notes.xyz", "missing.npy"],
                                            {"final.npy": {"axis_order": "(nx, ny, nz)"}})}
    assert set(entries) == {"final.npy", "final.mrc", "notes.xyz"}     # the names given that exist, no other
    npy = entries["final.npy"]
    assert (npy["writer"], npy["version"], npy["dtype"], npy["shape"]) == ("numpy", np.__version__, "float64",
                                                                           [5, 4, 3])
    assert npy["axis_order"] == "(nx, ny, nz)" and npy["bytes"] == (tmp_path / "final.npy").stat().st_size
    mrc = entries["final.mrc"]
    assert (mrc["writer"], mrc["version"], mrc["shape_zyx"]) == ("mrcfile", mrcfile.__version__, [3, 4, 5])
    np.testing.assert_allclose(mrc["voxel_size_A"], [2.0, 2.5, 3.0], rtol=1e-6)
    np.testing.assert_allclose(mrc["origin_A"], [-4.0, -3.75, -3.0], rtol=1e-6)
    assert entries["notes.xyz"]["writer"] == "unknown" and entries["notes.xyz"]["version"] is None


def test_versions_and_the_written_record(tmp_path):
    assert version("numpy") == metadata.version("numpy")
    assert version("indreg") and version("no-such-package-xyz") == "unknown"
    np.save(tmp_path / "a.npy", np.zeros(3, dtype=np.float32))
    sub = tmp_path / "sub"
    sub.mkdir()
    np.save(sub / "b.npy", np.zeros((2, 2)))
    out = write_record(tmp_path / "run.json", tmp_path, ["a.npy", "sub/b.npy", "run.json"], run="test")
    on_disk = json.loads((tmp_path / "run.json").read_text())
    assert on_disk == out and out["run"] == "test" and out["writer"] == "indreg"
    assert [e["path"] for e in out["outputs"]] == ["a.npy", "sub/b.npy", "run.json"]
    assert out["outputs"][0]["dtype"] == "float32"


@pytest.mark.skipif(not ome_zarr_available(), reason="needs the optional ome-zarr package")
def test_ome_zarr_scale_is_read_back(tmp_path):
    write_ome_zarr(tmp_path / "v.zarr", np.ones((4, 3, 2)), (1.0, 2.0, 3.0), (0.5, 1.0, 1.5))
    e = describe(tmp_path / "v.zarr", tmp_path)
    assert (e["format"], e["writer"], e["shape_zyx"]) == ("OME-Zarr", "ome-zarr", [2, 3, 4])
    assert e["scale_zyx"] == [3.0, 2.0, 1.0] and e["translation_zyx"] == [1.5, 1.0, 0.5]
    assert e["units"] == ["angstrom"] * 3 and e["zarr_version"] == metadata.version("zarr")
