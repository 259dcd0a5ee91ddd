"""Seconds to quality: wall-clock time until the deformed template first reaches the paper's SSIM.

For each suite (1: J -> V, 64^2; 3: Shepp-Logan, 256^2) and mode (``algorithm1``: the paper's Algorithm 1
preset, ``indreg-register experiment=<suite>``; ``fast``: ``solver=fast``; ablations below), the problem is
built as the app builds it (``indreg.experiments.build`` on the composed config, so data, operators and solver
are the app's), then ``solver.step`` runs until the solver stops (``solver.max_iter`` of the preset, or the
solver's own convergence test). Only the steps are timed; after every step, outside the timed region, the
deformed template ``W(K m, I)`` (the problem's deformation, its grid) is compared with the ground truth:
SSIM in the paper's convention (``metrics.ssim_paper``) decides when the paper's value is reached (suite 3:
0.9039, suite 1: 0.911, the authors' code; the 3D electron-tomography presets ``et128`` / ``et256``: the honest
SSIM 0.93, issue #20's target, the column "SSIM*" then means it), and the honest SSIM / PSNR (``metrics.ssim`` / ``psnr``, data
range of the ground truth) are reported then and at the end; "stays from" is the time from which SSIM* does not
drop below the paper's value again until the end; "SSIM >= 0.92 at" the first time the honest SSIM reaches
0.92 (the fast mode's target at the end of suite 3). The ground truth is only measured, never given
to a solver. Before the timed runs every mode runs a few untimed iterations (one-time initialisation).

Modes (``--modes``; each a list of config overrides on top of the suite's preset):

    algorithm1               the paper's preset (reinterpolate, Algorithm 1, step 0.02)
    fast                     solver=fast (coarse to fine, Algorithm 1 with step 0.08 on every level, compose)
    algorithm1_compose       Algorithm 1 with deformation.interpolation=compose
    algorithm1_compose_step  Algorithm 1 with compose and step 0.08 (fast on one grid)
    fast_reinterpolate       solver=fast with the paper's reinterpolation
    fast_step                solver=fast with the paper's step 0.02
    fast_level_iter          solver=fast with 20 iterations (instead of up to 100) on the 2x coarser grid
    fast_lbfgs               solver=fast with L-BFGS (exact gradient, strong Wolfe) on every level
    lbfgs_compose            single-grid L-BFGS (solver=lbfgs) with compose

    python scripts/bench_time_to_quality.py                             # suites 1 and 3, algorithm1 and fast
    python scripts/bench_time_to_quality.py --suites 3 --modes algorithm1 fast algorithm1_compose --repeat 2
    python scripts/bench_time_to_quality.py --suites et128 --modes fast fast_f2 --threads 1

Prints one Markdown table, a row per run with what its mode changes; its last two columns compare the seconds
to SSIM* with those of ``algorithm1`` (the speed-up) and of ``fast`` (for an ablation, what the part of fast it
removes or replaces gains) in the same repetition. ``--json FILE`` also writes the rows. Timings depend on
the machine's load: run with ``OMP_NUM_THREADS`` fixed and compare modes measured in the same invocation
(``--repeat`` interleaves the modes ``repeat`` times).
"""
from __future__ import annotations

import argparse
import json
import math
import time

SUITES = {  # suite: (preset, SSIM* threshold, the metric it is read on)
    "1": ("suite1_jv", 0.911, "ssim_paper"), "3": ("suite3_shepp_logan", 0.9039, "ssim_paper"),
    # electron tomography in 3D (issue #20's targets): no paper value, the honest SSIM 0.93 is SSIM*
    "et128": ("suite_et_3d_128", 0.93, "ssim"), "et256": ("suite_et_3d_256", 0.93, "ssim")}
HONEST = 0.92   # the honest SSIM the fast mode must end above on suite 3 (time to it: a column of the table)
MODES = {   # mode: (config overrides, what it changes)
    "algorithm1": ([], "the paper's preset: one grid, reinterpolate, step 0.02"),
    "fast": (["solver=fast"], "coarse to fine + compose + step 0.08"),
    "algorithm1_compose": (["deformation.interpolation=compose"], "paper's + compose"),
    "algorithm1_compose_step": (["deformation.interpolation=compose", "solver.step_size=0.08"],
                                "paper's + compose + step 0.08 (fast, one grid)"),
    "fast_reinterpolate": (["solver=fast", "deformation.interpolation=reinterpolate"], "fast, reinterpolate"),
    "fast_step": (["solver=fast", "solver.optimizer_kwargs.step_size=0.02"], "fast, step 0.02"),
    "fast_level_iter": (["solver=fast", "solver.optimizer_kwargs.level_iter=[40,20]"],
                        "fast, 20 iterations on the 2x coarser grid"),
    "fast_lbfgs": (["solver=fast", "solver.optimizer_kwargs.inner=lbfgs",
                    "solver.optimizer_kwargs.level_iter=[30,40]"], "fast, L-BFGS on every level"),
    "lbfgs_compose": (["solver=lbfgs", "deformation.interpolation=compose"], "one grid, L-BFGS + compose"),
    "fast_f2": (["solver=fast", "deformation.velocity_factor=2"], "fast, velocity on a 2x coarser grid"),
    "fast_f4": (["solver=fast", "deformation.velocity_factor=4"], "fast, velocity on a 4x coarser grid"),
    "algorithm1_f4": (["deformation.velocity_factor=4"], "preset, velocity on a 4x coarser grid"),
}


