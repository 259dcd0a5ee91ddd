"""Alignment in the fit: per-projection shifts and the tilt-axis angle estimated by projection matching against
the current reconstruction's projection, alternating with the registration (docs/alignment.md).

The data model is ``T_s f`` (``indreg.alignment.operator.AlignedOperator``). Every :data:`ALIGN_EVERY` iterations
the image ``f_k`` of the current iterate is projected, ``P = T f_k``, and the shifts (and with ``"shifts+axis"``
the angle) are re-fitted to the data with ``f_k`` fixed: ``min_{s, alpha} (1/2) ||S_{s, alpha} P - g||^2`` by
Gauss-Newton (:func:`estimate`); the first estimate (iteration 0, against the template) starts from the peak of
every projection's cross-correlation with ``P`` (:func:`coarse_shifts`), later ones from the previous estimate.

Notes
-----
- Shifts in detector pixels, ``(num_projections, c)``: ``c = 1`` (2D, across the axis) or 2 (tilt series:
  across, along); the angle in radians here, in degrees in reports.
- Gauge: a translation ``(a, b)`` of the object in the plane orthogonal to the axis moves projection ``k`` by
  ``a cos(theta_k) + b sin(theta_k)`` across the axis, one along it moves every projection alike along it; the
  deformation carries such a translation (the template can move), so by default (``"offset+translation"``)
  the shifts are kept orthogonal to them: across the axis to ``1, cos(theta_k), sin(theta_k)`` (the constant
  too: an offset of the axis, at most nearly a translation over a limited tilt range), along it to ``1``
  (:func:`gauge`); the true shifts are known only up to these. ``"translation"`` keeps the constant across
  the axis (the axis' offset is estimated), ``"none"`` keeps everything: the template fixes the frame, the
  shifts move the data onto it and the deformation is left the change of shape (:data:`ALIGN_GAUGES`).
- Bound: ``|s| <= MAX_SHIFT_FRACTION`` of the detector's extent along the component, ``|alpha| <=
  MAX_ANGLE_DEG``; a shift or angle clamped to its bound is reported by a warning.

Longer than 450 lines: one algorithm (projection matching's Gauss-Newton step with its gauge, bounds and prior),
most of it numpydoc.
"""
from __future__ import annotations

import logging
import math

import torch

from .modes import (ALIGN_GAUGES, ALIGN_MODES, INTERPOLATIONS, MAX_ANGLE_DEG, MAX_SHIFT_FRACTION, MIN_PROJECTIONS,
                    check_choice)
from .operator import AlignedOperator, projection_frame
from .state import AlignmentState

__all__ = ["GN_ITERATIONS", "GN_MAX_STEP", "GN_TOL", "SCALE_ROUNDS", "SCALE_TOL", "aligned", "angle_uncertainty",
           "bounds", "coarse_shifts", "estimate", "first_start", "fit_scale", "gauge", "projection_matching",
           "turn_projection"]

log = logging.getLogger("indreg")

#: Gauss-Newton iterations of one estimate, and the largest step of a shift per iteration (pixels: the
#: interpolation is one polynomial in ``s`` only within a cell).
GN_ITERATIONS = 15
GN_MAX_STEP = 1.0
#: Gauss-Newton stops when no shift moved more than this (px) and the angle not more than this (deg).
GN_TOL = 1e-3
#: :func:`fit_scale`: at most this many rounds (shifts, then scale), stopping when the scale moved by less than
#: ``SCALE_TOL`` (relative).
SCALE_ROUNDS, SCALE_TOL = 8, 1e-4


