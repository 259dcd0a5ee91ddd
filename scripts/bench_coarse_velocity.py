"""Benchmark of ``velocity_factor`` (the velocity on a coarser grid, ``CoarseVelocityDeformation``) in 3D.

The ``suite_et_3d`` problem: 3D Shepp-Logan -> swirled (``indreg.phantoms``) on ``n^3`` cells of [-16, 16]^3, a
tilt series about y of 61 tilts (-60..60 degrees, step 2) on an ``n x n`` detector as wide as the volume, white
noise at 10 dB (seed 0), sigma 3, N = 10, gamma 1e-6, ``interpolation="compose"``, Algorithm 1 with step 0.1 and
step halving (the preset's solver), float32, run by ``indreg.register``.

Variants: a factor ``f`` (``velocity_factor=f`` with the preset's ``compose``; 1 is the full grid), or ``1r``: the
full grid with re-interpolation and the paper's gradient (``scripts/bench_register.py --volumes``' setting).

Time table: for every size, variant and device (the CPU; CUDA too where a GPU is present, its peak memory the
device's peak allocation) a fresh subprocess builds the data, runs ``--warmup`` iterations, then
``--iters`` more; it reports the median wall and CPU seconds (process time, all threads) per iteration between
the callbacks, evaluations per iteration, the peak RSS of the process (``ru_maxrss``: Python, torch and the data
included) and its growth over the RSS before ``register``. The factors run interleaved (1, 2, 4, 1, 2, 4, ... per
size, ``--rounds`` times): on the shared 2-core machine compare the ratios within one invocation, and the CPU
seconds, steadier than the wall time under load.

Every worker keeps large freed arrays in the heap, as the app does (``indreg._malloc.use_heap_allocator``); run
with ``INDREG_MALLOC=system`` for glibc's default (every 64 MiB volume page-faulted in afresh).

Quality table (``--quality SIZE``): the same problem for ``--quality-iters`` iterations per factor (the preset's
100); the honest SSIM / PSNR (``indreg.metrics``) against the swirled phantom at a few iteration counts, the
min Jacobian and the relative data residual at the end, wall / CPU seconds of the whole run.

    python scripts/bench_coarse_velocity.py --sizes 64 128 --factors 1 2 4 --rounds 2
    python scripts/bench_coarse_velocity.py --sizes 256 --factors 1 2 4 --rounds 1 --iters 2
    python scripts/bench_coarse_velocity.py --sizes 256x256x96 --factors 2 4 --rounds 1   # the slab
    python scripts/bench_coarse_velocity.py --sizes --quality 64
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time


def _rss_gib() -> float:
    import os

    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 30


def _shape(size: str) -> tuple:
    """``"128"`` -> ``(128, 128, 128)``; ``"256x256x96"`` -> a slab (``suite_et_3d_slab``'s box of cubic cells)."""
    parts = tuple(int(p) for p in str(size).lower().split("x"))
    return parts * 3 if len(parts) == 1 else parts


def _problem(size: str):
    """Operator, template, data and target of ``size``; the phantoms (exact, supersampled: minutes at 256^3) are
    cached in the temporary directory, so the fresh process of every row does not rebuild them."""
    import tempfile
    from pathlib import Path

    import torch

    import indreg  # noqa: F401  (first: it sets OMP_WAIT_POLICY=PASSIVE before torch starts OpenMP)
    from indreg import phantoms
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
    from indreg.inputs import box_domain
    from indreg.noise import add_white_noise

    shape = _shape(size)
    dom = box_domain(shape, 16.0)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 2, det_count=shape[0], det_min=-16.0,
                                                            det_max=16.0))
    cache = Path(tempfile.gettempdir()) / "indreg_bench_cache" / f"et_{'x'.join(map(str, shape))}.pt"
    if cache.exists():
        template, data, target = torch.load(cache)
    else:
        target = phantoms.get("shepp_logan_3d_swirl", dom)
        data, _ = add_white_noise(T(target), snr_db=10.0, seed=0, event_dims=3)
        template = phantoms.get("shepp_logan_3d", dom)
        cache.parent.mkdir(exist_ok=True)
        torch.save((template, data, target), cache)
    return T, template.float(), data.float(), target


