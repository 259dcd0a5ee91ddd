"""Alignment by gold fiducials: beads found in every view, tracked through the series and fitted by a rigid
specimen, as IMOD's ``beadtrack`` and ``tiltalign`` do it.

A gold bead is a small dense sphere: in line integrals a bright round spot a few pixels wide, far above the
specimen's contrast, at every tilt (it projects to a disc whatever the angle). Where a slab carries them (most
cryo-ET specimens: beads on both faces of the ice), their positions measure every view's shift directly, with no
reconstruction and no part of the specimen that must stay inside the detector.

Notes
-----
- The model (the axis frame of ``indreg.alignment.xcorr``: x across the tilt axis, y along it): bead ``j`` at
  ``(X_j, Y_j, Z_j)`` in the specimen lies in view ``k`` at ``q = (X_j cos(theta_k) + Z_j sin(theta_k), Y_j)``,
  and the raw view holds it at ``p = R(alpha) (q + v_k)``. Linear in the beads and the shifts for a given angle
  ``alpha``: one least-squares problem across the axis (``X, Z, v_across``) and one along it (``Y, v_along``).
- Gauge: a translation of the specimen moves the shifts by ``a cos + b sin`` across and a constant along; the
  solution takes the gauge of the shifts it started from (least squares over the views with beads), so views
  without beads keep theirs.
- Detection: maxima of the scale-normalised Laplacian of Gaussian ``-s^2 LoG_s`` above :data:`BEAD_SNR` times
  its robust standard deviation (1.4826 MAD over the view), the position refined by a parabola through the
  logarithms of the peak and its neighbours (exact for a Gaussian). The scale ``s``: the one of
  :data:`SCALES_PX` where the view nearest zero tilt's :data:`BEAD_COUNT`-th strongest maximum is largest
  against that spread (a bead of diameter ``D`` answers most at ``s`` near ``D / (2 sqrt 2)``).
- Tracking (``beadtrack``'s way): the beads of the view nearest zero tilt are the seeds; the other views follow
  outward in order of ``|theta|``, each matched to the model's prediction and the model solved again after it, so
  the beads' depths are known before the high tilts need them; a view's offset from the prediction is voted over
  all prediction-detection pairs within :data:`WINDOW_PX` (a start tens of pixels off is found), then each
  predicted bead takes its nearest detection within :data:`START_RADIUS_PX` (a detection two beads claim is
  dropped). Then all views are matched and solved again until the matches stop changing, the radius four times
  the residual (at least :data:`MIN_RADIUS_PX`); a seed found in fewer than half the views is no bead.
- The tilt axis: the residual of the fit over trial angles ``alpha +- AXIS_SPAN_DEG``, the vertex of the
  parabola through the best and its neighbours; its standard error from the parabola's curvature (the residual
  sum of squares' rise by one noise variance).
- Determined where at least :data:`MIN_BEADS` beads are each found in at least half the views, every view holds
  at least two of them, and the fit's residual is below :data:`MAX_RESIDUAL_PX`; else the reason is given.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .xcorr import _rotation

__all__ = ["BEAD_SNR", "FiducialAlignment", "bead_residual", "bead_scale", "detect_beads", "fiducial_alignment"]

#: Detection threshold: the LoG response over its robust standard deviation.
BEAD_SNR = 5.0
#: Trial LoG scales (full-size px): beads of about 3 to 25 px across.
SCALES_PX = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 8.0)
#: The rank of the maximum that picks the scale (a handful of beads is enough).
BEAD_COUNT = 5
#: Half-width (full-size px) of the vote for a view's offset from the model.
WINDOW_PX = 40.0
#: The first match radius and the smallest one (full-size px).
START_RADIUS_PX, MIN_RADIUS_PX = 10.0, 3.0
#: Fewest beads for a determined fit, and the largest residual (full-size px RMS) it may leave.
MIN_BEADS, MAX_RESIDUAL_PX = 4, 2.0
#: The tilt-axis search: half-span and step (degrees).
AXIS_SPAN_DEG, AXIS_STEP_DEG = 1.5, 0.25


def _response(image: np.ndarray, s: float) -> tuple:
    """``(-s^2 LoG_s image, its robust standard deviation)``."""
    from scipy.ndimage import gaussian_laplace

    r = -s * s * gaussian_laplace(np.asarray(image, dtype=np.float64), s)
    return r, 1.4826 * float(np.median(np.abs(r - np.median(r)))) + 1e-30


def _maxima(r: np.ndarray, s: float) -> np.ndarray:
    """Flat indices of the local maxima of ``r`` over a ``2s + 1`` square, the border of ``s`` px left out."""
    from scipy.ndimage import maximum_filter

    peak = r == maximum_filter(r, size=2 * int(s) + 1)
    m = max(int(math.ceil(s)), 1)
    peak[:m], peak[-m:], peak[:, :m], peak[:, -m:] = False, False, False, False
    return np.flatnonzero(peak)


def bead_scale(image: np.ndarray) -> float:
    """The LoG scale at which the beads of ``image`` answer most (module Notes).

    Parameters
    ----------
    image : numpy.ndarray
        ``(ny, nx)`` one view in line integrals (beads bright), best the one nearest zero tilt.

    Returns
    -------
    float
        One of :data:`SCALES_PX` (px).
    """
    best, scale = -1.0, SCALES_PX[0]
    for s in SCALES_PX:
        r, sd = _response(image, s)
        values = np.sort(r.flat[_maxima(r, s)])[::-1]
        score = values[min(BEAD_COUNT, values.size) - 1] / sd if values.size else 0.0
        if score > best:
            best, scale = score, s
    return float(scale)


def detect_beads(image: np.ndarray, scale: float, snr: float = BEAD_SNR) -> np.ndarray:
    """Beads of one view (module Notes).

    Parameters
    ----------
    image : numpy.ndarray
        ``(ny, nx)`` line integrals (beads bright).
    scale : float
        The LoG scale (px; :func:`bead_scale`).
    snr : float
        The threshold: the response over its robust spread.

    Returns
    -------
    numpy.ndarray
        ``(n, 3)`` rows ``(x, y, strength)``: ``x`` across the columns and ``y`` down the rows from the image's
        centre (px, sub-pixel), ``strength`` the response over its spread.
    """
    r, sd = _response(image, scale)
    ny, nx = r.shape
    idx = _maxima(r, scale)
    idx = idx[r.flat[idx] > snr * sd]
    i, j = np.divmod(idx, nx)

    def vertex(lo, mid, hi):                  # a Gaussian's three-point fit: the parabola through the logarithms
        lo, mid, hi = (np.log(np.maximum(t, 1e-6 * mid)) for t in (lo, mid, hi))
        curve = lo - 2 * mid + hi
        return np.clip(np.where(curve < 0, 0.5 * (lo - hi) / np.where(curve < 0, curve, -1.0), 0.0), -0.5, 0.5)
    di = vertex(r[i - 1, j], r[i, j], r[i + 1, j])
    dj = vertex(r[i, j - 1], r[i, j], r[i, j + 1])
    return np.stack([j + dj - (nx - 1) / 2, i + di - (ny - 1) / 2, r[i, j] / sd], 1)


def _solve(obs: np.ndarray, angles: np.ndarray, nb: int) -> tuple:
    """The model's least squares (module Notes) for observations ``(k, j, qx, qy, ...)``: ``(X, Z, Y, v (K, 2),
    residuals (n, 2))``, the gauge left at ``v``'s smallest ``a cos + b sin`` across and mean along."""
    K = len(angles)
    k, j = obs[:, 0].astype(int), obs[:, 1].astype(int)
    n, rows = len(obs), np.arange(len(obs))
    A = np.zeros((n, 2 * nb + K))
    A[rows, j], A[rows, nb + j], A[rows, 2 * nb + k] = np.cos(angles[k]), np.sin(angles[k]), 1.0
    B = np.zeros((n, nb + K))
    B[rows, j], B[rows, nb + k] = 1.0, 1.0
    sx = np.linalg.lstsq(A, obs[:, 2], rcond=None)[0]
    sy = np.linalg.lstsq(B, obs[:, 3], rcond=None)[0]
    res = np.stack([obs[:, 2] - A @ sx, obs[:, 3] - B @ sy], 1)
    X, Z, Y, v = sx[:nb], sx[nb:2 * nb], sy[:nb], np.stack([sx[2 * nb:], sy[nb:]], 1)
    seen = np.bincount(k, minlength=K) > 0
    G = np.stack([np.cos(angles), np.sin(angles)], 1)
    ab = np.linalg.lstsq(G[seen], v[seen, 0], rcond=None)[0]
    c = v[seen, 1].mean()
    v[:, 0] -= G @ ab
    v[:, 1] -= c
    v[~seen] = 0.0
    return X + ab[0], Z + ab[1], Y + c, v, res


