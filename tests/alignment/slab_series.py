"""A synthetic slab tilt series made without indreg (numpy only): Gaussian blobs in a slab much wider than the
detector and dense beads on its two faces, projected analytically (a 3D Gaussian of width ``s`` and amplitude
``a`` integrates along any line to ``a s sqrt(2 pi) exp(-d^2 / 2 s^2)``, ``d`` the line's distance from its
centre), a uniform slab ``mu t / cos(theta)``, known shifts and a tilt axis turned by ``alpha`` in the detector
(a feature at the ideal point ``q`` lands at ``p = R(alpha) q + s_k``), and Poisson counts of ``dose`` per pixel."""
import math

import numpy as np


#: Gold fiducials as on the measured cryo-ET series (docs/real_data_cryoet.md): beads about 10 px across (3 px
#: Gaussians), their LoG response 8-11 times its spread as the measured beads' 9-38 (the measured stack's noise is
#: below 40 counts' Poisson noise, so their contrast, 0.5 in line integrals, is doubled here), dense enough for a
#: 128 px detector.
GOLD = dict(bead_width=3.0, bead_amplitude=1.33, beads_per_px=0.0012)


def slab_series(width=64, rows=48, tilts=21, max_deg=60.0, thickness=20.0, alpha_deg=4.0, max_shift=8.0,
                dose=40.0, seed=0, blobs_per_px=0.1, beads_per_px=0.004, mu=0.004, bead_width=1.5, bead_amplitude=1.0):
    """``dict(intensities (K, rows, width), clean (line integrals), deg (IMOD-free: the geometry's angles), shifts
    (K, 2) px of the raw detector (x across columns, y along rows), alpha, dose, mu, features)``; ``features``: the
    centres ``X`` (across), ``Y`` (along), ``Z`` (depth), widths ``S`` and amplitudes ``A`` (the 3D Gaussian's
    is ``A / 10``); :data:`GOLD` makes the beads gold fiducials."""
    rng = np.random.default_rng(seed)
    deg = np.linspace(-max_deg, max_deg, tilts)
    theta = np.radians(deg)
    area = 3.5 * width * (rows + 20)
    n, m = int(blobs_per_px * area), int(beads_per_px * area)
    X = rng.uniform(-1.75 * width, 1.75 * width, n + m)
    Y = rng.uniform(-rows / 2 - 10, rows / 2 + 10, n + m)
    Z = np.concatenate([rng.uniform(-thickness / 2 + 2, thickness / 2 - 2, n),
                        rng.choice([-thickness / 2, thickness / 2], m)])
    S = np.concatenate([rng.uniform(1.0, 3.0, n), np.full(m, bead_width)])
    A = np.concatenate([rng.uniform(0.02, 0.1, n), np.full(m, bead_amplitude)])
    shifts = rng.uniform(-max_shift, max_shift, (tilts, 2))
    shifts[np.argmin(np.abs(deg))] = 0.0
    px, py = np.meshgrid(np.arange(width) - (width - 1) / 2, np.arange(rows) - (rows - 1) / 2)
    a = math.radians(alpha_deg)
    clean = np.empty((tilts, rows, width))
    for k in range(tilts):
        dx, dy = px - shifts[k, 0], py - shifts[k, 1]
        qs, qt = math.cos(a) * dx + math.sin(a) * dy, -math.sin(a) * dx + math.cos(a) * dy
        s = X * math.cos(theta[k]) + Z * math.sin(theta[k])
        near = np.abs(s) < width
        img = np.full((rows, width), mu * thickness / math.cos(theta[k]))
        for chunk in np.array_split(np.flatnonzero(near), max(1, near.sum() // 256)):
            r2 = (qs[None] - s[chunk, None, None]) ** 2 + (qt[None] - Y[chunk, None, None]) ** 2
            amp = (A[chunk] * S[chunk] * math.sqrt(2 * math.pi) / 10)[:, None, None]
            img += (amp * np.exp(-r2 / (2 * S[chunk, None, None] ** 2))).sum(0)
        clean[k] = img
    counts = rng.poisson(dose * np.exp(-clean)).astype(np.float64)
    return dict(intensities=counts, clean=clean, deg=deg, shifts=shifts, alpha=alpha_deg, dose=dose, mu=mu,
                features=dict(X=X, Y=Y, Z=Z, S=S, A=A))


def axis_frame_shifts(shifts: np.ndarray, alpha_deg: float) -> np.ndarray:
    """The raw detector's shifts ``s_k`` as the axis frame's ``v_k = R(alpha)^T s_k`` (indreg.alignment.xcorr)."""
    a = math.radians(alpha_deg)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return shifts @ R


def gauge_rms(v: np.ndarray, truth: np.ndarray, deg: np.ndarray, constant: bool = False) -> tuple:
    """RMS (across, along) of ``v - truth`` with ``a cos + b sin`` (with ``constant`` also ``c``: the tilt axis'
    offset) removed across the axis and the mean along it."""
    theta = np.radians(deg)
    B = np.stack([np.cos(theta), np.sin(theta)] + ([np.ones_like(theta)] if constant else []), 1)
    e = v - truth
    across = e[:, 0] - B @ np.linalg.lstsq(B, e[:, 0], rcond=None)[0]
    along = e[:, 1] - e[:, 1].mean()
    return float(np.sqrt((across ** 2).mean())), float(np.sqrt((along ** 2).mean()))
