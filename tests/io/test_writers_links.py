"""Every public writer (``write_image``, ``write_volume``, ``write_tilt_series`` with its ``.tlt``, ``write_mrc``,
``write_ome_zarr``) writes through ``indreg._outfiles``: a link planted at the target (to a file or a directory
outside) is replaced by the new output and what it pointed to is untouched."""
import numpy as np
import pytest

from indreg.domain import ImageDomain
from indreg.io import write_image, write_tilt_series, write_volume
from indreg.io.volume_files import ome_zarr_available, write_mrc, write_ome_zarr

VOLUME = np.arange(24, dtype=np.float64).reshape(2, 3, 4)


def _planted(tmp_path, name):
    outside = tmp_path / "outside"
    outside.mkdir(exist_ok=True)
    victim = outside / f"victim-{name}"
    victim.write_text("precious")
    run = tmp_path / "run"
    run.mkdir(exist_ok=True)
    (run / name).symlink_to(victim)
    return run / name, victim


WRITERS = {
    "a.npy": lambda p: write_image(p, VOLUME),
    "a.mrc": lambda p: write_image(p, VOLUME),
    "v.npy": lambda p: write_volume(p, VOLUME, ImageDomain((2, 3, 4), (0, 0, 0), (2, 3, 4))),
    "v.mrc": lambda p: write_volume(p, VOLUME),
    "m.mrc": lambda p: write_mrc(p, VOLUME, (1.0, 1.0, 1.0)),
}


@pytest.mark.parametrize("name", list(WRITERS))
def test_writers_replace_a_planted_link(tmp_path, name):
    target, victim = _planted(tmp_path, name)
    WRITERS[name](target)
    assert victim.read_text() == "precious"
    assert target.is_file() and not target.is_symlink()
    assert sorted(p.name for p in target.parent.iterdir()) == [name]      # no scratch left


def test_tilt_series_and_its_angles_replace_planted_links(tmp_path):
    stack, victim = _planted(tmp_path, "s.mrc")
    tlt, tlt_victim = _planted(tmp_path, "s.tlt")
    write_tilt_series(stack, np.ones((3, 4, 5)), np.deg2rad([-10.0, 0.0, 10.0]))
    assert victim.read_text() == "precious" and tlt_victim.read_text() == "precious"
    assert not stack.is_symlink() and not tlt.is_symlink()
    np.testing.assert_allclose(np.loadtxt(tlt), [-10, 0, 10])


@pytest.mark.skipif(not ome_zarr_available(), reason="needs the optional ome-zarr package")
def test_ome_zarr_replaces_a_planted_directory_link_and_an_old_store(tmp_path):
    outside = tmp_path / "outside.zarr"
    outside.mkdir()
    (outside / "precious").write_text("x")
    run = tmp_path / "run"
    run.mkdir()
    (run / "r.zarr").symlink_to(outside, target_is_directory=True)
    write_ome_zarr(run / "r.zarr", VOLUME, (1.0, 1.0, 1.0))
    assert sorted(p.name for p in outside.iterdir()) == ["precious"]
    assert (run / "r.zarr").is_dir() and not (run / "r.zarr").is_symlink()
    write_ome_zarr(run / "r.zarr", 2 * VOLUME, (1.0, 1.0, 1.0))          # over an existing store: replaced whole
    assert sorted(p.name for p in run.iterdir()) == ["r.zarr"]