def _offset(pred: np.ndarray, points: np.ndarray, window: float) -> np.ndarray:
    """The view's offset from the model: the densest 3 px cell of all prediction-detection differences within
    ``window``, refined by their median within 2 px."""
    diff = (points[None, :, :] - pred[:, None, :]).reshape(-1, 2)
    diff = diff[np.all(np.abs(diff) < window, 1)]
    if diff.size == 0:
        return np.zeros(2)
    edges = np.arange(-math.ceil(window), math.ceil(window) + 1.0, 1.0)
    h = np.histogram2d(diff[:, 0], diff[:, 1], bins=(edges, edges))[0]
    from scipy.ndimage import uniform_filter

    i, j = np.unravel_index(np.argmax(uniform_filter(h, 3, mode="constant")), h.shape)
    centre = np.array([edges[i] + 0.5, edges[j] + 0.5])
    near = diff[np.linalg.norm(diff - centre, axis=1) < 2.0]
    return np.median(near, 0) if near.size else centre


def _match(pred: np.ndarray, points: np.ndarray, radius: float) -> tuple:
    """``(bead indices, detection indices)``: each predicted bead's nearest detection within ``radius``, those
    two beads claim dropped."""
    from scipy.spatial import cKDTree

    if points.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    dist, nearest = cKDTree(points).query(pred, distance_upper_bound=radius)
    ok = np.isfinite(dist)
    counts = np.bincount(nearest[ok], minlength=len(points))
    ok &= counts[np.minimum(nearest, len(points) - 1)] == 1
    return np.flatnonzero(ok), nearest[ok]


