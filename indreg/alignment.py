"""Alignment in the fit: per-projection shifts and the tilt-axis angle estimated by projection matching against
the current reconstruction's projection, alternating with the registration (docs/alignment.md).

The data model is ``T_s f`` (``indreg.forward.shift.AlignedOperator``). Every :data:`ALIGN_EVERY` iterations
the image ``f_k`` of the current iterate is projected, ``P = T f_k``, and the shifts (and with ``"shifts+axis"``
the angle) are re-fitted to the data with ``f_k`` fixed: ``min_{s, alpha} (1/2) ||S_{s, alpha} P - g||^2`` by
Gauss-Newton (:func:`estimate`); the first estimate (iteration 0, against the template) starts from the peak of
every projection's cross-correlation with ``P`` (:func:`coarse_shifts`), later ones from the previous estimate.

Convention:
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
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import torch

from .forward.shift import INTERPOLATIONS, AlignedOperator, projection_frame
from .solvers.state import RefitSolver

__all__ = ["ALIGN_MODES", "ALIGN_GAUGES", "ALIGN_EVERY", "MAX_SHIFT_FRACTION", "MAX_ANGLE_DEG", "MAX_ANGLE_SE_DEG",
           "MIN_PROJECTIONS", "SCALE_ROUNDS", "SCALE_TOL", "STACK_ANGLE", "AlignmentSolver", "aligned",
           "angle_uncertainty", "coarse_shifts", "estimate", "find_aligned", "fit_scale", "gauge", "hold_stack_angle",
           "operator_summary", "plot_shifts", "projection_matching", "stack_angle", "summary", "turn_projection",
           "wrap"]

log = logging.getLogger("indreg")

ALIGN_MODES = ("none", "shifts", "shifts+axis")
#: What the shifts are kept orthogonal to (module Convention); the first is the default.
ALIGN_GAUGES = ("offset+translation", "translation", "none")
#: Iterations between two estimates (docs/alignment.md: re-estimating more often did not recover the shifts
#: better and costs a Gauss-Newton solve each time).
ALIGN_EVERY = 10
#: Bound on ``|s|`` as a fraction of the detector's pixels along the component.
MAX_SHIFT_FRACTION = 0.25
#: Bound on the tilt-axis angle.
MAX_ANGLE_DEG = 10.0
#: Fewest projections that can be aligned (the gauge removes three shifts across the axis).
MIN_PROJECTIONS = 4
#: Gauss-Newton iterations of one estimate, and the largest step of a shift per iteration (pixels: the
#: interpolation is one polynomial in ``s`` only within a cell).
GN_ITERATIONS = 15
GN_MAX_STEP = 1.0
#: Gauss-Newton stops when no shift moved more than this (px) and the angle not more than this (deg).
GN_TOL = 1e-3
#: :func:`fit_scale`: at most this many rounds (shifts, then scale), stopping when the scale moved by less than
#: ``SCALE_TOL`` (relative).
SCALE_ROUNDS, SCALE_TOL = 8, 1e-4
#: Above this standard error (deg, :func:`angle_uncertainty`) the tilt-axis angle is reported as undetermined.
MAX_ANGLE_SE_DEG = 0.2
#: ``"shifts+axis"`` first estimates the angle from the stack alone (:func:`stack_angle`) and, where that
#: determines it, holds it in the fit; ``False``: the angle is estimated in the fit only (docs/alignment.md).
STACK_ANGLE = True


# ---------------------------------------------------------------------------------------------------- the model
def aligned(operator, mode: str, label: str = "align", gauge: str = ALIGN_GAUGES[0], interpolation: str = "linear"):
    """``operator`` wrapped in an ``AlignedOperator`` for ``mode`` (``"none"``: itself) whose shifts are kept in
    ``gauge`` (:data:`ALIGN_GAUGES`), with ``interpolation`` (``"linear"`` or ``"cubic"``, ``AlignedOperator``);
    one-line errors for a bad mode, gauge or interpolation, an operator that is not parallel-beam, the angle
    without a tilt series, and too few projections."""
    if mode not in ALIGN_MODES:
        raise ValueError(f"{label} must be one of {', '.join(map(repr, ALIGN_MODES))}, got {mode!r}")
    if gauge not in ALIGN_GAUGES:
        raise ValueError(f"{label}_gauge must be one of {', '.join(map(repr, ALIGN_GAUGES))}, got {gauge!r}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"{label}_interpolation must be one of {', '.join(map(repr, INTERPOLATIONS))}, got "
                         f"{interpolation!r}")
    if mode == "none":
        return operator
    if isinstance(operator, AlignedOperator):   # an imported alignment (indreg.io.alignment_files): the fit's start
        return _started(operator, mode, label, gauge, interpolation)
    try:
        _, count, *_ = projection_frame(operator)
    except TypeError as e:
        raise TypeError(f"{label}={mode!r}: {e}") from None
    if mode == "shifts+axis" and len(operator.range_shape) != 3:
        raise ValueError(f"{label}='shifts+axis' needs a 3D tilt series (TiltSeriesTransform): a 2D sinogram has "
                         f"no tilt-axis angle; use {label}='shifts'")
    if count < MIN_PROJECTIONS:
        raise ValueError(f"{label}={mode!r} needs at least {MIN_PROJECTIONS} projections, the data have {count}")
    op = AlignedOperator(operator, interpolation=interpolation)
    op.mode, op.gauge, op.records, op.at_bound = mode, gauge, [], 0   # records: the estimates, for summary()
    return op


def _started(given: AlignedOperator, mode: str, label: str, gauge: str, interpolation: str) -> AlignedOperator:
    """A copy of ``given`` (its shifts, angle and matrices) whose first estimate starts from its alignment instead of
    the cross-correlation peaks."""
    op = aligned(given.operator, mode, label, gauge, interpolation)
    op.shifts, op.angle, op.edge, op.matrices = given.shifts.clone(), given.angle.clone(), given.edge, given.matrices
    op.started = bool(given.shifts.abs().max() > 0)   # zero shifts: nothing to start from (a rotation only)
    return op


def _first_start(op: AlignedOperator, projection: torch.Tensor, data: torch.Tensor) -> torch.Tensor:
    """Where the first estimate starts: the operator's own shifts when they were given (:func:`_started`), else the
    cross-correlation peaks (:func:`coarse_shifts`) of the data with the projection moved by the operator's angle
    and matrices at zero shift (the identity without them), in the gauge."""
    if getattr(op, "started", False):
        return op.shifts
    P = projection.double()
    if op.matrices is not None or float(op.angle) != 0:
        P = op.warp(P, torch.zeros_like(op.shifts).to(P.device), op.angle)
    return gauge(op, coarse_shifts(op, P, data.double()).cpu())


def _bounds(op: AlignedOperator) -> torch.Tensor:
    """``|s|`` bounds per component (pixels)."""
    sizes = [op.columns, op.rows][:op.components]
    return torch.tensor([MAX_SHIFT_FRACTION * n for n in sizes], dtype=torch.float64)


def gauge(op: AlignedOperator, shifts: torch.Tensor) -> torch.Tensor:
    """``shifts`` with what a translation of the object explains removed (module Convention), by ``op.gauge``:
    ``"offset+translation"`` (also an operator without one) across the axis the least-squares fit of ``c + a
    cos(theta_k) + b sin(theta_k)``, along it the mean; ``"translation"`` keeps ``c``, the tilt axis' offset from
    the detector's middle; ``"none"`` returns ``shifts`` as they are."""
    kind = getattr(op, "gauge", ALIGN_GAUGES[0])
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
    axis (a start off the integers: there bilinear interpolation has its kinks)."""
    K, R, D = op.num_projections, op.rows, op.columns
    p, g = projection.reshape(K, R, D), data.reshape(K, R, D)
    size = (2 * R, 2 * D)
    corr = torch.fft.irfft2(torch.fft.rfft2(g, size).mul(torch.fft.rfft2(p, size).conj()), size)
    bound = _bounds(op).floor().long().tolist() + [0]
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
             angle: torch.Tensor, axis: bool = False, iterations: int = GN_ITERATIONS) -> tuple:
    """Gauss-Newton (Levenberg-damped) on ``(1/2) ||S_{s, alpha} P - g||^2`` from ``(shifts, angle)`` with the
    projection ``P`` fixed; shifts kept in the gauge (:func:`gauge`) and within the bounds. Returns ``(shifts, angle,
    at_bound)`` (float64, CPU; ``at_bound``: how many shifts or angles ended at their bound)."""
    P, g = projection.detach().double(), data.detach().double()
    K, c = op.num_projections, op.components
    bounds, amax = _bounds(op).to(P.device), math.radians(MAX_ANGLE_DEG)
    s = torch.maximum(torch.minimum(gauge(op, shifts.double().cpu()).to(P.device), bounds), -bounds)
    a = angle.double().to(P.device).clamp(-amax, amax)
    cost, damping = _cost(op, P, g, s, a), 1e-6
    for _ in range(iterations):
        warped, columns = op.warp_derivatives(P, s, a, axis)
        H, b = _normal_equations(columns, warped - g, K, c, axis)
        while damping < 1e8:
            step = -torch.linalg.solve(H + damping * torch.diag(H.diagonal().clamp_min(1e-12)), b)
            step = step * min(1.0, GN_MAX_STEP / max(float(step[:K * c].abs().max()), 1e-30))
            s_new = torch.maximum(torch.minimum(gauge(op, s + step[:K * c].reshape(K, c)), bounds), -bounds)
            a_new = (a + step[-1]).clamp(-amax, amax) if axis else a
            new = _cost(op, P, g, s_new, a_new)
            if new < cost:
                moved = max(float((s_new - s).abs().max()), math.degrees(abs(float(a_new - a))))
                s, a, cost, damping = s_new, a_new, new, max(damping / 10, 1e-9)
                break
            damping *= 10
        else:
            break
        if moved < GN_TOL:
            break
    at_bound = int((s.abs() >= bounds - 1e-9).sum()) + int(axis and abs(float(a)) >= amax - 1e-12)
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


def fit_scale(op: AlignedOperator, template: torch.Tensor, data: torch.Tensor, rounds: int = SCALE_ROUNDS,
              tol: float = SCALE_TOL) -> tuple:
    """The template's least-squares scale through the alignment that matches its projection to the data: ``min_{c,
    s, alpha} ||c S_{s, alpha} T I - g||^2``, where the plain fit ``<T I, g> / <T I, T I>`` is biased by the data's
    drift (:func:`indreg.units.compare_units`). Alternating minimisation, so the objective never increases: the
    start of the first in-fit estimate (:func:`_first_start`: the cross-correlation peaks, scale-free, or ``op``'s
    given alignment), then ``rounds`` times ``c`` in closed form and the alignment of ``c T I`` (:func:`estimate`,
    the angle too with ``"shifts+axis"`` unless the stack's angle is held: :func:`hold_stack_angle`), until ``c``
    moves by less than ``tol`` (relative).
    Returns ``(c, shifts, angle, rounds done)``; ``op`` is left as it was."""
    with torch.no_grad():
        P, g = op.operator(template).detach().double(), data.detach().double()
        s, a = _first_start(op, P, g), op.angle.double()
        c, done = _scale(op, P, g, s, a), 0
        while done < rounds and math.isfinite(c) and c > 0:
            s, a, _ = estimate(op, c * P, g, s, a, op.mode == "shifts+axis" and not getattr(op, "held", False))
            c, previous, done = _scale(op, P, g, s, a), c, done + 1
            if abs(c - previous) <= tol * abs(previous):
                break
    return c, s, a, done


def turn_projection(operator, image: torch.Tensor) -> torch.Tensor:
    """``T(L f)`` for a ``TiltSeriesTransform`` ``T``: the projection of the derivative of the image ``f`` turned
    about the beam at tilt 0 (the axis orthogonal to the tilt axis and the detector columns), at no turn; ``L f =
    u d_t f - t d_u f`` with ``u`` across the axis, ``t`` along it (central differences). At tilt ``theta`` this turn
    is an in-plane rotation of the projection by ``cos(theta)`` times the turn, plus an out-of-plane part."""
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
    variance per datum (``2 cost / (data - unknowns)``). ``inf`` when the data cannot tell the angle from a turn of
    the object (a narrow tilt range, an object that looks alike at every turn); above :data:`MAX_ANGLE_SE_DEG`
    the angle is not determined by the data."""
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
                        interpolation: str = "linear", progress=None) -> tuple:
    """Alignment without a template (e.g. of the scan a template is made from): ``rounds`` times a nonnegative SIRT
    reconstruction (``iters`` iterations) through the current alignment, then the alignment re-fitted to its
    projection (:func:`estimate`; the first start at the cross-correlation peaks, :func:`coarse_shifts`). The
    shifts keep the tilt axis' offset (gauge ``"translation"``, :func:`gauge`): a constant shift is an object
    translation only where ``cos(theta) ~ 1``, and over a wide tilt range removing it moves the axis
    (docs/alignment.md). The estimates use ``interpolation``; SIRT needs a nonnegative matrix and runs through
    bilinear interpolation.
    ``operator`` may be an ``AlignedOperator`` (an imported alignment, a known tilt-axis rotation): the estimates
    start from its shifts (from the cross-correlation when they are all zero) and keep its matrices.
    ``progress(round, record)``, if given, is called after every round.
    Returns ``(aligned operator, its SIRT reconstruction, records)``, ``records`` one ``(SIRT residual, largest
    move in px)`` per round (the relative residual before the round's estimate)."""
    from .forward.sirt import sirt

    if mode == "none":
        raise ValueError("projection_matching needs mode 'shifts' or 'shifts+axis', got 'none'")
    op, records = aligned(operator, mode, "projection_matching", "translation", interpolation), []
    for r in range(rounds):
        x, history = sirt(_bilinear(op), data, num_iter=iters, nonneg=True)
        P, before = op.operator(x), op.shifts.clone()
        start = _first_start(op, P, data) if r == 0 else op.shifts
        op.shifts, op.angle, op.at_bound = estimate(op, P, data, start, op.angle, mode == "shifts+axis")
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