# ---------------------------------------------------------------------------------------------------- the model
def aligned(operator, mode: str, label: str = "align", gauge: str = ALIGN_GAUGES[0],
            interpolation: str = "linear") -> tuple:
    """The data model ``T_s`` of ``operator`` and the fit's state, for ``mode``.

    Parameters
    ----------
    operator : LinearOperator
        A parallel-beam ``RayTransform`` or a ``TiltSeriesTransform``, or an ``AlignedOperator`` (an imported
        alignment: the fit starts from its shifts and keeps its angle and matrices).
    mode : str
        ``"none"``, ``"shifts"`` or ``"shifts+axis"`` (``ALIGN_MODES``).
    label : str
        The option's name in messages.
    gauge : str
        What the shifts leave to the deformation (``ALIGN_GAUGES``).
    interpolation : str
        ``"linear"`` or ``"cubic"`` (``AlignedOperator``).

    Returns
    -------
    operator : AlignedOperator or LinearOperator
        The data model ``T_s`` (``operator`` itself for mode ``"none"``).
    state : AlignmentState or None
        The fit's state (None for mode ``"none"``).

    Raises
    ------
    ValueError, TypeError
        One line for a bad mode, gauge or interpolation, an operator that is not parallel-beam, the angle without a
        tilt series, and too few projections.
    """
    check_choice(label, mode, ALIGN_MODES)
    check_choice(f"{label}_gauge", gauge, ALIGN_GAUGES)
    check_choice(f"{label}_interpolation", interpolation, INTERPOLATIONS)
    if mode == "none":
        return operator, None
    given = operator if isinstance(operator, AlignedOperator) else None
    try:
        _, count, *_ = projection_frame(given.operator if given is not None else operator)
    except TypeError as e:
        raise TypeError(f"{label}={mode!r}: {e}") from None
    if mode == "shifts+axis" and len(operator.range_shape) != 3:
        raise ValueError(f"{label}='shifts+axis' needs a 3D tilt series (TiltSeriesTransform): a 2D sinogram has "
                         f"no tilt-axis angle; use {label}='shifts'")
    if count < MIN_PROJECTIONS:
        raise ValueError(f"{label}={mode!r} needs at least {MIN_PROJECTIONS} projections, the data have {count}")
    if given is None:
        return AlignedOperator(operator, interpolation=interpolation), AlignmentState(mode, gauge)
    op = AlignedOperator(given.operator, given.shifts.clone(), float(given.angle), interpolation, given.edge,
                         given.matrices)
    return op, AlignmentState(mode, gauge, started=bool(given.shifts.abs().max() > 0))   # zero: a rotation only


def first_start(op: AlignedOperator, state: AlignmentState, projection: torch.Tensor,
                data: torch.Tensor) -> torch.Tensor:
    """Where the first estimate starts: the operator's own shifts when the fit was started from them
    (``state.started``), else the cross-correlation peaks (:func:`coarse_shifts`) of the data with the projection
    moved by the operator's angle and matrices at zero shift (the identity without them), in the gauge.

    Parameters
    ----------
    op : AlignedOperator
        The data model.
    state : AlignmentState
        The fit's state (``started``, ``gauge``).
    projection, data : torch.Tensor
        ``P = T f`` and ``g``, ``op.range_shape``.

    Returns
    -------
    torch.Tensor
        Shifts ``(K, c)`` in pixels.
    """
    if state.started:
        return op.shifts
    P = projection.double()
    if op.matrices is not None or float(op.angle) != 0:
        P = op.warp(P, torch.zeros_like(op.shifts).to(P.device), op.angle)
    return gauge(op, coarse_shifts(op, P, data.double()).cpu(), state.gauge)


def bounds(op: AlignedOperator) -> torch.Tensor:
    """``|s|`` bounds per component: ``MAX_SHIFT_FRACTION`` of the detector's pixels (or the operator's own
    ``max_shift_fraction``, set by :func:`projection_matching`).

    Parameters
    ----------
    op : AlignedOperator
        The data model.

    Returns
    -------
    torch.Tensor
        ``(c,)`` float64, pixels (across, [along]).
    """
    sizes = [op.columns, op.rows][:op.components]
    fraction = getattr(op, "max_shift_fraction", MAX_SHIFT_FRACTION)
    return torch.tensor([fraction * n for n in sizes], dtype=torch.float64)


