"""Misaligned projections: ``T_s f``, the projections of ``f`` shifted per projection and, for a tilt series,
rotated in-plane by the tilt-axis angle.

Measured tilt series drift: projection ``k`` is the ideal one moved by ``s_k`` on the detector, and the tilt axis
lies at an angle ``alpha`` to the detector rows. :class:`AlignedOperator` models both as a linear map ``S`` of the
data space after a parallel-beam operator ``T`` (a 2D ``RayTransform`` or a 3D ``TiltSeriesTransform``): ``T_s f =
S_{s, alpha} T f``, with ``S`` an interpolation of every projection image at moved points: bilinear, or cubic
convolution (Keys' kernel, ``a = -1/2``, 4 x 4 neighbours: a fractional shift keeps the image's sharpness, where
bilinear interpolation blurs it by up to half a pixel; its weights are not all nonnegative). ``S`` acts on the data
space only, whose inner product is a constant times the plain sum, so the adjoint is ``T^* S^T`` with ``S^T`` the
exact transpose of the interpolation (a scatter-add of the same weights). ``S`` is differentiable in the data, the
shifts and the angle (its weights are; the cell indices are piecewise constant).

Notes
-----
- A projection image has axes ``(rows, columns)``: rows along the tilt axis (a 2D sinogram has one row),
  columns across it (the detector bins ``s_d``). Pixels are the detector cells: ``det_cell`` across,
  ``row_cell`` (the cell side along the tilt axis) along.
- ``shifts`` ``(num_projections, c)`` in pixels, ``c = 1`` in 2D (across the axis) and ``c = 2`` for a tilt
  series (``[:, 0]`` across, ``[:, 1]`` along the axis); ``angle`` ``alpha`` in radians (tilt series only).
- A feature at the ideal detector point ``q = (s, t)`` (physical units; ``t = 0`` at the middle row, ``s``
  as ``det_points``) appears at ``p = R(alpha) q + (s_k det_cell, s_k' row_cell)``, ``R`` the counter-clockwise
  rotation of the ``(s, t)`` plane about the tilt axis' point ``(0, 0)``. So ``(S y)(p) = y(R(-alpha)(p - shift))``.
- ``matrices`` (optional, ``(num_projections, 2, 2)``, tilt series only): a fixed linear map ``B_k`` of the
  ``(s, t)`` plane per projection (another tool's per-tilt rotation, magnification, stretch;
  ``indreg.alignment.files``), applied before the tilt-axis rotation: ``p = R(alpha) B_k q + shift``, so
  ``(S y)(p) = y(B_k^{-1} R(-alpha)(p - shift))``. Without it ``B_k = I``.
- Beyond the detector ``y`` is its nearest edge pixel (``edge="nearest"``: a specimen that runs out of the
  field of view, a rod along the axis, continues there) or zero (``edge="zero"``).
"""
from __future__ import annotations

import torch

from .._checks import check_tensor
from .modes import EDGES, INTERPOLATIONS
from ..forward.algebra import OperatorAlgebra
from ..forward.operator import check_data_pair, check_operator

__all__ = ["AlignedOperator", "EDGES", "INTERPOLATIONS", "KEEP_BYTES", "cubic_kernel", "cubic_slope",
           "projection_frame"]

#: Largest size of the interpolation's indices and weights an operator keeps between calls (``AlignedOperator``):
#: 16 int64 indices and 16 weights per detector pixel with the cubic kernel (10 tilts of 128^2 pixels in
#: float64: 40 MiB); beyond it they are recomputed per call, as they are while they take part in a gradient.
KEEP_BYTES = 2 ** 28


def cubic_kernel(x: torch.Tensor) -> torch.Tensor:
    """Keys' cubic convolution kernel (``a = -1/2``): 1 at 0, 0 at the other integers, support ``|x| < 2``; it
    reproduces quadratics and is continuously differentiable."""
    x = x.abs()
    near = (1.5 * x - 2.5) * x * x + 1
    far = ((-0.5 * x + 2.5) * x - 4) * x + 2
    return torch.where(x <= 1, near, torch.where(x < 2, far, torch.zeros_like(x)))


def _linear_kernel(x: torch.Tensor) -> torch.Tensor:
    """The hat ``1 - |x|``, its derivative at 0 taken from the right (as the cell index ``floor`` is)."""
    return torch.where(x >= 0, 1 - x, 1 + x).clamp_min(0)