# ---------------------------------------------------------------------------------------------------- in the fit
def stack_angle(op: AlignedOperator, data: torch.Tensor):
    """The tilt-axis angle of ``data`` from the stack alone, by the moment conditions of every detector row
    (``indreg.axis_moments.estimate_axis_angle``): no reconstruction, so no turn of the object about the beam can
    take part of it up. ``None`` where it does not apply: pixels not square, a given alignment (imported shifts, an
    angle, per-tilt matrices); :meth:`~indreg.axis_moments.AxisEstimate.refused` (not determined, with the reason)
    for a stack that cannot tell the angle (too few tilts whose specimen stays on the detector, too few rows)."""
    from .axis_moments import AxisEstimate, estimate_axis_angle

    _, K, R, D, _, det_cell, row_cell = projection_frame(op.operator)
    if getattr(op, "started", False) or op.matrices is not None or float(op.angle) != 0:
        return None
    if data.numel() != K * R * D:
        log.info("tilt-axis angle from the stack: skipped (data of shape %s, not one stack)", tuple(data.shape))
        return None
    if abs(det_cell / row_cell - 1) > 1e-6:
        log.info("tilt-axis angle from the stack: skipped (pixels %.4g x %.4g are not square)", det_cell, row_cell)
        return None
    try:
        return estimate_axis_angle(data.detach().double().cpu().reshape(K, R, D).numpy(),
                                   op.operator.geometry.angles.double().cpu().numpy(), scan_deg=MAX_ANGLE_DEG)
    except ValueError as e:
        return AxisEstimate.refused(str(e), K)


