"""Which tool wrote what: a record of a run's output files (format, the writing tool and its version, units and
conventions), so that the next tool in a pipeline knows what it got.

Notes
-----
- One entry per file (a directory for OME-Zarr, TensorBoard, Hydra's ``.hydra``): ``path`` (relative to the
  run directory), ``format``, ``writer`` and ``version`` (the Python package that wrote the bytes: ``numpy``
  for ``.npy``, ``mrcfile`` for MRC, ``ome-zarr`` and ``zarr`` for OME-Zarr, ``matplotlib`` for figures,
  ``imageio`` for GIFs, ``torch`` for checkpoints and TensorBoard, ``indreg`` for its own text formats),
  ``bytes``.
- What the file says of itself is read back from it, not copied from the run: a ``.npy``'s dtype and shape
  (its header), an MRC's shape, voxel size and origin (its header, Angstrom by the format), an OME-Zarr's scale,
  translation and units (its metadata, read with ``ome-zarr``; the array is not loaded).
- The writer's conventions (axis order, units, the voxel size of an ``.npy``, which has none) come from the
  caller (``describe(..., **conventions)``; :func:`record` takes them per file name).
- Files the record does not know (another suffix) are listed with ``format`` their suffix and ``writer``
  ``"unknown"``: nothing in the directory is left out.
"""
from __future__ import annotations

import json
from importlib import metadata
from pathlib import Path

import numpy as np

__all__ = ["FORMATS", "version", "describe", "record", "write_record"]

#: Suffix -> (format, writing package).
FORMATS = {
    ".npy": ("NPY (numpy .npy 1.0)", "numpy"),
    ".mrc": ("MRC2014", "mrcfile"),
    ".zarr": ("OME-Zarr", "ome-zarr"),
    ".json": ("JSON", "indreg"),
    ".xf": ("IMOD .xf", "indreg"),
    ".tlt": ("IMOD .tlt", "indreg"),
    ".aln": ("AreTomo .aln", "indreg"),
    ".png": ("PNG", "matplotlib"),
    ".gif": ("GIF", "imageio"),
    ".pt": ("PyTorch checkpoint (torch.save)", "torch"),
    ".npz": ("NPZ (numpy .npz)", "numpy"),
    ".log": ("text log (Hydra's job log, Python logging)", "hydra-core"),
    ".md": ("Markdown", "indreg"),
}
#: Directories written by a tool as a whole, by name.
DIRECTORIES = {"tensorboard": ("TensorBoard event files", "torch"), ".hydra": ("Hydra configuration (YAML)",
                                                                               "hydra-core")}


def version(package: str) -> str:
    """The installed version of ``package`` (``indreg``'s own when not installed as a distribution)."""
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        if package == "indreg":
            from .. import __version__
            return __version__
        return "unknown"


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _npy(path: Path) -> dict:
    with open(path, "rb") as f:
        major, _ = np.lib.format.read_magic(f)
        shape, fortran, dtype = (np.lib.format.read_array_header_1_0 if major == 1 else
                                 np.lib.format.read_array_header_2_0)(f)
    return {"dtype": str(dtype), "shape": list(shape), "order": "F" if fortran else "C"}


def _mrc(path: Path) -> dict:
    import mrcfile

    with mrcfile.open(path, header_only=True, permissive=True) as mrc:
        h = mrc.header
        v = mrc.voxel_size
        return {"shape_zyx": [int(h.nz), int(h.ny), int(h.nx)], "mode": int(h.mode),
                "voxel_size_A": [float(v.x), float(v.y), float(v.z)],
                "origin_A": [float(h.origin.x), float(h.origin.y), float(h.origin.z)],
                "axis_order": "sections (z, y, x): x fastest (MRC's mapc, mapr, maps = "
                              f"{int(h.mapc)}, {int(h.mapr)}, {int(h.maps)})"}


def _zarr(path: Path) -> dict:
    """An OME-Zarr image's first scale: shape, scale, translation and units from its metadata, read with
    ``ome-zarr``'s reader (as napari's plugin does; the array itself is not loaded)."""
    from .volume_files import ome_zarr_available

    out = {"zarr_version": version("zarr")}
    if ome_zarr_available():
        from ome_zarr.io import parse_url
        from ome_zarr.reader import Reader

        node = next(iter(Reader(parse_url(str(path)))()))
        transforms = {t["type"]: t for t in node.metadata["coordinateTransformations"][0]}
        out.update(shape_zyx=list(node.data[0].shape), scale_zyx=transforms["scale"]["scale"],
                   translation_zyx=transforms.get("translation", {}).get("translation"),
                   units=[a.get("unit") for a in node.metadata["axes"]], axis_order="(z, y, x)")
    return out


_READERS = {".npy": _npy, ".mrc": _mrc, ".zarr": _zarr}


def describe(path, root=None, **conventions) -> dict:
    """The record of one output file (module Notes): its format, writer and version, size, what it says of
    itself, and the caller's ``conventions``."""
    path = Path(path)
    suffix = path.suffix.lower()
    fmt, writer = DIRECTORIES.get(path.name) or FORMATS.get(suffix) or (suffix.lstrip(".") or "file", "unknown")
    entry = {"path": str(path.relative_to(root)) if root is not None else path.name, "format": fmt,
             "writer": writer, "version": version(writer) if writer != "unknown" else None, "bytes": _size(path)}
    if suffix in _READERS and path.exists():
        entry.update(_READERS[suffix](path))
    entry.update(conventions)
    return entry


def record(directory, conventions: dict | None = None, skip=()) -> list:
    """One :func:`describe` entry per file of ``directory`` (sorted; the known tool directories and ``.zarr`` as one
    entry each, other subdirectories walked; names in ``skip`` left out); ``conventions`` maps a file name to the
    conventions its writer adds (e.g. ``{"final.npy": {"axis_order": "(nx, ny, nz)", ...}}``)."""
    directory = Path(directory)
    conventions = conventions or {}
    entries = []

    def walk(d: Path):
        for p in sorted(d.iterdir()):
            if p.name in skip or p.is_symlink():
                continue
            if p.is_dir() and p.name not in DIRECTORIES and p.suffix.lower() != ".zarr":
                walk(p)
            else:
                entries.append(describe(p, directory, **conventions.get(p.name, {})))

    walk(directory)
    return entries


def write_record(path, directory, conventions: dict | None = None, **extra) -> dict:
    """``path`` (JSON): ``extra`` and ``outputs``, the :func:`record` of ``directory`` (``path`` itself listed as
    written by indreg); returns it."""
    from .._outfiles import open_replacing

    path = Path(path)
    out = {"writer": "indreg", "version": version("indreg"), **extra,
           "outputs": record(directory, conventions, skip={path.name})}
    out["outputs"].append({"path": path.name, "format": "JSON", "writer": "indreg", "version": version("indreg")})
    with open_replacing(path, "w") as f:
        json.dump(out, f, indent=1)
    return out
