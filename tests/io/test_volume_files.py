"""Volumes for viewers: MRC with voxel size and origin read back by mrcfile, OME-Zarr (optional ome-zarr) with its
scale and translation read back by ome-zarr's reader."""
import mrcfile
import numpy as np
import pytest

from indreg.io.volume_files import ome_zarr_available, read_ome_zarr_scale, write_mrc, write_ome_zarr

VOLUME = np.random.default_rng(0).random((6, 5, 4))   # (nx, ny, nz), all sides different


def test_mrc_header_voxel_size_and_origin(tmp_path):
    record = write_mrc(tmp_path / "v.mrc", VOLUME, (2.5, 3.0, 3.5), (-7.5, -6.0, -5.25))
    assert record["writer"] == "mrcfile" and record["voxel_size_A"] == [2.5, 3.0, 3.5]
    with mrcfile.open(tmp_path / "v.mrc") as mrc:
        assert mrc.data.shape == (4, 5, 6)   # (z, y, x)
        np.testing.assert_allclose(mrc.data, VOLUME.transpose(2, 1, 0), rtol=1e-6)
        np.testing.assert_allclose([mrc.voxel_size.x, mrc.voxel_size.y, mrc.voxel_size.z], [2.5, 3.0, 3.5])
        np.testing.assert_allclose([mrc.header.origin.x, mrc.header.origin.y, mrc.header.origin.z],
                                   [-7.5, -6.0, -5.25])


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="finite real 3D array"):
        write_mrc(tmp_path / "v.mrc", VOLUME[0], (1, 1, 1))
    with pytest.raises(ValueError, match="voxel_size needs 3 positive"):
        write_mrc(tmp_path / "v.mrc", VOLUME, (1, 0, 1))
    if not ome_zarr_available():
        with pytest.raises(ValueError, match="needs the optional package ome-zarr"):
            write_ome_zarr(tmp_path / "v.zarr", VOLUME, (1, 1, 1))


@pytest.mark.skipif(not ome_zarr_available(), reason="the optional package ome-zarr is not installed")
def test_ome_zarr_scale_and_translation(tmp_path):
    record = write_ome_zarr(tmp_path / "v.zarr", VOLUME, (2.5, 3.0, 3.5), (-7.5, -6.0, -5.25))
    assert record["writer"] == "ome-zarr"
    data, scale, translation, units = read_ome_zarr_scale(tmp_path / "v.zarr")
    np.testing.assert_allclose(data, VOLUME.transpose(2, 1, 0), rtol=1e-6)
    assert scale == [3.5, 3.0, 2.5] and translation == [-5.25, -6.0, -7.5] and units == ["angstrom"] * 3


def test_write_volume_puts_the_domains_origin_in_the_header(tmp_path):
    """``indreg.io.write_volume`` (the registration app's ``final.mrc``): voxel size and the centre of voxel 0."""
    from indreg import ImageDomain
    from indreg.io import write_volume

    domain = ImageDomain((6, 5, 4), (-3.0, -1.25, 0.0), (3.0, 1.25, 6.0))
    write_volume(tmp_path / "v.mrc", np.zeros(domain.shape), domain)
    with mrcfile.open(tmp_path / "v.mrc") as mrc:
        np.testing.assert_allclose([mrc.voxel_size.x, mrc.voxel_size.y, mrc.voxel_size.z], [1.0, 0.5, 1.5])
        np.testing.assert_allclose([mrc.header.origin.x, mrc.header.origin.y, mrc.header.origin.z],
                                   [-2.5, -1.0, 0.75])