OPTIONS = dict(sigma=3.0, num_steps=10, gamma=1e-6, interpolation="compose", step_size=0.1, step_halving=True)


def _variant(v: str) -> dict:
    """``register()`` options of a variant: ``"f"`` -> ``velocity_factor=f``; ``"1r"`` -> re-interpolation."""
    if v == "1r":
        return {**OPTIONS, "interpolation": "reinterpolate", "velocity_factor": 1}
    return {**OPTIONS, "velocity_factor": int(v)}


def worker_time(size: int, variant: str, iters: int, warmup: int, threads: int, device: str = "cpu") -> dict:
    import torch

    import indreg
    from indreg._malloc import use_heap_allocator

    use_heap_allocator()   # the app's allocator policy (INDREG_MALLOC=system: glibc's default)

    torch.set_num_threads(threads)
    T, template, data, _ = _problem(size)
    rss_before = _rss_gib()
    marks = []

    cuda = device.startswith("cuda")

    def mark(state, info):
        if cuda:
            torch.cuda.synchronize()
        marks.append((time.perf_counter(), time.process_time(), info["evaluations"]))

    result = indreg.register(template, data, T, max_iter=warmup + iters, callback=mark, device=device,
                             **_variant(variant))
    # CUDA: the device's peak allocation (the process's RSS is the host's)
    peak = torch.cuda.max_memory_allocated() / 2 ** 30 if cuda else \
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    if cuda:
        rss_before = 0.0
    timed = marks[warmup - 1:] if warmup > 0 else marks
    wall = [b[0] - a[0] for a, b in zip(timed, timed[1:])]
    cpu = [b[1] - a[1] for a, b in zip(timed, timed[1:])]
    return {"size": size, "variant": variant, "device": device, "s_per_it": statistics.median(wall),
            "cpu_per_it": statistics.median(cpu),
            "evals_per_it": (timed[-1][2] - timed[0][2]) / max(len(wall), 1), "peak_gib": peak,
            "growth_gib": peak - rss_before, "objective": result.objective}


def worker_quality(size: int, variant: str, iters: int, threads: int, at: list) -> dict:
    import torch

    import indreg
    from indreg import metrics

    torch.set_num_threads(threads)
    T, template, data, target = _problem(size)
    kept = {}

    def keep(state, info):
        if info["iteration"] in at:
            kept[info["iteration"]] = state.momentum.clone()
        return False

    t0, c0 = time.perf_counter(), time.process_time()
    r = indreg.register(template, data, T, max_iter=iters, callback=keep, target=target, **_variant(variant))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    ssim = {it: metrics.ssim(r.problem.reconstruction((m,)), target) for it, m in sorted(kept.items())}
    return {"size": size, "variant": variant, "iters": iters, "ssim_at": ssim, "ssim": r.ssim, "psnr": r.psnr,
            "min_jacobian": r.min_jacobian, "residual": r.residual, "wall": wall, "cpu": cpu,
            "evaluations": r.history[-1]["evaluations"]}


def _name(v: str) -> str:
    return "f = 1, reinterpolate, paper" if v == "1r" else f"f = {v}"


