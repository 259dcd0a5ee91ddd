"""Benchmark of the LDDMM deformation operator (issue 3): time, memory, kernel crossover, interpolation blur.

    python scripts/bench_deform.py                 # forward / forward+backward table: paper, exact, autograd
    python scripts/bench_deform.py --action mass_preserving --interpolation compose   # another variant
    python scripts/bench_deform.py --kernel        # GaussianKernel: matrix vs FFT (the "auto" crossover)
    python scripts/bench_deform.py --blur          # interpolation="reinterpolate" vs "compose" (J, Shepp-Logan)
    python scripts/bench_deform.py --ndim 3 --sizes 64 128 --steps 10 --modes paper exact   # 3D volumes
    python scripts/bench_deform.py --ndim 3 --sizes 128 --steps 10 --iteration --no-main    # Algorithm 1 in 3D

Timing: median over ``--repeats`` runs after a warm-up, float32, ``torch.set_num_threads(--threads)``; per
size one fresh subprocess times the three backward modes and both phases in interleaved rounds (per round and
combination one untimed call, then three timed ones), so the ratios are measured in one run under the same
machine state.
Memory: every (size, mode, phase) in another fresh subprocess, after building the inputs and a warm-up,
measured two ways over one call (the extra memory of that call over its inputs: trajectories, saved
tensors / autograd graph, outputs, gradients; the velocity gradient alone is 11 MB at 256^2, N = 20):
- "RSS": the increase of the process's peak resident set (``ru_maxrss``; transparent huge pages off, so it
  grows page by page): what the operating system charges, allocator fragmentation included;
- "live": the peak of the bytes malloc has handed out (glibc ``mallinfo2``), read after every aten op
  (a ``TorchDispatchMode``): the live tensors at op boundaries, independent of the allocator's caching,
  the CPU analogue of ``torch.cuda.max_memory_allocated``.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

from torch.utils._python_dispatch import TorchDispatchMode

from indreg import GaussianKernel, ImageDomain, LDDMMDeformation
from indreg.deform import functional as Fd


def smooth_velocity(domain, num_steps, displacement, sigma=2.0, dtype=torch.float32, seed=0):
    """A kernel-smoothed random velocity, constant in time, max |v| = ``displacement`` (physical units)."""
    g = torch.Generator().manual_seed(seed)
    d = domain.ndim
    v = GaussianKernel(domain, sigma)(torch.randn(d, *domain.shape, dtype=torch.float64, generator=g))
    v = displacement * v / v.abs().max()
    return v.expand(num_steps + 1, d, *domain.shape).to(dtype).contiguous()


MODES = ["paper", "exact", "autograd"]  # --modes
VARIANT = {"action": "geometric", "interpolation": "reinterpolate"}  # set from the command line
NDIM = [2]  # --ndim


def problem(n, num_steps, mode):
    domain = ImageDomain.paper(n, NDIM[0])
    points = domain.points(torch.float32)
    template = torch.exp(-sum(p ** 2 for p in points) / 50) * (1 + 0.3 * torch.cos(points[0] / 2))
    velocity = smooth_velocity(domain, num_steps, 2.0).requires_grad_()
    grad_out = torch.sin(points[1] / 3) * domain.cell_volume
    return LDDMMDeformation(domain, num_steps, backward=mode, **VARIANT), velocity, template, grad_out


def call(W, velocity, template, grad_out, phase):
    out = W(velocity, template)
    if phase == "fwd+bwd":
        out.backward(grad_out)
        velocity.grad = None
    return out


def combos():
    return [(mode, phase) for mode in MODES for phase in ("fwd", "fwd+bwd")]


def time_worker(n, num_steps, repeats, threads):
    """Median times of all modes and phases, interleaved call by call (the ratios see the same machine state)."""
    torch.set_num_threads(threads)
    problems = {mode: problem(n, num_steps, mode) for mode in MODES}
    COMBOS = combos()
    for mode, phase in COMBOS:
        call(*problem(16, num_steps, mode), phase)  # warm-up of the code paths
        call(*problems[mode], phase)
    times = {combo: [] for combo in COMBOS}
    for _ in range(max(1, repeats // 3)):  # rounds: per combo one untimed call (its steady state), three timed
        for mode, phase in COMBOS:
            call(*problems[mode], phase)
            for _ in range(3):
                t0 = time.perf_counter()
                call(*problems[mode], phase)
                times[mode, phase].append(time.perf_counter() - t0)
    print(json.dumps({f"{mode} {phase}": statistics.median(t) for (mode, phase), t in times.items()}))


def memory_worker(n, mode, phase, num_steps, threads):
    torch.set_num_threads(threads)
    _disable_huge_pages()
    call(*problem(16, num_steps, mode), phase)  # warm-up of the code paths
    args = problem(n, num_steps, mode)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    call(*args, phase)
    rss = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024
    for _ in range(2):  # the first pass warms up the dispatch mode itself
        with LivePeak() as live:
            call(*args, phase)
    print(json.dumps({"rss_mb": rss, "live_mb": live.peak / 2 ** 20}))


def iteration_worker(n, num_steps, repeats, threads):
    """Seconds per Algorithm-1 iteration (kernel, deformation forward + backward, tilt-series projector and its
    adjoint, min Jacobian) on a 3D problem, with and without step halving, and the process's peak RSS (MB)."""
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
    from indreg.solvers import Algorithm1, IndirectRegistration, SolverState

    torch.set_num_threads(threads)
    domain = ImageDomain.paper(n, 3)
    points = domain.points(torch.float32)
    template = torch.exp(-sum(p ** 2 for p in points) / 50)
    target = torch.exp(-sum((p - s) ** 2 for p, s in zip(points, (2.0, -1.0, 1.0))) / 50)
    # 61 tilts, -60..60 degrees, about the y axis, a detector as wide as the domain
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 2, det_count=n, det_min=-16.0, det_max=16.0))
    W = LDDMMDeformation(domain, num_steps, backward=VARIANT.get("backward", "paper"), action=VARIANT["action"],
                         interpolation=VARIANT["interpolation"])
    problem_ = IndirectRegistration(T, W, GaussianKernel(domain, 6.0), template, T(target), gamma=1e-6)
    out = {}
    # the API's default (every step checks folding: min Jacobian each time) and the paper's fixed-step loop with
    # the folding check every 10 iterations
    for name, options in (("halving", {"step_halving": True}), ("fixed", {"jacobian_every": 10})):
        solver = Algorithm1(problem_, step_size=0.02, max_iter=repeats + 1, **options)
        state = SolverState(problem_.zero_momentum())
        solver.step(state)  # warm-up (and the first evaluation)
        times, cpu, evaluations = [], [], solver.evaluations
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            solver.step(state)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        out[name] = statistics.median(times)
        out[name + "_cpu"] = statistics.median(cpu)  # CPU seconds of all threads: the wall time on idle cores
        out[name + "_evaluations"] = (solver.evaluations - evaluations) / repeats
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(out))


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]


