"""Alignment in the fit on a simulated misaligned tilt series (docs/alignment.md).

The suite_et_3d data (3D Shepp-Logan -> the same bent and swirled on [-16, 16]^3, tilt axis y, -60..60 degrees in
2-degree steps, detector as wide as the volume, white noise at 10 dB) with known random shifts (uniform random, in
the gauge of ``indreg.alignment.gauge``, scaled to at most ``max_shift`` px across and along the axis) and, in a
second series, the tilt axis also rotated by ``--angle`` degrees in the detector plane. Three registrations with
the same settings: no alignment on the aligned series, ``align="shifts"`` on the shifted one,
``align="shifts+axis"`` on the shifted and rotated one. Prints a table: the shifts' RMS error (px, across / along
the axis, in that gauge), the angle's error (deg), SSIM, relative residual and seconds of each run.

    OMP_NUM_THREADS=1 python scripts/bench_alignment.py            # 64^3, 100 iterations, velocity_factor 2
    python scripts/bench_alignment.py --size 32 --iterations 30    # a quick look
"""
from __future__ import annotations

import argparse
import math
import time

import torch

import indreg
from indreg import ImageDomain, noise, phantoms
from indreg.alignment import gauge
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.forward.shift import AlignedOperator


def arguments():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=64, help="volume side (cells), 64: suite_et_3d")
    p.add_argument("--iterations", type=int, default=100, help="Algorithm 1 iterations of each run")
    p.add_argument("--velocity-factor", type=int, default=2, help="the velocity on a grid this many times coarser")
    p.add_argument("--max-shift", type=float, default=8.0, help="largest true shift (px)")
    p.add_argument("--angle", type=float, default=3.0, help="true tilt-axis angle (deg)")
    p.add_argument("--snr", type=float, default=10.0, help="white noise (dB); inf: exact data")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


def simulated(a) -> tuple:
    domain = ImageDomain.paper(a.size, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 2, det_count=a.size, det_min=-16.0,
                                                               det_max=16.0))
    template = phantoms.get("shepp_logan_3d", domain)
    target = phantoms.get("shepp_logan_3d_swirl", domain)
    gen = torch.Generator().manual_seed(a.seed)
    shifts = gauge(AlignedOperator(T), torch.rand(T.range_shape[0], 2, generator=gen, dtype=torch.float64) * 2 - 1)
    shifts = shifts * (a.max_shift / shifts.abs().amax(dim=0))
    angle = torch.tensor(math.radians(a.angle), dtype=torch.float64)
    series = [T(target), AlignedOperator(T, shifts)(target), AlignedOperator(T, shifts, angle)(target)]
    if math.isfinite(a.snr):
        series = [noise.add_white_noise(y, snr_db=a.snr, seed=a.seed)[0] for y in series]
    return T, template, target, series, shifts


def main():
    a = arguments()
    T, template, target, series, true = simulated(a)
    options = dict(sigma=3.0, num_steps=10, gamma=1e-6, step_size=0.1, max_iter=a.iterations,
                   velocity_factor=a.velocity_factor, interpolation="compose", target=target)
    print(f"{a.size}^3, {T.range_shape[0]} tilts, shifts up to {a.max_shift} px, axis {a.angle} deg, "
          f"SNR {a.snr} dB, {a.iterations} iterations, velocity_factor {a.velocity_factor}, "
          f"{torch.get_num_threads()} thread(s)")
    print("| series | align | shifts RMS error across / along (px) | axis angle error (deg) | SSIM | residual | "
          "seconds |")
    print("|---|---|---|---|---|---|---|")
    for name, data, align, angle in (("aligned", series[0], "none", 0.0), ("shifted", series[1], "shifts", 0.0),
                                     ("shifted, axis rotated", series[2], "shifts+axis", a.angle)):
        t0 = time.perf_counter()
        r = indreg.register(template, data, T, align=align, **options)
        seconds = time.perf_counter() - t0
        errors = "- | -"
        if r.alignment:
            rms = (torch.tensor(r.alignment["shifts_px"], dtype=torch.float64) - true).pow(2).mean(0).sqrt()
            errors = f"{rms[0]:.3f} / {rms[1]:.3f} | {r.alignment['axis_angle_deg'] - angle:+.3f}"
        print(f"| {name} | {align} | {errors} | {r.ssim:.4f} | {r.residual:.4f} | {seconds:.0f} |")


if __name__ == "__main__":
    main()
