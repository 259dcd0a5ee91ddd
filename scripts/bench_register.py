"""Benchmark of the registration solvers: seconds per iteration and peak memory on the paper's suites.

For each suite (1: 64^2, 10x92, sigma 6; 3: 256^2, 10x362, sigma 2; 2: 438^2, 6x620, sigma 2; N = 20),
solver (Algorithm 1; L-BFGS with strong-Wolfe line search) and dtype, a fresh subprocess builds the
problem, runs ``--warmup`` iterations, then times ``--iters`` iterations (median seconds per iteration;
for L-BFGS also seconds per forward/backward evaluation = total time / evaluations). Memory is the peak
resident set size of that subprocess (``ru_maxrss``, includes Python + torch, about 0.3 GiB) and its
growth during the iterations (peak minus the resident size before the first iteration). "CPU s / it" is
the process CPU time per iteration (all threads): on a shared, overloaded machine it is a steadier figure
than the wall-clock time (with 2 threads on an overloaded machine OpenMP spinning inflates both).
Prints one Markdown table with the authors' ODL reference times (suite 1: 0.13 s/it, suite 3: 0.93 s/it).

``--busy SUITE`` adds a second table for Algorithm 1 on that suite with one core kept busy by another process
(a Python busy loop started and stopped by this script), against the idle runs of the same invocation: 1 and
2 threads idle, 2 threads busy with torch's default OpenMP wait policy (torch imported before indreg, the
variable unset), 2 threads busy with indreg's ``OMP_WAIT_POLICY=PASSIVE``, and 1 thread busy. The ratio
column divides by the 1-thread idle time.

    python scripts/bench_register.py                      # all suites, float32, 2 threads
    python scripts/bench_register.py --suites 1 3 --dtypes float32 float64 --iters 10
    python scripts/bench_register.py --suites 3 --solvers algorithm1 --busy 3
    python scripts/bench_register.py --suites --volumes 64 128 --volume-steps 10 20   # 3D rows only

``--volumes`` adds a 3D table (Algorithm 1, float32): 3D Shepp-Logan -> swirled (``indreg.phantoms``) on
``n^3`` cells of [-16, 16]^3, a tilt series about y of 61 tilts (-60..60 degrees, step 2) on an ``n x n``
detector, sigma 3, ``N`` time steps from ``--volume-steps``.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

SUITES = {  # grid, angles, bins, sigma, template, target, step size
    "1": (64, 10, 92, 6.0, "j", "v", 0.02),
    "3": (256, 10, 362, 2.0, "shepp_logan_template", "shepp_logan", 0.02),
    "2": (438, 6, 620, 2.0, "six_objects_template", "six_objects_target", 0.04),
}
ODL_SECONDS = {"1": 0.13, "3": 0.93}


def _rss_gib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2 ** 30


def worker(suite: str, solver_name: str, dtype_name: str, iters: int, warmup: int, threads: int) -> dict:
    import torch  # after indreg when the wait policy is indreg's (see _spawn)

    from indreg import ImageDomain, phantoms
    from indreg.deform.kernel import GaussianKernel
    from indreg.deform.lddmm import LDDMMDeformation
    from indreg.forward import ParallelBeamGeometry, RayTransform
    from indreg.noise import add_white_noise
    from indreg.solvers import Algorithm1, IndirectRegistration, SolverState, TorchOptimSolver

    torch.set_num_threads(threads)
    n, angles, bins, sigma, template, target, step = SUITES[suite]
    dtype = getattr(torch, dtype_name)
    dom = ImageDomain.paper(n)
    T = RayTransform(dom, ParallelBeamGeometry.paper(angles, bins))
    data, _ = add_white_noise(T(phantoms.get(target, dom)), std=1.0, seed=0)
    problem = IndirectRegistration(T, LDDMMDeformation(dom, num_steps=20), GaussianKernel(dom, sigma),
                                   phantoms.get(template, dom).to(dtype), data.to(dtype), gamma=1e-6)
    if solver_name == "algorithm1":
        solver = Algorithm1(problem, step_size=step)
    else:
        solver = TorchOptimSolver(problem, "lbfgs")
    state = SolverState(problem.zero_momentum())
    for _ in range(warmup):
        solver.step(state)
    rss_before = _rss_gib()
    evals_before = solver.evaluations
    times, cpu = [], []
    for _ in range(iters):
        t0, c0 = time.perf_counter(), time.process_time()
        info = solver.step(state)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    evaluations = solver.evaluations - evals_before
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    return {"suite": suite, "solver": solver_name, "dtype": dtype_name, "s_per_it": statistics.median(times),
            "cpu_per_it": statistics.median(cpu),
            "s_per_eval": sum(times) / max(evaluations, 1), "evals_per_it": evaluations / iters,
            "peak_gib": peak, "growth_gib": peak - rss_before, "objective": info["objective"]}


def worker_3d(size: int, num_steps: int, iters: int, warmup: int, threads: int) -> dict:
    import indreg  # noqa: F401  (first: it sets OMP_WAIT_POLICY=PASSIVE before torch starts OpenMP)
    import torch

    from indreg import ImageDomain, phantoms
    from indreg.deform.kernel import GaussianKernel
    from indreg.deform.lddmm import LDDMMDeformation
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
    from indreg.noise import add_white_noise
    from indreg.solvers import Algorithm1, IndirectRegistration, SolverState

    torch.set_num_threads(threads)
    dom = ImageDomain.paper(size, ndim=3)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 2, det_count=size, det_min=-16.0, det_max=16.0))
    data, _ = add_white_noise(T(phantoms.get("shepp_logan_3d_swirl", dom)), snr_db=10.0, seed=0, event_dims=3)
    problem = IndirectRegistration(T, LDDMMDeformation(dom, num_steps=num_steps), GaussianKernel(dom, 3.0),
                                   phantoms.get("shepp_logan_3d", dom).float(), data.float(), gamma=1e-6)
    solver = Algorithm1(problem, step_size=0.02)
    state = SolverState(problem.zero_momentum())
    for _ in range(warmup):
        solver.step(state)
    times, cpu = [], []
    for _ in range(iters):
        t0, c0 = time.perf_counter(), time.process_time()
        solver.step(state)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    return {"size": size, "num_steps": num_steps, "s_per_it": statistics.median(times),
            "cpu_per_it": statistics.median(cpu), "peak_gib": peak}


def volume_table(args) -> None:
    """Algorithm 1 on tilt-series problems of ``--volumes`` sizes and ``--volume-steps`` time steps."""
    rows = []
    for size in args.volumes:
        for n in args.volume_steps:
            cmd = [sys.executable, __file__, "--worker3d", str(size), str(n), "--iters", str(args.iters),
                   "--warmup", str(args.warmup), "--threads", str(args.threads)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
            print(f"# done: volume {size}^3 N={n}", file=sys.stderr)
    print(f"\n3D: Algorithm 1, float32, tilt series 61 x n x n (+-60 degrees), {args.threads} threads; median over "
          f"{args.iters} iterations; peak = process peak RSS\n")
    print("| grid | N | s / iteration | CPU s / it | peak GiB |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['size']}^3 | {r['num_steps']} | {r['s_per_it']:.3f} | {r['cpu_per_it']:.3f} | {r['peak_gib']:.2f} |")


def _spawn(suite, solver, dtype, args, threads, policy="indreg") -> dict:
    """One worker process. ``policy="unset"``: no OMP_WAIT_POLICY and torch imported before indreg (torch's
    default spinning); ``"indreg"``: indreg is imported first and sets PASSIVE."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    first = "torch" if policy == "unset" else "indreg"
    cmd = [sys.executable, "-c", f"import {first}, runpy, sys; sys.argv = sys.argv[1:]; "
           f"runpy.run_path(sys.argv[0], run_name='__main__')", __file__, "--worker", suite, solver, dtype,
           "--iters", str(args.iters), "--warmup", str(args.warmup), "--threads", str(threads)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env).stdout
    return json.loads(out.strip().splitlines()[-1])


