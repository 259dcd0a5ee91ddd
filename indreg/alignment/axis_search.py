"""The tilt axis' angle of a slab specimen by common lines over the part of the slab every view sees.

With the tilt axis right, every view's projection onto the axis (its sum across the axis) is the same 1D
profile of the specimen along the axis, up to a shift along it: the common line of all views. A trial angle off
by ``delta`` sums along a slanted direction: a feature at ``s`` across the axis lands ``delta * s`` away along it,
and ``s = x cos(theta) + z sin(theta)`` changes with the tilt, so the views' profiles disagree. A slab has no
edge inside the detector, so each view is summed over the columns that see the same part of the slab at every
tilt, ``|s| <= (W / 2) cos(theta_k)`` (the mid-plane's ``|x| <= W / 2``, tapered), after the shifts found so far
(``indreg.alignment.slab``); no reconstruction takes part, so no turn of the specimen about the beam can take the
angle up (the reason ``projection_matching``'s refinement is not trusted, docs/alignment.md).

Notes
-----
- The score of a trial angle: the mean over the views of the correlation coefficient of the view's
  high-passed profile with the views' mean profile, each view moved along the axis to its best match (within
  :data:`ALONG_PX` px, a parabola through the peak).
- The scan: ``alpha0 +- span`` every ``step`` degrees; the estimate is the vertex of the parabola through the
  best trial and its neighbours; the rows are split in halves (two independent parts of the specimen), each
  scanned alike, and the standard error is the larger of half the halves' difference and the whole's
  distance from their mean. Not determined (with the reason) where a best score lies at the scan's end, the
  parabola has no maximum, or the standard error exceeds :data:`MAX_SE_DEG`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .xcorr import axis_frame, taper_window

__all__ = ["ALONG_PX", "MAX_SE_DEG", "AxisSearch", "common_line_score", "search_axis_angle", "view_profiles"]

#: Above this standard error (degrees) the angle is reported as not determined.
MAX_SE_DEG = 0.2
#: Largest move of a view's profile along the axis in the score (px of the level).
ALONG_PX = 4
#: Gaussian width (px) of the smooth part subtracted from every profile.
PROFILE_HIGHPASS_PX = 8.0


def view_profiles(lines: np.ndarray, angles_rad: np.ndarray, alpha_deg: float, shifts: np.ndarray) -> np.ndarray:
    """``(K, rows)``: every view's weighted mean across the axis over the columns every view sees (module
    docstring), high-passed along the axis; ``shifts`` ``(K, 2)`` px of ``lines`` in the axis frame."""
    from scipy.ndimage import gaussian_filter1d

    frames = axis_frame(lines, alpha_deg, shifts)
    K, ny, nx = frames.shape
    out = np.empty((K, ny))
    for k in range(K):
        w = taper_window(ny, nx, 0.1, nx / 2 * abs(math.cos(angles_rad[k])))[ny // 2]
        out[k] = frames[k] @ w / w.sum()
    return out - gaussian_filter1d(out, PROFILE_HIGHPASS_PX, axis=1, mode="reflect")


def common_line_score(profiles: np.ndarray) -> float:
    """The mean correlation coefficient of every profile with the mean profile, each at its best shift along the
    axis within :data:`ALONG_PX` (Hann-windowed, zero-padded)."""
    K, n = profiles.shape
    window = np.hanning(n)
    mean = profiles.mean(0) * window
    M = np.fft.rfft(mean, 2 * n)
    lags = np.fft.fftfreq(2 * n, 1 / (2 * n))
    allowed = np.abs(lags) <= ALONG_PX
    total = 0.0
    for k in range(K):
        a = profiles[k] * window
        c = np.fft.irfft(np.fft.rfft(a, 2 * n) * M.conj(), 2 * n)
        norm = math.sqrt(float(a @ a) * float(mean @ mean))
        total += float(np.where(allowed, c, -np.inf).max()) / norm if norm > 0 else 0.0
    return total / K


def _vertex(x: np.ndarray, y: np.ndarray) -> tuple:
    """``(vertex, reason)``: the parabola's vertex through the best sample and its neighbours, or None and why."""
    i = int(np.argmax(y))
    if i == 0 or i == len(y) - 1:
        return None, f"the best score lies at the scan's end ({x[i]:.2f} deg)"
    c = np.polyfit(x[i - 1:i + 2], y[i - 1:i + 2], 2)
    if not c[0] < 0:
        return None, "the scores have no maximum"
    return float(-c[1] / (2 * c[0])), ""


@dataclass(frozen=True)
class AxisSearch:
    """:func:`search_axis_angle`'s result.

    Attributes
    ----------
    angle_deg : float or None
        The estimate (None when not found).
    se_deg : float or None
        Its standard error (None when not determined).
    determined : bool
        Whether the data determine it (module Notes).
    reason : str
        Why not, where not.
    halves_deg : tuple
        The two halves' estimates.
    scan : list
        ``(trial, score)`` pairs.
    """
    angle_deg: float | None
    se_deg: float | None
    determined: bool
    reason: str
    halves_deg: tuple = ()
    scan: list = field(default_factory=list)

    def describe(self) -> str:
        """One line for the log."""
        if self.angle_deg is None:
            return f"tilt-axis angle not determined: {self.reason}"
        se = "" if self.se_deg is None else f" +- {self.se_deg:.3f}"
        state = "" if self.determined else f" (not determined: {self.reason})"
        return f"tilt-axis angle from common lines: {self.angle_deg:.3f}{se} deg{state}"


def search_axis_angle(lines: np.ndarray, angles_rad: np.ndarray, alpha0_deg: float, shifts: np.ndarray,
                      span: float = 2.0, step: float = 0.25) -> AxisSearch:
    """Scan the tilt axis' angle by common lines (module docstring).

    Parameters
    ----------
    lines : numpy.ndarray
        ``(K, ny, nx)`` line integrals (any binning).
    angles_rad : numpy.ndarray
        Tilt angles (radians).
    alpha0_deg : float
        The angle the scan is centred on (degrees from Y, counter-clockwise).
    shifts : numpy.ndarray
        ``(K, 2)`` the views' shifts in px of ``lines`` (axis frame, ``indreg.alignment.xcorr``).
    span, step : float
        The scan's half width and step (degrees).

    Returns
    -------
    AxisSearch
    """
    trials = alpha0_deg + np.arange(-span, span + step / 2, step)
    half = lines.shape[1] // 2
    scores = np.array([[common_line_score(P), common_line_score(P[:, :half]), common_line_score(P[:, half:])]
                       for P in (view_profiles(lines, angles_rad, a, shifts) for a in trials)])
    scan = [(float(a), float(s)) for a, s in zip(trials, scores[:, 0])]
    whole, reason = _vertex(trials, scores[:, 0])
    parts = [_vertex(trials, scores[:, i]) for i in (1, 2)]
    if whole is None:
        return AxisSearch(None, None, False, reason, (), scan)
    if any(p[0] is None for p in parts):
        why = next(p[1] for p in parts if p[0] is None)
        return AxisSearch(whole, None, False, f"a half of the rows: {why}", (), scan)
    halves = (parts[0][0], parts[1][0])
    se = max(abs(halves[0] - halves[1]) / 2, abs(whole - sum(halves) / 2))
    ok = se <= MAX_SE_DEG
    reason = "" if ok else f"standard error {se:.3f} deg above {MAX_SE_DEG}"
    return AxisSearch(whole, se, ok, reason, halves, scan)
