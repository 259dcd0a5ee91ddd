"""Benchmark of the baselines (FBP, SIRT, TV) of a ``suite_et_3d_256``-sized tilt series over two ranks against one
process (``indreg.forward.split``).

The problem: a 256^3 volume on ``[-16, 16]^3`` (a ball and an offset ellipsoid: the costs do not depend on the
values), 61 tilts about y from -60 to 60 degrees on a 256-column detector, float32, white noise; TV with the preset's
weight order (``mu`` = 0.1) and, as in the app, ``opnorm_iter`` = 100 power iterations. Four variants
(``--variants``), each in a fresh process: ``threads``, one process with two threads (the whole volume, as the app
without ranks); ``before``, one process with one thread (what a 2-rank run did before: rank 0 alone, the whole
volume, while rank 1 waited); ``ranks``, ``torchrun --nproc_per_node=2`` with one thread a rank (each its rows, TV
with a one-slice halo, rank 0 gathers); ``slabs``, one process with two threads running FBP and SIRT slab by slab
(``--slab-size`` slices; no TV: it runs whole there). Wall seconds of each baseline (gathering included), each
rank's peak resident set (``VmHWM``, reset after the set-up: Python, torch, the projector, the data and what the
baselines add) after FBP and SIRT and after all, and how far the volumes are from the whole
volume's (relative max difference, float32).

``--scale s`` divides the iteration counts (SIRT 100, TV 200, power iterations 100) by ``s`` and multiplies the
measured seconds of SIRT and TV back by ``s`` (both are linear in their iteration counts; FBP is measured as is): a
table of the preset's counts in a tenth of the time. The machine's load is printed with the table.

    python scripts/bench_baselines.py                 # the preset's counts (about 20 minutes on 2 cores)
    python scripts/bench_baselines.py --scale 10      # a tenth of the iterations, extrapolated
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("fbp", "sirt", "tv")


def _problem(n: int):
    """``(T, y, mu)``: the tilt series of an ``n^3`` volume and its noisy data, float32."""
    import torch

    from indreg import ImageDomain
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
    from indreg.forward.tv import intensity_scale

    dom = ImageDomain.paper(n, 3)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 2, det_count=n, det_min=-16.0, det_max=16.0))
    x, y, z = dom.points(torch.float32)
    f = ((x ** 2 + y ** 2 + z ** 2) < 100).float() + 0.5 * ((((x - 4) / 6) ** 2 + (y / 3) ** 2 + (z / 8) ** 2) < 1)
    g = T(f)
    g += 0.1 * float(g.abs().max()) * torch.randn(g.shape, generator=torch.Generator().manual_seed(0))
    return T, g, 0.1 * intensity_scale(T, g)


def _peak_gib() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 2 ** 20


#: The variants: ``(label, child, threads)``.
VARIANTS = {"threads": ("1 process, 2 threads", "one", 2),
            "before": ("2 ranks before (rank 0 alone, the whole volume, 1 thread)", "one", 1),
            "ranks": ("2 ranks, 1 thread each", "ranks", 1),
            "slabs": ("1 process, 2 threads, FBP and SIRT by slabs", "slabs", 2)}


def child(a) -> None:
    """One variant, timed: ``one`` the whole volume, ``ranks`` this rank's rows (gathered on rank 0), ``slabs`` FBP
    and SIRT slab by slab in one process (no TV: it runs whole there)."""
    import numpy as np
    import torch
    import torch.distributed as dist

    from indreg.forward import fbp, sirt, tv_reconstruction
    from indreg.forward.split import by_slabs, gather_rows, split_rows

    from bench_slabs import _reset_peak   # this script's directory is first on sys.path

    T, g, mu = _problem(a.size)
    ranks = a.child == "ranks"
    if ranks:
        dist.init_process_group("gloo")
        T = split_rows(T, dist.group.WORLD)
        g = T.data_rows(g)
    _reset_peak(torch.device("cpu"))
    setup = _peak_gib()
    runs = {"fbp": lambda op, y: fbp(op, y),
            "sirt": lambda op, y: sirt(op, y, num_iter=100 // a.scale, nonneg=True)[0],
            "tv": lambda op, y: tv_reconstruction(op, y, mu=mu, num_iter=200 // a.scale,
                                                  opnorm_iter=100 // a.scale)[0]}
    if a.child == "slabs":
        runs = {k: (lambda method: lambda op, y: by_slabs(method, op, y, a.slab_size))(runs[k]) for k in NAMES[:2]}
    seconds, peaks, rank = {}, [], dist.get_rank() if ranks else 0
    for name, run in runs.items():
        if ranks:
            dist.barrier()
        t0 = time.perf_counter()
        x = run(T, g)
        x = gather_rows(x, T) if ranks else x
        seconds[name] = time.perf_counter() - t0
        peaks.append(_peak_gib())
        if rank == 0:
            np.save(Path(a.out) / f"{a.child}_{name}.npy", x.numpy())   # "one": the last whole run's
        del x
    peaks = [torch.tensor(peaks)]
    if ranks:
        peaks = peaks * dist.get_world_size()
        dist.all_gather(peaks, peaks[0].clone())
        dist.destroy_process_group()
    if rank == 0:   # each rank's peak after FBP, after SIRT (and after TV)
        print(json.dumps({"seconds": seconds, "peaks": [p.tolist() for p in peaks], "setup": setup}))


def _run(variant: str, threads: int, a, out: str) -> dict:
    launcher = [sys.executable] + (["-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
                                   if variant == "ranks" else [])
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONPATH=str(ROOT))
    cmd = [*launcher, __file__, "--child", variant, "--size", str(a.size), "--scale", str(a.scale), "--slab-size",
           str(a.slab_size), "--out", out]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"{variant} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]), wall=time.perf_counter() - t0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--scale", type=int, default=1, help="divide the iteration counts by this, multiply SIRT's and "
                                                        "TV's seconds by it")
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    p.add_argument("--slab-size", type=int, default=32)
    p.add_argument("--child", choices=["one", "ranks", "slabs"])
    p.add_argument("--out")
    a = p.parse_args()
    if a.child:
        return child(a)
    import numpy as np

    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as out:
        runs = {v: _run(VARIANTS[v][1], VARIANTS[v][2], a, out) for v in a.variants}
        done = {VARIANTS[v][1] for v in runs}
        diff = {f"{c} {k.upper()}": float(np.abs(np.load(f"{out}/{c}_{k}.npy") - np.load(f"{out}/one_{k}.npy")).max()
                                          / np.abs(np.load(f"{out}/one_{k}.npy")).max())
                for c in ("ranks", "slabs") for k in NAMES if c in done and "one" in done
                and os.path.exists(f"{out}/{c}_{k}.npy")}
    factor = {"fbp": 1, "sirt": a.scale, "tv": a.scale}
    load = " / ".join(f"{x:.2f}" for x in load0) + " before, " + " / ".join(f"{x:.2f}" for x in os.getloadavg())
    counts = "" if a.scale == 1 else f" (measured at 1/{a.scale} of the iterations, times x {a.scale})"
    print(f"\n{a.size}^3, 61 tilts, float32, SIRT 100 and TV 200 iterations{counts}, slabs of {a.slab_size} "
          f"slices; load {load} after\n")
    print("| run | FBP s | SIRT s | TV s | baselines s | peak GiB per rank (after FBP + SIRT / all) "
          "| rank 0 after set-up GiB | process wall s |\n|---|---|---|---|---|---|---|---|")
    total = {}
    for v, r in runs.items():
        sec = {k: r["seconds"][k] * factor[k] for k in r["seconds"]}
        total[v] = sum(sec.values())
        print(f"| {VARIANTS[v][0]} | " + " | ".join(f"{sec[k]:.1f}" if k in sec else "-" for k in NAMES)
              + f" | {total[v]:.1f} | " + ", ".join(f"{p[1]:.2f} / {p[-1]:.2f}" for p in r["peaks"])
              + f" | {r['setup']:.2f} | {r['wall']:.0f} |")
    if "ranks" in total and "threads" in total:
        print(f"\n2 ranks / 1 process with 2 threads: {total['ranks'] / total['threads']:.2f}x the baselines' seconds"
              + (f" (before: {total['before'] / total['threads']:.2f}x)" if "before" in total else ""))
    print("against the whole volume (relative max difference): "
          + ", ".join(f"{k} {d:.1e}" for k, d in diff.items()))


if __name__ == "__main__":
    main()
