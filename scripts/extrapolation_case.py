"""The edge validation on a case where the template is nearly right (docs/evaluation.md, "Which volume to trust").

The target is slice 40 of the 3D Shepp-Logan phantom on 64^3 cells of [-16, 16]^3 (its (x, y) plane); the template
is "an earlier scan": the neighbouring slice (``--offset`` slices away) reconstructed by SIRT (100 iterations,
nonnegative) from a full 180-degree scan (90 angles, ``--template-snr`` dB). The data: 60 parallel angles over 180
degrees (3-degree steps, 92 bins), white noise at ``--snr`` dB; of the angles within ``--range`` degrees, every second
is fitted and the others held out for validation; every angle outside the range is the test set (the missing
range, used by nothing). Printed: the relative residual on the validation and the test angles of the template alone,
LDDMM, the residual model (``register()``'s defaults, ``sigma=2``) and the volume the edge validation picks
(``indreg.registration.extrapolation``), and the edge validation's own scores.

    python scripts/extrapolation_case.py [--offset 1] [--range 30] [--snr 10] [--template-snr 15]
"""
from __future__ import annotations

import argparse
import json
import time

import indreg  # first: OMP_WAIT_POLICY (indreg._openmp)
import numpy as np
import torch

from indreg import noise, phantoms
from indreg.registration.extrapolation import blend, choose_extrapolation
from indreg.evaluation.score import relative_residual
from indreg.forward import sirt


def case(offset: int, limit: float, snr: float, template_snr: float) -> tuple:
    """``(template, data of the fit and validation angles, their operator, holdout, operators and data by set)``."""
    volume = phantoms.get("shepp_logan_3d", indreg.ImageDomain.paper(64, 3)).double()
    d = indreg.ImageDomain.paper(64)
    target, neighbour = volume[:, :, 40].clone(), volume[:, :, 40 + offset].clone()
    full = indreg.RayTransform(d, indreg.ParallelBeamGeometry(det_count=92, angles=torch.arange(0, 180, 2.0,
                                                              dtype=torch.float64), angle_unit="deg"))
    scan, _ = noise.add_white_noise(full(neighbour), snr_db=template_snr, seed=1)
    template = sirt(full, scan, num_iter=100, nonneg=True)[0]
    deg = np.arange(-88.5, 90.0, 3.0)
    T = indreg.RayTransform(d, indreg.ParallelBeamGeometry(det_count=92, angles=torch.tensor(deg), angle_unit="deg"))
    g, _ = noise.add_white_noise(T(target), snr_db=snr, seed=0)
    inside = np.flatnonzero(np.abs(deg) <= limit)
    sets = {"fit": inside[::2], "validation": inside[1::2], "test": np.flatnonzero(np.abs(deg) > limit)}
    rows = np.sort(np.concatenate([sets["fit"], sets["validation"]]))
    holdout = [int(i) for i in np.flatnonzero(np.isin(rows, sets["validation"]))]
    ops = {k: indreg.restrict(T, v.tolist()) for k, v in sets.items()}
    return template, g[rows], indreg.restrict(T, rows.tolist()), holdout, ops, {k: g[v] for k, v in sets.items()}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--offset", type=int, default=1)
    p.add_argument("--range", type=float, default=30.0)
    p.add_argument("--snr", type=float, default=10.0)
    p.add_argument("--template-snr", type=float, default=15.0)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    template, data, T, holdout, ops, ys = case(a.offset, a.range, a.snr, a.template_snr)
    options = dict(holdout=holdout, sigma=2.0, uncertainty=False)
    t0 = time.perf_counter()
    runs = {m: indreg.register(template, data, T, model=m, **options) for m in ("lddmm", "residual")}
    t1 = time.perf_counter()
    choice = choose_extrapolation(template, data, T, **options)
    t2 = time.perf_counter()
    chosen = template if choice.choice == "template" else blend(runs[choice.choice], choice.alpha)
    volumes = {"template alone": template, "LDDMM": runs["lddmm"].deformed, "residual model": runs["residual"].deformed,
               f"chosen: {choice.choice}, alpha {choice.alpha:g}": chosen}
    print(f"| volume | validation ({len(ys['validation'])}) | test: the missing range ({len(ys['test'])}) |\n"
          "|---|---|---|")
    for name, v in volumes.items():
        print(f"| {name} | {relative_residual(ops['validation'], v, ys['validation']):.4f} | "
              f"{relative_residual(ops['test'], v, ys['test']):.4f} |")
    print("edge validation:", json.dumps(choice.summary()["extrapolation_edge_residuals"], default=float))
    print(f"seconds: the two registrations {t1 - t0:.0f}, the edge validation {t2 - t1:.0f}")


if __name__ == "__main__":
    main()
