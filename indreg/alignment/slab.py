"""Projection matching of a slab specimen (wider than the detector) through the wide box, coarse to fine.

Every round: the views resampled into the axis frame at the current shifts (``indreg.alignment.xcorr``), a
weighted back-projection (WBP) of them into the wide box (``indreg.forward.wide_box``: every ray that reaches the
detector stays inside it), and each view matched against the re-projection of that volume *less its own
contribution* (leave-one-out: a view's own back-projection would pull the match towards its current shift): the
band-passed, tapered cross-correlation's peak moves the view. The cross-correlation with cosine stretching starts
it (``indreg.alignment.xcorr.coarse_alignment``).

Notes
-----
- Line integrals in, a stack ``(K, ny, nx)`` (``indreg.units.transmission`` turns intensities into them); shifts
  ``(K, 2)`` in pixels of the full-size stack, across / along the tilt axis in the axis frame
  (``indreg.alignment.xcorr``'s Notes); levels binned by powers of 2 (``indreg.alignment.app.levels``).
- Leave-one-out: with ``q`` the WBP-filtered views and ``x = T^* q``, view ``k``'s reference is ``T_k x -
  T_k T_k^* q_k`` (``T_k`` the view's own operator on the same wide box), exact for the discretised operator.
- Each view is compared where every view sees the same part of the slab: ``|s| <= (W / 2) cos(theta_k)``
  across the axis (the mid-plane seen at tilt 0), tapered; both images high-passed (a Gaussian of
  :data:`HIGHPASS_PX` px subtracted) before the WBP and the match, so the slab's smooth thickness profile and
  the detector's edges take no part.
- Gauge: across the axis ``a cos(theta) + b sin(theta)`` (a translation of the specimen) is removed every
  round, along it the mean; what is left is what the data determine.
- The box: ``thickness`` px deep about the depth ``centre`` (px from the volume's middle), widened so that every
  ray of every tilt through it reaches it (``indreg.forward.wide_box.wide_box``). :func:`specimen_depth`
  measures the depth from a WBP of a thick box.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .xcorr import BAND, TAPER, axis_frame, coarse_alignment, correlate, taper_window

__all__ = ["HIGHPASS_PX", "SEARCH_PX", "SlabAlignment", "aligned_slab_operator", "binned", "gauge_fix",
           "leave_one_out", "match_views", "slab_operators", "slab_projection_matching", "specimen_depth"]

log = logging.getLogger("indreg.align")

#: Gaussian width (px of the level) of the smooth part subtracted before the WBP and the match.
HIGHPASS_PX = 8.0
#: Largest move of a view in one round (px of the level): the cross-correlation starts it within a few pixels, and
#: a wider search lets a weak view (the highest tilts of a slab) jump to a false peak.
SEARCH_PX = 3.0


def binned(stack: np.ndarray, b: int) -> np.ndarray:
    """Block means ``b x b`` of every view (the remainder cropped about the middle, as
    ``indreg.alignment.moments.binned``)."""
    from .moments import binned as _binned

    return np.asarray(_binned(np.asarray(stack, dtype=np.float64), b), dtype=np.float64)


def _highpass(frames: np.ndarray, sigma: float = HIGHPASS_PX) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return np.stack([f - gaussian_filter(f, sigma, mode="reflect") for f in frames])


def _slab_box(nx: int, ny: int, thickness: float, centre: float, box_angles: np.ndarray) -> tuple:
    """``(box, make)``: the wide box of the slab widened for ``box_angles`` and ``make(theta)``, the tilt series'
    operator of the given box (unit voxels, the detector ``nx`` pixels wide)."""
    import torch

    from ..domain import ImageDomain
    from ..forward import TiltSeriesGeometry, TiltSeriesTransform
    from ..forward.wide_box import wide_box

    nz = max(int(round(thickness)), 2)
    domain = ImageDomain((nx, ny, nz), (-nx / 2, -ny / 2, centre - nz / 2), (nx / 2, ny / 2, centre + nz / 2))

    def make(theta):
        return TiltSeriesTransform(domain, TiltSeriesGeometry(torch.as_tensor(theta, dtype=torch.float64), nx,
                                                              -nx / 2, nx / 2, angle_unit="rad"))
    return wide_box(make(np.asarray(box_angles, dtype=np.float64))), make


def slab_operators(angles_rad: np.ndarray, nx: int, ny: int, thickness: float, centre: float = 0.0,
                   box_angles: np.ndarray | None = None) -> tuple:
    """The tilt series' operator on the wide box (unit voxels, the detector ``nx`` pixels wide) of a slab
    ``thickness`` px deep about the depth ``centre``, and one operator per view on the same box; the box is
    widened for ``box_angles`` (default the angles themselves: give the whole series' to compare subsets)."""
    theta = np.asarray(angles_rad, dtype=np.float64)
    box, make = _slab_box(nx, ny, thickness, centre, theta if box_angles is None else box_angles)
    return box.widen(make(theta)), [box.widen(make(theta[k:k + 1])) for k in range(len(theta))]


def aligned_slab_operator(angles_rad: np.ndarray, nx: int, ny: int, thickness: float, alpha_deg: float,
                          shifts: np.ndarray, centre: float = 0.0, box_angles: np.ndarray | None = None,
                          interpolation: str = "linear"):
    """:func:`slab_operators`' operator with the alignment ``(alpha_deg, shifts)`` in it (the axis frame's:
    ``shifts`` ``(K, 2)`` px of these views, ``indreg.alignment.xcorr``'s Notes), applied to the projections as
    the maps ``M = R(alpha)``, ``d = R(alpha) v`` (``indreg.alignment.files.to_operator``), so that the raw views
    are compared and fitted without being resampled. ``interpolation="linear"`` keeps the matrix nonnegative (SIRT
    needs it; cubic convolution's weights are not)."""
    from .files import Alignment, to_operator
    from .xcorr import _rotation

    theta = np.asarray(angles_rad, dtype=np.float64)
    M = _rotation(alpha_deg)
    maps = Alignment(np.tile(M, (len(theta), 1, 1)), np.asarray(shifts, dtype=np.float64) @ M.T,
                     np.degrees(theta), np.arange(len(theta)))
    box, make = _slab_box(nx, ny, thickness, centre, theta if box_angles is None else box_angles)
    return box.widen(to_operator(make(theta), maps, interpolation=interpolation))


def _filtered(T, frames):
    """The WBP-filtered views (Hamming-windowed ramp, padded; each tilt weighted by its quadrature cell)."""
    import torch

    from ..forward.fbp import fbp_filter

    y = torch.from_numpy(np.ascontiguousarray(frames))
    g, m = T.geometry, y.shape[-1]
    response = fbp_filter(m, g.det_cell, "hamming", 1.0, True, y.dtype, y.device)
    q = torch.fft.irfft(torch.fft.rfft(y, n=2 * m, dim=-1) * response, n=2 * m, dim=-1)[..., :m]
    return (q * (g.angle_weights / g.angle_cell).to(q)[:, None, None]).contiguous()


def leave_one_out(T, views: list, frames: np.ndarray) -> tuple:
    """Every view's reference: the re-projection of the WBP of ``frames`` (already high-passed) less the view's own
    contribution (module Notes). Returns ``(references (K, ny, nx), volume)`` as numpy arrays."""
    q = _filtered(T, frames)
    x = T.adjoint(q)
    P = T(x)
    for k, S in enumerate(views):
        weight = T.geometry.data_weight / S.geometry.data_weight   # T_k^* = this times S^*
        P[k] -= weight * S(S.adjoint(q[k:k + 1]))[0]
    return P.numpy(), x


def match_views(references: np.ndarray, frames: np.ndarray, angles_rad: np.ndarray, limit: tuple,
                band: tuple = BAND, taper: float = TAPER) -> tuple:
    """Each view's shift against its reference (``indreg.alignment.xcorr.correlate``) where every view sees the same
    part of the slab (module Notes), and the correlation coefficients: ``(d (K, 2), peaks (K,))``."""
    K, ny, nx = frames.shape
    d, peaks = np.zeros((K, 2)), np.zeros(K)
    for k in range(K):
        w = taper_window(ny, nx, taper, nx / 2 * abs(math.cos(angles_rad[k])))
        a = (frames[k] - (frames[k] * w).sum() / w.sum()) * w
        r = (references[k] - (references[k] * w).sum() / w.sum()) * w
        d[k], peaks[k] = correlate(r, a, limit, band)
    return d, peaks


def gauge_fix(shifts: np.ndarray, angles_rad: np.ndarray) -> np.ndarray:
    """``shifts`` less what a translation of the specimen explains: across ``a cos + b sin`` (least squares), along
    the mean."""
    B = np.stack([np.cos(angles_rad), np.sin(angles_rad)], 1)
    out = np.array(shifts, dtype=np.float64)
    out[:, 0] -= B @ np.linalg.lstsq(B, out[:, 0], rcond=None)[0]
    out[:, 1] -= out[:, 1].mean()
    return out


def specimen_depth(volume, field: tuple, fraction: float = 0.25) -> tuple:
    """``(thickness, centre)`` px of the specimen in a WBP ``volume`` ``(nx_w, ny, nz)`` of high-passed views: the
    planes whose mean square inside the detector's columns ``field`` (a slice) rises above ``fraction`` of the way
    from the emptiest plane's level to the fullest's; ``None`` when every plane does (the box too thin to tell)."""
    x = np.asarray(volume)[field]
    energy = (x.astype(np.float64) ** 2).mean(axis=(0, 1))
    lo, hi = float(np.percentile(energy, 10)), float(energy.max())
    full = np.flatnonzero(energy > lo + fraction * (hi - lo))
    if full.size == 0 or (full[0] == 0 and full[-1] == energy.size - 1):
        return None
    nz = energy.size
    return float(full[-1] - full[0] + 1), float((full[0] + full[-1]) / 2 - (nz - 1) / 2)


@dataclass
class SlabAlignment:
    """:func:`slab_projection_matching`'s result.

    Attributes
    ----------
    shifts : numpy.ndarray
        ``(K, 2)`` px of the full-size stack (axis frame, across / along, in the gauge).
    peaks : numpy.ndarray
        ``(K,)`` the last round's correlation coefficients.
    at_bound : numpy.ndarray
        ``(K, 2)`` whether a shift ended at its bound.
    bound : tuple
        ``(across, along)`` px.
    thickness, centre : float
        The box used at the finest level (px, full size).
    history : list
        One record per round.
    """
    shifts: np.ndarray
    peaks: np.ndarray
    at_bound: np.ndarray
    bound: tuple
    thickness: float
    centre: float
    history: list = field(default_factory=list)


def _round(lines_b, angles, alpha_deg, v, b, ops, bound_b, limit):
    """One round at binning ``b``: the shifts ``v`` (full-size px) moved by the views' matches; ``(v, d, peaks,
    volume)``."""
    frames = _highpass(axis_frame(lines_b, alpha_deg, v / b))
    references, volume = leave_one_out(*ops, frames)
    d, peaks = match_views(references, frames, angles, limit)
    v = np.clip(gauge_fix(v + d * b, angles), -np.array(bound_b) * b, np.array(bound_b) * b)
    return v, d * b, peaks, volume


def _depth(volume, nx: int, thickness: float, centre: float, margin: float = 0.25) -> tuple:
    """The box for the next rounds from a WBP ``volume``: the specimen's depth (:func:`specimen_depth`) widened by
    ``margin`` of it each side, about its centre; the box as it was where the volume cannot tell."""
    pad = (volume.shape[0] - nx) // 2
    found = specimen_depth(volume, (slice(pad, pad + nx),))
    if found is None:
        return thickness, centre, False
    depth, middle = found
    return depth * (1 + 2 * margin) + 4, centre + middle, True


def slab_projection_matching(lines: np.ndarray, angles_rad: np.ndarray, alpha_deg: float, levels: list,
                             rounds: list, thickness: float | None = None, bound: tuple | None = None,
                             start: np.ndarray | None = None, progress=None, centre: float = 0.0) -> SlabAlignment:
    """Align a slab's tilt series (module docstring): the stretched cross-correlation at the coarsest level
    (unless ``start``), then ``rounds[i]`` rounds of leave-one-out projection matching at binning ``levels[i]``.

    Parameters
    ----------
    lines : numpy.ndarray
        ``(K, ny, nx)`` line integrals of the raw stack (the tilt axis at ``alpha_deg`` from Y).
    angles_rad : numpy.ndarray
        Tilt angles, radians (indreg's sign; a mirror changes no shift).
    alpha_deg : float
        The tilt axis' angle from Y, counter-clockwise (degrees).
    levels, rounds : list
        Binnings, coarse to fine, and the rounds at each.
    thickness : float, optional
        The box's depth in full-size px; default: measured from a WBP of a box ``0.75 nx`` deep after the first
        round (:func:`specimen_depth`), that depth plus a quarter each side.
    bound : tuple, optional
        Largest ``|shift|`` (across, along) in full-size px; default a quarter of the stack's columns and rows.
    start : numpy.ndarray, optional
        ``(K, 2)`` starting shifts (full-size px, axis frame).
    progress : callable, optional
        ``progress(record)`` after every round.
    centre : float
        The box's depth centre (full-size px from the middle) with a given ``thickness``.

    Returns
    -------
    SlabAlignment
    """
    K, ny, nx = lines.shape
    angles = np.asarray(angles_rad, dtype=np.float64)
    bound = (0.25 * nx, 0.25 * ny) if bound is None else tuple(float(v) for v in bound)
    given = thickness is not None
    depth, centre = (float(thickness), float(centre)) if given else (0.75 * nx, 0.0)
    clock, history = time.perf_counter(), []
    v = None if start is None else np.asarray(start, dtype=np.float64).copy()
    for level, (b, count) in enumerate(zip(levels, rounds)):
        lines_b = binned(lines, b)
        bound_b = (bound[0] / b, bound[1] / b)
        if v is None:
            coarse = coarse_alignment(axis_frame(lines_b, alpha_deg), angles, bound_b)
            v = gauge_fix(coarse.shifts * b, angles)
            history.append({"bin": b, "round": "xcorr", "peak_mean": float(coarse.peaks.mean()),
                            "seconds": time.perf_counter() - clock})
        limit = (SEARCH_PX, SEARCH_PX)
        ops = slab_operators(angles, lines_b.shape[2], lines_b.shape[1], depth / b, centre / b)
        for r in range(count):
            v, d, peaks, volume = _round(lines_b, angles, alpha_deg, v, b, ops, bound_b, limit)
            record = {"bin": b, "round": r + 1, "largest_move_px": float(np.abs(d).max()),
                      "peak_mean": float(peaks.mean()), "thickness_px": depth, "centre_px": centre,
                      "seconds": time.perf_counter() - clock}
            history.append(record)
            if progress is not None:
                progress(record)
            if level == 0 and r == 0 and not given:
                depth_b, centre_b, found = _depth(volume.numpy(), lines_b.shape[2], depth / b, centre / b)
                depth, centre = depth_b * b, centre_b * b
                log.info("slab: the specimen's depth %s (%.0f px deep about %.0f, full size)",
                         "measured" if found else "not measured: the box kept", depth, centre)
                ops = slab_operators(angles, lines_b.shape[2], lines_b.shape[1], depth / b, centre / b)
    at = np.abs(v) >= np.array(bound) - 1e-6
    return SlabAlignment(v, peaks, at, bound, depth, centre, history)