class LivePeak(TorchDispatchMode):
    """Peak of malloc's bytes in use (``mallinfo2``: heap + mmapped) after every aten op, over the baseline
    at entry; nan without glibc >= 2.33."""

    def __enter__(self):
        try:
            self._mallinfo = ctypes.CDLL(None).mallinfo2
            self._mallinfo.restype = _MallInfo2
            self.base, self.peak = self._in_use(), 0
        except (OSError, AttributeError):
            self._mallinfo, self.peak = None, float("nan")
        return super().__enter__()

    def _in_use(self):
        info = self._mallinfo()
        return info.uordblks + info.hblkhd

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if self._mallinfo is not None:
            self.peak = max(self.peak, self._in_use() - self.base)
        return out


def _disable_huge_pages():
    """``prctl(PR_SET_THP_DISABLE, 1)`` (Linux): resident memory then grows in 4 KiB pages, not 2 MiB."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(41, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def run(a, *worker_args):
    cmd = [sys.executable, __file__, "--worker", *map(str, worker_args), "--steps", str(a.steps),
           "--repeats", str(a.repeats), "--threads", str(a.threads), "--action", a.action,
           "--interpolation", a.interpolation, "--ndim", str(a.ndim), "--modes", *a.modes]
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main_table(a):
    results = {}
    for n in a.sizes:
        times = run(a, "time", n)
        for mode, phase in combos():
            results[n, mode, phase] = {"time": times[f"{mode} {phase}"], **run(a, "memory", n, mode, phase)}
            print(f"  {n}^{a.ndim} {mode:8s} {phase:7s} {results[n, mode, phase]}", file=sys.stderr)
    print(f"\n### LDDMMDeformation, N = {a.steps}, float32, {a.threads} thread(s), {a.action}, {a.interpolation}\n")
    print("| size | backward | forward (s) | fwd+bwd (s) | fwd: RSS / live (MB) | fwd+bwd: RSS / live (MB) |")
    print("|---|---|---|---|---|---|")
    for n in a.sizes:
        for mode in MODES:
            f, b = results[n, mode, "fwd"], results[n, mode, "fwd+bwd"]
            print(f"| {n}^{a.ndim} | {mode} | {f['time']:.4f} | {b['time']:.4f} | {f['rss_mb']:.1f} / "
                  f"{f['live_mb']:.1f} | {b['rss_mb']:.1f} / {b['live_mb']:.1f} |")
    if len(a.sizes) > 1:
        exponents(results, a.sizes, a.ndim)
    if {"exact", "paper", "autograd"} <= set(MODES):
        ratios(results, a.sizes)


def iteration_table(a):
    print(f"\n### Algorithm 1 in 3D (tilt series, 61 tilts), N = {a.steps}, float32, {a.threads} thread(s), "
          f"{a.action}, {a.interpolation}, median s / iteration\n")
    print("| size | backward | step halving, min Jacobian every step: wall / CPU s (evaluations) | fixed step, min "
          "Jacobian every 10th: wall / CPU s | peak RSS of the process (MB) |")
    print("|---|---|---|---|---|")
    for n in a.sizes:
        for mode in MODES:
            if mode == "autograd":
                continue
            r = run(a, "iteration", n, mode)
            print(f"| {n}^3 | {mode} | {r['halving']:.2f} / {r['halving_cpu']:.2f} ({r['halving_evaluations']:.1f}) | "
                  f"{r['fixed']:.2f} / {r['fixed_cpu']:.2f} | {r['peak_rss_mb']:.0f} |")


def ratios(results, sizes):
    """fwd+bwd ratios between the modes, measured in the same run."""
    print("\n| size | exact / paper: time, RSS, live | exact / autograd: time, RSS, live | autograd / paper: time |")
    print("|---|---|---|---|")
    for n in sizes:
        ex, pa, au = (results[n, mode, "fwd+bwd"] for mode in ("exact", "paper", "autograd"))
        keys = ("time", "rss_mb", "live_mb")
        r = lambda x, y: " / ".join(f"{x[k] / max(y[k], 1e-9):.2f}" for k in keys)  # noqa: E731
        print(f"| {n} | {r(ex, pa)} | {r(ex, au)} | {au['time'] / pa['time']:.2f} |")


def exponents(results, sizes, ndim=2):
    """Least-squares exponent p of time ~ pixels^p over the sizes."""
    print("\n| backward | exponent fwd (time ~ pixels^p) | exponent fwd+bwd |")
    print("|---|---|---|")
    pixels = np.log([float(n) ** ndim for n in sizes])
    for mode in MODES:
        p = [np.polyfit(pixels, np.log([results[n, mode, ph]["time"] for n in sizes]), 1)[0]
             for ph in ("fwd", "fwd+bwd")]
        print(f"| {mode} | {p[0]:.2f} | {p[1]:.2f} |")


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
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--action", default="geometric", choices=Fd.ACTIONS)
    p.add_argument("--interpolation", default="reinterpolate", choices=Fd.INTERPOLATIONS)
    p.add_argument("--kernel", action="store_true", help="also the kernel matrix/FFT table")
    p.add_argument("--blur", action="store_true", help="also the reinterpolate/compose table")
    p.add_argument("--ndim", type=int, default=2, choices=(2, 3), help="2D images or 3D volumes (sizes n^ndim)")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES, help="backward modes to time")
    p.add_argument("--iteration", action="store_true", help="also seconds per Algorithm-1 iteration (3D)")
    p.add_argument("--no-main", action="store_true", help="skip the time/memory table")
    p.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    a = p.parse_args()
    VARIANT.update(action=a.action, interpolation=a.interpolation)
    NDIM[0] = a.ndim
    MODES[:] = a.modes
    if a.worker:
        if a.worker[0] == "time":
            time_worker(int(a.worker[1]), a.steps, a.repeats, a.threads)
        elif a.worker[0] == "iteration":
            VARIANT["backward"] = a.worker[2]
            iteration_worker(int(a.worker[1]), a.steps, a.repeats, a.threads)
        else:
            memory_worker(int(a.worker[1]), a.worker[2], a.worker[3], a.steps, a.threads)
        return
    torch.set_num_threads(a.threads)
    if not a.no_main:
        main_table(a)
    if a.iteration:
        iteration_table(a)

    if a.kernel:
        kernel_table(a)
    if a.blur:
        blur_table(a)


if __name__ == "__main__":
    main()
