"""Spatiotemporal reconstruction of the breathing phantom (``indreg.dynamic``) against the baselines, on the same data.

Data: ``indreg.dynamic.acquisition`` (64^2 on [-16, 16]^2, K = 12 frames at t_k = k/12, 5 parallel-beam angles per
frame, the 60 angles of all frames uniform on [0, pi), 92 bins, white noise at --snr dB per frame). Rows:

    fbp_frame     FBP (Hamming 0.4) of every frame from its own 5 angles
    tv_frame      TV (Chambolle-Pock, 500 iterations) of every frame; mu the best of --mus (an oracle choice)
    fbp_static    one FBP of all 60 angles (motion ignored), compared with every frame
    tv_static     one TV of all data (motion ignored), mu the best of --mus
    known         model="spatiotemporal", the template f_0 given
    joint         template unknown: Algorithm 1 on (m, I) together (TV(I) smoothed); sigma 6, 4x the step,
                  --unknown-iters iterations
    intertwined   template unknown: per outer iteration a TV reconstruction of I through the current motion (50
                  Chambolle-Pock iterations) and 10 registration steps; the same settings

Scores: mean SSIM / PSNR over the frames (against the true f_{t_k}, data range of each true frame); for the
registrations the mean displacement error ``|phi_{t_k,0}(x) - phi^true_{t_k,0}(x)|`` in pixels over the
phantom's support (and over the whole grid), and for the unknown template the SSIM of the recovered template
and the outer iteration at which the frames' mean SSIM first comes within 0.01 of its final value. Time: CPU
seconds per iteration and peak RSS growth (``cost``: fresh subprocesses, 1 thread, at 64^2 and 256^2) of the
spatiotemporal run (template known; unknown, joint) against one LDDMM registration of the same grid and N (f_0 to
the last frame's data); ``saved_mib``: the autograd graph of one gradient, per backward.

    OMP_NUM_THREADS=1 python scripts/bench_spatiotemporal.py              # ~3 min on one core
    python scripts/bench_spatiotemporal.py --snr 10 --iters 200
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch

import indreg
from indreg import dynamic, metrics
from indreg.forward import TimeSeriesOperator, fbp, intensity_scale, tv_reconstruction

COMMON = dict(num_steps=12, sigma=3.0, gamma=1e-5)


def scores(frames, d) -> dict:
    s = [metrics.ssim(f, g) for f, g in zip(frames, d.frames)]
    p = [metrics.psnr(f, g) for f, g in zip(frames, d.frames)]
    return {"ssim": sum(s) / len(s), "psnr": sum(p) / len(p)}


def motion_error(result, d) -> dict:
    """Mean ``|phi_{t_k,0} - phi^true_{t_k,0}|`` in pixels: over the support of the phantom and the whole grid."""
    p = result.problem
    nu = p.velocity(result.momentum)
    steps = torch.arange(p.num_steps + 1).reshape(-1, 1, 1, 1)
    est = torch.stack([p.deformation_field(nu * (steps <= j)) for j in p.indices]) - p.domain.points(nu.dtype)
    err = (est - d.motion).norm(dim=1) / p.domain.cell_sides[0]
    support = (d.template != 0).expand_as(err)
    return {"motion_px": float(err[support].mean()), "motion_px_grid": float(err.mean()),
            "motion_px_identity": float((d.motion.norm(dim=1) / p.domain.cell_sides[0])[support].mean())}


def baselines(d, mus) -> dict:
    T = TimeSeriesOperator(d.operators)
    out = {"fbp_frame": scores(torch.stack([fbp(Tk, g) for Tk, g in zip(d.operators, d.data)]), d)}
    out["fbp_static"] = scores(fbp_static(d).expand_as(d.frames), d)
    unit = intensity_scale(T, d.data)
    best = {}
    for mu in mus:
        frames = torch.stack([tv_reconstruction(Tk, g, mu * intensity_scale(Tk, g), 500)[0]
                              for Tk, g in zip(d.operators, d.data)])
        static = tv_reconstruction(T, d.data, mu * unit, 500)[0]
        for name, rec in (("tv_frame", frames), ("tv_static", static.expand_as(d.frames))):
            s = dict(scores(rec, d), mu_rel=mu)
            if name not in best or s["ssim"] > best[name]["ssim"]:
                best[name] = s
    out.update(best)
    return out


def fbp_static(d):
    """One FBP of all angles (the frames' 5-angle sets merged into one sinogram)."""
    angles = torch.cat([Tk.geometry.angles for Tk in d.operators])
    order = angles.argsort()
    T = indreg.RayTransform(d.domain, indreg.ParallelBeamGeometry(angles=angles[order].tolist(), det_count=92,
                                                                  det_min=-24.0, det_max=24.0))
    return fbp(T, d.data.reshape(-1, 92)[order])


def run_registration(d, template, iters, **options) -> dict:
    """One spatiotemporal run through the shared loop (``indreg.registration.run``), scored every 5 iterations."""
    t0 = time.process_time()
    curve = []
    holder = {}

    def callback(state, info):
        if "problem" in holder and info["iteration"] % 5 == 0:
            curve.append((info["iteration"], scores(holder["problem"].all_frames(state.iterate), d)["ssim"]))

    setup = indreg.registration.run.setup(template, list(d.data), d.operators, model="spatiotemporal", times=d.times,
                             max_iter=iters, **{**COMMON, **options})
    holder["problem"] = setup.problem
    state = indreg.registration.run.initial_state(setup.problem)
    loop = indreg.registration.run.RegistrationLoop(setup.problem, setup.solver, state, iters, callback=callback)
    status = loop.run()
    cpu = time.process_time() - t0
    r = indreg.registration.run.build_result(setup.problem, state, loop.history, loop.seconds, status)
    out = dict(scores(r.frames, d), **motion_error(r, d), cpu_per_iteration=cpu / max(r.iterations, 1),
               iterations=r.iterations, status=r.status, warnings=r.warnings)
    if template is None:
        out["template_ssim"] = metrics.ssim(r.template, d.template)
        final = out["ssim"]
        first = next((it for it, s in curve if s >= final - 0.01), r.iterations)
        out["iterations_to_within_0.01"] = first
    return out


def cost(kind: str, size: int, iters: int = 8) -> dict:
    """Peak RSS growth (MiB) and the median CPU seconds per iteration (iterations 2..``iters``: the first, at
    ``m = 0``, runs the per-frame path) of ``kind`` in a fresh subprocess (1 thread) on ``size^2``, K = 12:
    ``lddmm`` (one registration: f_0 to the last frame's data, the same grid and N), ``known`` / ``unknown``
    (spatiotemporal, template given / joint). The data are simulated here and loaded there, so that the
    subprocess's peak before the run is torch's and the data's, and the growth is the run's."""
    import tempfile

    d = dynamic.acquisition(size, 12, 5, det_count=int(1.45 * size), snr_db=15.0)
    with tempfile.TemporaryDirectory() as tmp:
        path = f"{tmp}/data.pt"
        torch.save(d, path)
        code = f"""
import resource, statistics, time, torch, indreg
torch.set_num_threads(1)
d = torch.load("{path}", weights_only=False)
c = dict(num_steps=12, sigma=3.0, gamma=1e-5, step_size=0.05, max_iter={iters})
stamps = []
cb = lambda state, info: stamps.append(time.process_time())
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
if "{kind}" == "lddmm":
    indreg.register(d.template, d.data[-1], d.operators[-1], callback=cb, **c)
else:
    indreg.register(None if "{kind}" == "unknown" else d.template, list(d.data), d.operators,
                    model="spatiotemporal", times=d.times, template_update="joint", callback=cb, **c)
steps = [b - a for a, b in zip(stamps, stamps[1:])]
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024, statistics.median(steps))
"""
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    mib, cpu = out.stdout.strip().splitlines()[-1].split()
    return {"peak_rss_growth_mib": float(mib), "cpu_per_iteration": float(cpu)}


def saved_mib(size: int) -> dict:
    """MiB of tensors autograd saves for one gradient of the known-template model at a random momentum (unique
    storages, ``saved_tensors_hooks``), per ``backward``; the records the custom Functions keep on ``ctx`` are not
    seen (the exact mode's: about one velocity field per frame)."""
    from indreg.solvers import SpatiotemporalRegistration

    d = dynamic.acquisition(size, 12, 5, det_count=int(1.45 * size), snr_db=15.0)
    T, K = TimeSeriesOperator(d.operators), indreg.GaussianKernel(d.domain, 3.0)
    out = {}
    for backward in ("autograd", "exact"):
        W = indreg.LDDMMDeformation(d.domain, 12, backward=backward)
        p = SpatiotemporalRegistration(T, W, K, d.template, d.data, d.times, 1e-5)
        m = 0.1 * torch.randn(p.momentum_shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        seen = {}

        def pack(t):
            seen[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
            return t
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            p.gradient((m,))
        out[backward] = sum(seen.values()) / 2 ** 20
    out["velocity_field"] = 13 * 2 * size * size * 8 / 2 ** 20
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--snr", type=float, default=15.0)
    parser.add_argument("--iters", type=int, default=150)
    parser.add_argument("--step", type=float, default=0.05)
    parser.add_argument("--unknown-iters", type=int, default=600, help="iterations with the template unknown")
    parser.add_argument("--mus", type=float, nargs="+", default=[0.3, 1.0, 3.0, 9.1])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256], help="grids of the cost rows")
    parser.add_argument("--cost-only", action="store_true", help="only the cost rows")
    parser.add_argument("--json", default=None)
    a = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = {"cost": {f"{k}_{n}": cost(k, n) for n in a.sizes for k in ("lddmm", "known", "unknown")},
            "saved_mib": {n: saved_mib(n) for n in a.sizes}}
    if not a.cost_only:
        rows.update(quality(a))
    print(json.dumps(rows, indent=1))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


def quality(a) -> dict:
    """The scores of every row on the same data (module docstring)."""
    d = dynamic.acquisition(64, 12, 5, snr_db=a.snr)
    rows = baselines(d, a.mus)
    rows["template_static"] = scores(d.template.expand_as(d.frames), d)
    rows["known"] = run_registration(d, d.template, a.iters, step_size=a.step)
    tv = intensity_scale(TimeSeriesOperator(d.operators), d.data) / 2   # TV(I) weight: 1 x the data's unit / 2
    unknown = dict(sigma=6.0, step_size=4 * a.step, template_tv_weight=tv)
    for update in ("joint", "intertwined"):
        rows[update] = run_registration(d, None, a.unknown_iters, template_update=update, **unknown)
    return rows


if __name__ == "__main__":
    main()
