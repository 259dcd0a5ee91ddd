"""An MRC file whose header announces an extended header beyond the file's end (2^31 bytes in a 1 kB file) is
refused in one line before ``mrcfile`` reads it (it used to allocate gigabytes, then fail after 25 s)."""
import resource
import struct
import time

import mrcfile
import numpy as np
import pytest

from indreg.io import DataFileError, read_stack, read_voxel_size
from indreg.io.provenance import describe


@pytest.fixture()
def crafted(tmp_path):
    path = tmp_path / "ext.mrc"
    with mrcfile.new(path) as m:
        m.set_data(np.zeros((2, 4, 4), np.float32))
    head = bytearray(path.read_bytes())
    head[92:96] = struct.pack("<i", 2 ** 31 - 1)
    path.write_bytes(bytes(head))
    return path


def test_extended_header_beyond_the_file_is_refused_at_once(crafted):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    for read in (read_stack, read_voxel_size):
        with pytest.raises(DataFileError, match=r"ext\.mrc: its header announces an extended header of 2147483647 "
                                                r"bytes, but the file has 1152 bytes"):
            read(crafted)
    assert "unreadable" in describe(crafted)
    grown_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert time.perf_counter() - t0 < 2.0 and grown_kib < 200_000


def test_a_right_extended_header_still_reads(tmp_path):
    path = tmp_path / "ok.mrc"
    with mrcfile.new(path) as m:
        m.set_data(np.ones((2, 4, 4), np.float32))
        m.set_extended_header(np.zeros(8, dtype=np.uint8))
    np.testing.assert_allclose(read_stack(path), 1.0)
