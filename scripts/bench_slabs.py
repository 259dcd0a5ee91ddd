"""Benchmark of the slab-wise data term (``indreg.problems.slabs``) and of one registration across processes.

Three tables (Markdown), each row from a fresh subprocess (its peak memory its own):

- ``whole``: a tilt series (61 tilts, -60..60 degrees, about y) of an ``n^3`` volume, velocity factor ``f``, N time
  steps: seconds per gradient (median of ``--reps`` after one warm-up) and peak memory, whole-volume
  (``IndirectRegistration``) against slab-wise (``SlabwiseRegistration``, ``--slab-size`` or automatic), the
  variants interleaved (``--rounds`` rounds) so that their ratio is of one run; per-slab costs (the replicated
  coarse flow, sweep and kernel, and the seconds per slice) for the prediction below.
- ``big``: a ``1024 x 1024 x 256`` volume (the tilt axis y of 1024 slices, 61 tilts on a 1024-column detector),
  ``f = 4``, ``N = 10``, one process: Algorithm 1 with step halving for ``--big-iters`` iterations, seconds per
  iteration and the peak; the template and target are phantoms of a 4x coarser grid interpolated (the phantoms'
  float64 coordinates of the full grid would take 6 GiB).
- ``ranks``: ``indreg-register experiment=suite_et_3d_256`` (``--ranks-iters`` iterations, no baselines unless
  ``--ranks-baselines``; ``--ranks-size`` another ``phantom.size`` for a quick look) under ``torchrun
  --nproc_per_node=2`` with one thread a rank, against one process with two threads (``--ranks-runs``: which of the
  two, and one process slab-wise): objective, each rank's peak and wall time, slabs per rank, all-reduce bytes per
  iteration; the seconds of each set-up and output stage of every process (``CLI_STAGES``: phantoms, projection and
  noise, set-up, baselines, the loop, the outputs); and the time per iteration that the measured per-slice and
  replicated costs predict for ``1024 x 1024 x 256`` on 8 and 64 ranks.
- ``stages`` (not in the default set): milliseconds per slice of each stage of a slab's gradient at
  ``1024 x 1024 x 256`` (``big``'s problem at the first iterate: the upsampling ``P_s u_N``, the grid, the warp, the
  projector, its transpose, the warp's adjoint and ``P_s^T``), ``--stage-slabs`` slabs after a warm-up one.

Memory: the process's peak resident set (``VmHWM``, reset after the set-up: the template, the data and what the
gradients or iterations add, Python and torch included; CUDA: the device's peak allocation). Timings on a shared
machine are noisy: the load average is printed with each table.

    python scripts/bench_slabs.py                              # the three tables (about 15 minutes on 2 cores)
    python scripts/bench_slabs.py --tables whole --n 128       # a quick look
    python scripts/bench_slabs.py --tables whole big --device cuda
    python scripts/bench_slabs.py --tables ranks --ranks-runs two one --ranks-iters 100   # the whole preset's run
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GIB = 2 ** 30


# ------------------------------------------------------------------------------------------------ in the child
def _peak_gib(device) -> float:
    import torch
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / GIB
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 2 ** 20


def _reset_peak(device) -> None:
    """Start the peak afresh after the set-up (its float64 phantoms): glibc's free memory back to the system, the
    kernel's high-water mark reset (``/proc/self/clear_refs``); CUDA: the allocator's peak."""
    import ctypes

    import torch
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _problem(shape, box, factor, steps, device, slab_size, max_memory, coarse_phantoms):
    """The tilt-series problem of ``shape`` (cubic cells, ``box`` the half-widths) and its momentum after one
    gradient step (so that the template moves)."""
    import torch
    import torch.nn.functional as F
    from indreg import ImageDomain, phantoms
    from indreg.deform import CoarseVelocityDeformation, GaussianKernel, coarse_domain
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
    from indreg.problems import IndirectRegistration
    from indreg.problems.slabs import SlabwiseRegistration

    dom = ImageDomain(shape, tuple(-b for b in box), box)
    geom = TiltSeriesGeometry.uniform(-60, 60, 2, det_count=shape[0], det_min=-box[0], det_max=box[0])
    T = TiltSeriesTransform(dom, geom)
    c = coarse_phantoms
    small = ImageDomain(tuple(n // c for n in shape), dom.min_pt, dom.max_pt)

    def volume(name):
        v = phantoms.get(name, small).to(torch.float32)
        if c > 1:
            v = F.interpolate(v[None, None], size=shape, mode="trilinear", align_corners=False)[0, 0]
        return v.to(device)

    template = volume("shepp_logan_3d")
    data = T(volume("shepp_logan_3d_swirl"))
    cd = coarse_domain(dom, factor)
    args = (T, CoarseVelocityDeformation(dom, cd, num_steps=steps), GaussianKernel(cd, 3.0), template, data, 1e-6)
    slab = SlabwiseRegistration(*args, slab_size=slab_size, max_memory=max_memory) \
        if slab_size or max_memory else None
    problem = slab or IndirectRegistration(*args)
    m = torch.zeros(problem.momentum_shape, device=device)
    _reset_peak(device)
    return problem, m


def child_gradient(a) -> dict:
    import torch
    device = torch.device(a.device)
    problem, m = _problem((a.n,) * 3, (16.0,) * 3, a.factor, a.steps, device, a.slab_size, None, 1)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    _, h, _ = problem.l2_gradient(m)          # warm-up, and a step so that the template moves
    m = m - 0.1 * h / float(h.abs().max())
    times = []
    for _ in range(a.reps):
        sync()
        t = time.perf_counter()
        terms, h, _ = problem.l2_gradient(m)
        sync()
        times.append(time.perf_counter() - t)
    out = {"seconds": statistics.median(times), "peak_gib": _peak_gib(device), "objective": terms["objective"],
           "grad_norm": float(h.norm())}
    if hasattr(problem, "slab_ranges"):
        out.update(slab_costs(problem, m, sync))
    return out


def slab_costs(problem, m, sync) -> dict:
    """The replicated part of a slab-wise gradient (flow, kernel, sweep: the total less the slabs) and the seconds
    per fine slice, from one timed pass over the slabs."""
    import torch
    nu = problem.velocity(m)
    sync()
    t0 = time.perf_counter()
    slots, jac, _ = problem._flow(nu)
    sync()
    t1 = time.perf_counter()
    kappa = torch.zeros(problem.image_domain.ndim, *problem.domain.shape, dtype=m.dtype, device=m.device)
    for start, stop in problem.slab_ranges:
        problem._slab(slots[-1], None, start, stop, (kappa, None))
    sync()
    t2 = time.perf_counter()
    sync()
    t3 = time.perf_counter()
    problem.l2_gradient(m)
    sync()
    total = time.perf_counter() - t3
    slices = problem.image_domain.shape[problem.axis]
    return {"slab_size": problem.slab_size, "slabs": len(problem.slab_ranges), "flow_s": t1 - t0,
            "per_slice_s": (t2 - t1) / slices, "replicated_s": total - (t2 - t1),
            "allreduce_bytes": problem.allreduce_bytes}


def child_big(a) -> dict:
    import torch
    from indreg.solvers import Algorithm1, SolverState
    device = torch.device(a.device)
    problem, m = _problem((1024, 1024, 256), (16.0, 16.0, 4.0), 4, 10, device, None, a.max_memory, 4)
    setup = _peak_gib(device)
    solver = Algorithm1(problem, step_size=0.1, max_iter=a.big_iters, step_halving=True)
    state = SolverState(m)
    walls = []
    for _ in range(a.big_iters):
        t = time.perf_counter()
        info = solver.step(state)
        walls.append(time.perf_counter() - t)
    return {"seconds_per_iteration": statistics.median(walls), "walls": walls, "peak_gib": _peak_gib(device),
            "setup_gib": setup, "slab_size": getattr(problem, "slab_size", None),  # None: whole volume, no slabs
            "slabs": len(getattr(problem, "slab_ranges", ())),
            "objective": info["objective"], "evaluations": info.get("evaluations"),
            "dtype": str(problem.template.dtype)}


STAGES = ("upsample_rows", "_grid", "_sample", "_project", "_backproject", "_sample_adjoint", "upsample_rows_adjoint")


def child_stages(a) -> dict:
    """Milliseconds per fine slice of each stage of ``SlabwiseRegistration._slab`` (with its gradient) at
    1024 x 1024 x 256 (``child_big``'s problem) for ``--stage-slabs`` slabs at the middle of the tilt axis, at the
    momentum ``-0.1 h`` (``h`` the gradient at 0: the first iterate's displacements), after one warm-up slab."""
    import collections

    import torch
    from indreg.problems import slabs
    device = torch.device(a.device)
    problem, m = _problem((1024, 1024, 256), (16.0, 16.0, 4.0), 4, 10, device, None, a.max_memory, 4)
    _, h, _ = problem.l2_gradient(m)
    m = m.sub_(h, alpha=0.1)
    del h
    with torch.no_grad():
        slots, _, _ = problem._flow(problem.velocity(m))
        u = slots[-1].clone()
        del slots
    spent = collections.defaultdict(float)

    def timed(name, fn):
        def run(*args, **kwargs):
            t = time.perf_counter()
            out = fn(*args, **kwargs)
            spent[name] += time.perf_counter() - t
            return out
        return run

    for name in STAGES:
        owner = slabs.SlabwiseRegistration if name in ("_grid", "_sample", "_project", "_backproject") else slabs
        setattr(owner, name, timed(name, getattr(owner, name)))
    kappa = torch.zeros(3, *problem.domain.shape, device=device)
    mid = len(problem.slab_ranges) // 2
    with torch.no_grad():
        for k, s in enumerate(range(mid - 1, mid + a.stage_slabs)):
            if k == 1:
                spent.clear()
                t = time.perf_counter()
            problem._slab(u, None, *problem.slab_ranges[s], (kappa, None))
    slices = a.stage_slabs * problem.slab_size
    out = {name: spent[name] / slices * 1e3 for name in STAGES}
    out["total"] = (time.perf_counter() - t) / slices * 1e3
    return {"ms_per_slice": out, "slab_size": problem.slab_size}


#: The app's set-up and output stages timed by ``child_cli``: (module, attribute, label); a label with ``{0}``
#: takes the call's first argument (the phantom's name). Nested stages are timed inside their parents.
CLI_STAGES = (
    ("indreg.experiments.runner", "_distributed", "process group"),
    ("indreg.experiments.runner", "build", "build (all below)"),
    ("indreg.phantoms", "get", "phantom {0}"),
    ("indreg.experiments.builtin_sources", "make_data", "data: projection and noise"),
    ("indreg.noise", "add_white_noise", "data: noise"),
    ("indreg.experiments.builtin_sources", "check_tilt_axis", "data: tilt-axis check"),
    ("indreg.experiments.build", "fine_arrays_in", "cast to the run's dtype"),
    ("indreg.registration.run", "setup", "setup (units, problem, solver)"),
    ("indreg.experiments.runner", "baselines", "baselines"),
    ("indreg.registration.run.RegistrationLoop", "run", "the registration loop"),
    ("indreg.experiments.runner", "finish", "outputs (all below)"),
    ("indreg.experiments.outputs", "build_result", "result (deformed, phi, residual, min Jacobian)"),
    ("indreg.experiments.outputs", "figures_of_merit", "SSIM / PSNR"),
    ("indreg.experiments.outputs", "save_array", "arrays written"),
    ("indreg.experiments.outputs", "save_frames", "trajectory (frames written)"),
    ("indreg.io", "write_volume", "final.mrc"),
    ("indreg.experiments.outputs", "write_figures", "figures"),
)


def _time_stages(spent: dict) -> None:
    """Wrap each of ``CLI_STAGES`` so that its seconds add up in ``spent`` (by label)."""
    import importlib

    def wrap(fn, label):
        def timed(*args, **kwargs):
            key = label.format(*args) if "{0}" in label else label
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[key] = spent.get(key, 0.0) + time.perf_counter() - t
        return timed

    for module, name, label in CLI_STAGES:
        path, _, cls = module.rpartition(".") if module.endswith("RegistrationLoop") else (module, "", "")
        owner = getattr(importlib.import_module(path), cls) if cls else importlib.import_module(module)
        setattr(owner, name, wrap(getattr(owner, name), label))


def child_cli(overrides) -> None:
    """``indreg-register`` with ``overrides``; at exit one JSON line with this rank's peak, wall time and the
    seconds of its set-up and output stages (``CLI_STAGES``)."""
    import atexit
    t0 = time.perf_counter()
    spent: dict = {}

    def report():
        with open("/proc/self/status") as f:
            peak = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 2 ** 20
        print("RANKSTAT " + json.dumps({"rank": int(os.environ.get("RANK", "0")), "peak_gib": peak,
                                        "wall_s": time.perf_counter() - t0, "stages": spent}),
              file=sys.stderr, flush=True)

    atexit.register(report)
    _time_stages(spent)
    from indreg.experiments import runner
    finish = runner.finish

    def finish_after_the_loop(*args, **kwargs):   # the peak of the registration, before the outputs
        with open("/proc/self/status") as f:
            loop = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 2 ** 20
        print("LOOPSTAT " + json.dumps({"loop_peak_gib": loop}), file=sys.stderr, flush=True)
        return finish(*args, **kwargs)

    runner.finish = finish_after_the_loop
    from indreg.experiments.register import main
    sys.argv = ["indreg-register", *overrides]
    main()


# ------------------------------------------------------------------------------------------------ in the parent
def _spawn(args, threads, extra_env=None, launcher=(sys.executable,)) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONPATH=str(ROOT), **(extra_env or {}))
    return subprocess.run([*launcher, *args], env=env, capture_output=True, text=True, cwd=ROOT)


def _json(proc) -> dict:
    if proc.returncode != 0:
        raise SystemExit(f"child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _load() -> str:
    return " / ".join(f"{x:.2f}" for x in os.getloadavg())


def table_whole(a) -> dict:
    rows = {"whole": [], "slab": []}
    for _ in range(a.rounds):
        for variant in rows:
            cmd = [__file__, "--child", "gradient", "--n", str(a.n), "--factor", str(a.factor), "--steps",
                   str(a.steps), "--reps", str(a.reps), "--device", a.device]
            cmd += ["--slab-size", str(a.slab_size if variant == "slab" else 0)]     # 0: whole volume
            rows[variant].append(_json(_spawn(cmd, a.threads)))
    w, s = ({k: statistics.median(r[k] for r in rows[v]) for k in ("seconds", "peak_gib")} for v in rows)
    slab = rows["slab"][-1]
    print(f"\n{a.n}^3, f = {a.factor}, N = {a.steps}, 61 tilts, {a.threads} thread(s), {a.device}; load {_load()}\n")
    print("| variant | s / gradient | peak GiB | objective |\n|---|---|---|---|")
    for v in rows:
        label = v if v == "whole" else f"slab-wise ({slab['slabs']} x {slab['slab_size']} slices)"
        print(f"| {label} | "
              + " | ".join(f"{statistics.median(r[k] for r in rows[v]):{f}}" for k, f in
                           (("seconds", ".2f"), ("peak_gib", ".2f"), ("objective", ".6g"))) + " |")
    print(f"\nslab / whole: time {s['seconds'] / w['seconds']:.2f}x, peak {s['peak_gib'] / w['peak_gib']:.2f}x; "
          f"gradients agree to {abs(rows['slab'][-1]['grad_norm'] / rows['whole'][-1]['grad_norm'] - 1):.1e} "
          f"(norm); per slice {slab['per_slice_s'] * 1e3:.1f} ms, replicated (flow, kernel, sweep) "
          f"{slab['replicated_s']:.2f} s, all-reduce {slab['allreduce_bytes'] / 2 ** 20:.1f} MiB")
    return slab


def table_big(a) -> None:
    cmd = [__file__, "--child", "big", "--big-iters", str(a.big_iters), "--device", a.device]
    if a.max_memory:
        cmd += ["--max-memory", str(a.max_memory)]
    r = _json(_spawn(cmd, a.threads))
    print(f"\n1024 x 1024 x 256, f = 4, N = 10, 61 tilts, one process, {a.threads} thread(s), {a.device}; "
          f"load {_load()}\n")
    print("| slabs | s / iteration | peak GiB | after set-up GiB | dtype |\n|---|---|---|---|---|")
    slabs = f"{r['slabs']} x {r['slab_size']} slices" if r["slabs"] else "whole volume"
    print(f"| {slabs} | {r['seconds_per_iteration']:.1f} "
          f"({', '.join(f'{w:.1f}' for w in r['walls'])}) | {r['peak_gib']:.2f} | {r['setup_gib']:.2f} | "
          f"{r['dtype']} |")


def table_stages(a) -> None:
    cmd = [__file__, "--child", "stages", "--stage-slabs", str(a.stage_slabs), "--device", a.device]
    if a.max_memory:
        cmd += ["--max-memory", str(a.max_memory)]
    r = _json(_spawn(cmd, a.threads))
    print(f"\n1024 x 1024 x 256, slabs of {r['slab_size']} slices, ms per 1024 x 256 slice; load {_load()}\n")
    print("| stage | ms / slice |\n|---|---|")
    for name, ms in r["ms_per_slice"].items():
        print(f"| {name} | {ms:.1f} |")


def _cli(name, threads, launcher, overrides, tmp) -> tuple:
    """One ``indreg-register`` run: ``(metrics, per-rank stats, slabs per rank x slices)``."""
    out = Path(tmp) / re.sub(r"\W+", "_", name)
    proc = _spawn([__file__, "--child", "cli", "--", *overrides, f"hydra.run.dir={out}"], threads, launcher=launcher)
    if proc.returncode != 0:
        raise SystemExit(f"{name} failed:\n{proc.stderr[-3000:]}")
    stats = [json.loads(line.split("RANKSTAT ", 1)[1]) for line in proc.stderr.splitlines() if "RANKSTAT " in line]
    loop = [json.loads(line.split("LOOPSTAT ", 1)[1]) for line in proc.stderr.splitlines() if "LOOPSTAT " in line]
    stats = sorted(stats, key=lambda s: s["rank"])
    stats[0].update(loop[0])     # rank 0 writes the outputs; the others' peak is their loop's
    split = re.search(r"slab_size=(\d+), slabs=(\d+)", proc.stderr + proc.stdout)
    slabs = "whole" if split is None else f"{int(split[2]) // len(stats)} x {split[1]}"
    return json.loads((out / "metrics.json").read_text()), stats, slabs


#: The runs of the ``ranks`` table (``--ranks-runs``): name, threads, launched by torchrun, extra overrides.
RANK_RUNS = {"one": ("1 process, 2 threads", 2, False, []),
             "two": ("2 ranks, 1 thread each", 1, True, []),
             "slab": ("1 process, 2 threads, slab-wise", 2, False, ["deformation.slab_size=32"])}


def table_ranks(a, slab) -> None:
    base = ["experiment=suite_et_3d_256", f"solver.max_iter={a.ranks_iters}", "logging.figure=false",
            "logging.tensorboard=false", "logging.progress=false", "device=cpu"]
    base += [] if a.ranks_baselines else ["baseline=none"]
    base += [] if a.ranks_size == 256 else [f"phantom.size={a.ranks_size}", f"geometry.det_count={a.ranks_size}"]
    torchrun = (sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2")
    with tempfile.TemporaryDirectory() as tmp:
        runs = {name: _cli(name, threads, torchrun if ranked else (sys.executable,), base + extra, tmp)
                for name, threads, ranked, extra in (RANK_RUNS[k] for k in a.ranks_runs)}
    size = "" if a.ranks_size == 256 else f" at {a.ranks_size}^3"
    print(f"\nsuite_et_3d_256{size}, {a.ranks_iters} iterations, {'with' if a.ranks_baselines else 'no'} baselines; "
          f"load {_load()}\n")
    print("| run | ranks | slabs per rank x slices | all-reduce / gradient | s / it | per-rank peak GiB (rank 0: loop "
          "/ with the outputs) | per-rank wall s | objective | SSIM |\n|---|---|---|---|---|---|---|---|---|")
    for name, (m, stats, slabs) in runs.items():
        ar = 0 if len(stats) == 1 else (3 * 64 ** 3 + 1) * 4     # dL/du_N on the 64^3 velocity grid, and the fit
        peaks = [f"{stats[0]['loop_peak_gib']:.2f} / {stats[0]['peak_gib']:.2f}"] + \
            [f"{s['peak_gib']:.2f}" for s in stats[1:]]
        print(f"| {name} | {len(stats)} | {slabs} | {ar / 2 ** 20:.1f} MiB | {m['seconds_per_iteration']:.2f} | "
              + ", ".join(peaks) + " | " + ", ".join(f"{s['wall_s']:.0f}" for s in stats)
              + f" | {m['objective']:.8g} | {m['ssim']:.4f} |")
    stage_table(runs)
    one, two = (runs.get(RANK_RUNS[k][0]) for k in ("one", "two"))
    if one is None or two is None:
        return
    ratios = [f"wall time {max(s['wall_s'] for s in two[1]) / one[1][0]['wall_s']:.2f}x (the slower rank)",
              f"s / it {two[0]['seconds_per_iteration'] / one[0]['seconds_per_iteration']:.2f}x",
              f"objective {abs(two[0]['objective'] / one[0]['objective'] - 1):.1e} relative (float32)"]
    loop_peak = max([two[1][0]["loop_peak_gib"]] + [s["peak_gib"] for s in two[1][1:]])
    ratios.append(f"loop peak {loop_peak / one[1][0]['loop_peak_gib']:.2f}x")
    print("\n2 ranks / 1 process: " + "; ".join(ratios))
    if slab is not None:
        predict(slab, a)


def stage_table(runs: dict) -> None:
    """Seconds of each set-up and output stage (``CLI_STAGES``), one column a process; ``other``: the wall time
    less the top-level stages (imports, the config, the checkpoint's checks, the final all-reduce)."""
    columns = [(f"{name}, rank {s['rank']}" if len(stats) > 1 else name, s) for name, (_, stats, _) in runs.items()
               for s in stats]
    seen = list(dict.fromkeys(k for _, s in columns for k in s["stages"]))
    labels = [k for _, _, label in CLI_STAGES for k in seen if k == label or k.startswith(label.split("{0}")[0])
              and "{0}" in label]
    top = [label for _, _, label in CLI_STAGES if label in ("process group", "build (all below)", "baselines",
                                                             "the registration loop", "outputs (all below)")]
    print("\n| stage (s) | " + " | ".join(c for c, _ in columns) + " |\n|---|" + "---|" * len(columns))
    for label in labels:
        print(f"| {label} | " + " | ".join(f"{s['stages'].get(label, 0.0):.1f}" for _, s in columns) + " |")
    print("| other | " + " | ".join(f"{s['wall_s'] - sum(s['stages'].get(k, 0.0) for k in top):.1f}"
                                  for _, s in columns) + " |")
    print("| **wall** | " + " | ".join(f"**{s['wall_s']:.1f}**" for _, s in columns) + " |")


def predict(slab, a) -> None:
    """Seconds per gradient of 1024 x 1024 x 256 (f = 4: coarse 256 x 256 x 64) on P ranks, from this machine's
    per-slice and replicated costs (16x the n^3 run's replicated part: the coarse grid has 16x the cells) and a
    ring all-reduce at 10 GB/s (2 (P-1)/P bytes per rank)."""
    scale = (256 * 256 * 64) / (a.n // a.factor) ** 3
    per_slice = slab["per_slice_s"] * (1024 * 256) / (a.n * a.n)     # a slice of 1024 x 256 cells
    replicated = slab["replicated_s"] * scale
    nbytes = slab["allreduce_bytes"] * scale
    print("\nprediction, 1024 x 1024 x 256 (per-slice and replicated costs of this CPU; a GPU divides both):\n")
    print("| ranks | slices per rank | slabs s | replicated s | all-reduce s (10 GB/s) | s / gradient |\n"
          "|---|---|---|---|---|---|")
    for p in (1, 8, 64):
        comm = 0.0 if p == 1 else 2 * (p - 1) / p * nbytes / 10e9
        slabs = per_slice * 1024 / p
        print(f"| {p} | {1024 // p} | {slabs:.2f} | {replicated:.2f} | {comm:.3f} | {slabs + replicated + comm:.2f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tables", nargs="+", default=["whole", "big", "ranks"],
                   choices=["whole", "big", "ranks", "stages"])
    p.add_argument("--n", type=int, default=256)
    p.add_argument("--factor", type=int, default=4)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--slab-size", type=int, default=32)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--big-iters", type=int, default=2)
    p.add_argument("--ranks-iters", type=int, default=5)
    p.add_argument("--ranks-runs", nargs="+", default=list(RANK_RUNS), choices=list(RANK_RUNS),
                   help="the ranks table's runs: one process, two ranks, one process slab-wise")
    p.add_argument("--ranks-size", type=int, default=256, help="the ranks table's phantom.size (a quick look)")
    p.add_argument("--ranks-baselines", action="store_true", help="the ranks table's runs with the baselines")
    p.add_argument("--max-memory", type=float, default=None, help="bytes for a gradient's working set (e.g. 8e9)")
    p.add_argument("--stage-slabs", type=int, default=8)
    p.add_argument("--device", default="cpu")
    p.add_argument("--child", choices=["gradient", "big", "cli", "stages"])
    a, rest = p.parse_known_args()
    if a.child == "cli":
        return child_cli([x for x in rest if x != "--"])
    if a.child:
        print(json.dumps({"gradient": child_gradient, "big": child_big, "stages": child_stages}[a.child](a)))
        return
    slab = table_whole(a) if "whole" in a.tables else None
    if "big" in a.tables:
        table_big(a)
    if "ranks" in a.tables:
        table_ranks(a, slab)
    if "stages" in a.tables:
        table_stages(a)


if __name__ == "__main__":
    main()