def gauge(op: AlignedOperator, shifts: torch.Tensor, kind: str = ALIGN_GAUGES[0]) -> torch.Tensor:
    """``shifts`` with what a translation of the object explains removed (module Notes).

    Parameters
    ----------
    op : AlignedOperator
        The data model (its angles).
    shifts : torch.Tensor
        ``(K, c)``, pixels.
    kind : {"offset+translation", "translation", "none"}
        ``"offset+translation"``: across the axis the least-squares fit of ``c + a cos(theta_k) + b sin(theta_k)``
        removed, along it the mean; ``"translation"`` keeps ``c``, the tilt axis' offset from the detector's
        middle; ``"none"`` removes nothing.

    Returns
    -------
    torch.Tensor
        The shifts in the gauge (a new tensor).
    """
    if kind == "none":
        return shifts.clone()
    theta = op.operator.geometry.angles.to(shifts)
    ones = [] if kind == "translation" else [torch.ones_like(theta)]
    basis = torch.stack(ones + [torch.cos(theta), torch.sin(theta)], dim=1)
    across = shifts[:, :1] - basis @ torch.linalg.lstsq(basis, shifts[:, :1]).solution
    return torch.cat([across, shifts[:, 1:] - shifts[:, 1:].mean(dim=0, keepdim=True)], dim=1)


# ---------------------------------------------------------------------------------------------------- estimation
def coarse_shifts(op: AlignedOperator, projection: torch.Tensor, data: torch.Tensor) -> torch.Tensor:
    """Shifts ``(K, c)`` at the peak of every projection's cross-correlation with ``data`` within the bound
    (zero-padded FFTs, so no wrap-around), refined by a parabola through the peak and its neighbours along each
    axis (a start off the integers: there bilinear interpolation has its kinks).

    Parameters
    ----------
    op : AlignedOperator
        The data model (its frame and bounds).
    projection, data : torch.Tensor
        ``P`` and ``g``, ``op.range_shape``.

    Returns
    -------
    torch.Tensor
        Shifts ``(K, c)``, float64 on the CPU, pixels.
    """
    K, R, D = op.num_projections, op.rows, op.columns
    p, g = projection.reshape(K, R, D), data.reshape(K, R, D)
    size = (2 * R, 2 * D)
    corr = torch.fft.irfft2(torch.fft.rfft2(g, size).mul(torch.fft.rfft2(p, size).conj()), size)
    bound = bounds(op).floor().long().tolist() + [0]
    lags = [torch.fft.fftfreq(n, 1 / n, device=corr.device).round().long() for n in size]
    allowed = (lags[0].abs().view(-1, 1) <= bound[1]) & (lags[1].abs().view(1, -1) <= bound[0])
    peak = corr.masked_fill(~allowed, -math.inf).reshape(K, -1).argmax(dim=1)
    r, c = peak // size[1], peak % size[1]
    k = torch.arange(K, device=corr.device)
    out = []
    for axis, i, n in ((1, c, size[1]), (0, r, size[0])):   # (columns, rows)
        def at(d):
            return corr[k, (r + d) % size[0], c] if axis == 0 else corr[k, r, (c + d) % size[1]]
        lo, mid, hi = at(-1), at(0), at(1)
        curvature = lo - 2 * mid + hi
        delta = torch.where(curvature < 0, 0.5 * (lo - hi) / curvature.clamp(max=-1e-30), torch.zeros_like(mid))
        out.append(lags[axis][i].double() + delta.clamp(-0.5, 0.5).double())
    return torch.stack(out, dim=1)[:, :op.components].cpu()


def _jacobian(op: AlignedOperator, projection: torch.Tensor, shifts: torch.Tensor, angle: torch.Tensor,
              axis: bool) -> list:
    """Directional derivatives of ``S P`` along every shift component (all projections at once: projection ``k``
    depends on ``s_k`` only) and along the angle (``AlignedOperator.warp_derivatives``)."""
    return op.warp_derivatives(projection, shifts, angle, axis)[1]


