"""Metamorphosis vs LDDMM: quality on suite 4 (missing ventricle, extra disc), a template with wrong grey values,
limited angles and a specimen on a uniform background, and cost per iteration / memory at 256^2, N = 20.

    python scripts/bench_metamorphosis.py quality --case background --iters 1000 --masks template data
    python scripts/bench_metamorphosis.py quality --case missing --size 128 --iters 300 --tau-rels 0.01 0.1 \
        --start-fractions 0 0.6 --masks data none
    python scripts/bench_metamorphosis.py quality --case limited --iters 500 --gamma 1e-5
    python scripts/bench_metamorphosis.py cost --size 256 --steps 20 --repeat 5
    python scripts/bench_metamorphosis.py tau-figure RESULTS.jsonl|MULTIRUN_DIR [--lddmm RUN_DIR] --figure tau.png
    python scripts/bench_metamorphosis.py table PRESET,METHOD,RUN_DIR ... [--figure table.md]

``quality`` runs LDDMM and metamorphosis through ``indreg.register`` (Algorithm 1, the suite's gamma / sigma /
step, no step halving, every other option at its default) on the same noisy data (10 angles x 362 bins at the
suite's SNR, seed 0; ``limited``: 20 angles over [0, pi/4], noise std 0.25) and prints SSIM / PSNR (honest and
paper convention) and the RMS error in the region where template and target differ in kind (``region_mask``: the
ventricle the suite-4 template lacks, the background the template lacks; the whole image otherwise; key
``ventricle_rms``), and the seconds per iteration, as one JSON line per run (``--out`` appends them to a file).
Metamorphosis runs once per ``--masks`` x ``--start-fractions`` x ``--tau-rels`` (and absolute ``--taus``). The
background case (``on_background``): the suite-3 template on a zero background, the target the suite-3 target on
a uniform background of ``BACKGROUND`` (0.3 of the skull's 1.0) filling the field of view outside the head (a
specimen in resin or ice); ``missing_background``: the suite-4 template that lacks a ventricle, the target on that
background. ``cost`` times one objective + gradient evaluation (``l2_gradient``: forward and
backward of the deformation and of T) of both models, interleaved, and the peak of live tensor memory
(``tracemalloc`` on torch's CPU allocations is not available, so the run is repeated under ``torch.profiler``
memory profiling).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time

import torch

import indreg
from indreg import ImageDomain, metrics, noise, phantoms
from indreg.deform import GaussianKernel, LDDMMDeformation, MetamorphosisDeformation
from indreg.forward import ParallelBeamGeometry, RayTransform
from indreg.solvers import IndirectRegistration, MetamorphosisRegistration

CASES = {  # template, SNR (dB, code convention) of the suite
    "missing": ("shepp_logan_template_missing", 7.06),
    "contrast": ("shepp_logan_template_contrast", 7.06),
    "extra": ("shepp_logan_template_extra", 6.46),
    "background": ("shepp_logan_template", 7.06),
    "missing_background": ("shepp_logan_template_missing", 7.06),   # the missing ventricle, the target on background
    "limited": ("shepp_logan_template_contrast", None),   # 20 angles over [0, pi/4], noise std 0.25 (--gamma 1e-5)
}
BACKGROUND = 0.3   # the background case: the target on a uniform disc of this value (the skull's is 1.0)
# the target's ventricle that the suite-4 template lacks: where the ventricle must appear
ventricle_mask = phantoms.missing_ventricle_mask


def problem_data(case: str, size: int, dtype=torch.float64):
    dom = ImageDomain.paper(size)
    bins = int(round(size * 362 / 256))
    T = RayTransform(dom, ParallelBeamGeometry(20, bins, -24.0, 24.0, angles=[2.25 * k for k in range(20)],
                                               angle_unit="deg") if case == "limited" else
                     ParallelBeamGeometry.paper(10, bins))
    name, snr = CASES[case]
    template, target = phantoms.get(name, dom).to(dtype), phantoms.get("shepp_logan", dom).to(dtype)
    if case in ("background", "missing_background"):
        target = on_background(target, dom, BACKGROUND)
    data, _ = noise.add_white_noise(T(target), snr_db=snr, std=0.25 if snr is None else None, seed=0)
    return dom, T, template, target, data


def on_background(target: torch.Tensor, domain, level: float, radius: float = 1.5) -> torch.Tensor:
    """The Shepp-Logan ``target`` on a uniform background: ``level`` on the disc of radius ``radius`` (normalised
    frame, [-1, 1]; 1.5: the whole square field of view) outside the head's outer ellipse (a specimen in resin or
    ice); the template keeps 0 there."""
    disc = phantoms.ellipse_phantom(domain, ((1.0, radius, radius, 0.0, 0.0, 0.0),))
    head = phantoms.ellipse_phantom(domain, ((1.0, *phantoms.SHEPP_LOGAN_ELLIPSES[0][1:]),))
    return target + level * disc * (1 - head)


def scores(image, target, mask) -> dict:
    image = image.detach().double()
    return {"ssim": metrics.ssim(image, target), "psnr": metrics.psnr(image, target),
            "ssim_paper": metrics.ssim_paper(image, target), "psnr_paper": metrics.psnr_paper(image, target),
            "ventricle_rms": float(((image - target)[mask] ** 2).mean().sqrt())}


def quality(args) -> list:
    """LDDMM and metamorphosis through ``indreg.register`` (the defaults' own path) on the same data: one row per
    run; metamorphosis once per ``--masks`` x ``--tau-rels`` (or absolute ``--taus``), all other options default."""
    dom, T, template, target, data = problem_data(args.case, args.size, torch.float32)
    region, rows = region_mask(args.case, dom, template, target), []
    common = dict(gamma=args.gamma, sigma=args.sigma, step_size=args.step, max_iter=args.iters,
                  num_steps=args.steps, step_halving=False, target=target, progress=False)
    runs = [] if args.no_lddmm else [("lddmm", {})]
    for mask in args.masks:
        for fraction in args.start_fractions:
            base = {"source_mask": None if mask == "none" else mask, "source_start_fraction": fraction}
            runs += [("metamorphosis", {**base, "tau_rel": tau_rel}) for tau_rel in args.tau_rels]
            runs += [("metamorphosis", {**base, "tau": tau, "source_start": round(fraction * args.iters)})
                     for tau in args.taus]
    for model, options in runs:
        t0 = time.perf_counter()
        r = indreg.register(template, data, T, model=model, **options, **common)
        row = {"case": args.case, "model": model, "size": args.size, "iters": args.iters, **options,
               "s_per_iter": (time.perf_counter() - t0) / max(args.iters, 1), **scores(r.deformed, target, region)}
        if model == "metamorphosis":
            row.update(tau=r.problem.tau, deformation_part=metrics.ssim(r.deformation_part.double(), target))
        rows.append(row)
        if args.save:
            torch.save({"final": r.deformed, "target": target, **r.outputs},
                       f"{args.save}_{model}_" + "_".join(map(str, options.values())) + ".pt")
    return rows


def region_mask(case: str, domain, template: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Where template and target differ in kind (the error there is the "region error"): the ventricle the suite-4
    template lacks (``missing``, ``missing_background``), the background outside the head (``background``), else the
    whole image."""
    if case in ("missing", "missing_background"):
        return ventricle_mask(domain)
    if case == "background":
        return on_background(torch.zeros_like(target), domain, 1.0) > 0.5
    return torch.ones_like(target, dtype=torch.bool)


def cost(args) -> list:
    torch.set_num_threads(args.threads)
    dom, T, template, target, data = problem_data("missing", args.size, torch.float32)
    K = GaussianKernel(dom, 2.0)
    lddmm = IndirectRegistration(T, LDDMMDeformation(dom, args.steps), K, template, data, 1e-7)
    meta = MetamorphosisRegistration(T, MetamorphosisDeformation(dom, args.steps), K, template, data, 1e-7, 1.0)
    g = torch.Generator().manual_seed(0)
    m = torch.randn(lddmm.momentum_shape, generator=g).float()
    m *= dom.cell_sides[0] / float(lddmm.velocity(m).abs().max())
    z = torch.randn(meta.source_shape, generator=g).float()
    calls = {"lddmm": lambda: lddmm.l2_gradient(m), "metamorphosis": lambda: meta.l2_gradient(m, z)}
    times = {k: [] for k in calls}
    for _ in range(args.repeat):
        for k, f in calls.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    rows = []
    for k, f in calls.items():
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], profile_memory=True) as prof:
            f()
        peak = _peak_bytes(prof)
        rows.append({"model": k, "size": args.size, "N": args.steps, "threads": args.threads,
                     "s_per_eval_min": min(times[k]), "s_per_eval_median": sorted(times[k])[len(times[k]) // 2],
                     "peak_live_MB": peak / 2 ** 20})
    return rows


def _run_row(directory, model: str) -> dict:
    """A ``tau-figure`` row from an ``indreg-register`` run dir: SSIM / PSNR of ``f(1)`` (and of ``W(nu, I)``),
    data fit, source norm ``sqrt(2 E_source / tau)`` (``||zeta||`` in ``L2([0,1], L2)`` or the source RKHS),
    RMS error in the target's ventricle (suite-4 missing template), TV's SSIM."""
    m, images, _ = _run(directory)
    row = {"model": model, "tau": m["hparams"].get("tau") if model == "metamorphosis" else None, "ssim": m["ssim"],
           "psnr": m["psnr"],
           "data_fit": m["data_fit"], "deformation_part": m.get("deformation_part_ssim", m["ssim"]),
           "source_norm": math.sqrt(2 * m.get("source_regulariser", 0.0) / m["hparams"]["tau"])
           if m["hparams"].get("tau") else 0.0, "tv_ssim": m.get("tv_ssim")}
    if m["hparams"].get("template") == "shepp_logan_template_missing":
        mask = ventricle_mask(ImageDomain.paper(images["target"].shape[0]))
        row["ventricle_rms"] = float(((images["final"] - images["target"])[mask] ** 2).mean().sqrt())
    return row


def tau_rows(source: str, lddmm: str | None = None) -> list:
    """Rows of a ``quality`` JSON-lines file, or of a Hydra multirun (``sweep=metamorphosis_tau``: one run dir per
    job, ``tau`` from its metrics) plus, optionally, an LDDMM run dir on the same data."""
    from pathlib import Path

    path = Path(source)
    if path.is_file():
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    rows = [_run_row(f.parent, "metamorphosis") for f in sorted(path.glob("*/metrics.json"))
            if json.loads(f.read_text()).get("status") in ("completed", "converged")]
    return rows + ([_run_row(lddmm, "lddmm")] if lddmm else [])


def tau_figure(args) -> list:
    """Against tau (log scale): SSIM of f(1) and of W(nu, I), data fit, source norm, RMS error in the ventricle
    (when known); LDDMM (and TV's SSIM) as horizontal lines. Prints a markdown table too."""
    from pathlib import Path

    from matplotlib.figure import Figure

    rows = tau_rows(args.source, args.lddmm)
    meta = sorted((r for r in rows if r["model"] == "metamorphosis"), key=lambda r: r["tau"])
    lddmm = [r for r in rows if r["model"] == "lddmm"]
    panels = [("ssim", "SSIM (honest)"), ("data_fit", r"data fit $\frac{1}{2}\|T f(1) - g\|^2$"),
              ("source_norm", r"source norm $\|\zeta\|$"), ("ventricle_rms", "RMS error in the ventricle")]
    panels = [p for p in panels if p[0] in meta[0]]
    fig = Figure(figsize=(3.4 * len(panels), 3.4), layout="constrained")
    taus = [r["tau"] for r in meta]
    for ax, (key, label) in zip(fig.subplots(1, len(panels)), panels):
        ax.semilogx(taus, [r[key] for r in meta], "o-", label="metamorphosis f(1)")
        if key == "ssim":
            ax.semilogx(taus, [r["deformation_part"] for r in meta], "s--", label=r"its part $W(\nu, I)$")
            tv = next((r["tv_ssim"] for r in rows if r.get("tv_ssim") is not None), None)
            if args.baselines:
                tv = json.loads((Path(args.baselines) / "metrics.json").read_text())["tv_ssim"]
            if tv is not None:
                ax.axhline(tv, color="tab:green", lw=1, ls=":", label="TV")
        if key in ("data_fit", "source_norm"):
            ax.set_yscale("log")
        for r in lddmm[:1]:
            if key in r and key != "source_norm":
                ax.axhline(r[key], color="k", lw=1, label="LDDMM")
        ax.set_xlabel(r"$\tau$  (small: reconstruction-like, large: LDDMM-like)", fontsize="small")
        ax.set_title(label)
        if key == "ssim":
            ax.legend(fontsize="small")
    fig.savefig(args.figure, dpi=100)
    keys = ["tau", "ssim", "psnr", "deformation_part", "data_fit", "source_norm"] + \
        (["ventricle_rms"] if "ventricle_rms" in meta[0] else [])
    print("| " + " | ".join(["model"] + keys) + " |\n|" + "---|" * (len(keys) + 1))
    for r in meta + lddmm:
        print("| " + " | ".join([r["model"]] + [f"{r[k]:.4g}" if isinstance(r.get(k), float) else str(r.get(k))
                                                 for k in keys]) + " |")
    return meta + lddmm


def _run(directory: str) -> tuple:
    """``(metrics.json, final, target, fbp, tv, baseline seconds)`` of an ``indreg-register`` run dir."""
    import re
    from pathlib import Path

    import numpy as np

    d = Path(directory)
    m = json.loads((d / "metrics.json").read_text())
    images = {k: torch.from_numpy(np.load(d / f"{k}.npy")).double() for k in ("final", "target", "fbp", "tv")
              if (d / f"{k}.npy").is_file()}
    log = (d / "register.log").read_text() if (d / "register.log").is_file() else ""
    found = re.search(r"baselines \(FBP, TV \d+ iterations\) in ([0-9.]+) s", log)
    return m, images, float(found.group(1)) if found else None


def table(args) -> list:
    """One markdown row per method from ``indreg-register`` run dirs given as ``PRESET,METHOD,DIR`` (FBP and TV
    rows from a dir's baselines when it has them; METHOD ``baselines``: only those); the RMS error inside the
    target's ventricle, and its ratio to
    the preset's LDDMM row, for the suite-4 missing-ventricle template."""
    rows = []
    for spec in args.runs:
        preset, method, directory = spec.split(",", 2)
        m, images, baseline_s = _run(directory)
        mask = ventricle_mask(ImageDomain.paper(images["target"].shape[0])) \
            if m["hparams"].get("template") == "shepp_logan_template_missing" else None
        entries = [] if method == "baselines" else [(method, "final", m["seconds"])]  # "baselines": FBP, TV only
        entries += [(name.upper(), name, baseline_s) for name in ("fbp", "tv") if name in images]
        for label, key, seconds in entries:
            image, target = images[key], images["target"]
            row = {"preset": preset, "method": label, "ssim": metrics.ssim(image, target),
                   "psnr": metrics.psnr(image, target), "seconds": seconds,
                   "s_per_iter": m["seconds_per_iteration"] if key == "final" else None}
            if key == "final" and "deformation_part_ssim" in m:
                row["deformation_part_ssim"] = m["deformation_part_ssim"]
            if mask is not None:
                row["ventricle_rms"] = float(((image - target)[mask] ** 2).mean().sqrt())
            rows.append(row)
    reference = {r["preset"]: r["ventricle_rms"] for r in rows if r["method"] == "LDDMM" and "ventricle_rms" in r}
    lines = ["| preset | method | SSIM (honest) | PSNR (dB) | RMS error in the ventricle (ratio to LDDMM) | seconds |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        vent = "" if "ventricle_rms" not in r else f"{r['ventricle_rms']:.3f}" + (
            f" ({r['ventricle_rms'] / reference[r['preset']]:.2f})" if r["preset"] in reference else "")
        secs = "" if r["seconds"] is None else f"{r['seconds']:.0f}" + (
            " (FBP + TV)" if r["s_per_iter"] is None else f" ({r['s_per_iter']:.2f}/it)")
        lines.append(f"| {r['preset']} | {r['method']} | {r['ssim']:.3f} | {r['psnr']:.2f} | {vent} | {secs} |")
    text = "\n".join(lines) + "\n"
    if args.figure and args.figure.endswith(".md"):
        with open(args.figure, "w") as f:
            f.write(text)
    print(text)
    return rows


def _peak_bytes(prof) -> int:
    """Peak of the running sum of allocations minus frees over the profiled events (live tensor memory)."""
    events = sorted((e.time_range.start, e.cpu_memory_usage) for e in prof.events() if e.cpu_memory_usage)
    live = peak = 0
    for _, delta in events:
        live += delta
        peak = max(peak, live)
    return peak


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=("quality", "cost", "tau-figure", "table"))
    p.add_argument("source", nargs="?", help="tau-figure: a quality JSON-lines file or a multirun dir")
    p.add_argument("runs", nargs="*", help="table: PRESET,METHOD,RUN_DIR of indreg-register runs")
    p.add_argument("--figure", default="tau_sweep.png", help="tau-figure: output image; table: a .md file")
    p.add_argument("--lddmm", default=None, help="tau-figure: an LDDMM run dir on the same data (reference lines)")
    p.add_argument("--baselines", default=None, help="tau-figure: a run dir on the same data with TV's SSIM")
    p.add_argument("--case", choices=sorted(CASES), default="missing")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--gamma", type=float, default=1e-7)
    p.add_argument("--sigma", type=float, default=2.0)
    p.add_argument("--step", type=float, default=0.02)
    p.add_argument("--taus", type=float, nargs="*", default=[], help="quality: absolute tau values")
    p.add_argument("--tau-rels", type=float, nargs="*", default=[0.01], help="quality: tau_rel values")
    p.add_argument("--start-fractions", type=float, nargs="*", default=[indreg.registration.models.RELATIVE_DEFAULTS[
        "source_start_fraction"]], help="quality: source_start_fraction values")
    p.add_argument("--masks", nargs="*", default=["data"], choices=("data", "template", "none"),
                   help="quality: source_mask values (none: no mask)")
    p.add_argument("--no-lddmm", action="store_true", help="metamorphosis runs only")
    p.add_argument("--save", default=None, help="prefix of .pt files with the resulting images")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.mode == "table" and args.source:
        args.runs = [args.source, *args.runs]
    rows = {"quality": quality, "cost": cost, "tau-figure": tau_figure, "table": table}[args.mode](args)
    for r in rows:
        line = json.dumps(r)
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")


if __name__ == "__main__":
    sys.exit(main())