def _matched(k: int, points: np.ndarray, model: tuple, angles: np.ndarray, radius: float, window: float) -> list:
    """View ``k``'s rows ``(k, bead, qx, qy, detection)``: the model's predictions moved by the voted offset, each
    matched to its nearest detection within ``radius``."""
    X, Z, Y, v = model
    pred = np.stack([X * math.cos(angles[k]) + Z * math.sin(angles[k]), Y], 1) + v[k]
    j, i = _match(pred, points - _offset(pred, points, window), radius)
    return [(k, jj, *points[ii], ii) for jj, ii in zip(j, i)]


def _rows(rows: list) -> np.ndarray:
    return np.array(rows, dtype=np.float64).reshape(-1, 5)


def _track(points: list, angles: np.ndarray) -> tuple:
    """Seeds, then view by view outward from the zero tilt, then match and solve over all views until the matches
    stop changing (module Notes): ``(obs, X, Z, Y, v, res)``, ``obs`` rows ``(view, bead, qx, qy, detection)``,
    fewer than 3 where nothing could be tracked."""
    K = len(angles)
    order = np.argsort(np.abs(angles), kind="stable")
    seeds = points[order[0]]
    nb = len(seeds)
    model = (seeds[:, 0] / math.cos(angles[order[0]]), np.zeros(nb), seeds[:, 1].copy(), np.zeros((K, 2)))
    rows = [(order[0], j, *seeds[j], j) for j in range(nb)]
    res = np.zeros((0, 2))
    for k in order[1:]:                                   # beadtrack's way: the model grows with the views
        rows += _matched(k, points[k], model, angles, START_RADIUS_PX, WINDOW_PX)
        if len(rows) >= 3:
            *model, res = _solve(_rows(rows), angles, nb)
    radius, previous, obs = START_RADIUS_PX, None, _rows(rows)
    for _ in range(8):
        if len(obs) < 3:
            return obs, *model, res
        if previous is not None and obs[:, :2].tobytes() == previous:
            break
        previous = obs[:, :2].tobytes()
        *model, res = _solve(obs, angles, nb)
        radius = max(MIN_RADIUS_PX, 4 * float(np.sqrt((res ** 2).sum(1).mean())))
        obs = _rows([r for k in range(K) for r in _matched(k, points[k], model, angles, radius, 3 * radius)])
    seen = np.bincount(obs[:, 1].astype(int), minlength=nb)
    kept = seen >= K / 2                                  # a seed found in fewer views is no bead
    obs = obs[kept[obs[:, 1].astype(int)]]
    obs[:, 1] = (np.cumsum(kept) - 1)[obs[:, 1].astype(int)]
    if len(obs) < 3:
        X, Z, Y, v = model
        return obs, X[kept], Z[kept], Y[kept], v, np.zeros((0, 2))
    return obs, *_solve(obs, angles, int(kept.sum()))


def _in_frame(raw_points: list, alpha_deg: float, shifts: np.ndarray) -> list:
    """Raw positions ``p`` as axis-frame positions ``q = R(alpha)^T p - v`` (module Notes)."""
    R = _rotation(alpha_deg)
    return [p @ R - s for p, s in zip(raw_points, shifts)]