def _normal_equations(columns: list, residual: torch.Tensor, K: int, c: int, axis: bool) -> tuple:
    """Gauss-Newton's ``J^T J`` and ``J^T r`` for the unknowns ``(s_{0,0}, ..., s_{K-1,c-1}, alpha)``."""
    flat = [j.reshape(K, -1) for j in columns]
    r = residual.reshape(K, -1)
    n = K * c + int(axis)
    H, b = r.new_zeros(n, n), r.new_zeros(n)
    idx = torch.arange(K, device=r.device) * c
    for i in range(c):
        b[idx + i] = (flat[i] * r).sum(1)
        for j in range(c):
            H[idx + i, idx + j] = (flat[i] * flat[j]).sum(1)
    if axis:
        for i in range(c):
            H[idx + i, -1] = H[-1, idx + i] = (flat[i] * flat[c]).sum(1)
        H[-1, -1], b[-1] = (flat[c] ** 2).sum(), (flat[c] * r).sum()
    return H, b


def _cost(op: AlignedOperator, projection: torch.Tensor, data: torch.Tensor, shifts: torch.Tensor,
          angle: torch.Tensor) -> float:
    return 0.5 * float(((op.warp(projection, shifts, angle) - data) ** 2).sum())


def estimate(op: AlignedOperator, projection: torch.Tensor, data: torch.Tensor, shifts: torch.Tensor,
             angle: torch.Tensor, axis: bool = False, iterations: int = GN_ITERATIONS,
             kind: str = ALIGN_GAUGES[0], prior: tuple | None = None) -> tuple:
    """Gauss-Newton (Levenberg-damped) on ``(1/2) ||S_{s, alpha} P - g||^2`` from ``(shifts, angle)`` with the
    projection ``P`` fixed; shifts kept in the gauge ``kind`` (:func:`gauge`) and within the bounds (:func:`bounds`).

    Parameters
    ----------
    op : AlignedOperator
        The data model.
    projection, data : torch.Tensor
        ``P`` and ``g``, ``op.range_shape``.
    shifts : torch.Tensor
        The start, ``(K, c)`` pixels.
    angle : torch.Tensor
        The start of the tilt-axis angle (radians, 0-d).
    axis : bool
        Fit the angle too.
    iterations : int
        At most this many Gauss-Newton iterations (stops earlier when nothing moves more than ``GN_TOL``).
    kind : str
        The gauge (:func:`gauge`).
    prior : tuple, optional
        ``(alpha_0, sd)`` (radians; with ``axis``) adds ``(w / 2) (alpha - alpha_0)^2``, ``w = sigma^2 / sd^2`` with
        ``sigma^2`` the residual's variance per datum at the start: a Gaussian prior in the data's scale.

    Returns
    -------
    shifts : torch.Tensor
        ``(K, c)`` float64 on the CPU.
    angle : torch.Tensor
        Radians, float64 on the CPU.
    at_bound : int
        How many shifts or angles ended at their bound.
    """
    P, g = projection.detach().double(), data.detach().double()
    K, c = op.num_projections, op.components
    bound, amax = bounds(op).to(P.device), math.radians(MAX_ANGLE_DEG)
    s = torch.maximum(torch.minimum(gauge(op, shifts.double().cpu(), kind).to(P.device), bound), -bound)
    a = angle.double().to(P.device).clamp(-amax, amax)
    cost, damping = _cost(op, P, g, s, a), 1e-6
    weight = 0.0
    if axis and prior is not None:
        weight = 2 * cost / max(g.numel() - K * c - 1, 1) / prior[1] ** 2
        cost += 0.5 * weight * (float(a) - prior[0]) ** 2
    for _ in range(iterations):
        warped, columns = op.warp_derivatives(P, s, a, axis)
        H, b = _normal_equations(columns, warped - g, K, c, axis)
        if weight:
            H[-1, -1] += weight
            b[-1] += weight * (float(a) - prior[0])
        while damping < 1e8:
            step = -torch.linalg.solve(H + damping * torch.diag(H.diagonal().clamp_min(1e-12)), b)
            step = step * min(1.0, GN_MAX_STEP / max(float(step[:K * c].abs().max()), 1e-30))
            s_new = torch.maximum(torch.minimum(gauge(op, s + step[:K * c].reshape(K, c), kind), bound), -bound)
            a_new = (a + step[-1]).clamp(-amax, amax) if axis else a
            new = _cost(op, P, g, s_new, a_new) + (0.5 * weight * (float(a_new) - prior[0]) ** 2 if weight else 0.0)
            if new < cost:
                moved = max(float((s_new - s).abs().max()), math.degrees(abs(float(a_new - a))))
                s, a, cost, damping = s_new, a_new, new, max(damping / 10, 1e-9)
                break
            damping *= 10
        else:
            break
        if moved < GN_TOL:
            break
    at_bound = int((s.abs() >= bound - 1e-9).sum()) + int(axis and abs(float(a)) >= amax - 1e-12)
    return s.cpu(), a.cpu(), at_bound


