"""Benchmark of the LDDMM deformation operator (issue 3): time, memory, kernel crossover, interpolation blur.

    python scripts/bench_deform.py                 # forward / forward+backward table, both backward modes
    python scripts/bench_deform.py --kernel        # GaussianKernel: matrix vs FFT (the "auto" crossover)
    python scripts/bench_deform.py --blur          # interpolation="reinterpolate" vs "compose" (J, Shepp-Logan)

Timing: median over ``--repeats`` runs after a warm-up, float32, ``torch.set_num_threads(--threads)``.
Memory: every (size, mode, phase) runs in a fresh subprocess; after building the inputs and a warm-up
on a 16^2 problem the peak RSS (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) is read as the baseline,
then one call is made and the increase of the peak RSS is reported: the extra memory of that call over
its inputs (trajectories, saved tensors / autograd graph, outputs, gradients).
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

from indreg import GaussianKernel, ImageDomain, LDDMMDeformation
from indreg.deform import functional as Fd


def smooth_velocity(domain, num_steps, displacement, sigma=2.0, dtype=torch.float32, seed=0):
    """A kernel-smoothed random velocity, constant in time, max |v| = ``displacement`` (physical units)."""
    g = torch.Generator().manual_seed(seed)
    v = GaussianKernel(domain, sigma)(torch.randn(2, *domain.shape, dtype=torch.float64, generator=g))
    v = displacement * v / v.abs().max()
    return v.expand(num_steps + 1, 2, *domain.shape).to(dtype).contiguous()


def problem(n, num_steps, mode):
    domain = ImageDomain.paper(n)
    x, y = domain.points(torch.float32)
    template = torch.exp(-(x ** 2 + y ** 2) / 50) * (1 + 0.3 * torch.cos(x / 2))
    velocity = smooth_velocity(domain, num_steps, 2.0).requires_grad_()
    grad_out = torch.sin(y / 3) * domain.cell_volume
    return LDDMMDeformation(domain, num_steps, backward=mode), velocity, template, grad_out


def call(W, velocity, template, grad_out, phase):
    out = W(velocity, template)
    if phase == "fwd+bwd":
        out.backward(grad_out)
        velocity.grad = None
    return out


def worker(n, mode, phase, num_steps, repeats, threads):
    torch.set_num_threads(threads)
    call(*problem(16, num_steps, mode), phase)  # warm-up of the code paths
    args = problem(n, num_steps, mode)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out = call(*args, phase)
    peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024
    del out
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call(*args, phase)
        times.append(time.perf_counter() - t0)
    print(json.dumps({"time": statistics.median(times), "peak_mb": peak_mb}))


def run_worker(n, mode, phase, a):
    cmd = [sys.executable, __file__, "--worker", str(n), mode, phase, "--steps", str(a.steps),
           "--repeats", str(a.repeats), "--threads", str(a.threads)]
    return json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])


def main_table(a):
    results = {}
    for n in a.sizes:
        for mode in ("paper", "autograd"):
            for phase in ("fwd", "fwd+bwd"):
                results[n, mode, phase] = run_worker(n, mode, phase, a)
                print(f"  {n}^2 {mode:8s} {phase:7s} {results[n, mode, phase]}", file=sys.stderr)
    print(f"\n### LDDMMDeformation, N = {a.steps}, float32, {a.threads} thread(s), geometric, reinterpolate\n")
    print("| size | backward | forward (s) | fwd+bwd (s) | peak mem fwd (MB) | peak mem fwd+bwd (MB) |")
    print("|---|---|---|---|---|---|")
    for n in a.sizes:
        for mode in ("paper", "autograd"):
            f, b = results[n, mode, "fwd"], results[n, mode, "fwd+bwd"]
            print(f"| {n}^2 | {mode} | {f['time']:.4f} | {b['time']:.4f} | {f['peak_mb']:.1f} | {b['peak_mb']:.1f} |")
    print("\n| backward | exponent fwd (time ~ pixels^p) | exponent fwd+bwd |")
    print("|---|---|---|")
    pixels = np.log([n * n for n in a.sizes])
    for mode in ("paper", "autograd"):
        p = [np.polyfit(pixels, np.log([results[n, mode, ph]["time"] for n in a.sizes]), 1)[0]
             for ph in ("fwd", "fwd+bwd")]
        print(f"| {mode} | {p[0]:.2f} | {p[1]:.2f} |")
    if 256 in a.sizes:
        pa, au = results[256, "paper", "fwd+bwd"], results[256, "autograd", "fwd+bwd"]
        print(f"\nAt 256^2 fwd+bwd: autograd / paper time = {au['time'] / pa['time']:.2f}x, "
              f"memory = {au['peak_mb'] / max(pa['peak_mb'], 1e-9):.2f}x")


def kernel_table(a):
    print(f"\n### GaussianKernel on 42 fields (21 two-component), float32, {a.threads} thread(s), median ms\n")
    print("| size | matrix | fft | auto picks |")
    print("|---|---|---|---|")
    for n in a.kernel_sizes:
        domain = ImageDomain.paper(n)
        f = torch.randn(21, 2, n, n)
        row = {}
        for method in ("matrix", "fft"):
            K = GaussianKernel(domain, 2.0, method=method)
            K.apply(f)
            times = []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                K.apply(f)
                times.append(time.perf_counter() - t0)
            row[method] = 1e3 * statistics.median(times)
        auto = GaussianKernel(domain, 2.0).resolved_method(torch.device("cpu"))
        print(f"| {n}^2 | {row['matrix']:.1f} | {row['fft']:.1f} | {auto} |")


def blur_table(a):
    from indreg import phantoms
    print("\n### interpolation: reinterpolate (paper) vs compose, float64, velocity constant in time\n")
    print("| case | N | interpolation | there-and-back rel. L2 error | sharpness kept (grad energy ratio) "
          "| rel. L2 error vs compose N=320 |")
    print("|---|---|---|---|---|---|")
    for name, n, disp in (("j", 64, 3.0), ("shepp_logan", 256, 3.0)):
        domain = ImageDomain.paper(n)
        image = phantoms.get(name, domain)
        grad_energy = float(Fd.gradient(image, domain).norm())
        for num_steps in (20, 80):
            v = smooth_velocity(domain, num_steps, disp, sigma=4.0, dtype=torch.float64)
            ref_v = smooth_velocity(domain, 320, disp, sigma=4.0, dtype=torch.float64)
            reference = LDDMMDeformation(domain, 320, interpolation="compose")(ref_v, image)
            for interpolation in ("reinterpolate", "compose"):
                W = LDDMMDeformation(domain, num_steps, interpolation=interpolation)
                deformed = W(v, image)
                back = W(-v, deformed)
                err = float((back - image).norm() / image.norm())
                sharp = float(Fd.gradient(back, domain).norm()) / grad_energy
                ref_err = float((deformed - reference).norm() / reference.norm())
                print(f"| {name} {n}^2, max |v| = {disp} | {num_steps} | {interpolation} | {err:.4f} | {sharp:.3f} "
                      f"| {ref_err:.4f} |")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256, 438])
    p.add_argument("--kernel-sizes", type=int, nargs="+", default=[64, 128, 256, 438, 512, 768])
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--kernel", action="store_true", help="also the kernel matrix/FFT table")
    p.add_argument("--blur", action="store_true", help="also the reinterpolate/compose table")
    p.add_argument("--no-main", action="store_true", help="skip the time/memory table")
    p.add_argument("--worker", nargs=3, metavar=("SIZE", "MODE", "PHASE"), help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.worker:
        worker(int(a.worker[0]), a.worker[1], a.worker[2], a.steps, a.repeats, a.threads)
        return
    torch.set_num_threads(a.threads)
    if not a.no_main:
        main_table(a)
    if a.kernel:
        kernel_table(a)
    if a.blur:
        blur_table(a)


if __name__ == "__main__":
    main()