def _refit(obs: np.ndarray, raw: np.ndarray, angles: np.ndarray, alpha_deg: float, start: np.ndarray) -> tuple:
    """The matches ``obs`` (raw positions ``raw``) solved for the tilt axis ``alpha_deg``: ``_solve``'s tuple."""
    k = obs[:, 0].astype(int)
    moved = obs.copy()
    moved[:, 2:4] = raw @ _rotation(alpha_deg) - start[k]
    return _solve(moved, angles, int(obs[:, 1].max()) + 1)


def _axis(obs: np.ndarray, raw: np.ndarray, angles: np.ndarray, alpha_deg: float, start: np.ndarray) -> tuple:
    """``(angle, standard error)`` degrees from the fit's residual over trial angles (module Notes); ``(None,
    reason)`` where the best lies at the scan's end or the parabola has no minimum."""
    trials = alpha_deg + np.arange(-AXIS_SPAN_DEG, AXIS_SPAN_DEG + 1e-9, AXIS_STEP_DEG)
    rss = np.array([(_refit(obs, raw, angles, a, start)[4] ** 2).sum() for a in trials])
    i = int(np.argmin(rss))
    if i in (0, len(trials) - 1):
        return None, f"the smallest residual lies at the search's end ({trials[i]:.2f} deg)"
    curve = (rss[i - 1] - 2 * rss[i] + rss[i + 1]) / AXIS_STEP_DEG ** 2
    if curve <= 0:
        return None, "the residual has no minimum over the tilt-axis angle"
    best = trials[i] + 0.5 * AXIS_STEP_DEG * (rss[i - 1] - rss[i + 1]) / (rss[i - 1] - 2 * rss[i] + rss[i + 1])
    dof = max(2 * len(obs) - 3 * (int(obs[:, 1].max()) + 1) - 2 * len(angles), 1)
    return float(best), float(math.sqrt(2 * rss[i] / dof / curve))


@dataclass
class FiducialAlignment:
    """:func:`fiducial_alignment`'s result.

    Attributes
    ----------
    determined : bool
        Whether the beads fix the shifts (module Notes); ``reason`` says why not.
    shifts : numpy.ndarray
        ``(K, 2)`` px (axis frame, across / along, in the starting shifts' gauge); the start where not determined.
    scale_px : float
        The detection's LoG scale.
    beads : numpy.ndarray
        ``(n, 3)`` the tracked beads' ``(X, Y, Z)`` px.
    observations : int
        Matched bead positions over all views.
    residual_px : tuple
        RMS (across, along) of the fit.
    angle_deg, angle_se_deg : float or None
        The tilt axis from the beads (with ``search_axis``) and its standard error.
    reason : str
    per_view : numpy.ndarray
        ``(K,)`` beads found in each view.
    positions : numpy.ndarray
        ``(n, 4)`` rows ``(view, bead, x, y)``: every matched bead where the raw view holds it (px from its centre).
    """
    determined: bool
    shifts: np.ndarray
    scale_px: float
    beads: np.ndarray
    observations: int
    residual_px: tuple
    angle_deg: float | None = None
    angle_se_deg: float | None = None
    reason: str = ""
    per_view: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def record(self) -> dict:
        """The JSON record (``align.json``'s ``slab.fiducials``)."""
        return {"determined": self.determined, "reason": self.reason, "beads": len(self.beads),
                "observations": self.observations, "residual_px": list(self.residual_px),
                "scale_px": self.scale_px, "angle_deg": self.angle_deg, "angle_se_deg": self.angle_se_deg,
                "per_view": [int(n) for n in self.per_view]}

    def describe(self) -> str:
        """One log line."""
        head = (f"{len(self.beads)} beads (LoG scale {self.scale_px:g} px), {self.observations} positions, "
                f"residual {self.residual_px[0]:.2f} / {self.residual_px[1]:.2f} px across / along")
        if self.angle_deg is not None:
            head += f", tilt axis {self.angle_deg:.3f} +- {self.angle_se_deg:.3f} deg"
        return head if self.determined else f"not determined ({self.reason}); {head}"


