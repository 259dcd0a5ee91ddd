"""A registration on a synthetic slab aligned by indreg's slab alignment, against the same run on unshifted data.

The slab is ``tests/alignment/slab_series.py``'s (made with numpy only, not indreg's projector): Gaussian blobs over
3.5 detector widths and dense beads on both faces in a slab of ice, projected analytically, the tilt axis turned by
4 degrees in the detector, Poisson counts of 40 a pixel (a cryo-ET dose). Two series share every feature and every
count's draw: one unshifted, one with known shifts up to ``--max-shift`` px. The shifted one is aligned by
``slab_projection_matching`` (the stretched cross-correlation, then leave-one-out projection matching through the
wide box, bin 2 then bin 1: what ``indreg-align`` runs on a slab); the estimated shifts are taken in the gauge of the
true ones (``a cos + b sin`` across and the mean along, a translation of the specimen, moved to the truth's), since
the data cannot tell a translated specimen. Both stacks are resampled into the tilt axis' frame and registered
(LDDMM) from the same template, the truth's features each moved by a smooth field, on the same wide box. Printed:
the alignment's RMS error (px), and SSIM inside the field of view (the detector's columns) against the truth for
the registration on the unshifted data, on the shifted data resampled at the true shifts (what a perfect alignment
would give: a view shifted by ``v`` px lacks ``|v|`` px at one edge, filled by its nearest pixel) and on the aligned
data, and the differences.

With ``--gold`` the beads are gold fiducials as on the measured cryo-ET series, and the shifts are then fixed by
them (``indreg.alignment.fiducials``), as ``indreg-align`` does on a slab that holds them.

    python scripts/slab_registration_check.py [--width 128] [--rows 96] [--iters 40] [--seed 3] [--gold]
"""
from __future__ import annotations

import argparse
import math
from dataclasses import replace
import sys
import time
from pathlib import Path

import numpy as np
import torch

import indreg
from indreg import metrics
from indreg.alignment.fiducials import fiducial_alignment
from indreg.alignment.slab import slab_operators, slab_projection_matching
from indreg.alignment.xcorr import axis_frame

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "alignment"))
from slab_series import GOLD, axis_frame_shifts, gauge_rms, slab_series  # noqa: E402  (the test suite's slab, numpy)


def rasterise(features: dict, domain, mu: float, thickness: float, moved: bool) -> torch.Tensor:
    """The slab on ``domain``'s grid (x across, y along the axis, z depth; indreg's z is the series' ``-Z``): ``mu``
    inside ``|z| <= thickness / 2`` plus every feature, a Gaussian of amplitude ``A / 10`` and width ``S``;
    ``moved``: every centre displaced by a smooth field of 2 px (the template)."""
    X, Y, Z, S, A = (features[k] for k in ("X", "Y", "Z", "S", "A"))
    if moved:
        X = X + 2.0 * np.sin(2 * math.pi * Y / 24.0)
        Y = Y + 1.5 * np.sin(2 * math.pi * X / 40.0)
        Z = Z + 1.5 * np.cos(2 * math.pi * X / 60.0)
    axes = [a.numpy() for a in domain.axes()]
    vol = np.zeros(domain.shape)
    vol[:, :, np.abs(axes[2]) <= thickness / 2] = mu
    for x, y, z, s, a in zip(X, Y, -Z, S, A / 10.0):
        r = 3.5 * s
        sel = [np.flatnonzero(np.abs(ax - c) <= r) for ax, c in zip(axes, (x, y, z))]
        if any(len(i) == 0 for i in sel):
            continue
        gx, gy, gz = (np.exp(-(ax[i] - c) ** 2 / (2 * s * s)) for ax, i, c in zip(axes, sel, (x, y, z)))
        vol[np.ix_(*sel)] += a * gx[:, None, None] * gy[None, :, None] * gz[None, None, :]
    return torch.from_numpy(vol)


def in_gauge_of(v: np.ndarray, truth: np.ndarray, deg: np.ndarray) -> np.ndarray:
    """``v`` with its gauge part (``a cos + b sin`` across, the mean along) replaced by the truth's."""
    theta = np.radians(deg)
    B = np.stack([np.cos(theta), np.sin(theta)], 1)
    e = v - truth
    out = v.copy()
    out[:, 0] -= B @ np.linalg.lstsq(B, e[:, 0], rcond=None)[0]
    out[:, 1] -= e[:, 1].mean()
    return out