def _grid(size: str, v: str) -> str:
    shape = _shape(size)
    if v != "1r":
        shape = tuple(n // int(v) for n in shape)
    return f"{shape[0]}^3" if len(set(shape)) == 1 else "x".join(map(str, shape))


def _spawn(args: list) -> dict:
    out = subprocess.run([sys.executable, __file__, *map(str, args)], capture_output=True, text=True)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else f"exit {out.returncode}"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _devices() -> list:
    """The CPU, and CUDA where a GPU is present (its rows: the device's peak allocation as peak memory)."""
    import torch

    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def time_table(args) -> None:
    rows, devices = {}, _devices()
    for r in range(args.rounds):
        for size in args.sizes:
            for f in args.factors:
                for device in devices:
                    row = _spawn(["--worker-time", size, f, "--iters", args.iters, "--warmup", args.warmup,
                                  "--threads", args.threads, "--device", device])
                    rows.setdefault((size, f, device), []).append(row)
                    print(f"# round {r + 1}: {size} f={f} {device}: {row}", file=sys.stderr)
    print(f"\n`indreg.register`, suite_et_3d settings (sigma 3, N = 10, compose, Algorithm 1, step 0.1 with step "
          f"halving), float32, {args.threads} thread(s); median over {args.iters} iterations after {args.warmup} "
          f"warm-up, {args.rounds} interleaved round(s) (one value per round); ratio = the variant's CPU s / it over "
          f"the first variant's in the same round\n")
    print(f"| grid | variant | velocity grid | device | s / iteration | CPU s / it | CPU ratio to {args.factors[0]} | "
          "evaluations / it | peak GiB (RSS; CUDA: device) | growth GiB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        for f in args.factors:
            for device in devices:
                runs = rows[(size, f, device)]
                head = f"| {_grid(size, '1r')} | {_name(f)} | {_grid(size, f)} | {device} |"
                if any("error" in x for x in runs):
                    print(f"{head} {next(x['error'] for x in runs if 'error' in x)} | | | | | |")
                    continue
                base = rows.get((size, args.factors[0], device), [])
                ratios = [x["cpu_per_it"] / b["cpu_per_it"] for x, b in zip(runs, base) if "error" not in b]
                join = lambda key, fmt: " / ".join(format(x[key], fmt) for x in runs)  # noqa: E731
                print(f"{head} {join('s_per_it', '.2f')} | {join('cpu_per_it', '.2f')} | "
                      f"{' / '.join(f'{q:.2f}' for q in ratios)} | {join('evals_per_it', '.1f')} | "
                      f"{join('peak_gib', '.2f')} | {join('growth_gib', '.2f')} |")


def quality_table(args) -> None:
    at = args.quality_at + [args.quality_iters]
    rows = [_spawn(["--worker-quality", args.quality, f, "--quality-iters", args.quality_iters, "--threads",
                    args.threads, "--quality-at", *at]) for f in args.factors]
    print(f"\nQuality at {args.quality}^3 (suite_et_3d settings, {args.quality_iters} iterations, float32, "
          f"{args.threads} thread(s)): honest SSIM against the swirled phantom after k iterations\n")
    print("| variant | " + " | ".join(f"SSIM @ {k}" for k in at) + " | PSNR | min Jacobian | residual | "
          "evaluations | wall s | CPU s |")
    print("|---|" + "---|" * (len(at) + 6))
    for f, r in zip(args.factors, rows):
        if "error" in r:
            print(f"| {_name(f)} | {r['error']} |")
            continue
        ssim = " | ".join(f"{r['ssim_at'].get(str(k), float('nan')):.4f}" for k in at)
        print(f"| {_name(f)} | {ssim} | {r['psnr']:.2f} | {r['min_jacobian']:.3f} | {r['residual']:.4f} | "
              f"{r['evaluations']} | {r['wall']:.0f} | {r['cpu']:.0f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="*", default=["64", "128"], help="n (n^3 cells) or a slab NXxNYxNZ")
    p.add_argument("--factors", nargs="+", default=["1", "2", "4"], help="velocity factors; 1r: re-interpolation")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--iters", type=int, default=3)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--quality", type=int, default=None, help="grid size of the quality table (e.g. 64)")
    p.add_argument("--quality-iters", type=int, default=100)
    p.add_argument("--quality-at", type=int, nargs="*", default=[25, 50])
    p.add_argument("--worker-time", nargs=2, default=None, help=argparse.SUPPRESS)
    p.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    p.add_argument("--worker-quality", nargs=2, default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker_time:
        print(json.dumps(worker_time(args.worker_time[0], args.worker_time[1], args.iters, args.warmup,
                                     args.threads, args.device)))
    elif args.worker_quality:
        print(json.dumps(worker_quality(args.worker_quality[0], args.worker_quality[1], args.quality_iters,
                                        args.threads, args.quality_at)))
    else:
        if args.sizes:
            time_table(args)
        if args.quality:
            quality_table(args)


if __name__ == "__main__":
    main()
