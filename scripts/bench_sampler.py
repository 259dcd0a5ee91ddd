"""Benchmark of 3D trilinear sampling on the CPU (issue 20): the plane-wise sampler vs ``grid_sample``.

    python scripts/bench_sampler.py                      # 64^3 and 128^3, float32, 1 thread
    python scripts/bench_sampler.py --sizes 96 --threads 2 --dtype float64

Per size one process times, interleaved call by call (the ratios see the same machine state), the median CPU
seconds (``time.process_time``: on a shared machine the wall clock counts other processes' time) of
``grid_sample`` (3D, the scalar CPU kernel), ``functional.sampling._planewise_sample`` (linear along x of one
batched 2D ``grid_sample``), and, for the transpose and the grid derivative, ``grid_sampler_3d_backward``.
Points: the cell centres displaced uniformly by up to 0.75 cells per axis (one velocity step), a single
channel, as one time step of the deformation.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch
import torch.nn.functional as F

from indreg.deform.functional import sampling as S


def displaced_grid(n, dtype, reach=0.75, seed=0):
    g = torch.Generator().manual_seed(seed)
    lin = (torch.arange(n, dtype=dtype) * 2 + 1) / n - 1
    centres = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij")[::-1], dim=-1)
    grid = centres + (torch.rand(1, n, n, n, 3, generator=g, dtype=dtype) * 2 - 1) * (2 * reach / n)
    return grid.movedim(-1, 1).contiguous().movedim(1, -1)  # planar, as functional._Steps builds it


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    dtype = getattr(torch, a.dtype)
    print(f"\n### 3D trilinear sampling, one channel, {a.dtype}, {a.threads} thread(s), median CPU ms\n")
    print("| size | grid_sample | plane-wise | speed-up | grid_sampler_3d_backward (transpose / + grid) |")
    print("|---|---|---|---|---|")
    for n in a.sizes:
        grid = displaced_grid(n, dtype)
        f, g = torch.randn(1, 1, n, n, n, dtype=dtype), torch.randn(1, 1, n, n, n, dtype=dtype)
        calls = {
            "grid_sample": lambda: F.grid_sample(f, grid, mode="bilinear", align_corners=False),
            "planewise": lambda: S._planewise_sample(f, grid, "zeros"),
            "transpose": lambda: torch.ops.aten.grid_sampler_3d_backward(g, f, grid, 0, 0, False, [True, False]),
            "both": lambda: torch.ops.aten.grid_sampler_3d_backward(g, f, grid, 0, 0, False, [True, True]),
        }
        times = {k: [] for k in calls}
        for call in calls.values():
            call()
        for _ in range(a.repeats):
            for k, call in calls.items():
                t0 = time.process_time()
                call()
                times[k].append(time.process_time() - t0)
        m = {k: statistics.median(v) * 1e3 for k, v in times.items()}
        print(f"| {n}^3 | {m['grid_sample']:.1f} | {m['planewise']:.1f} | {m['grid_sample'] / m['planewise']:.2f}x | "
              f"{m['transpose']:.1f} / {m['both']:.1f} |")


if __name__ == "__main__":
    main()
