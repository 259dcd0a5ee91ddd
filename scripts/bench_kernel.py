"""Benchmark of GaussianKernel (issue 20): ms per application of each method, accuracy against the dense form.

    python scripts/bench_kernel.py                       # the table below, CPU (and CUDA when available)
    python scripts/bench_kernel.py --sizes 64,64 128,128,128 --sigma 3 --repeats 5 --threads 2

Per size: a field ``(N + 1, d, *shape)`` = (11, d, ...) in float32 on the paper's domain ``[-16, 16]^d`` (a
slab keeps cubic cells: ``[-16, 16]^2 x [-6, 6]`` for 256 x 256 x 96), sigma 3 (the ET preset). Times are the
median over ``--repeats`` rounds after one warm-up call per method (eigendecomposition and caches built);
within a round the methods run one after the other (interleaved), so the ratios see the same machine state.
"max rel diff" is ``max |K f - K_matrix f| / max |K_matrix f|`` over the first time step (``f[:1]``) in float32,
and "dense rounding" the same for the float32 dense form against the float64 one: the new methods agree with
the dense form at its own rounding level. The FFT is skipped where its padded spectra would exceed
``--fft-max-gb``, the dense matrix form (``d n^(d+1)``) where a single call would exceed ``--matrix-max-gmac``
(then its time is the one-step time x 11, marked ``~``).
"""
from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from indreg import GaussianKernel, ImageDomain

METHODS = ("matrix", "fft", "lowrank", "auto")
DEFAULT_SIZES = ("64,64", "256,256", "64,64,64", "128,128,128", "256,256,96", "256,256,256")


def domain_of(shape):
    h = 32.0 / shape[0]  # cubic cells, the x axis spans [-16, 16]
    return ImageDomain(shape, tuple(-n * h / 2 for n in shape), tuple(n * h / 2 for n in shape))


def timed(fn, device):
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    out = fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0, out


def rel(a, b):
    return float((a - b).abs().max() / b.abs().max())


def bench(shape, sigma, repeats, device, a):
    domain = domain_of(shape)
    d = domain.ndim
    f = torch.randn(11, d, *shape, generator=torch.Generator().manual_seed(0)).to(device)
    kernels = {m: GaussianKernel(domain, sigma, method=m) for m in METHODS}
    points = math.prod(shape)
    skip = {}
    padded = math.prod(2 * n for n in shape) * 11 * d * 8 / 1e9  # complex64 half spectrum, ~2^d x the batch
    if padded > a.fft_max_gb:
        skip["fft"] = "skipped"
    if 11 * d * points * sum(shape) / 1e9 > a.matrix_max_gmac:
        skip["matrix"] = "one step"
    one = f[:1]
    dense = kernels["matrix"].apply(one)
    dense64 = kernels["matrix"].apply(one.double())
    diff = {m: rel(K.apply(one), dense) for m, K in kernels.items() if skip.get(m) != "skipped"}
    times = {m: [] for m in METHODS if skip.get(m) != "skipped"}
    for m in times:  # warm-up
        kernels[m].apply(one if m in skip else f)
    for _ in range(repeats):
        for m in times:
            if m in skip:
                t, _ = timed(lambda: kernels[m].apply(one), device)
                times[m].append(11 * t)
            else:
                times[m].append(timed(lambda: kernels[m].apply(f), device)[0])
    ms = {m: 1e3 * statistics.median(t) for m, t in times.items()}
    auto = kernels["auto"].resolved_method(device, torch.float32)
    cell = "x".join(map(str, shape))
    ranks = ",".join(str(kernels["lowrank"].rank(ax)) for ax in range(d))

    def fmt(m):
        if m not in ms:
            return "skipped"
        return ("~" if m in skip else "") + (f"{ms[m]:.1f}" if ms[m] < 100 else f"{ms[m]:.0f}")

    print(f"| {device.type} | {cell} | {sigma / domain.cell_sides[0]:.1f} | {ranks} | "
          + " | ".join(fmt(m) for m in METHODS)
          + f" | {auto} | {ms['matrix'] / ms['auto']:.1f}x | {rel(dense, dense64):.1e} | "
          + " | ".join(f"{diff[m]:.1e}" if m in diff else "-" for m in ("fft", "lowrank")) + " |")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=list(DEFAULT_SIZES), help="shapes as nx,ny[,nz]")
    p.add_argument("--sigma", type=float, default=3.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: steadier on a shared machine)")
    p.add_argument("--fft-max-gb", type=float, default=2.0)
    p.add_argument("--matrix-max-gmac", type=float, default=100.0)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    print(f"### GaussianKernel on (11, d, *shape) float32 fields, sigma {a.sigma}, {torch.get_num_threads()} "
          f"CPU thread(s), median ms of {a.repeats}\n")
    print("| device | shape | sigma / h | rank r | matrix | fft | lowrank | auto | auto picks "
          "| matrix / auto | dense rounding | max rel diff fft | lowrank |")
    print("|" + "---|" * 13)
    for device in devices:
        for size in a.sizes:
            bench(tuple(int(n) for n in size.split(",")), a.sigma, a.repeats, device, a)


if __name__ == "__main__":
    main()