def register(template, truth, data, T, field, iters, sigma) -> tuple:
    """LDDMM from ``template`` to ``data``; ``(SSIM in the field of view, relative residual, seconds)``."""
    t0 = time.perf_counter()
    r = indreg.register(template.float(), data.float(), T, model="lddmm", sigma=sigma, max_iter=iters,
                        num_steps=10, wide_box=False, background=None, uncertainty=False,
                        split=False, progress=False)
    ssim = metrics.ssim(r.deformed.double()[field], truth[field])
    return ssim, float(r.residual), time.perf_counter() - t0


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--rows", type=int, default=96)
    p.add_argument("--tilts", type=int, default=41)
    p.add_argument("--thickness", type=float, default=40.0)
    p.add_argument("--max-shift", type=float, default=20.0)
    p.add_argument("--iters", type=int, default=40)
    p.add_argument("--sigma", type=float, default=4.0)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--gold", action="store_true", help="gold beads as on the measured cryo-ET series (slab_series' "
                                                       "docstring), the shifts then fixed by them as indreg-align does")
    a = p.parse_args(argv)
    kw = dict(width=a.width, rows=a.rows, tilts=a.tilts, thickness=a.thickness, seed=a.seed,
              **(GOLD if a.gold else {}))
    still, moving = slab_series(max_shift=0.0, **kw), slab_series(max_shift=a.max_shift, **kw)
    deg, alpha = moving["deg"], moving["alpha"]
    theta = -np.radians(deg)   # indreg's sign (tests/alignment/test_slab_alignment.py)
    lines = {name: -np.log(np.maximum(s["intensities"], 0.5) / s["dose"]) for name, s in
             (("unshifted", still), ("shifted", moving))}

    t0 = time.perf_counter()
    found = slab_projection_matching(lines["shifted"], theta, alpha, [2, 1], [6, 2])
    if a.gold:
        beads = fiducial_alignment(lines["shifted"], theta, alpha, found.shifts)
        print(f"fiducials: {beads.describe()}")
        found = replace(found, shifts=beads.shifts)
    seconds = time.perf_counter() - t0
    truth_v = axis_frame_shifts(moving["shifts"], alpha)
    across, along = gauge_rms(found.shifts, truth_v, deg)
    print(f"alignment: {across:.2f} / {along:.2f} px RMS across / along in the gauge ({seconds:.0f} s)")

    box_depth = a.thickness + 8.0
    T, _ = slab_operators(theta, a.width, a.rows, box_depth)
    domain = T.domain
    features = moving["features"]
    truth = rasterise(features, domain, moving["mu"], a.thickness, moved=False)
    template = rasterise(features, domain, moving["mu"], a.thickness, moved=True)
    stacks = {"unshifted": axis_frame(lines["unshifted"], alpha),
              "shifted, the true shifts": axis_frame(lines["shifted"], alpha, truth_v),
              "aligned": axis_frame(lines["shifted"], alpha, in_gauge_of(found.shifts, truth_v, deg))}
    clean = torch.from_numpy(axis_frame(still["clean"], alpha))
    fit = float((T(truth) - clean).norm() / clean.norm())
    print(f"the truth's projections against the series' noise-free ones (the axis frame): {fit:.4f} relative")
    xs = domain.axes()[0].numpy()
    field = np.ix_(np.flatnonzero(np.abs(xs) <= a.width / 2), np.arange(domain.shape[1]), np.arange(domain.shape[2]))
    print(f"template: SSIM {metrics.ssim(template[field], truth[field]):.4f} in the field of view")
    rows = {}
    for name, stack in stacks.items():
        rows[name] = register(template, truth, torch.from_numpy(stack), T, field, a.iters, a.sigma)
        print(f"{name}: SSIM {rows[name][0]:.4f} in the field of view, residual {rows[name][1]:.4f}, "
              f"{rows[name][2]:.0f} s", flush=True)
    ssim = {name: r[0] for name, r in rows.items()}
    print(f"SSIM difference, aligned - unshifted: {ssim['aligned'] - ssim['unshifted']:+.4f} (the alignment's "
          f"error: aligned - the true shifts {ssim['aligned'] - ssim['shifted, the true shifts']:+.4f}; the views' "
          f"edges, filled by their nearest pixel where a shift moved them off the detector: the true shifts - "
          f"unshifted {ssim['shifted, the true shifts'] - ssim['unshifted']:+.4f})")


if __name__ == "__main__":
    main()
