"""A registration to a slab specimen's data on the wide box against the detector-wide box (docs/slab.md).

The specimen: a slab of ice (value 1) of thickness 8, four times as wide as the detector, holding ellipses (0.4 to 1.0
more) inside and outside the field of view; 2D parallel beam, tilts -60..60 degrees every 2, a detector of 64 bins on
[-16, 16]. Its data are exact line integrals computed here with numpy (chords of ellipses and of the slab's rectangle:
not indreg's projector), plus white noise (``--snr-db``). The template: the same slab with every ellipse moved and
resized (the target is the template deformed), digitised on the detector-wide box [-16, 16] x [-6, 6] (64 x 24 cells),
as a user would have it. Every 4th tilt is held out. Printed: the held-out relative residual and SSIM inside the field
of view against the target, for the detector-wide box, the defaults (``wide_box='auto'``: the border decides) and the
wide box with each template padding (LDDMM, sigma 4, 10 time steps, the other options the defaults), and SIRT
(100 iterations, nonnegative) on both boxes.

    python scripts/slab_box.py [--iters 100] [--snr-db 20] [--seed 3] [--ndim 3]

``--ndim 3``: the same as a tilt series about y (8 slices of 0.5 along y, the ellipses ellipsoids, semi-axes 1.5 to
3 along y), on a 64 x 8 x 24 box.
"""
from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import torch

import indreg
from indreg import metrics
from indreg.forward import ParallelBeamGeometry, RayTransform, TiltSeriesGeometry, TiltSeriesTransform, sirt
from indreg.forward.wide_box import slab_thickness, wide_box

W, THICK, HALF_V, CELLS = 32.0, 8.0, 6.0, 64


def chords_ellipse(theta, s, cx, cy, a, b, phi):
    """Length of the line ``{s w + r w_perp}`` inside the ellipse (centre, semi-axes a, b, turned by phi)."""
    th, s = theta[:, None], s[None, :]
    sp = s - (cx * np.cos(th) + cy * np.sin(th))
    al = th - phi
    a2 = (a * np.cos(al)) ** 2 + (b * np.sin(al)) ** 2
    return np.where(a2 > sp ** 2, 2 * a * b * np.sqrt(np.maximum(a2 - sp ** 2, 0)) / a2, 0.0)