def _gram(columns: list, K: int, c: int) -> torch.Tensor:
    """``J^T J`` for the unknowns ``(s_{0,0}, ..., s_{K-1,c-1}, g_1, ...)`` from ``columns``: the ``c`` shift
    derivatives (projection ``k`` depends on ``s_k`` only), then those of parameters of all projections."""
    flat = torch.stack([j.reshape(K, -1) for j in columns])            # (columns, K, pixels)
    block = torch.einsum("ikp,jkp->kij", flat[:c], flat[:c])            # per projection
    cross = torch.einsum("ikp,jkp->kij", flat[:c], flat[c:]).reshape(K * c, -1)
    glob = torch.einsum("ikp,jkp->ij", flat[c:], flat[c:])
    H = torch.block_diag(*block)
    return torch.cat([torch.cat([H, cross], dim=1), torch.cat([cross.T, glob], dim=1)])


def _scale(op: AlignedOperator, projection: torch.Tensor, data: torch.Tensor, shifts: torch.Tensor,
           angle: torch.Tensor) -> float:
    """``c = <S P, g> / <S P, S P>`` (the data inner product, :func:`indreg.units.compare_units`'s fit) through the
    alignment ``(shifts, angle)``."""
    SP = op.warp(projection, shifts, angle)
    den = float(op.inner_data(SP, SP).sum())
    return float(op.inner_data(SP, data).sum()) / den if den > 0 else math.nan


def fit_scale(op: AlignedOperator, state: AlignmentState, template: torch.Tensor, data: torch.Tensor,
              rounds: int = SCALE_ROUNDS, tol: float = SCALE_TOL) -> tuple:
    """The template's least-squares scale through the alignment that matches its projection to the data.

    ``min_{c, s, alpha} ||c S_{s, alpha} T I - g||^2``, where the plain fit ``<T I, g> / <T I, T I>`` is biased by
    the data's drift (``indreg.units.compare_units``). Alternating minimisation, so the objective never increases:
    the start of the first in-fit estimate (:func:`first_start`: the cross-correlation peaks, scale-free, or the
    operator's given alignment), then ``rounds`` times ``c`` in closed form and the alignment of ``c T I``
    (:func:`estimate`, the angle too where ``state.axis``), until ``c`` moves by less than ``tol`` (relative).

    Parameters
    ----------
    op : AlignedOperator
        The data model (left as it was).
    state : AlignmentState
        The fit's mode, gauge and start.
    template, data : torch.Tensor
        ``I`` (``op.domain.shape``) and ``g`` (``op.range_shape``).
    rounds : int
        At most this many rounds.
    tol : float
        Relative change of ``c`` that stops them.

    Returns
    -------
    c : float
        The scale (nan when the projection is zero).
    shifts : torch.Tensor
        ``(K, c)`` pixels.
    angle : torch.Tensor
        Radians.
    rounds : int
        Rounds done.
    """
    with torch.no_grad():
        P, g = op.operator(template).detach().double(), data.detach().double()
        s, a = first_start(op, state, P, g), op.angle.double()
        c, done = _scale(op, P, g, s, a), 0
        while done < rounds and math.isfinite(c) and c > 0:
            s, a, _ = estimate(op, c * P, g, s, a, state.axis, kind=state.gauge, prior=state.prior)
            c, previous, done = _scale(op, P, g, s, a), c, done + 1
            if abs(c - previous) <= tol * abs(previous):
                break
    return c, s, a, done