def hold_stack_angle(op: AlignedOperator, data: torch.Tensor) -> bool:
    """Estimate the angle from the stack (:func:`stack_angle`), once per operator, before anything else fits the
    alignment (the template's scale, :func:`fit_scale`, or the first in-fit estimate), and set it on ``op``:
    ``True`` (``op.held``: hold it in the fit) where the data determine it; else a warning, and the fit estimates
    it."""
    if op.mode != "shifts+axis":
        return False
    if hasattr(op, "stack_estimate"):   # estimated before (or off: None)
        return bool(getattr(op, "held", False))
    e = op.stack_estimate = stack_angle(op, data) if STACK_ANGLE else None
    op.held = e is not None and e.determined
    if e is None:
        return False
    log.info(e.describe())
    if op.held:
        op.angle = torch.tensor(math.radians(e.angle_deg), dtype=torch.float64)
        op.angle_se = e.se_deg
        return True
    why = e.reason or (f"s.e. {e.se_deg:.3f} deg" if math.isfinite(e.se_deg) else "s.e. inf deg")
    log.warning("tilt-axis angle not determined by the data (%s, from the stack's moment conditions): it is "
                "estimated in the fit, where a turn of the object about the beam can take part of it up; measure it "
                "beforehand and rotate the stack, or use align='shifts'", why)
    return False