def compose(overrides: list):
    """The app's config for ``overrides`` (Hydra compose API on the app's config dir), validated."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from indreg.experiments import register
    from indreg.experiments.config import CONFIG_DIR, validate

    GlobalHydra.instance().clear()
    with initialize_config_dir(version_base="1.3", config_dir=str(CONFIG_DIR), job_name="bench"):
        cfg = hydra_compose(register._CONFIG_NAME, overrides=overrides)
    validate(cfg)
    return cfg


def build(suite: str, mode: str, extra: list):
    from indreg.experiments.build import build as build_experiment
    from indreg.experiments.build import seed_everything

    cfg = compose([f"experiment={SUITES[suite][0]}", "device=cpu", *MODES[mode][0], *extra])
    seed_everything(cfg.seed)
    return build_experiment(cfg)


def quality(exp, momentum) -> dict:
    from indreg import metrics

    f = exp.problem.deformed(momentum).to("cpu").double()
    t = exp.target_64
    return {"ssim_paper": metrics.ssim_paper(f, t), "ssim": metrics.ssim(f, t), "psnr": metrics.psnr(f, t)}


def warm_up(suite: str, mode: str, extra: list, steps: int = 3) -> None:
    from indreg.solvers import SolverState

    exp = build(suite, mode, extra)
    state = SolverState(exp.problem.zero_momentum())
    for _ in range(steps):
        exp.solver.step(state)


def measure(suite: str, mode: str, extra: list, max_seconds: float) -> dict:
    """Run one mode to its end (or ``max_seconds`` of solver time); the first iterate at the paper's SSIM."""
    from indreg.solvers import SolverState

    exp = build(suite, mode, extra)
    _, threshold, metric = SUITES[suite]
    solver, state = exp.solver, SolverState(exp.problem.zero_momentum())
    seconds, hit, stays, honest, info, status = 0.0, None, None, None, None, None
    while status is None and seconds < max_seconds:
        t0 = time.perf_counter()
        info = solver.step(state)
        seconds += time.perf_counter() - t0
        status = solver.status(info)
        q = quality(exp, state.momentum)      # untimed
        point = dict(q, seconds=seconds, iteration=state.iteration, evaluations=info["evaluations"])
        if q["ssim"] >= HONEST:
            honest = honest or point
        if q[metric] >= threshold:
            hit = hit or point
            stays = stays or point
        else:
            stays = None
    end = dict(quality(exp, state.momentum), seconds=seconds, iteration=state.iteration,
               evaluations=info["evaluations"], status=status or "time limit", objective=info["objective"])
    return {"suite": suite, "mode": mode, "hit": hit, "stays": stays, "honest": honest, "end": end,
            "solver": repr(solver)}


def _f(x, fmt):
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def _base(rows: list, r: dict, mode: str):
    """The run of ``mode`` in ``r``'s suite and repetition that reached the paper's SSIM (None if none)."""
    return next((b for b in rows if b["suite"] == r["suite"] and b["mode"] == mode and b["run"] == r["run"]
                 and b["hit"]), None)


def _ratio(num, den) -> str:
    return f"{num['hit']['seconds'] / den['hit']['seconds']:.1f}x" if num and den else "-"


def table(rows: list) -> str:
    """One row per run; the last two columns compare the seconds to SSIM* with the same repetition's
    ``algorithm1`` (speed-up) and ``fast`` (an ablation's time over fast's: what the part it removes gains)."""
    head = ("| suite | mode | what it changes | run | SSIM* reached at: s | it | evals | SSIM / PSNR then "
            f"| stays >= SSIM* from: s | SSIM >= {HONEST} at: s | end: s | it | status | SSIM* / SSIM / PSNR at end "
            "| speed-up to SSIM* vs algorithm1 | time to SSIM* / fast's |")
    out = [head, "|" + "---|" * 16]
    for r in rows:
        h, e, st, hon = r["hit"] or {}, r["end"], r["stays"] or {}, r.get("honest") or {}
        out.append(f"| {r['suite']} | {r['mode']} | {MODES[r['mode']][1]} | {r['run']} | "
                   f"{_f(h.get('seconds'), '.2f')} | {_f(h.get('iteration'), 'd')} | "
                   f"{_f(h.get('evaluations'), 'd')} | {_f(h.get('ssim'), '.4f')} / {_f(h.get('psnr'), '.2f')} | "
                   f"{_f(st.get('seconds'), '.2f')} | {_f(hon.get('seconds'), '.2f')} | {e['seconds']:.2f} | "
                   f"{e['iteration']} | {e['status']} | "
                   f"{e['ssim_paper']:.4f} / {e['ssim']:.4f} / {e['psnr']:.2f} | "
                   f"{_ratio(_base(rows, r, 'algorithm1'), r if r['hit'] else None)} | "
                   f"{_ratio(r if r['hit'] else None, _base(rows, r, 'fast'))} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suites", nargs="+", default=["3", "1"], choices=sorted(SUITES))
    ap.add_argument("--modes", nargs="+", default=["algorithm1", "fast"], choices=list(MODES))
    ap.add_argument("--repeat", type=int, default=1, help="interleaved repetitions of all modes")
    ap.add_argument("--max-seconds", type=float, default=600.0, help="solver time limit of one run")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    ap.add_argument("--json", default=None, help="also write the rows to this file")
    ap.add_argument("--override", action="append", default=[], dest="overrides",
                    help="a config override applied to every run (key=value; repeatable)")
    args = ap.parse_args()
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s)", flush=True)
    rows = []
    for suite in args.suites:
        for mode in args.modes:
            warm_up(suite, mode, args.overrides)
        for run in range(1, args.repeat + 1):
            modes = args.modes if run % 2 else args.modes[::-1]
            for mode in modes:
                r = dict(measure(suite, mode, args.overrides, args.max_seconds), run=run)
                rows.append(r)
                print(json.dumps(r), flush=True)
    rows.sort(key=lambda r: (r["suite"], r["run"], list(MODES).index(r["mode"])))
    print(table(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