def turn_projection(operator, image: torch.Tensor) -> torch.Tensor:
    """``T(L f)`` for a ``TiltSeriesTransform`` ``T``: the projection of the derivative of the image ``f`` turned
    about the beam at tilt 0 (the axis orthogonal to the tilt axis and the detector columns), at no turn; ``L f =
    u d_t f - t d_u f`` with ``u`` across the axis, ``t`` along it (central differences). At tilt ``theta`` this turn
    is an in-plane rotation of the projection by ``cos(theta)`` times the turn, plus an out-of-plane part.

    Parameters
    ----------
    operator : TiltSeriesTransform
        ``T``.
    image : torch.Tensor
        ``f``, ``operator.domain.shape``.

    Returns
    -------
    torch.Tensor
        ``T(L f)``, ``operator.range_shape``, in ``image``'s dtype.
    """
    g = operator.geometry
    u, t = g.slice_axes[0], g.axis
    f = image.detach().double()
    grid = torch.meshgrid(*operator.domain.axes(device=f.device), indexing="ij")
    sides = operator.domain.cell_sides
    d_u, d_t = (torch.gradient(f, spacing=sides[i], dim=i)[0] for i in (u, t))
    return operator((grid[u] * d_t - grid[t] * d_u).to(image.dtype))


def angle_uncertainty(op: AlignedOperator, image: torch.Tensor, data: torch.Tensor) -> float:
    """The standard error (degrees) of ``op``'s tilt-axis angle when the object may also turn about the beam (the
    deformation can carry such a turn, and at low tilts it looks like the angle): Gauss-Newton's normal matrix of
    ``(1/2) ||S_{s, alpha}(T f + beta T(L f)) - g||^2`` in the shifts, the angle and the turn ``beta``
    (:func:`turn_projection`) at ``op``'s alignment and ``beta = 0``, its inverse's angle entry times the residual's
    variance per datum (``2 cost / (data - unknowns)``).

    Parameters
    ----------
    op : AlignedOperator
        The data model at its alignment (a tilt series).
    image : torch.Tensor
        ``f``, ``op.domain.shape``.
    data : torch.Tensor
        ``g``, ``op.range_shape``.

    Returns
    -------
    float
        Degrees; ``inf`` when the data cannot tell the angle from a turn of the object (a narrow tilt range, an
        object that looks alike at every turn). Above :data:`MAX_ANGLE_SE_DEG` the angle is not determined by
        the data.
    """
    T = op.operator
    P, g = T(image.detach()).double(), data.detach().double()
    s, a = op.shifts.to(P.device), op.angle.to(P.device)
    K, c = op.num_projections, op.components
    columns = _jacobian(op, P, s, a, True) + [op.warp(turn_projection(T, image).double(), s, a)]
    H = _gram(columns, K, c)
    cost = 0.5 * float(((op.warp(P, s, a) - g) ** 2).sum())
    sigma2 = 2 * cost / max(g.numel() - H.shape[0], 1)
    e = torch.zeros(H.shape[0], dtype=H.dtype, device=H.device)
    e[K * c] = 1
    try:
        variance = float(torch.linalg.solve(H, e)[K * c]) * sigma2
    except RuntimeError:   # singular: the angle has no effect the turn or the shifts cannot make
        return math.inf
    return math.degrees(math.sqrt(variance)) if variance > 0 and math.isfinite(variance) else math.inf