class AlignmentSolver(RefitSolver):
    """A solver that re-estimates the alignment of ``operator`` (an ``AlignedOperator`` in ``inner.problem``) every
    ``every`` iterations from the image of the current iterate, then takes ``inner``'s step.

    ``operator``: made by :func:`aligned` (its ``mode``; ``records``, ``(iteration, shifts, angle)`` per estimate,
    and ``at_bound`` are kept on it for :func:`summary`). ``data``: the data the shifts are fitted to
    (``operator``'s range; all projections, held-out ones included). After an estimate the inner solver's cached
    objective and gradient (and a torch.optim optimizer's memory) are dropped: they belong to the old data model.
    """

    name = "alignment"

    def __init__(self, inner, operator: AlignedOperator, data: torch.Tensor, every: int = ALIGN_EVERY):
        super().__init__(inner, every)
        self.operator, self.data = operator, data
        self.axis = operator.mode == "shifts+axis"
        self.what = "shifts and tilt-axis angle" if self.axis else "shifts"

    def refit(self, state) -> None:
        """Estimate the alignment at ``state.iterate`` and set it on the operator."""
        op = self.operator
        with torch.no_grad():
            image = self.problem.reconstruction(state.iterate)
            P = op.operator(image)
            start = op.shifts
            if not op.records:   # first estimate: the given alignment, else the cross-correlation peak
                if self.axis and hold_stack_angle(op, self.data):
                    self.axis = False
                start = _first_start(op, P, self.data)
            op.shifts, op.angle, op.at_bound = estimate(op, P, self.data, start, op.angle, self.axis)
            if self.axis:
                op.angle_se = angle_uncertainty(op, image, self.data)
        op.records.append((state.iteration, op.shifts.clone(), float(op.angle)))
        if op.at_bound:
            log.warning("iteration %d: %d alignment parameter(s) at their bound (|s| <= %s px, |alpha| <= %g deg): "
                        "the data may be misaligned beyond it, or the template too unlike the data", state.iteration,
                        op.at_bound, [round(float(b), 2) for b in _bounds(op)], MAX_ANGLE_DEG)

    def report(self, info: dict) -> dict:
        info["alignment_rms"] = float(self.operator.shifts.pow(2).sum(1).mean().sqrt())
        return info

    def summary(self) -> dict:
        return operator_summary(self.operator, self.every)

    def state_dict(self) -> dict:
        return dict(self.inner.state_dict(), alignment_shifts=self.operator.shifts.clone(),
                    alignment_angle=float(self.operator.angle), alignment_records=list(self.operator.records),
                    alignment_angle_se=float(getattr(self.operator, "angle_se", math.inf)),
                    alignment_angle_held=bool(getattr(self.operator, "held", False)))

    def load_state_dict(self, d: dict) -> None:
        d = dict(d)
        self.operator.shifts = d.pop("alignment_shifts").double()
        self.operator.angle = torch.tensor(float(d.pop("alignment_angle")), dtype=torch.float64)
        self.operator.records = list(d.pop("alignment_records"))
        self.operator.angle_se = float(d.pop("alignment_angle_se", math.inf))
        self.operator.held = bool(d.pop("alignment_angle_held", False))
        self.axis = self.operator.mode == "shifts+axis" and not self.operator.held
        self.inner.load_state_dict(d)


