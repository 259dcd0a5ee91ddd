"""Writing result images, volumes and tilt series (re-exported by :mod:`indreg.io`).

Convention:
    - ``write_image``: any array as it is (``.npy`` float64, ``.mrc`` float32), no reorientation.
    - ``write_volume``: ``(nx, ny, nz)``; MRC stores sections ``(z, y, x)`` with the domain's cell sides as voxel size.
    - ``write_tilt_series``: ``(num_tilts, det_rows, det_cols)`` as an MRC stack plus ``stem.tlt`` in degrees.
    - Every problem raises :class:`DataFileError`, one line naming the file.
    - Every file is written through :mod:`indreg._outfiles` (a fresh file renamed over the target): a link at the
      target is replaced, never written through.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .._checks import check_positive
from .._outfiles import open_replacing, replacing
from ._files import _as_path, _fail, _Problem
from ..domain import ImageDomain

__all__ = ["WRITE_FORMATS", "write_image", "write_volume", "write_tilt_series"]

WRITE_FORMATS = (".npy", ".mrc")
MRC = (".mrc", ".st", ".ali")


def write_image(path, array) -> Path:
    """Write a result array (numpy or torch, any shape for ``.npy``; 2D/3D for ``.mrc``) as it is.

    Convention:
        - No reorientation: an image ``(nx, ny)`` is stored ``(x, y)``, so :func:`read_image` gives it back.
        - ``.npy`` keeps float64; ``.mrc`` stores float32 (MRC mode 2), overwriting an existing file.

    Raises:
        DataFileError: unknown extension, non-numeric or non-finite data, or the file cannot be written.
    """
    path = _as_path(path, "output")
    suffix = path.suffix.lower()
    if suffix not in WRITE_FORMATS:
        raise _fail("output", path, f"cannot write format {suffix or '(no extension)'!r}; use {WRITE_FORMATS}")
    if hasattr(array, "detach"):   # torch tensor
        array = array.detach().cpu().numpy()
    data = np.asarray(array)
    if data.dtype.kind not in "biuf" or data.size == 0:
        raise _fail("output", path, f"needs a non-empty real numeric array, got dtype {data.dtype}, shape {data.shape}")
    if not np.isfinite(data).all():
        raise _fail("output", path, "array has non-finite values (NaN or Inf)")
    try:
        if suffix == ".npy":
            with replacing(path) as new:
                np.save(new, np.asarray(data, dtype=np.float64))
        else:
            if data.ndim not in (2, 3):
                raise _Problem(f"MRC needs a 2D or 3D array, got shape {data.shape}")
            import mrcfile

            with replacing(path) as new, mrcfile.new(new, overwrite=True) as mrc:
                mrc.set_data(np.asarray(data, dtype=np.float32))
    except _Problem as problem:
        raise _fail("output", path, problem) from None
    except OSError as err:
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None
    return path


def _finite_array(array, path: Path, ndim: int, what: str) -> np.ndarray:
    if hasattr(array, "detach"):   # torch tensor
        array = array.detach().cpu().numpy()
    data = np.asarray(array)
    if data.dtype.kind not in "biuf" or data.ndim != ndim or data.size == 0:
        raise _fail("output", path, f"{what} must be a non-empty real {ndim}D array, got dtype {data.dtype}, "
                                    f"shape {data.shape}")
    if not np.isfinite(data).all():
        raise _fail("output", path, "array has non-finite values (NaN or Inf)")
    return data


def _write_mrc(path: Path, sections: np.ndarray, voxel_size, origin=None) -> None:
    import mrcfile

    try:
        with replacing(path) as new, mrcfile.new(new, overwrite=True) as mrc:
            mrc.set_data(np.ascontiguousarray(sections, dtype=np.float32))
            if voxel_size is not None:
                mrc.voxel_size = tuple(float(h) for h in voxel_size)
            if origin is not None:
                mrc.header.origin = tuple(float(o) for o in origin)
    except OSError as err:
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None


def write_volume(path, volume, domain=None) -> Path:
    """Write a volume ``(nx, ny, nz)`` (axis 0 = x) as ``.mrc`` or ``.npy``.

    Convention:
        - ``.mrc``: float32 (mode 2), sections ``(z, y, x)`` (x fastest, MRC's standard axis order), so
          IMOD/ChimeraX show x, y, z as indreg's; the voxel size in the header is the domain's cell sides
          ``(hx, hy, hz)`` in the domain's length unit (MRC readers take it as Angstrom), 1 without a domain; the
          header's origin the centre of voxel ``(0, 0, 0)`` (``min_pt + h / 2``), as ChimeraX and napari place a
          grid (``indreg.io.volume_files``), 0 without a domain.
        - ``.npy``: float64 ``(nx, ny, nz)`` as it is (no voxel size).
        - ``read_volume`` (and ``read_voxel_size``) give both back.

    Raises:
        DataFileError: unknown extension, not a finite real 3D array, a shape other than ``domain.shape``, or
        the file cannot be written.
    """
    path = _as_path(path, "output")
    suffix = path.suffix.lower()
    if suffix not in WRITE_FORMATS:
        raise _fail("output", path, f"cannot write format {suffix or '(no extension)'!r}; use {WRITE_FORMATS}")
    data = _finite_array(volume, path, 3, "volume")
    if domain is not None and not isinstance(domain, ImageDomain):
        raise TypeError(f"domain must be an ImageDomain or None, got {type(domain).__name__}")
    if domain is not None and tuple(data.shape) != tuple(domain.shape):
        raise _fail("output", path, f"volume has shape {data.shape} but the domain has {tuple(domain.shape)}")
    if suffix == ".npy":
        try:
            with replacing(path) as new:
                np.save(new, np.asarray(data, dtype=np.float64))
        except OSError as err:
            raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None
    else:
        _write_mrc(path, data.transpose(2, 1, 0), None if domain is None else domain.cell_sides,
                   None if domain is None else [a + h / 2 for a, h in zip(domain.min_pt, domain.cell_sides)])
    return path


def write_tilt_series(path, data, angles, pixel_size: float | None = None) -> Path:
    """Write a tilt series ``(num_tilts, det_rows, det_cols)`` as an MRC stack (sections = tilts, as stored)
    and its angles (radians) as ``stem.tlt`` in degrees, one a line: what ``read_tilt_series`` reads.
    ``pixel_size``: the detector cell (x and y of the header; z = 1)."""
    path = _as_path(path, "output")
    if path.suffix.lower() not in MRC:
        raise _fail("output", path, f"a tilt series is written as MRC ({', '.join(MRC)})")
    stack = _finite_array(data, path, 3, "tilt series")
    radians = np.asarray(angles.detach().cpu() if hasattr(angles, "detach") else angles, dtype=np.float64)
    if radians.shape != (stack.shape[0],) or not np.isfinite(radians).all():
        raise _fail("output", path, f"needs {stack.shape[0]} finite angles (one per tilt), got shape {radians.shape}")
    if pixel_size is not None:
        pixel_size = check_positive(pixel_size, "pixel_size")
    _write_mrc(path, stack, None if pixel_size is None else (pixel_size, pixel_size, 1.0))
    tlt = path.with_suffix(".tlt")
    try:
        with open_replacing(tlt, "w") as f:
            np.savetxt(f, np.rad2deg(radians), fmt="%.6f")
    except OSError as err:
        raise _fail("output", tlt, f"cannot be written ({type(err).__name__}: {err})") from None
    return path
