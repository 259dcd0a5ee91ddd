"""Crafted input files, as an attacker would hand them over: each is refused in one line (``DataFileError``) or
read safely; nothing in them runs and no byte outside the file is read."""
import struct

import numpy as np
import pytest

from indreg import io

h5py = pytest.importorskip("h5py")


class _Opens:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def test_an_npz_with_an_object_array_is_refused_and_not_unpickled(tmp_path):
    np.savez(tmp_path / "t.npz", a=np.array([_Opens(tmp_path / "marker")], dtype=object))
    with pytest.raises(io.DataFileError, match=r"t\.npz: holds Python objects \(pickled data\), not numbers$"):
        io.read_image(str(tmp_path / "t.npz"), name="template")
    assert not (tmp_path / "marker").exists()


@pytest.fixture
def other(tmp_path):
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["data"] = np.ones((8, 8))
    return tmp_path / "other.h5"


def test_an_hdf5_external_link_is_refused(tmp_path, other):
    with h5py.File(tmp_path / "t.h5", "w") as f:
        f["data"] = h5py.ExternalLink(str(other), "/data")
    with pytest.raises(io.DataFileError, match=rf"dataset '/data' is an external link to {other}; indreg reads only "
                                               "data stored in the file itself$"):
        io.read_image(f"{tmp_path / 't.h5'}:/data")


def test_hdf5_external_raw_storage_is_refused_and_the_outside_bytes_never_read(tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_bytes(b"secret" * 20)
    with h5py.File(tmp_path / "t.hspy", "w") as f:
        f.create_dataset("data", shape=(8, 8), dtype="u1", external=[(str(secret), 0, 64)])
    with pytest.raises(io.DataFileError, match=r"dataset '/data' has external storage \(.*secret\.txt'\)"):
        io.read_image(str(tmp_path / "t.hspy"))


def test_an_hdf5_virtual_dataset_is_refused(tmp_path, other):
    with h5py.File(tmp_path / "t.h5", "w") as f:
        layout = h5py.VirtualLayout(shape=(8, 8), dtype="f8")
        layout[:] = h5py.VirtualSource(str(other), "data", shape=(8, 8))
        f.create_virtual_dataset("data", layout)
    with pytest.raises(io.DataFileError, match=r"dataset '/data' is a virtual dataset"):
        io.read_image(str(tmp_path / "t.h5"))


def test_an_ordinary_hdf5_dataset_is_read(other):
    assert io.read_image(str(other)).shape == (8, 8)


def test_an_mrc_header_claiming_a_huge_size_is_refused_without_allocating_it(tmp_path):
    mrcfile = pytest.importorskip("mrcfile")
    path = tmp_path / "huge.mrc"
    with mrcfile.new(path) as m:
        m.set_data(np.zeros((4, 4, 4), np.float32))
    blob = bytearray(path.read_bytes())
    blob[0:12] = struct.pack("<3i", 100000, 100000, 100000)   # nx, ny, nz: 4e15 bytes of float32
    path.write_bytes(bytes(blob))
    with pytest.raises(io.DataFileError, match=r"huge\.mrc: not a readable MRC file \(Expected 4000000000000000 "
                                               r"bytes in data block"):
        io.read_volume(str(path))