def chords_rectangle(theta, s, x0, x1, y0, y1):
    """Length of the line ``{s w + r w_perp}`` inside ``[x0, x1] x [y0, y1]`` (slab law: ``t / cos theta``)."""
    th, s = theta[:, None], s[None, :]
    c, sn = np.cos(th) + 0 * s, np.sin(th) + 0 * s
    p, d = (s * c, s * sn), (-sn, c)
    t0, t1 = np.full(c.shape, -np.inf), np.full(c.shape, np.inf)
    for pa, da, lo, hi in ((p[0], d[0], x0, x1), (p[1], d[1], y0, y1)):
        flat = np.abs(da) < 1e-15
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo - pa) / da, (hi - pa) / da
        t0 = np.where(flat, t0, np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(flat, np.where((pa < lo) | (pa > hi), -np.inf, t1), np.minimum(t1, np.maximum(ta, tb)))
    return np.clip(t1 - t0, 0, None)


def specimen(seed: int, moved: bool) -> list:
    """The slab's ellipses ``(cx, cz, a, b, phi, value, cy, ay)`` in the slice plane (x, beam), ``cy`` / ``ay`` their
    centre and semi-axis along the tilt axis (3D: ellipsoids); ``moved``: the target's (each moved and resized)."""
    rng = np.random.default_rng(seed)
    shapes = []
    for cx in np.arange(-58.0, 59.0, 7.0):
        e = [cx + rng.uniform(-2, 2), rng.uniform(-1.5, 1.5), rng.uniform(1.5, 3.0), rng.uniform(0.8, 1.6),
             rng.uniform(0, np.pi), rng.uniform(0.4, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(1.5, 3.0)]
        if moved:
            e[0] += rng.uniform(-1.5, 1.5)
            e[1] += rng.uniform(-0.6, 0.6)
            e[2] *= rng.uniform(0.8, 1.25)
            e[3] *= rng.uniform(0.8, 1.2)
        shapes.append(e)
    return shapes


def _scale(y, cy, ay):
    """An ellipsoid's section at height ``y`` along the tilt axis: its ellipse scaled by this (0: missed); 1 in 2D."""
    return 1.0 if y is None else np.sqrt(np.clip(1 - ((y - cy) / ay) ** 2, 0, None))


def project(shapes, theta, s, rows=None) -> np.ndarray:
    """``(tilts, bins)``, or with ``rows`` (heights along the tilt axis) ``(tilts, rows, bins)``."""
    out = []
    for y in ([None] if rows is None else rows):
        p = chords_rectangle(theta, s, -2 * W, 2 * W, -THICK / 2, THICK / 2)
        for cx, cz, a, b, phi, value, cy, ay in shapes:
            r = _scale(y, cy, ay)
            if r > 0:
                p = p + value * chords_ellipse(theta, s, cx, cz, a * r, b * r, phi)
        out.append(p)
    return out[0] if rows is None else np.stack(out, 1)


def digitise(shapes, domain, supersample: int = 4) -> torch.Tensor:
    """The specimen on ``domain`` (2D ``(x, z)``, or 3D ``(x, y, z)`` with the tilt axis y), each cell the mean of
    ``supersample^d`` points."""
    off = (np.arange(supersample) + 0.5) / supersample
    axes = [a + (np.arange(n)[:, None] + off[None]).reshape(-1) * h
            for a, n, h in zip(domain.min_pt, domain.shape, domain.cell_sides)]
    grids = np.meshgrid(*axes, indexing="ij")
    X, Z = grids[0], grids[-1]
    Y = grids[1] if domain.ndim == 3 else None
    f = (np.abs(Z) <= THICK / 2).astype(float)
    for cx, cz, a, b, phi, value, cy, ay in shapes:
        r = 1.0 if Y is None else np.sqrt(np.clip(1 - ((Y - cy) / ay) ** 2, 0, None))
        u = (X - cx) * np.cos(phi) + (Z - cz) * np.sin(phi)
        v = -(X - cx) * np.sin(phi) + (Z - cz) * np.cos(phi)
        f = f + value * ((r > 0) & ((u / np.maximum(a * r, 1e-12)) ** 2 + (v / np.maximum(b * r, 1e-12)) ** 2 <= 1))
    shape = [x for n in domain.shape for x in (n, supersample)]
    return torch.from_numpy(f.reshape(shape).mean(axis=tuple(range(1, 2 * domain.ndim, 2))))


def held_out_sirt(T, data, rows, iters: int) -> float:
    """SIRT on the kept tilts, its relative residual on the held-out ones."""
    keep = [k for k in range(data.shape[0]) if k not in rows]
    fit = indreg.forward.restrict(T, keep)
    x, _ = sirt(fit, data[keep], iters, nonneg=True)
    test = indreg.forward.restrict(T, rows)
    r = test(x) - data[rows]
    return float(test.norm_data(r) / test.norm_data(data[rows]))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--iters", type=int, default=100)
    p.add_argument("--snr-db", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--ndim", type=int, default=2, choices=(2, 3), help="3: a tilt series about y, 8 slices")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    torch.set_num_threads(1)
    tilts = np.arange(-60.0, 60.1, 2.0)
    if a.ndim == 2:
        domain = indreg.ImageDomain((CELLS, 24), (-W / 2, -HALF_V), (W / 2, HALF_V))
        geometry = ParallelBeamGeometry(det_count=CELLS, det_min=-W / 2, det_max=W / 2, angles=tilts,
                                        angle_unit="deg")
        T, rows_y = RayTransform(domain, geometry), None
    else:
        domain = indreg.ImageDomain((CELLS, 8, 24), (-W / 2, -2.0, -HALF_V), (W / 2, 2.0, HALF_V))
        T = TiltSeriesTransform(domain, TiltSeriesGeometry(tilts, CELLS, -W / 2, W / 2, angle_unit="deg"))
        geometry, rows_y = T.geometry, domain.axes()[1].numpy()
    theta, s = geometry.angles.numpy(), geometry.det_points.numpy()
    clean = torch.from_numpy(project(specimen(a.seed, True), theta, s, rows_y))
    data, _ = indreg.noise.add_white_noise(clean, snr_db=a.snr_db, seed=a.seed)
    template, target = digitise(specimen(a.seed, False), domain), digitise(specimen(a.seed, True), domain)
    rows = list(range(0, len(theta), 4))
    box = wide_box(T, thickness=slab_thickness(template, domain, domain.ndim - 1))
    print(f"detector-wide box {domain.shape}, wide box {box.domain.shape} ({box.width_factor:.2f} x; thickness "
          f"{box.thickness:g}); {len(theta)} tilts, every 4th held out; {a.snr_db:g} dB")
    print(f"{'run':34s} {'held-out residual':>18s} {'SSIM (FOV)':>11s} {'fit residual':>13s} {'min Jac':>8s} {'s':>6s}")
    print(f"{'the template itself':34s} {'':18s} {metrics.ssim(template, target):11.4f}")
    runs = [("LDDMM, detector-wide box", dict(wide_box=False)), ("LDDMM, defaults (wide_box='auto')", {})]
    runs += [(f"LDDMM, wide box, padding {m}", dict(wide_box=True, template_padding=m)) for m in ("edge", "level",
                                                                                                 "zero")]
    for name, extra in runs:
        t0 = time.perf_counter()
        r = indreg.register(template, data, T, target=target, holdout=rows, max_iter=a.iters, sigma=4.0,
                            num_steps=10, **extra)
        print(f"{name:34s} {r.holdout['holdout_residual']:18.4f} {r.ssim:11.4f} {r.residual:13.4f} "
              f"{r.min_jacobian:8.3f} {time.perf_counter() - t0:6.1f}" + ("" if extra else
                                                                        f"  (border: {r.units.border}, box "
                                                                        f"{r.units.box_width:.2f} x)"))
    for name, op in (("SIRT 100, detector-wide box", T), ("SIRT 100, wide box", box.widen(T))):
        print(f"{name:34s} {held_out_sirt(op, data, rows, 100):18.4f}")


if __name__ == "__main__":
    main()