def projection_matching(operator, data: torch.Tensor, mode: str = "shifts", rounds: int = 4, iters: int = 50,
                        interpolation: str = "linear", progress=None, max_shift: float | None = None) -> tuple:
    """Alignment without a template (e.g. of the scan a template is made from): ``rounds`` times a nonnegative SIRT
    reconstruction (``iters`` iterations) through the current alignment, then the alignment re-fitted to its
    projection (:func:`estimate`; the first start at the cross-correlation peaks, :func:`coarse_shifts`). The
    shifts keep the tilt axis' offset (gauge ``"translation"``, :func:`gauge`): a constant shift is an object
    translation only where ``cos(theta) ~ 1``, and over a wide tilt range removing it moves the axis
    (docs/alignment.md). The estimates use ``interpolation``; SIRT needs a nonnegative matrix and runs through
    bilinear interpolation.
    ``operator`` may be an ``AlignedOperator`` (an imported alignment, a known tilt-axis rotation): the estimates
    start from its shifts (from the cross-correlation when they are all zero) and keep its matrices.

    Parameters
    ----------
    operator : LinearOperator
        A parallel-beam ``RayTransform``, a ``TiltSeriesTransform`` or an ``AlignedOperator``.
    data : torch.Tensor
        ``g``, ``operator.range_shape``.
    mode : {"shifts", "shifts+axis"}
        What is estimated (``"shifts+axis"``: a tilt series).
    rounds : int
        SIRT-then-estimate rounds.
    iters : int
        SIRT iterations per reconstruction.
    interpolation : {"linear", "cubic"}
        The estimates' interpolation.
    progress : callable, optional
        ``progress(round, record)``, called after every round.
    max_shift : float, optional
        The shifts' bound as a fraction of the detector's pixels (default ``MAX_SHIFT_FRACTION``).

    Returns
    -------
    operator : AlignedOperator
        The aligned data model.
    image : torch.Tensor
        Its SIRT reconstruction.
    records : list of tuple
        One ``(SIRT residual, largest move in px)`` per round (the relative residual before the round's
        estimate).

    Raises
    ------
    ValueError, TypeError
        Mode ``"none"`` and the errors of :func:`aligned`.
    """
    from ..forward.sirt import sirt

    if mode == "none":
        raise ValueError("projection_matching needs mode 'shifts' or 'shifts+axis', got 'none'")
    (op, state), records = aligned(operator, mode, "projection_matching", "translation", interpolation), []
    if max_shift is not None:
        op.max_shift_fraction = float(max_shift)
    for r in range(rounds):
        x, history = sirt(_bilinear(op), data, num_iter=iters, nonneg=True)
        P, before = op.operator(x), op.shifts.clone()
        start = first_start(op, state, P, data) if r == 0 else op.shifts
        op.shifts, op.angle, state.at_bound = estimate(op, P, data, start, op.angle, state.axis, kind=state.gauge)
        norm = op.inner_data(data, data).sqrt()
        records.append((float(history["data_residual"][-1] / norm), float((op.shifts - before).abs().max())))
        if progress is not None:
            progress(r, records[-1])
    x, _ = sirt(_bilinear(op), data, num_iter=iters, nonneg=True)
    return op, x, records


def _bilinear(op: AlignedOperator) -> AlignedOperator:
    """``op``'s alignment with bilinear interpolation (nonnegative weights, as SIRT needs): ``op`` itself if it has
    it."""
    if op.interpolation == "linear":
        return op
    return AlignedOperator(op.operator, op.shifts, float(op.angle), "linear", op.edge, op.matrices)