def _verdict(per_bead: np.ndarray, per_view: np.ndarray, residual: tuple, views: int) -> str:
    """Why the fit does not fix the shifts, or ``""`` (module Notes)."""
    kept = int((per_bead >= views / 2).sum())
    if kept < MIN_BEADS:
        return f"{kept} beads found in half the views or more, {MIN_BEADS} needed"
    if per_view.min() < 2:
        return f"{int((per_view < 2).sum())} view(s) hold fewer than 2 beads"
    if max(residual) > MAX_RESIDUAL_PX:
        return f"the beads do not fit a rigid specimen (residual {max(residual):.2f} px > {MAX_RESIDUAL_PX})"
    return ""


def fiducial_alignment(lines: np.ndarray, angles_rad: np.ndarray, alpha_deg: float, shifts: np.ndarray,
                       search_axis: bool = False) -> FiducialAlignment:
    """Align a tilt series by the gold beads it holds (module docstring).

    Parameters
    ----------
    lines : numpy.ndarray
        ``(K, ny, nx)`` line integrals of the raw stack (beads bright), the tilt axis at ``alpha_deg`` from Y.
    angles_rad : numpy.ndarray
        Tilt angles, radians.
    alpha_deg : float
        The tilt axis' angle from Y, counter-clockwise (degrees).
    shifts : numpy.ndarray
        ``(K, 2)`` starting shifts, full-size px in the axis frame (``indreg.alignment.xcorr``'s Notes); tens of
        pixels off is enough.
    search_axis : bool
        Also estimate the tilt axis' angle from the beads (module Notes).

    Returns
    -------
    FiducialAlignment
    """
    K, ny, nx = lines.shape
    angles = np.asarray(angles_rad, dtype=np.float64)
    start = np.asarray(shifts, dtype=np.float64)
    scale = bead_scale(lines[int(np.argmin(np.abs(angles)))])
    raw = [detect_beads(view, scale)[:, :2] for view in lines]
    obs, X, Z, Y, v, res = _track(_in_frame(raw, alpha_deg, start), angles)
    if len(obs) < 3:
        return FiducialAlignment(False, start, scale, np.zeros((0, 3)), 0, (0.0, 0.0),
                                 reason="no bead tracked", per_view=np.zeros(K, int))
    k, j = obs[:, 0].astype(int), obs[:, 1].astype(int)
    per_view = np.bincount(k, minlength=K)
    residual = tuple(float(r) for r in np.sqrt((res ** 2).mean(0)))
    reason = _verdict(np.bincount(j, minlength=len(Y)), per_view, residual, K)
    raw_obs = np.array([raw[kk][int(ii)] for kk, ii in zip(k, obs[:, 4])])
    result = FiducialAlignment(not reason, start + v if not reason else start, scale, np.stack([X, Y, Z], 1),
                               len(obs), residual, reason=reason, per_view=per_view,
                               positions=np.column_stack([k, j, raw_obs]))
    if search_axis and not reason:
        found, se = _axis(obs, raw_obs, angles, alpha_deg, start)
        if found is None:
            result.reason = se
        else:
            result.angle_deg, result.angle_se_deg = found, se
            result.shifts = start + _refit(obs, raw_obs, angles, found, start)[3]
    return result


def bead_residual(result: FiducialAlignment, angles_rad: np.ndarray, alpha_deg: float, shifts: np.ndarray) -> tuple:
    """RMS (across, along) px of the beads' fit with the shifts held at ``shifts`` (``(K, 2)``, axis frame of
    ``alpha_deg``: another tool's alignment, say): only the beads' positions solved, so any gauge of ``shifts``
    scores alike.

    Parameters
    ----------
    result : FiducialAlignment
        A fit whose ``positions`` hold the matched beads.
    angles_rad : numpy.ndarray
        Tilt angles, radians.
    alpha_deg : float
        The tilt axis' angle from Y (degrees).
    shifts : numpy.ndarray
        ``(K, 2)`` px.

    Returns
    -------
    tuple
        ``(across, along)`` px.
    """
    k, j = result.positions[:, 0].astype(int), result.positions[:, 1].astype(int)
    q = result.positions[:, 2:4] @ _rotation(alpha_deg) - np.asarray(shifts, dtype=np.float64)[k]
    nb, rows = int(j.max()) + 1, np.arange(len(k))
    A = np.zeros((len(k), 2 * nb))
    A[rows, j], A[rows, nb + j] = np.cos(angles_rad[k]), np.sin(angles_rad[k])
    across = q[:, 0] - A @ np.linalg.lstsq(A, q[:, 0], rcond=None)[0]
    along = q[:, 1] - (np.bincount(j, q[:, 1], nb) / np.bincount(j, minlength=nb))[j]
    return float(np.sqrt((across ** 2).mean())), float(np.sqrt((along ** 2).mean()))