def busy_table(suite: str, args) -> None:
    """Algorithm 1 on ``suite``, idle and with one core kept busy by another process, in one invocation."""
    cases = [(1, "indreg", False), (2, "indreg", False), (2, "unset", True), (2, "indreg", True), (1, "indreg", True)]
    rows = []
    for threads, policy, busy in cases:
        spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
        try:
            rows.append((threads, policy, busy, _spawn(suite, "algorithm1", "float32", args, threads, policy)))
        finally:
            if spinner is not None:
                spinner.kill()
                spinner.wait()
        print(f"# done: busy table {threads} threads, {policy}, busy={busy}", file=sys.stderr)
    reference = rows[0][3]["s_per_it"]
    print(f"\nSuite {suite}, Algorithm 1, float32: one core busy (another process) vs idle; "
          f"ratio = s / iteration over the 1-thread idle run\n")
    print("| threads | OMP_WAIT_POLICY | other core | s / iteration | CPU s / it | ratio to 1 thread idle |")
    print("|---|---|---|---|---|---|")
    for threads, policy, busy, r in rows:
        name = "PASSIVE (indreg)" if policy == "indreg" else "unset (torch default)"
        print(f"| {threads} | {name} | {'busy' if busy else 'idle'} | {r['s_per_it']:.4f} | {r['cpu_per_it']:.4f} | "
              f"{r['s_per_it'] / reference:.2f}x |")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="*", default=["1", "3", "2"], choices=list(SUITES))
    parser.add_argument("--solvers", nargs="+", default=["algorithm1", "lbfgs"], choices=["algorithm1", "lbfgs"])
    parser.add_argument("--dtypes", nargs="+", default=["float32"], choices=["float32", "float64"])
    parser.add_argument("--iters", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--busy", choices=list(SUITES), help="add the one-core-busy table for this suite")
    parser.add_argument("--volumes", nargs="*", type=int, default=[], help="3D rows: grid sizes n (n^3 cells)")
    parser.add_argument("--volume-steps", nargs="+", type=int, default=[10, 20], help="3D rows: time steps N")
    parser.add_argument("--worker", nargs=3, metavar=("SUITE", "SOLVER", "DTYPE"), help=argparse.SUPPRESS)
    parser.add_argument("--worker3d", nargs=2, type=int, metavar=("SIZE", "N"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(*args.worker, args.iters, args.warmup, args.threads)))
        return
    if args.worker3d:
        print(json.dumps(worker_3d(*args.worker3d, args.iters, args.warmup, args.threads)))
        return
    rows = []
    for suite in args.suites:
        for solver in args.solvers:
            for dtype in args.dtypes:
                rows.append(_spawn(suite, solver, dtype, args, args.threads))
                print(f"# done: suite {suite} {solver} {dtype}", file=sys.stderr)
    if rows:
        suite_table(rows, args)
    if args.busy:
        busy_table(args.busy, args)
    if args.volumes:
        volume_table(args)


def suite_table(rows: list, args) -> None:
    print(f"torch threads: {args.threads}; median over {args.iters} iterations after {args.warmup} warm-up; "
          f"N = 20; peak = process peak RSS (incl. ~0.3 GiB Python + torch), growth = during the iterations\n")
    print("| suite | grid | solver | dtype | s / iteration | CPU s / it | evals / it | s / evaluation | ODL s / it | "
          "speed-up vs ODL | peak GiB | growth GiB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        n = SUITES[r["suite"]][0]
        odl = ODL_SECONDS.get(r["suite"])
        ratio = f"{odl / r['s_per_it']:.1f}x" if odl and r["solver"] == "algorithm1" else "-"
        print(f"| {r['suite']} | {n}^2 | {r['solver']} | {r['dtype']} | {r['s_per_it']:.4f} | {r['cpu_per_it']:.4f} | "
              f"{r['evals_per_it']:.2f} | {r['s_per_eval']:.4f} | {odl if odl else '-'} | {ratio} | "
              f"{r['peak_gib']:.2f} | {r['growth_gib']:.2f} |")


if __name__ == "__main__":
    main()
