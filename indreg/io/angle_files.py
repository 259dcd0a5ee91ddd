"""Tilt angles and acquisition metadata from text files: IMOD ``.tlt`` / ``.rawtlt`` angle lists, inline angle
lists, SerialEM / IMOD ``.mdoc`` tilt axis angles (re-exported by :mod:`indreg.io`).

Notes
-----
- Angles come back as float64 radians, 1D; ``unit`` (``"deg"`` default, ``"rad"``) is the unit of the numbers
  given. The angle ``theta`` is that of the detector direction ``w = (cos theta, sin theta)``.
- Problems with a file raise :class:`DataFileError` (one line naming it); with inline values ``ValueError``.
"""
from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path

import numpy as np

from ._files import MAX_TEXT_BYTES, _fail, _one_line, read_text
from .formats import split_path

__all__ = ["ANGLE_UNITS", "RADIAN_SPAN", "read_angles", "tilt_angles_for", "mdoc_for", "read_tilt_axis_angle"]

ANGLE_UNITS = ("deg", "rad")
#: Angles in degrees spanning at most this many (a little over pi) are probably radians: a warning says so.
RADIAN_SPAN = 3.2

log = logging.getLogger("indreg")


def _angle_file(path: Path, name: str) -> list:
    """Angles of a text file, one per line (IMOD ``.tlt``/``.rawtlt``); blank lines and ``#`` comments skipped."""
    lines = read_text(path, name).splitlines()
    angles = []
    for number, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        try:
            value = float(text)
        except ValueError:
            raise _fail(name, path, f"line {number} is not one angle: {text[:40]!r}") from None
        if not math.isfinite(value):
            raise _fail(name, path, f"line {number} is not a finite angle: {text!r}")
        angles.append(value)
    if not angles:
        raise _fail(name, path, "holds no angles")
    return angles


def _inline_angles(values, name: str) -> list:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(_one_line(f"{name} must be a list of numbers, got {values!r}"[:200])) from None
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1D list of numbers, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(_one_line(f"{name} must be finite, got {arr.tolist()}"))
    return arr.tolist()


def read_angles(spec, unit: str = "deg", *, name: str = "angles") -> np.ndarray:
    """Projection angles as float64 radians, 1D.

    Parameters
    ----------
    spec : str or os.PathLike or array_like
        A text file or an inline list of numbers (Notes).
    unit : {"deg", "rad"}
        The unit of the numbers.
    name : str
        How messages call the angles.

    Returns
    -------
    numpy.ndarray
        Float64 radians, 1D.

    Raises
    ------
    DataFileError
        A problem with the file (missing, junk line N, no angles, non-finite angle).
    ValueError
        Bad inline values, or ``angle_unit`` not ``"deg"``/``"rad"``.

    Notes
    -----
    - ``spec`` is a path to a text file (one angle per line, IMOD ``.tlt``/``.rawtlt`` style; blank
      lines and ``#`` comments allowed) or an inline list/tuple/array of numbers.
    - ``unit`` is ``"deg"`` or ``"rad"``: the unit of the given numbers. The angle ``theta`` is that of
      the detector direction ``w = (cos theta, sin theta)`` (see ``ParallelBeamGeometry``). Degrees that
      span at most about pi (:data:`RADIAN_SPAN`) log a warning that they may be radians.
    """
    if unit not in ANGLE_UNITS:
        raise ValueError(f"angle_unit must be 'deg' or 'rad', got {unit!r}")
    if isinstance(spec, (str, os.PathLike)):
        values = _angle_file(Path(spec), name)
    else:
        values = _inline_angles(spec, name)
    angles = np.asarray(values, dtype=np.float64)
    if unit == "deg":
        _check_degrees(angles, name)
        return np.deg2rad(angles)
    return angles


def _check_degrees(angles: np.ndarray, name: str) -> None:
    """Warn when angles read as degrees span at most :data:`RADIAN_SPAN` (e.g. 0..3.1 or -1.05..1.05): they are
    probably radians (``ParallelBeamGeometry`` refuses the reverse, radians beyond 2 pi)."""
    span = float(angles.max() - angles.min()) if angles.size > 1 else 0.0
    if 0 < span <= RADIAN_SPAN:
        log.warning("%s span only %.4g degrees (%.4g .. %.4g): they may be radians; if so, give the unit 'rad' "
                    "(angle_unit='rad', geometry.angle_unit=rad)", name, span, angles.min(), angles.max())


def tilt_angles_for(sinogram_path) -> Path | None:
    """The sibling angle file of a sinogram: ``stem.tlt``, else ``stem.rawtlt``, else ``None``.

    A ``:key`` suffix (``data.h5:/sino``) is ignored: the sibling of ``data.h5`` is ``data.tlt``.

    Parameters
    ----------
    sinogram_path : str or os.PathLike
        The data file.

    Returns
    -------
    pathlib.Path or None
        The angle file next to it, None if there is none.
    """
    path, _ = split_path(sinogram_path, "sinogram")
    for suffix in (".tlt", ".rawtlt"):
        candidate = path.with_suffix(suffix)
        if candidate.is_file():
            return candidate
    return None


_TILT_AXIS_KEY = re.compile(r"tilt\s*axis\s*angle\s*=[^\n,\]]*", re.IGNORECASE)
_TILT_AXIS = re.compile(r"tilt\s*axis\s*angle\s*=\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)(?![\w.])",
                        re.IGNORECASE)


def mdoc_for(stack_path) -> Path | None:
    """The SerialEM / IMOD metadata file of a stack: ``name.mrc.mdoc`` (SerialEM: the file name plus ``.mdoc``),
    else ``name.mdoc``, else ``None``. A ``:key`` suffix is ignored.

    Parameters
    ----------
    stack_path : str or os.PathLike
        The stack file.

    Returns
    -------
    pathlib.Path or None
        The ``.mdoc`` next to it, None if there is none.
    """
    path, _ = split_path(stack_path, "tilt series")
    for candidate in (path.with_name(path.name + ".mdoc"), path.with_suffix(".mdoc")):
        if candidate.is_file():
            return candidate
    return None


def read_tilt_axis_angle(mdoc, *, name: str = "mdoc") -> float | None:
    """The tilt axis angle (degrees) of an ``.mdoc`` file: the first ``TiltAxisAngle = a`` or ``Tilt axis angle =
    a`` (also inside a ``[T = ...]`` title line), ``None`` when the file has none. The angle is IMOD's and
    SerialEM's: from the image's Y axis to the tilt axis, counterclockwise positive (``indreg.alignment.tilt_axis``).

    Parameters
    ----------
    mdoc : str or os.PathLike
        The ``.mdoc`` file.
    name : str
        How messages call the file.

    Returns
    -------
    float or None
        Degrees, None when the file has no tilt-axis angle.

    Raises
    ------
    DataFileError
        The file cannot be read.
    """
    path = Path(mdoc)
    text = read_text(path, name, max_bytes=4 * MAX_TEXT_BYTES, errors="replace")
    key = _TILT_AXIS_KEY.search(text)
    if key is None:
        return None
    match = _TILT_AXIS.match(text, key.start())
    value = float(match.group(1)) if match else math.nan
    if not math.isfinite(value):
        line = text.count("\n", 0, key.start()) + 1
        raise _fail(name, path, f"line {line}: the tilt axis angle is not a finite number of degrees: "
                                f"{key.group(0).strip()[:60]!r}")
    return value
