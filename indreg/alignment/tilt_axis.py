"""The tilt axis in the detector image: bring a raw stack into indreg's layout, and check a stack's consistency.

indreg's tilt series have the tilt axis along the detector rows' index (IMOD's aligned layout: the image's Y,
docs/tilt_series.md): detector row ``j`` images slice ``j`` of the volume, orthogonal to the axis. Raw stacks often
have it along the image's X, or at an angle that the microscope software records (SerialEM / IMOD ``.mdoc``:
``Tilt axis angle = 85.3``, ``TiltAxisAngle = -90``).

Notes
-----
- A stack ``(num_tilts, rows, cols)`` is seen as IMOD shows a section: X = the column index (to the right),
  Y = the row index (upwards). ``tilt_axis_angle`` is the angle from the Y axis to the tilt axis,
  counterclockwise positive, in degrees (IMOD's rotation angle, SerialEM's tilt axis angle): 0 is indreg's
  layout, +-90 an axis along X.
- :func:`align_tilt_axis` rotates every tilt image by ``-tilt_axis_angle`` about its centre so that the axis
  runs along Y: a multiple of 90 degrees exactly (``np.rot90``: a transposition and a flip, rows and columns
  swap for an odd multiple), the rest (at most 45 degrees) by bilinear interpolation on the same grid (square
  pixels; pixels whose source lies outside the image take the nearest edge value, so the corners of a rotated
  image are extrapolated, not measured).
- :func:`check_tilt_axis`: in a parallel beam the mass of each slice orthogonal to the tilt axis is the same at
  every tilt, so with the axis along the rows' index every row sum (over the columns) is the same at every
  tilt, up to one scale per tilt (exposure, a slab's thickness). The check compares the per-row sums across the
  tilts with the per-column sums: the axis runs along the direction whose sums agree.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

log = logging.getLogger("indreg")

#: One direction must agree at least this many times better than the other to be decided.
MARGIN = 2.0
#: Below this inconsistency both directions agree: no verdict (e.g. a centred ball).
FLOOR = 1e-3


def align_tilt_axis(stack: np.ndarray, tilt_axis_angle: float) -> np.ndarray:
    """``stack`` ``(num_tilts, rows, cols)`` with every image rotated by ``-tilt_axis_angle`` degrees about its
    centre: the tilt axis then runs along the rows' index (module Notes). Exact (``np.rot90``) for multiples
    of 90 degrees, bilinear interpolation for the rest; returns a new float64 array."""
    quarter = round(tilt_axis_angle / 90.0)
    rest = tilt_axis_angle - 90.0 * quarter                       # in [-45, 45]
    out = np.rot90(np.asarray(stack, dtype=np.float64), k=quarter, axes=(-2, -1))
    if abs(rest) > 1e-9:
        out = rotate_images(out, rest)
    return np.ascontiguousarray(out)


def rotate_images(stack: np.ndarray, angle: float) -> np.ndarray:
    """Every image of ``stack`` ``(..., rows, cols)`` rotated by ``-angle`` degrees about its centre, on the same
    grid, by bilinear interpolation: ``out(p) = image(R(angle) p)`` with ``p = (x, y)`` centred pixel coordinates
    (x along the columns, y along the rows) and ``R`` the counterclockwise rotation. Sources outside the image take
    the nearest edge value."""
    from scipy.ndimage import map_coordinates

    a = np.asarray(stack, dtype=np.float64)
    rows, cols = a.shape[-2:]
    y, x = np.meshgrid(np.arange(rows) - (rows - 1) / 2, np.arange(cols) - (cols - 1) / 2, indexing="ij")
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    source = np.stack([s * x + c * y + (rows - 1) / 2, c * x - s * y + (cols - 1) / 2])   # (row, column) indices
    flat = a.reshape(-1, rows, cols)
    out = np.stack([map_coordinates(image, source, order=1, mode="nearest") for image in flat])
    return out.reshape(a.shape)


@dataclass(frozen=True)
class TiltAxisCheck:
    """How consistent a stack is with its tilt axis along the rows' index (:func:`check_tilt_axis`).

    ``row_inconsistency``: the spread of the per-row sums across the tilts (0: every tilt has the same row
    profile up to a scale, as an ideal aligned parallel-beam series); ``column_inconsistency``: the same of the
    per-column sums; ``direction``: ``"rows"`` (indreg's layout, the image's Y), ``"columns"`` (the axis runs along
    the image's X) or ``"undetermined"``."""
    row_inconsistency: float
    column_inconsistency: float

    @property
    def direction(self) -> str:
        r, c = self.row_inconsistency, self.column_inconsistency
        if max(r, c) < FLOOR:
            return "undetermined"
        if MARGIN * r < c:
            return "rows"
        if MARGIN * c < r:
            return "columns"
        return "undetermined"

    def describe(self) -> str:
        """One line for the log."""
        where = {"rows": "runs along the detector rows' index (the image's Y, indreg's layout)",
                 "columns": "runs along the image's X (the detector columns' index), not indreg's Y",
                 "undetermined": "direction is undetermined (both directions agree about as well)"}[self.direction]
        return (f"the tilt axis {where}: per-row sums vary {100 * self.row_inconsistency:.2f} % across the tilts, "
                f"per-column sums {100 * self.column_inconsistency:.2f} %")

    def metrics(self) -> dict:
        """The numbers for metrics.json."""
        return {"tilt_axis_inconsistency": self.row_inconsistency,
                "tilt_axis_inconsistency_columns": self.column_inconsistency,
                "tilt_axis_direction": self.direction}


def _spread(profiles: np.ndarray) -> float:
    """``sqrt(mean_k ||Q_k - s_k Q_mean||^2)`` of the unit-norm profiles ``Q_k = P_k / ||P_k||`` with the
    least-squares scale ``s_k`` of each: 0 when every tilt's profile is the same up to a scale, at most 1;
    invariant to one scale per tilt. All-zero profiles are left out."""
    norms = np.linalg.norm(profiles, axis=1)
    q = profiles[norms > 0] / norms[norms > 0, None]
    mean = q.mean(axis=0) if len(q) else np.zeros(profiles.shape[1])
    norm2 = float(mean @ mean)
    if len(q) < 2 or norm2 == 0.0:
        return 0.0
    residual = q - (q @ mean / norm2)[:, None] * mean[None, :]
    return math.sqrt(float((residual ** 2).sum()) / len(q))


def frame_level(a: np.ndarray) -> float:
    """The median of the images' outer frame (the ``max(1, n // 16)`` outermost rows and columns of every tilt):
    the detector's level outside the object, whichever way the tilt axis runs."""
    k0, k1 = max(1, a.shape[1] // 16), max(1, a.shape[2] // 16)
    frame = [a[:, :k0], a[:, -k0:], a[:, :, :k1], a[:, :, -k1:]]
    return float(np.median(np.concatenate([f.reshape(-1) for f in frame])))


def check_tilt_axis(stack) -> TiltAxisCheck:
    """Which way the tilt axis of ``stack`` ``(num_tilts, rows, cols)`` runs, and how consistent the stack is
    (module Notes): the per-row sums (over the columns) and the per-column sums (over the rows) of each tilt,
    compared across the tilts up to one scale per tilt, after the level of the images' outer frame is subtracted
    (``frame_level``: an offset adds the same to every profile and hides their differences)."""
    a = np.asarray(stack, dtype=np.float64)
    if a.ndim != 3:
        raise ValueError(f"stack must be (num_tilts, rows, cols), got shape {a.shape}")
    a = a - frame_level(a)
    return TiltAxisCheck(_spread(a.sum(axis=2)), _spread(a.sum(axis=1)))