def cubic_slope(x: torch.Tensor) -> torch.Tensor:
    """The derivative of :func:`cubic_kernel` (0 at 0 and beyond 2; continuous at 1)."""
    a = x.abs()
    inner = torch.where(a <= 1, (4.5 * a - 5) * a, torch.where(a < 2, (-1.5 * a + 5) * a - 4, torch.zeros_like(a)))
    return torch.sign(x) * inner


def _linear_slope(x: torch.Tensor) -> torch.Tensor:
    """The derivative of :func:`_linear_kernel` as autograd takes it: -1 from 0 (included) to 1 (included), +1 from
    -1 (included) to 0, 0 beyond."""
    return torch.where(torch.where(x >= 0, 1 - x, 1 + x) >= 0, torch.where(x >= 0, -1.0, 1.0), 0.0).to(x.dtype)


def projection_frame(operator) -> tuple:
    """``(operator, num_projections, rows, columns, det_points, det_cell, row_cell)`` of a parallel-beam
    ``RayTransform`` or a ``TiltSeriesTransform``; a one-line TypeError for any other operator."""
    from ..forward.geometry import ParallelBeamGeometry
    from ..forward.ray_transform import RayTransform
    from ..forward.tilt_series import TiltSeriesTransform

    if isinstance(operator, TiltSeriesTransform):
        g = operator.geometry
        return operator, g.num_tilts, g.det_rows, g.det_count, g.det_points, g.det_cell, g.row_cell
    if isinstance(operator, RayTransform) and isinstance(operator.geometry, ParallelBeamGeometry):
        g = operator.geometry
        return operator, g.num_angles, 1, g.det_count, g.det_points, g.det_cell, 1.0
    raise TypeError(f"alignment needs a parallel-beam RayTransform (2D) or a TiltSeriesTransform (3D), got "
                    f"{type(operator).__name__}" + (f" with {type(operator.geometry).__name__}"
                                                    if hasattr(operator, "geometry") else ""))


def _check_matrices(matrices, count: int, components: int) -> torch.Tensor:
    """``matrices`` as float64 ``(count, 2, 2)``, finite and invertible; one-line errors otherwise."""
    if components != 2:
        raise ValueError("matrices (a per-projection linear map of the detector plane) need a tilt series")
    m = check_tensor(torch.as_tensor(matrices, dtype=torch.float64), "matrices", (count, 2, 2))
    det = torch.linalg.det(m).abs()
    if not bool((det > 1e-6).all()):
        raise ValueError(f"matrices: projection {int(det.argmin())} has a singular matrix (|det| "
                         f"{float(det.min()):.3g})")
    return m


def _same(a, b) -> bool:
    """Whether two optional tensors are both None or equal."""
    return a is b or (a is not None and b is not None and torch.equal(a, b))