def find_aligned(operator) -> AlignedOperator | None:
    """The ``AlignedOperator`` in ``operator`` (itself, or under a ``RestrictedOperator``), else None."""
    while operator is not None and not isinstance(operator, AlignedOperator):
        operator = getattr(operator, "operator", None)
    return operator


def summary(problem) -> dict:
    """``result.alignment`` of a run on ``problem``: the mode, gauge, interpolation, shifts (px, per projection),
    tilt angles (deg), the tilt-axis angle (deg), the number of estimates and of parameters at their bound; ``{}``
    without alignment."""
    op = find_aligned(getattr(problem, "ray_transform", None))
    return {} if op is None else operator_summary(op)


def operator_summary(op: AlignedOperator, every: int = ALIGN_EVERY) -> dict:
    """:func:`summary` of the aligned operator ``op`` (estimated every ``every`` iterations; an imported alignment
    used as it is, ``indreg.io.alignment_files``, is mode ``fixed``), with the tilt-axis angle's standard error when
    it was estimated (a warning when it is above :data:`MAX_ANGLE_SE_DEG`)."""
    fixed = not hasattr(op, "mode")
    out = {"mode": "fixed" if fixed else op.mode, "gauge": None if fixed else op.gauge,
           "interpolation": op.interpolation,
           "tilt_angles_deg": [math.degrees(float(t)) for t in op.operator.geometry.angles],
           "shifts_px": op.shifts.tolist(), "components": ["across", "along"][:op.components],
           "axis_angle_deg": math.degrees(float(op.angle)), "estimates": len(getattr(op, "records", ())),
           "every": every, "at_bound": getattr(op, "at_bound", 0)}
    if not fixed and op.mode == "shifts+axis" and op.records:
        se = getattr(op, "angle_se", math.inf)
        stack = getattr(op, "stack_estimate", None)
        out["axis_angle_source"] = "stack" if getattr(op, "held", False) else "fit"
        if stack is not None:
            out["axis_angle_stack_deg"] = stack.angle_deg if math.isfinite(stack.angle_deg) else None
            out["axis_angle_stack_se_deg"] = stack.se_deg if math.isfinite(stack.se_deg) else None
        out["axis_angle_se_deg"] = se if math.isfinite(se) else None
        out["axis_angle_determined"] = se <= MAX_ANGLE_SE_DEG and (stack is None or stack.determined)
        if se > MAX_ANGLE_SE_DEG:
            log.warning("the tilt-axis angle is not determined by the data: %.3f deg with a standard error of %s deg "
                        "(above %g; the data cannot tell a turn of the axis from a turn of the object about the "
                        "beam): measure the angle beforehand and rotate the stack, or use align='shifts'",
                        math.degrees(float(op.angle)), f"{se:.3f}" if math.isfinite(se) else "inf",
                        MAX_ANGLE_SE_DEG)
    return out


