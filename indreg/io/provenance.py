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
  ``"unknown"``.
- Only the run's own outputs are listed: the caller names them (``names``); anything else in the directory (a
  user's notes, a foreign ``.npy``, 20,000 files of another tool) is neither listed nor opened, so the record's
  work is bounded by the run's own outputs. A name that is missing, a link or not a regular file (a FIFO, a
  socket, a device) is left out unopened; a file that cannot be read back (foreign or corrupt content) is listed
  with ``unreadable``, its reason in one line: the record never blocks and never fails a finished run. A
  directory's size counts at most :data:`MAX_WALK` entries.
"""
from __future__ import annotations

import json
import os
import stat
from importlib import metadata
from pathlib import Path

import numpy as np

__all__ = ["FORMATS", "MAX_WALK", "version", "describe", "record", "write_record"]

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


#: At most this many entries of an output directory (TensorBoard, OME-Zarr, ``.hydra``) are walked for its size.
MAX_WALK = 10_000


def _size(path: Path) -> dict:
    """``{"bytes": n}``: a file's size, or a directory's (its regular files, links not followed, at most
    :data:`MAX_WALK` entries: beyond, ``bytes_at_least`` instead)."""
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        return {"bytes": st.st_size}
    total, seen = 0, 0
    for root, dirs, files in os.walk(path, followlinks=False):
        for name in files:
            seen += 1
            if seen > MAX_WALK:
                return {"bytes_at_least": total}
            s = os.lstat(os.path.join(root, name))
            total += s.st_size if stat.S_ISREG(s.st_mode) else 0
    return {"bytes": total}


def _open_regular(path: Path):
    """``path`` opened for reading if it is a regular file: no link followed, a FIFO never waited on
    (``O_NONBLOCK``), anything else refused (``OSError``)."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(f"{path.name} is not a regular file")
    return os.fdopen(fd, "rb")


def _npy(path: Path) -> dict:
    with _open_regular(path) as f:
        major, _ = np.lib.format.read_magic(f)
        shape, fortran, dtype = (np.lib.format.read_array_header_1_0 if major == 1 else
                                 np.lib.format.read_array_header_2_0)(f)
    return {"dtype": str(dtype), "shape": list(shape), "order": "F" if fortran else "C"}


def _mrc(path: Path) -> dict:
    from mrcfile.mrcinterpreter import MrcInterpreter

    from ._files import mrc_header_problem

    with _open_regular(path) as f:
        problem = mrc_header_problem(f.read(1024), os.fstat(f.fileno()).st_size)
        if problem:
            raise ValueError(problem)
        f.seek(0)
        mrc = MrcInterpreter(iostream=f, permissive=True, header_only=True)
        h = mrc.header
        v = mrc.voxel_size
        return {"shape_zyx": [int(h.nz), int(h.ny), int(h.nx)], "mode": int(h.mode),
                "voxel_size_A": [float(v.x), float(v.y), float(v.z)],
                "origin_A": [float(h.origin.x), float(h.origin.y), float(h.origin.z)],
                "axis_order": "sections (z, y, x): x fastest (MRC's mapc, mapr, maps = "
                              f"{int(h.mapc)}, {int(h.mapr)}, {int(h.maps)})"}


def _zarr(path: Path) -> dict:
    """An OME-Zarr image's first scale: shape, scale, translation and units from its metadata, read with
    ``ome-zarr``'s reader (as napari's plugin does; the array itself is not loaded). A store holding a link or
    anything but directories and regular files is not read."""
    from .volume_files import ome_zarr_available

    out = {"zarr_version": version("zarr")}
    if ome_zarr_available():
        from ome_zarr.io import parse_url
        from ome_zarr.reader import Reader

        for root, dirs, files in os.walk(path, followlinks=False):
            for name in dirs + files:
                mode = os.lstat(os.path.join(root, name)).st_mode
                if not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
                    raise OSError(f"{os.path.join(root, name)} is a link or not a regular file")
        node = next(iter(Reader(parse_url(str(path)))()))
        transforms = {t["type"]: t for t in node.metadata["coordinateTransformations"][0]}
        out.update(shape_zyx=list(node.data[0].shape), scale_zyx=transforms["scale"]["scale"],
                   translation_zyx=transforms.get("translation", {}).get("translation"),
                   units=[a.get("unit") for a in node.metadata["axes"]], axis_order="(z, y, x)")
    return out


_READERS = {".npy": _npy, ".mrc": _mrc, ".zarr": _zarr}


def _listable(path: Path) -> bool:
    """``path`` exists and is a regular file or a directory, not a link (a FIFO, socket or device is left out)."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return False
    return stat.S_ISREG(mode) or stat.S_ISDIR(mode)


def describe(path, root=None, **conventions) -> dict:
    """The record of one output file (module Notes): its format, writer and version, size, what it says of
    itself (``unreadable``, a one-line reason, where it cannot be read back), and the caller's ``conventions``."""
    path = Path(path)
    suffix = path.suffix.lower()
    fmt, writer = DIRECTORIES.get(path.name) or FORMATS.get(suffix) or (suffix.lstrip(".") or "file", "unknown")
    entry = {"path": str(path.relative_to(root)) if root is not None else path.name, "format": fmt,
             "writer": writer, "version": version(writer) if writer != "unknown" else None}
    try:
        entry.update(_size(path))
        if suffix in _READERS:
            entry.update(_READERS[suffix](path))
    except Exception as e:   # foreign or corrupt content, a file replaced meanwhile: noted, never fatal
        entry["unreadable"] = f"{type(e).__name__}: " + " ".join(str(e).split())[:200]
    entry.update(conventions)
    return entry


def record(directory, names, conventions: dict | None = None) -> list:
    """One :func:`describe` entry for each of ``names`` (paths relative to ``directory``: the run's own outputs,
    module Convention) that is a regular file or a directory, sorted; ``conventions`` maps a name to the
    conventions its writer adds (e.g. ``{"final.npy": {"axis_order": "(nx, ny, nz)", ...}}``)."""
    directory = Path(directory)
    conventions = conventions or {}
    entries = []
    for name in sorted(set(str(n) for n in names)):
        p = directory / name
        parents = [directory / q for q in Path(name).parents if str(q) != "."]
        if _listable(p) and not any(q.is_symlink() for q in parents):
            entries.append(describe(p, directory, **conventions.get(name, {})))
    return entries


def write_record(path, directory, names, conventions: dict | None = None, **extra) -> dict:
    """``path`` (JSON): ``extra`` and ``outputs``, the :func:`record` of ``names`` in ``directory`` (``path``
    itself listed as written by indreg); returns it."""
    from .._outfiles import open_replacing

    path = Path(path)
    out = {"writer": "indreg", "version": version("indreg"), **extra,
           "outputs": record(directory, [n for n in names if str(n) != path.name], conventions)}
    out["outputs"].append({"path": path.name, "format": "JSON", "writer": "indreg", "version": version("indreg")})
    with open_replacing(path, "w") as f:
        json.dump(out, f, indent=1)
    return out