class AlignedOperator(OperatorAlgebra):
    """``T_s f = S_{s, alpha} T f`` for a parallel-beam ``T`` (module docstring), a ``LinearOperator`` in ``f``.

    ``shifts`` and ``angle`` are the current alignment, held as float64 tensors and set by the estimation
    (``indreg.alignment``); :meth:`apply` takes them as arguments (differentiable in all three). ``range_shape``
    and ``inner_data`` are ``T``'s.

    Parameters
    ----------
    operator : RayTransform or TiltSeriesTransform
        ``T``, parallel beam.
    shifts : array_like, optional
        ``(num_projections, c)`` pixels (default zeros).
    angle : float
        The tilt-axis angle ``alpha``, radians.
    interpolation : {"linear", "cubic"}
        Bilinear or cubic convolution (module docstring).
    edge : {"nearest", "zero"}
        Beyond the detector: its nearest edge pixel or zero.
    matrices : array_like, optional
        ``(num_projections, 2, 2)``: a fixed per-projection map ``B_k`` (tilt series only).

    Raises
    ------
    TypeError
        ``operator`` is no operator, or not a parallel-beam ray transform or tilt series.
    ValueError
        An unknown ``interpolation`` or ``edge``, shifts or matrices of the wrong shape or non-finite, singular
        matrices or matrices of a 2D sinogram.
    """

    def __init__(self, operator, shifts=None, angle=0.0, interpolation: str = "linear", edge: str = "nearest",
                 matrices=None):
        check_operator(operator, "operator")
        for name, value, allowed in (("interpolation", interpolation, INTERPOLATIONS), ("edge", edge, EDGES)):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        self.interpolation, self.edge = interpolation, edge
        frame = projection_frame(operator)
        self.operator, self.num_projections, self.rows, self.columns = frame[:4]
        self.det_points, self.det_cell, self.row_cell = frame[4].double(), float(frame[5]), float(frame[6])
        self.domain, self.range_shape = operator.domain, tuple(operator.range_shape)
        self.components = 1 if len(self.range_shape) == 2 else 2
        self.shifts = torch.zeros(self.num_projections, self.components, dtype=torch.float64) if shifts is None \
            else check_tensor(torch.as_tensor(shifts, dtype=torch.float64), "shifts",
                              (self.num_projections, self.components))
        self.angle = torch.as_tensor(float(angle), dtype=torch.float64)
        self.matrices = None if matrices is None else _check_matrices(matrices, self.num_projections,
                                                                      self.components)

    def __repr__(self) -> str:
        return f"AlignedOperator({self.operator!r}, {self.num_projections} projections, {self.components} shift(s))"

    # ------------------------------------------------------------------------------------------- interpolation
    def _points(self, shifts: torch.Tensor, angle: torch.Tensor, like: torch.Tensor) -> tuple:
        """Fractional (row, column) indices ``(K, rows, columns)`` of ``R(-alpha)(p - shift)`` for every pixel p."""
        opts = dict(dtype=like.dtype, device=like.device)
        shifts, angle = shifts.to(**opts), angle.to(**opts)
        s = self.det_points.to(**opts).view(1, 1, -1)
        t = ((torch.arange(self.rows, **opts) - (self.rows - 1) / 2) * self.row_cell).view(1, -1, 1)
        ds = (shifts[:, 0] * self.det_cell).view(-1, 1, 1)
        dt = (shifts[:, 1] * self.row_cell).view(-1, 1, 1) if self.components == 2 else torch.zeros_like(ds)
        c, n = torch.cos(angle), torch.sin(angle)
        qs = c * (s - ds) + n * (t - dt)
        qt = -n * (s - ds) + c * (t - dt)
        if self.matrices is not None:   # q = B_k^{-1} R(-alpha)(p - shift)
            inv = torch.linalg.inv(self.matrices).to(**opts).view(-1, 1, 1, 2, 2)
            qs, qt = inv[..., 0, 0] * qs + inv[..., 0, 1] * qt, inv[..., 1, 0] * qs + inv[..., 1, 1] * qt
        return qt / self.row_cell + (self.rows - 1) / 2, (qs - s[0, 0, 0]) / self.det_cell

    def _weights(self, shifts, angle, like) -> tuple:
        """Flat neighbour indices and weights ``(n, K, rows * columns)``: ``n = 16`` (cubic) or 4 (linear)
        neighbours, clamped to the detector (``edge="nearest"``) or weighted zero outside it."""
        return self._taps(*self._points(shifts, angle, like))[:2]

    def _taps(self, row: torch.Tensor, col: torch.Tensor, slopes: bool = False) -> tuple:
        """``(index, weight, row_slope, column_slope)`` of the points ``(row, col)`` (:meth:`_weights`); with
        ``slopes`` also every weight's derivative along the point's row and column coordinate (else None)."""
        r0, c0 = torch.floor(row.detach()), torch.floor(col.detach())
        fr, fc = row - r0, col - c0
        cubic = self.interpolation == "cubic"
        kernel, slope, taps = (cubic_kernel, cubic_slope, (-1, 0, 1, 2)) if cubic else \
            (_linear_kernel, _linear_slope, (0, 1))
        row_taps = (0,) if self.rows == 1 else taps   # a sinogram's one row: its points lie on it
        index, weight, d_row, d_col = [], [], [], []
        for dr in row_taps:
            wr, r = kernel(fr - dr), r0 + dr
            for dc in taps:
                wc, c = kernel(fc - dc), c0 + dc
                w = wr * wc
                inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.columns) if self.edge == "zero" else None
                if inside is not None:
                    w = w * inside
                index.append((r.clamp(0, self.rows - 1) * self.columns + c.clamp(0, self.columns - 1)).long())
                weight.append(w)
                if slopes:
                    d_row.append(slope(fr - dr) * wc if inside is None else slope(fr - dr) * wc * inside)
                    d_col.append(wr * slope(fc - dc) if inside is None else wr * slope(fc - dc) * inside)
        shape = (len(index), self.num_projections, -1)
        stacked = [torch.stack(t).reshape(shape) if t else None for t in (index, weight, d_row, d_col)]
        return tuple(stacked)

    def warp_derivatives(self, y: torch.Tensor, shifts: torch.Tensor, angle: torch.Tensor, axis: bool = False) \
            -> tuple:
        """``(S y, columns)``: ``S y`` (:meth:`warp`) and its derivatives (the same shape) along every shift
        component, all projections at once (projection ``k`` moves with ``s_k`` only), and with ``axis`` along the
        angle: Gauss-Newton's Jacobian columns (``indreg.alignment``), from the kernels' derivatives (one set of
        weights for all, where forward-mode autograd through :meth:`warp` recomputes them per column)."""
        from torch.func import jvp

        def points(s, a):
            return self._points(s, a, y)

        directions = []
        for c in range(self.components):
            ds = torch.zeros_like(shifts)
            ds[:, c] = 1
            directions.append((ds, torch.zeros_like(angle)))
        if axis:
            directions.append((torch.zeros_like(shifts), torch.ones_like(angle)))
        moves = [jvp(points, (shifts, angle), d)[1] for d in directions]   # d(row), d(col) per direction
        index, weight, d_row, d_col = self._taps(*self._points(shifts, angle, y), slopes=True)
        K = self.num_projections
        warped = self._gather(y, index, weight)
        columns = [self._gather(y, index, d_row * m_row.reshape(1, K, -1) + d_col * m_col.reshape(1, K, -1))
                   for m_row, m_col in moves]
        return warped, columns

    def _current_weights(self, like: torch.Tensor) -> tuple:
        """:meth:`_weights` at the operator's own ``shifts``, ``angle`` (and ``matrices``, interpolation, edge), in
        ``like``'s dtype and device, kept until one of them changes: the operator applied again at the same
        alignment (every iteration of a fit between two estimates, a baseline's solver) reuses them, bit for bit.
        Recomputed, not kept, while the shifts or the angle require a gradient."""
        if self.shifts.requires_grad or self.angle.requires_grad:
            return self._weights(self.shifts, self.angle, like)
        key = (like.dtype, like.device, self.interpolation, self.edge)
        kept = getattr(self, "_kept", None)
        if kept is not None and kept[0] == key and torch.equal(kept[1], self.shifts) and \
                torch.equal(kept[2], self.angle) and _same(kept[3], self.matrices):
            return kept[4]
        with torch.no_grad():
            weights = self._weights(self.shifts, self.angle, like)
        if sum(t.numel() * t.element_size() for t in weights) <= KEEP_BYTES:
            self._kept = (key, self.shifts.clone(), self.angle.clone(),
                          None if self.matrices is None else self.matrices.clone(), weights)
        return weights

    def _flat(self, y: torch.Tensor) -> torch.Tensor:
        return y.reshape(*y.shape[:y.dim() - len(self.range_shape)], self.num_projections, -1)

    def warp(self, y: torch.Tensor, shifts: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
        """``S y``: data ``(..., *range_shape)`` sampled at the moved points (module docstring)."""
        return self._gather(y, *self._weights(shifts, angle, y))

    def warp_transpose(self, y: torch.Tensor, shifts: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
        """``S^T y``: the exact transpose of :meth:`warp` (scatter-add of the same weights)."""
        return self._scatter(y, *self._weights(shifts, angle, y))

    def _gather(self, y: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        flat = self._flat(y)
        out = sum(w * flat.gather(-1, i.expand(flat.shape)) for i, w in zip(index, weight))
        return out.reshape(y.shape)

    def _scatter(self, y: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        flat = self._flat(y)
        out = flat.new_zeros(flat.shape)
        for i, w in zip(index, weight):
            out = out.scatter_add(-1, i.expand(flat.shape), w * flat)
        return out.reshape(y.shape)

    # ------------------------------------------------------------------------------------------- the operator
    def apply(self, f: torch.Tensor, shifts: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
        """``S_{shifts, angle} T f`` (differentiable in ``f``, ``shifts`` and ``angle``)."""
        return self.warp(self.operator(f), shifts, angle)

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        """``T_s f`` at the current ``shifts`` and ``angle``: images ``(..., *domain.shape)`` -> data (the
        interpolation's weights kept between calls at the same alignment, :meth:`_current_weights`)."""
        y = self.operator(f)
        return self._gather(y, *self._current_weights(y))

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """L2 adjoint ``T^* S^T y``."""
        y = check_tensor(y, "data", self.range_shape, finite=False)
        return self.operator.adjoint(self._scatter(y, *self._current_weights(y)))

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``T``'s data inner product."""
        check_data_pair(y1, y2, self.range_shape)
        return self.operator.inner_data(y1, y2)