def plot_shifts(alignment: dict, path: str | Path) -> None:
    """Shifts (px) against the tilt angle (deg), one line per component, the axis angle in the title when it was
    estimated (a mode with ``axis``)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    shifts = torch.tensor(alignment["shifts_px"])
    for i, name in enumerate(alignment["components"]):
        ax.plot(alignment["tilt_angles_deg"], shifts[:, i].numpy(), "o-", ms=3, label=f"{name} the tilt axis")
    ax.set_xlabel("tilt angle (deg)")
    ax.set_ylabel("shift (px)")
    angle = f": tilt-axis angle {alignment['axis_angle_deg']:.3f} deg" if "axis" in alignment["mode"] else \
        " (tilt-axis angle not estimated)"
    ax.set_title(f"alignment ({alignment['mode']}){angle}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def wrap(solver, operator, data: torch.Tensor, label: str = "align"):
    """``solver`` with the alignment of ``operator`` (from :func:`aligned`) in the fit: an :class:`AlignmentSolver`;
    ``solver`` itself when ``operator`` is not aligned. One-line error for solver='fast' (its coarse levels have
    no aligned operator)."""
    if not isinstance(operator, AlignedOperator) or not hasattr(operator, "mode"):   # none, or a fixed alignment
        return solver
    from .solvers import MultilevelSolver

    if isinstance(solver, MultilevelSolver):
        raise ValueError(f"{label}={operator.mode!r} needs solver='algorithm1' or a torch.optim solver, not 'fast'")
    return AlignmentSolver(solver, operator, data)
