"""Volumes where viewers open them at their size: MRC with the voxel size (Angstrom) and the origin in the header, and
OME-Zarr (the ``ome-zarr`` package, an optional extra: ``pip install indreg[zarr]``) with its physical scale.

Notes
-----
- ``volume`` ``(nx, ny, nz)`` (axis 0 = x, indreg's layout); MRC stores sections ``(z, y, x)``, OME-Zarr the
  array ``(z, y, x)`` with axes named so.
- ``voxel_size`` ``(hx, hy, hz)`` and ``origin`` ``(ox, oy, oz)`` in Angstrom: ``origin`` is the position of
  the centre of voxel ``(0, 0, 0)``; MRC's header ``origin`` holds it (``nxstart = nystart = nzstart = 0``),
  OME-Zarr's ``translation`` too (its ``scale`` the voxel size), both as ChimeraX and napari place a grid.
- Each writer returns what wrote the file (``{"path", "format", "writer", "version"}``) for a run's record.
- Both write through :mod:`indreg._outfiles` (a fresh file or directory renamed over the target): a link at the
  target is replaced, never written through.
"""
from __future__ import annotations

from importlib import metadata
from pathlib import Path

import numpy as np

from .._outfiles import replacing
from ._files import _as_path, _fail

__all__ = ["write_mrc", "write_ome_zarr", "ome_zarr_available", "read_ome_zarr_scale"]


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "unknown"


def _checked(volume, voxel_size, origin, path: Path) -> tuple:
    data = np.asarray(volume.detach().cpu().numpy() if hasattr(volume, "detach") else volume)
    if data.ndim != 3 or data.dtype.kind not in "biuf" or not np.isfinite(data).all():
        raise _fail("output", path, f"a volume must be a finite real 3D array (nx, ny, nz), got shape {data.shape}")
    h = tuple(float(v) for v in voxel_size)
    o = tuple(float(v) for v in origin)
    if len(h) != 3 or min(h) <= 0 or len(o) != 3 or not np.isfinite(h + o).all():
        raise _fail("output", path, f"voxel_size needs 3 positive and origin 3 finite numbers, got {h}, {o}")
    return data, h, o


def write_mrc(path, volume, voxel_size, origin=(0.0, 0.0, 0.0)) -> dict:
    """``volume`` as MRC (float32, sections ``(z, y, x)``) with ``voxel_size`` and ``origin`` (Angstrom) in the
    header (module Notes)."""
    import mrcfile

    path = _as_path(path, "output")
    data, h, o = _checked(volume, voxel_size, origin, path)
    try:
        with replacing(path) as new, mrcfile.new(new, overwrite=True) as mrc:
            mrc.set_data(np.ascontiguousarray(data.transpose(2, 1, 0), dtype=np.float32))
            mrc.voxel_size = h
            mrc.header.origin = o
            mrc.header.nxstart = mrc.header.nystart = mrc.header.nzstart = 0
    except OSError as err:
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None
    return {"path": path.name, "format": "MRC2014", "writer": "mrcfile", "version": _version("mrcfile"),
            "voxel_size_A": list(h), "origin_A": list(o)}


def ome_zarr_available() -> bool:
    """Whether the optional ``ome-zarr`` package is installed."""
    try:
        import ome_zarr.writer  # noqa: F401
    except ImportError:
        return False
    return True


def write_ome_zarr(path, volume, voxel_size, origin=(0.0, 0.0, 0.0)) -> dict:
    """``volume`` as a single-scale OME-Zarr image ``(z, y, x)`` in Angstrom with ``scale`` = the voxel size and
    ``translation`` = ``origin`` (module Notes), written by ``ome-zarr``; a one-line error without it."""
    path = _as_path(path, "output")
    data, h, o = _checked(volume, voxel_size, origin, path)
    if not ome_zarr_available():
        raise _fail("output", path, "OME-Zarr needs the optional package ome-zarr: pip install 'indreg[zarr]'")
    import zarr
    from ome_zarr.io import parse_url
    from ome_zarr.writer import write_image

    try:
        with replacing(path) as new:   # written in a private directory, renamed over path (a link there replaced)
            root = zarr.group(store=parse_url(str(new), mode="w").store, overwrite=True)
            write_image(np.ascontiguousarray(data.transpose(2, 1, 0), dtype=np.float32), root, axes=list("zyx"),
                        scale=dict(zip("zyx", h[::-1])), axes_units=dict.fromkeys("zyx", "angstrom"),
                        scale_factors=[])
            _set_translation(root, list(o[::-1]))
    except OSError as err:
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None
    return {"path": path.name, "format": "OME-Zarr", "writer": "ome-zarr", "version": _version("ome-zarr"),
            "voxel_size_A": list(h), "origin_A": list(o)}


def _set_translation(root, translation: list) -> None:
    """The first scale's ``translation`` in the image's metadata (ome-zarr's writer takes the scale only)."""
    attrs = root.attrs.asdict()
    meta = attrs["ome"] if "ome" in attrs else attrs
    transforms = [t for t in meta["multiscales"][0]["datasets"][0]["coordinateTransformations"]
                  if t["type"] != "translation"]
    meta["multiscales"][0]["datasets"][0]["coordinateTransformations"] = transforms + [
        {"type": "translation", "translation": translation}]
    root.attrs.update(attrs)


def read_ome_zarr_scale(path) -> tuple:
    """``(array (z, y, x), scale (z, y, x), translation (z, y, x), units)`` of the first scale of an OME-Zarr
    image, read with ``ome-zarr``'s reader (as napari's plugin does)."""
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    node = next(iter(Reader(parse_url(str(path)))()))
    transforms = {t["type"]: t for t in node.metadata["coordinateTransformations"][0]}
    units = [a.get("unit") for a in node.metadata["axes"]]
    return (np.asarray(node.data[0]), transforms["scale"]["scale"], transforms["translation"]["translation"], units)
