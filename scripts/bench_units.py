"""Unit invariance of the default options: the same registration with template and data in other intensity units
(x 1e-3, 1, 1e3, 1e6) and length units (the box and sigma x 13.44: nanometres for the paper's units).

With ``gamma`` and ``step_size`` unset, ``indreg.register`` takes them relative to the data term
(``indreg.units``: ``gamma = gamma_rel S``, ``step = step_rel / S``, ``S = ||g||^2 / L^2``), so every row of a
case should read the same. The paper's absolute values (``gamma=1e-6, step_size=0.02``) are shown beside them.

    python scripts/bench_units.py [--iters 200] [--dtype float32]
"""
from __future__ import annotations

import argparse
import time

import torch

import indreg
from indreg import noise, phantoms
from indreg.registration.run import count_halvings


def case(name: str, lam: float = 1.0):
    """(template, data, operator, target) of the paper's suite 1 (``j``) or suite 3 (``shepp_logan``) at 64^2, in a
    box ``lam`` times the paper's [-16, 16]^2."""
    paper = indreg.ImageDomain.paper(64)
    domain = indreg.ImageDomain(shape=(64, 64), min_pt=(-16 * lam,) * 2, max_pt=(16 * lam,) * 2)
    g0 = indreg.ParallelBeamGeometry.paper(10, 92)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=g0.angles, det_count=92,
                                                                det_min=g0.det_min * lam, det_max=g0.det_max * lam))
    pair = {"suite1": ("j", "v", 4.87), "suite3": ("shepp_logan_template", "shepp_logan", 7.06)}[name]
    template, target = phantoms.get(pair[0], paper), phantoms.get(pair[1], paper)
    data, _ = noise.add_white_noise(T(target), snr_db=pair[2], seed=0)
    return template, data, T, target


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    p.add_argument("--cases", nargs="+", default=["suite1", "suite3"])
    a = p.parse_args()
    print("| case | options | intensity x | length x | SSIM | residual | halvings | gamma | step | s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in a.cases:
        for options, label in (({}, "defaults (relative)"), ({"gamma": 1e-6, "step_size": 0.02}, "paper's absolute")):
            for scale, lam in ((1.0, 1.0), (1e-3, 1.0), (1e3, 1.0), (1e6, 1.0), (1.0, 13.44)):
                template, data, T, target = case(name, lam)
                t0 = time.perf_counter()
                r = indreg.register(scale * template, scale * data, T, sigma=(6.0 if name == "suite1" else 2.0) * lam,
                                    max_iter=a.iters, target=scale * target, dtype=a.dtype, **options)
                dt = time.perf_counter() - t0
                step = r.history[-1]["step_size"] if r.history else float("nan")
                print(f"| {name} | {label} | {scale:g} | {lam:g} | {r.ssim:.4f} | {r.residual:.4f} | "
                      f"{count_halvings(r.history)} | {r.problem.gamma:.3g} | {step:.3g} | {dt:.1f} |", flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
