"""Writing result images, volumes and tilt series (re-exported by :mod:`indreg.io`), each by the writer of its
suffix's registered format (``indreg.io.formats``).

Notes
-----
- ``write_image``: any array as it is (``.npy`` float64, ``.mrc`` float32), no reorientation.
- ``write_volume``: ``(nx, ny, nz)``; MRC stores sections ``(z, y, x)`` (a format's ``volume_order``) with the
  domain's cell sides as voxel size.
- ``write_tilt_series``: ``(num_tilts, det_rows, det_cols)`` as an MRC stack (a format of ``sections``) plus
  ``stem.tlt`` in degrees.
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
from .formats import FILE_FORMATS, FileFormat, get_format, suffixes

__all__ = ["write_image", "write_volume", "write_tilt_series"]


def _writer(path: Path) -> FileFormat:
    """The registered format that writes ``path``; else a one-line error listing the writable suffixes."""
    fmt = get_format(path.suffix)
    if fmt is None or fmt.write is None:
        suffix = path.suffix.lower() or "(no extension)"
        raise _fail("output", path, f"cannot write format {suffix!r}; use {', '.join(suffixes('write'))}")
    return fmt


def _write(fmt: FileFormat, path: Path, array: np.ndarray, **header) -> None:
    """``fmt.write`` of ``array`` to ``path`` (through ``indreg._outfiles.replacing``), with ``header`` (voxel size,
    origin) for a format that has one; every failure as one line naming the file."""
    try:
        with replacing(path) as new:   # a link at path replaced, never followed
            if fmt.read_voxel_size is not None:
                fmt.write(new, array, **header)
            else:
                fmt.write(new, array)
    except _Problem as problem:
        raise _fail("output", path, problem) from None
    except Exception as err:   # the writer's or its library's complaint, as one line
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None


def write_image(path, array) -> Path:
    """Write a result array as it is, in the format of its suffix.

    Parameters
    ----------
    path : str or os.PathLike
        The file; its suffix names a registered format with a writer.
    array : numpy.ndarray or torch.Tensor
        A non-empty, finite, real array.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    DataFileError
        An unknown or read-only suffix (the message lists the writable ones), non-numeric or non-finite data, or
        the file cannot be written.

    Notes
    -----
    - No reorientation: an image ``(nx, ny)`` is stored ``(x, y)``, so :func:`read_image` gives it back.
    - ``.npy`` keeps float64 (any shape); ``.mrc`` stores float32 (MRC mode 2, 2D or 3D), overwriting an
      existing file.
    """
    path = _as_path(path, "output")
    fmt = _writer(path)
    if hasattr(array, "detach"):   # torch tensor
        array = array.detach().cpu().numpy()
    data = np.asarray(array)
    if data.dtype.kind not in "biuf" or data.size == 0:
        raise _fail("output", path, f"needs a non-empty real numeric array, got dtype {data.dtype}, shape {data.shape}")
    if not np.isfinite(data).all():
        raise _fail("output", path, "array has non-finite values (NaN or Inf)")
    _write(fmt, path, data, voxel_size=None, origin=None)
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


def write_volume(path, volume, domain=None) -> Path:
    """Write a volume ``(nx, ny, nz)`` (axis 0 = x), e.g. as ``.mrc`` or ``.npy``.

    Parameters
    ----------
    path : str or os.PathLike
        The file; its suffix names a registered format with a writer.
    volume : numpy.ndarray or torch.Tensor
        A finite real 3D array ``(nx, ny, nz)``.
    domain : ImageDomain, optional
        The volume's domain: its shape must be the volume's; its cell sides and origin go to a format's header.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    DataFileError
        An unknown or read-only suffix, not a finite real 3D array, a shape other than ``domain.shape``, or the
        file cannot be written.
    TypeError
        ``domain`` is not an ``ImageDomain``.

    Notes
    -----
    - ``.mrc`` (``volume_order="zyx"``): float32 (mode 2), sections ``(z, y, x)`` (x fastest, MRC's standard
      axis order), so IMOD/ChimeraX show x, y, z as indreg's; the voxel size in the header is the domain's cell
      sides ``(hx, hy, hz)`` in the domain's length unit (MRC readers take it as Angstrom), 1 without a domain;
      the header's origin the centre of voxel ``(0, 0, 0)`` (``min_pt + h / 2``), as ChimeraX and napari place
      a grid (``indreg.io.volume_files``), 0 without a domain.
    - ``.npy``: float64 ``(nx, ny, nz)`` as it is (no voxel size).
    - ``read_volume`` (and ``read_voxel_size``) give both back.
    """
    path = _as_path(path, "output")
    fmt = _writer(path)
    data = _finite_array(volume, path, 3, "volume")
    if domain is not None and not isinstance(domain, ImageDomain):
        raise TypeError(f"domain must be an ImageDomain or None, got {type(domain).__name__}")
    if domain is not None and tuple(data.shape) != tuple(domain.shape):
        raise _fail("output", path, f"volume has shape {data.shape} but the domain has {tuple(domain.shape)}")
    stored = data.transpose(2, 1, 0) if fmt.volume_order == "zyx" else data
    _write(fmt, path, stored, voxel_size=None if domain is None else domain.cell_sides,
           origin=None if domain is None else [a + h / 2 for a, h in zip(domain.min_pt, domain.cell_sides)])
    return path


def write_tilt_series(path, data, angles, pixel_size: float | None = None) -> Path:
    """Write a tilt series as a stack of sections (MRC; sections = tilts, as stored) and its angles as ``stem.tlt``
    in degrees, one a line: what :func:`read_tilt_series` reads.

    Parameters
    ----------
    path : str or os.PathLike
        The stack; its suffix names a registered format of ``sections`` with a writer (``.mrc``, ``.st``, ``.ali``).
    data : numpy.ndarray or torch.Tensor
        A finite real ``(num_tilts, det_rows, det_cols)`` array.
    angles : numpy.ndarray, torch.Tensor or sequence of float
        Radians, one per tilt.
    pixel_size : float, optional
        The detector cell (x and y of the header; z = 1).

    Returns
    -------
    pathlib.Path
        The stack written.

    Raises
    ------
    DataFileError
        A suffix of no stack format, not a finite real 3D array, a wrong number of angles, or a file that cannot be
        written.
    ValueError
        ``pixel_size`` is not a positive number.
    """
    path = _as_path(path, "output")
    fmt = get_format(path.suffix)
    if fmt is None or fmt.write is None or not fmt.sections:
        stacks = [f for f in FILE_FORMATS.values() if f.sections and f.write is not None]
        raise _fail("output", path, f"a tilt series is written as {' or '.join(f.name for f in stacks)} "
                                    f"({', '.join(s for f in stacks for s in f.suffixes)})")
    stack = _finite_array(data, path, 3, "tilt series")
    radians = np.asarray(angles.detach().cpu() if hasattr(angles, "detach") else angles, dtype=np.float64)
    if radians.shape != (stack.shape[0],) or not np.isfinite(radians).all():
        raise _fail("output", path, f"needs {stack.shape[0]} finite angles (one per tilt), got shape {radians.shape}")
    if pixel_size is not None:
        pixel_size = check_positive(pixel_size, "pixel_size")
    _write(fmt, path, stack, voxel_size=None if pixel_size is None else (pixel_size, pixel_size, 1.0), origin=None)
    tlt = path.with_suffix(".tlt")
    try:
        with open_replacing(tlt, "w") as f:
            np.savetxt(f, np.rad2deg(radians), fmt="%.6f")
    except OSError as err:
        raise _fail("output", tlt, f"cannot be written ({type(err).__name__}: {err})") from None
    return path
