"""2D acquisition geometries: parallel beam and fan beam with a flat detector (conventions: docs/geometry.md).

Both share: angles in radians (float64, 1D, any order, non-uniform and limited sets allowed), a flat detector
line of ``det_count`` cell-centred bins on ``[det_min, det_max]``, data ``(..., num_angles, det_count)``, and
a scalar data-space weight ``angle_cell * det_cell`` (ODL's weighting). The detector extent may be left
``None``: ``RayTransform`` then resolves it from the image domain (``resolve``) so that it covers the domain.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .._checks import check_finite, check_int, check_nonnegative, check_positive

ANGLE_UNITS = ("rad", "deg")


def parse_angles(angles, angle_unit: str | None) -> torch.Tensor:
    """Explicit angles -> float64 CPU radians, 1D; errors for 2D, complex, empty, non-finite and
    degree-like values given without a unit (any ``|angle| > 2 pi`` with ``angle_unit=None``)."""
    if angle_unit is not None and angle_unit not in ANGLE_UNITS:
        raise ValueError(f"angle_unit must be 'rad', 'deg' or None, got {angle_unit!r}")
    if not isinstance(angles, torch.Tensor):
        arr = np.asarray(angles)
        if arr.dtype.kind not in "iufcb":
            raise TypeError(f"angles must be real numbers, got {arr.dtype} values")
        angles = torch.from_numpy(arr)
    a = angles.detach().cpu()
    if a.is_complex():
        raise TypeError(f"angles must be real numbers (not truncated), got complex dtype {a.dtype}")
    if a.dtype == torch.bool:
        raise TypeError("angles must be real numbers, got a boolean array")
    if a.dim() > 1:
        raise ValueError(f"angles must be a 1D list/array, got shape {tuple(a.shape)}")
    a = a.to(torch.float64).reshape(-1)
    if a.numel() == 0:
        raise ValueError("angles must contain at least one angle, got none")
    if not bool(torch.isfinite(a).all()):
        raise ValueError(f"angles must be finite, got {a.tolist()}")
    if angle_unit is None and float(a.abs().max()) > 2 * math.pi:
        raise ValueError(f"angles look like degrees (max |angle| = {float(a.abs().max()):g} > 2 pi): pass "
                         "angle_unit='deg', or angle_unit='rad' to accept them as radians")
    return a * (math.pi / 180.0) if angle_unit == "deg" else a


def midpoint_cells(angles: torch.Tensor, period: float) -> torch.Tensor:
    """Quadrature cells of an angle set by the midpoint rule on the circle of length ``period``.

    Sorted angles get the cell between the midpoints to their neighbours; the two end angles extend
    outwards by half the gap to their inner neighbour, both extensions together capped by the gap left
    to the end of the period (so a full uniform set gets ``period / n`` each and a limited set, e.g. a
    tilt series, gets its step). Sets spanning a full period or more measure lines more than once: their
    cells (ends extended by half a step) are scaled to sum to ``period`` (exact for uniform full turns).
    Returns the cells in the input order.
    """
    n = angles.numel()
    if n == 1:
        return torch.full((1,), period, dtype=torch.float64)
    order = torch.argsort(angles)
    a = angles[order]
    gaps = torch.diff(a)
    cells = torch.zeros(n, dtype=torch.float64)
    cells[:-1] += gaps / 2
    cells[1:] += gaps / 2
    ext = torch.stack([gaps[0] / 2, gaps[-1] / 2])
    span = float(a[-1] - a[0])
    room = period - span
    if room > 0:
        ext = ext * min(1.0, room / float(ext.sum())) if float(ext.sum()) > 0 else ext
        cells[0] += ext[0]
        cells[-1] += ext[1]
    else:
        cells[0] += ext[0]
        cells[-1] += ext[1]
        cells = cells * (period / float(cells.sum()))
    out = torch.empty_like(cells)
    out[order] = cells
    return out


class _Geometry:
    """Shared part of the 2D geometries: angles, flat detector, weights (see the module docstring)."""

    period = 2 * math.pi   # angular period of the measurement (pi for parallel beam)

    def _init_common(self, num_angles, det_count, det_min, det_max, angles, angle_unit, angle_weights,
                     default_span: float):
        if angles is None:
            if num_angles is None:
                raise ValueError("give num_angles (>= 1) or an explicit angles= list/tensor")
            n = check_int(num_angles, "num_angles", 1)
            angles = torch.arange(n, dtype=torch.float64) * (default_span / n)
            if angle_weights is None:   # exact midpoint cells of the uniform set
                angle_weights = torch.full((n,), default_span / n, dtype=torch.float64)
        else:
            angles = parse_angles(angles, angle_unit)
            if num_angles is not None and check_int(num_angles, "num_angles", 1) != angles.numel():
                raise ValueError(f"num_angles={num_angles} but {angles.numel()} angles were given")
        self.angles = angles
        self.det_count = check_int(det_count, "det_count", 1)
        self.det_min, self.det_max = _check_detector(det_min, det_max)
        self._angle_weights = None if angle_weights is None else _check_weights(angle_weights, angles.numel())

    @property
    def num_angles(self) -> int:
        return int(self.angles.numel())

    @property
    def is_resolved(self) -> bool:
        """Whether the detector extent is set (``det_min``/``det_max`` not ``None``)."""
        return self.det_min is not None

    def _require_detector(self):
        if not self.is_resolved:
            raise ValueError(f"{type(self).__name__} has no detector extent (det_min = det_max = None): pass "
                             "det_min/det_max, or call geometry.resolve(domain) (RayTransform does this)")

    @property
    def det_cell(self) -> float:
        """Detector bin width (at the detector)."""
        self._require_detector()
        return (self.det_max - self.det_min) / self.det_count

    @property
    def det_points(self) -> torch.Tensor:
        """Bin centres ``det_min + (d + 1/2) det_cell`` (float64, length ``det_count``)."""
        return self.det_min + (torch.arange(self.det_count, dtype=torch.float64) + 0.5) * self.det_cell

    @property
    def angle_weights(self) -> torch.Tensor:
        """Quadrature cell of every angle (``midpoint_cells`` over the period, unless given explicitly);
        used by FBP. The data-space inner product uses the scalar ``angle_cell`` instead."""
        if self._angle_weights is None:
            self._angle_weights = midpoint_cells(self.angles, self.period)
        return self._angle_weights

    @property
    def data_weight(self) -> float:
        """Weight of the data-space inner product, ``angle_cell * det_cell``."""
        return self.angle_cell * self.det_cell

    @property
    def shape(self) -> tuple:
        """Data shape ``(num_angles, det_count)``."""
        return (self.num_angles, self.det_count)

    def resolve(self, domain):
        """This geometry if its detector extent is set, else a copy whose detector covers ``domain``."""
        if self.is_resolved:
            return self
        half = self.covering_half_width(domain_radius(domain))
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.det_min, new.det_max = -half, half
        return new


def domain_radius(domain) -> float:
    """Largest distance from the origin to a corner of the domain (the half-diagonal when centred)."""
    return max(math.hypot(x, y) for x in (domain.min_pt[0], domain.max_pt[0])
               for y in (domain.min_pt[1], domain.max_pt[1]))


def _check_detector(det_min, det_max) -> tuple:
    if det_min is None and det_max is None:
        return None, None
    if det_min is None or det_max is None:
        raise ValueError(f"give both det_min and det_max, or neither (then the detector is fitted to the "
                         f"domain), got det_min={det_min}, det_max={det_max}")
    lo, hi = check_finite(det_min, "det_min"), check_finite(det_max, "det_max")
    if not lo < hi:
        raise ValueError(f"det_min must be < det_max, got det_min={det_min} >= det_max={det_max}")
    return lo, hi


def _check_weights(weights, n: int) -> torch.Tensor:
    try:
        w = torch.as_tensor(weights)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"angle_weights must be {n} finite positive numbers, got {type(weights).__name__}") from None
    if w.is_complex() or w.dtype == torch.bool:
        raise TypeError(f"angle_weights must be real numbers, got dtype {w.dtype}")
    w = w.detach().cpu().to(torch.float64)
    if w.shape != (n,) or not bool(torch.isfinite(w).all()) or not bool((w > 0).all()):
        raise ValueError(f"angle_weights must be {n} finite positive numbers, got {w.tolist()}")
    return w


class ParallelBeamGeometry(_Geometry):
    """Angles ``theta_k`` (radians) and a detector line ``[det_min, det_max]`` split into ``det_count`` cells.

    Parameters
    ----------
    num_angles : int, optional
        Number of angles; the default angles are uniform ``k * pi / num_angles`` on ``[0, pi)``. None with
        ``angles`` (if given with them, it must equal their number).
    det_count : int
        Number of detector bins (>= 1).
    det_min, det_max : float, optional
        Detector extent (``det_min < det_max``), physical units; both None (default): fitted to the domain by
        ``RayTransform``.
    angles : array_like, optional
        Explicit angles (1D, finite, real, any order).
    angle_unit : {None, "rad", "deg"}
        The unit of explicit angles; None (default) means radians and rejects values beyond ``2 pi`` as
        probable degrees.
    angle_weights : array_like, optional
        Explicit FBP quadrature cells (radians, positive, one per angle), default ``midpoint_cells``.

    Raises
    ------
    ValueError
        Neither ``num_angles`` nor ``angles``, a count that disagrees with ``angles``, empty, 2D, non-finite or
        degree-like angles without a unit, one of ``det_min`` / ``det_max`` alone or ``det_min >= det_max``,
        weights of the wrong length or not positive.
    TypeError
        Complex, boolean or non-numeric angles or weights, a non-integer count.

    Notes
    -----
    - A datum ``p(theta_k, s_d)`` is the line integral over ``{s_d w + t w_perp : t in R}`` with
      ``w = (cos theta, sin theta)`` and ``w_perp = (-sin theta, cos theta)`` (see ``RayTransform``);
      this is ODL's ``Parallel2dGeometry`` with its default axes, and ASTRA's ``parallel``.
    - Detector bins are cell-centred: ``s_d = det_min + (d + 1/2) * det_cell``,
      ``det_cell = (det_max - det_min) / det_count``, in the image domain's physical units.
    - Data are tensors ``(..., num_angles, det_count)``.
    - The data-space inner product is ``<p, q> = data_weight * sum p q`` with
      ``data_weight = angle_cell * det_cell`` and ``angle_cell = pi / num_angles``, as ODL weights its
      data space (every angle gets the same weight, whatever the angles are).
    - FBP weighs angle ``k`` by its quadrature cell ``angle_weights[k]`` (midpoint rule on the
      half-turn, ``midpoint_cells``): ``pi / n`` for ``n`` uniform angles on ``[0, pi)``, the step for a
      tilt series.
    - ``det_min = det_max = None``: the operator fits a symmetric detector reaching the domain's
      farthest corner (the half-diagonal for a centred domain), see ``resolve``.

    Examples
    --------
    >>> g = ParallelBeamGeometry.paper(num_angles=10, det_count=92)
    >>> round(float(g.angles[1]) * 180 / math.pi, 2), round(g.det_cell, 4)
    (18.95, 0.5217)
    """

    period = math.pi

    def __init__(self, num_angles: int | None = None, det_count: int = 1, det_min: float | None = None,
                 det_max: float | None = None, angles=None, angle_unit: str | None = None, angle_weights=None):
        self._init_common(num_angles, det_count, det_min, det_max, angles, angle_unit, angle_weights, math.pi)

    @classmethod
    def paper(cls, num_angles: int, det_count: int, det_min: float = -24.0, det_max: float = 24.0):
        """The authors' geometry: ODL's ``uniform_partition(0, pi, n, nodes_on_bdry=(True, False))``.

        Angles ``k * pi / (n - 1/2)``, ``k = 0..n-1`` (for n = 10: 0, 18.95, ..., 170.53 degrees), and
        the detector ``uniform_partition(-24, 24, det_count)``. FBP weighs every angle by ``pi / n`` (ODL's
        uniform cell, as the authors' FBP did), not by the midpoint rule.
        """
        n = check_int(num_angles, "num_angles", 1)
        angles = torch.arange(n, dtype=torch.float64) * (math.pi / (n - 0.5))
        return cls(det_count=det_count, det_min=det_min, det_max=det_max, angles=angles,
                   angle_weights=torch.full((n,), math.pi / n, dtype=torch.float64))

    @classmethod
    def tilt_series(cls, min_deg: float, max_deg: float, step_deg: float, det_count: int,
                    det_min: float | None = None, det_max: float | None = None):
        """Electron-tomography tilt series: angles ``min_deg, min_deg + step_deg, ..., max_deg`` (degrees,
        both ends included; ``max_deg - min_deg`` must be a multiple of ``step_deg``), e.g. ``(-60, 60, 2)``.

        Tilt 0 is ``theta = 0`` (rays along y, detector along x). FBP weighs every tilt by ``step_deg``.
        """
        step = check_positive(step_deg, "step_deg")
        lo, hi = check_finite(min_deg, "min_deg"), check_finite(max_deg, "max_deg")
        if not lo <= hi:
            raise ValueError(f"tilt_series needs min_deg <= max_deg, got {min_deg}, {max_deg}")
        count = (hi - lo) / step
        if not math.isfinite(count):
            raise ValueError(f"step_deg = {step_deg!r} is too small for [{lo}, {hi}] (infinitely many tilts)")
        if abs(count - round(count)) > 1e-9 * max(1.0, count):
            raise ValueError(f"max_deg - min_deg = {hi - lo} is not a multiple of step_deg = {step}")
        if hi - lo >= 180.0:
            raise ValueError(f"a tilt series spans less than 180 degrees, got [{lo}, {hi}]")
        degrees = lo + step * torch.arange(int(round(count)) + 1, dtype=torch.float64)
        return cls(det_count=det_count, det_min=det_min, det_max=det_max, angles=degrees, angle_unit="deg")

    @property
    def angle_cell(self) -> float:
        """Data-space weight of one angle, ``pi / num_angles``."""
        return math.pi / self.num_angles

    def covering_half_width(self, radius: float) -> float:
        """Detector half-width covering a disk of ``radius`` around the origin: ``radius``."""
        return radius

    def __repr__(self) -> str:
        return (f"ParallelBeamGeometry(num_angles={self.num_angles}, det_count={self.det_count}, "
                f"det_min={self.det_min}, det_max={self.det_max})")


class FanBeamGeometry(_Geometry):
    """Fan beam with a flat detector: a point source and a detector line rotating about the origin.

    Parameters
    ----------
    num_angles : int, optional
        Number of angles; default uniform ``2 pi k / num_angles`` on ``[0, 2 pi)``.
    det_count : int
        Number of detector bins (>= 1).
    src_radius : float
        Source-to-origin distance (> 0; required): ASTRA's ``source_origin``.
    det_radius : float
        Origin-to-detector distance (>= 0): ASTRA's ``origin_det`` (not source-to-detector).
    det_min, det_max, angles, angle_unit, angle_weights
        As for ``ParallelBeamGeometry``; the detector extent is measured at the detector.

    Raises
    ------
    ValueError
        No ``src_radius``, ``src_radius <= 0`` or ``det_radius < 0``, and the errors of
        ``ParallelBeamGeometry``.
    TypeError
        As for ``ParallelBeamGeometry``.

    Notes
    -----
    ODL's ``FanBeamGeometry`` defaults, ASTRA's ``fanflat``:

    - At angle ``beta`` the source is at ``S = src_radius * (sin beta, -cos beta)``, the detector's
      reference point (its foot from the origin) at ``C = det_radius * (-sin beta, cos beta)``, and the
      detector axis is ``e = (cos beta, sin beta)``; bin ``d`` sits at ``C + u_d e``,
      ``u_d = det_min + (d + 1/2) det_cell`` (physical units AT THE DETECTOR, not at the origin).
    - A datum ``p(beta_k, u_d)`` is the integral of the image along the whole line through ``S`` and the
      bin centre (the source must lie outside the domain).
    - Ray ``(beta, u)`` is the parallel ray ``(theta, s) = (beta - gamma, src_radius * sin gamma)``,
      ``gamma = atan(u / (src_radius + det_radius))``: as ``src_radius -> inf`` with ``det_radius = 0``
      the fan beam becomes ``ParallelBeamGeometry`` with the same angles and detector.
    - Data ``(..., num_angles, det_count)``; data-space weight ``angle_cell * det_cell`` with
      ``angle_cell = 2 pi / num_angles`` (ODL's weight for angles over a full turn).
    - ``det_min = det_max = None``: fitted by the operator to the fan through the domain's farthest corner
      ``r``: half-width ``(src_radius + det_radius) * tan(asin(r / src_radius))``.

    Examples
    --------
    >>> g = FanBeamGeometry(360, 512, src_radius=40.0, det_radius=40.0, det_min=-64.0, det_max=64.0)
    >>> g.shape, g.magnification
    ((360, 512), 2.0)
    """

    def __init__(self, num_angles: int | None = None, det_count: int = 1, src_radius: float = None,
                 det_radius: float = 0.0, det_min: float | None = None, det_max: float | None = None,
                 angles=None, angle_unit: str | None = None, angle_weights=None):
        if src_radius is None:
            raise ValueError("src_radius (source-to-origin distance, > 0) is required")
        self.src_radius = check_positive(src_radius, "src_radius")
        self.det_radius = check_nonnegative(det_radius, "det_radius")  # origin-to-detector distance
        self._init_common(num_angles, det_count, det_min, det_max, angles, angle_unit, angle_weights,
                          2 * math.pi)

    @property
    def magnification(self) -> float:
        """``(src_radius + det_radius) / src_radius``: detector length per unit length at the origin."""
        return (self.src_radius + self.det_radius) / self.src_radius

    @property
    def angle_cell(self) -> float:
        """Data-space weight of one angle, ``2 pi / num_angles``."""
        return 2 * math.pi / self.num_angles

    def covering_half_width(self, radius: float) -> float:
        """Detector half-width of the fan that covers a disk of ``radius`` around the origin."""
        if not radius < self.src_radius:
            raise ValueError(f"src_radius={self.src_radius} must exceed the domain radius {radius:g} (the source "
                             "must lie outside the domain)")
        return (self.src_radius + self.det_radius) * math.tan(math.asin(radius / self.src_radius))

    def __repr__(self) -> str:
        return (f"FanBeamGeometry(num_angles={self.num_angles}, det_count={self.det_count}, "
                f"src_radius={self.src_radius}, det_radius={self.det_radius}, det_min={self.det_min}, "
                f"det_max={self.det_max})")
