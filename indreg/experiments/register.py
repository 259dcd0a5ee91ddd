"""``indreg-register``: run one indirect registration experiment of the paper (a Hydra app).

Usage (configs in ``indreg/conf/``, the checkout's ``configs/``; every key can be overridden as ``key=value``)::

    indreg-register                                   # suite 1 (J -> V), the default experiment
    indreg-register experiment=suite3_shepp_logan dtype=float64 device=cuda
    indreg-register experiment=own_data_example       # the shipped example of your own data (files)
    indreg-register data=files data.template=T.png data.sinogram=S.npy geometry=parallel geometry.angles=A.tlt \
        geometry.det_min=-24 geometry.det_max=24 [data.target=G.npy]     # your files (docs/own_data.md)
    indreg-register hydra.run.dir=outputs/suite1      # a fixed run dir, so that it can be resumed:
    indreg-register hydra.run.dir=outputs/suite1 resume=true
    # the suite-3 table as one multirun: locally in 2 worker processes, or as a SLURM array job
    indreg-register -m sweep=suite3_table hydra/launcher=joblib hydra.launcher.n_jobs=2 \
        hydra.sweep.dir=multirun/suite3_table
    indreg-register -m sweep=suite3_table hydra/launcher=slurm hydra.launcher.partition=<partition> \
        hydra.sweep.dir=multirun/suite3_table resume=true
    indreg-sweep-table multirun/suite3_table                    # the paper's table (table.md, table.csv)
    tensorboard --logdir outputs                      # or the multirun dir (HParams tab compares the sweep)

A fixed ``hydra.run.dir`` / ``hydra.sweep.dir`` (the defaults contain the date and time) is what makes a run or
a sweep resumable: rerun the same command with ``resume=true``. See configs/README.md.

A run builds the problem (:mod:`indreg.experiments.build`: data from the ``data`` source, then the same setup as
``indreg.register``), computes the FBP and TV baselines from the same data, then runs the loop shared with
``indreg.register`` (``indreg.run.RegistrationLoop``) for ``solver.max_iter`` iterations: scalars to TensorBoard
every iteration; a progress line (``iteration i/total``, it/s, ETA), SSIM / PSNR (with a target) and the deformed
template every ``logging.every``; a checkpoint every ``logging.checkpoint_every`` and on SIGINT / SIGTERM (then
the process exits with 128 + signal number). ``resume=true`` continues from ``<run dir>/checkpoint.pt`` and ends
with the same numbers as an uninterrupted run. In a multirun every log line starts with ``[job <n>]``. Outputs in
the run dir: ``metrics.json``, ``history.json``, ``final.npy``, ``trajectory.npy``, ``velocity.npy``,
``momentum.npy``, ``deformation.npy`` (phi_{1,0}), ``target.npy``, ``template.npy``, ``data.npy``,
``data_clean.npy``, ``fbp.npy``, ``tv.npy``, ``figure.png``, ``tensorboard/``, ``checkpoint.pt`` (a model with
frames, ``spatiotemporal``: ``frames.npy``, ``frames.png`` and the movie ``frames.gif``; volumes also
``final.mrc``, with the voxel size in its header, and ``sirt.npy``; ``figure.png`` shows orthogonal slices); measured data
without a target have no ``target.npy`` / ``data_clean.npy`` and no SSIM / PSNR (``residual``, the relative data
misfit, is always in metrics.json).
"""
from __future__ import annotations

import json
import logging
import math
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from ..io import DataFileError
from ..run import RegistrationLoop, build_result, count_halvings, count_rejected, initial_state
from . import checkpoint as ckpt
from . import cli
from .build import build, seed_everything
from .config import CONFIG_DIR, ConfigError, register_schema, to_plain, validate

log = logging.getLogger(__name__)

# Config keys that may change between an interrupted run and its resumption.
_RESUMABLE = ("name", "device", "resume", "stop_after", "logging", "baseline")


class StopRequest:
    """SIGINT / SIGTERM handlers that only record the signal; the loop then checkpoints and exits.

    A second signal gets the previous handler (e.g. a second Ctrl-C raises KeyboardInterrupt at once).
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.signum = None
        self._previous = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # e.g. a launcher running jobs in threads: signals are not ours to handle
        for s in self.SIGNALS:
            self._previous[s] = signal.signal(s, self._handle)

    def _handle(self, signum, frame) -> None:
        self.signum = signum
        log.warning("received %s: writing a checkpoint after this iteration, then exiting",
                    signal.Signals(signum).name)
        self.restore()

    def restore(self) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}


def _numpy(x) -> np.ndarray:
    return x.detach().to("cpu", torch.float64).numpy()


def figures_of_merit(image, target_64, paper: bool = True) -> dict:
    """SSIM / PSNR against the target (data range of the target) and, for the paper's phantoms (``paper``:
    grey levels 0..1), also in the paper's convention (``ssim_paper`` / ``psnr_paper``: a fixed data range 2 / 1
    that means nothing for other units; docs/paper_notes.md)."""
    from .. import metrics

    x = image.detach().to("cpu", torch.float64)
    out = {"ssim": metrics.ssim(x, target_64), "psnr": metrics.psnr(x, target_64)}
    if paper:
        out.update(ssim_paper=metrics.ssim_paper(x, target_64), psnr_paper=metrics.psnr_paper(x, target_64))
    return out


def output_fom(image, truth, ndim: int) -> dict:
    """SSIM / PSNR of a model's output against its ground truth; a stack (one more axis than the domain's, e.g.
    frames) gets the means over its first axis."""
    if truth.dim() == ndim:
        return figures_of_merit(image, truth, paper=False)
    each = [figures_of_merit(a, b, paper=False) for a, b in zip(image, truth)]
    return {k: sum(e[k] for e in each) / len(each) for k in each[0]}


def tv_mu(cfg: DictConfig, exp) -> float:
    """The TV baseline's absolute weight: ``baseline.tv_mu`` times the data's intensity unit
    (``indreg.forward.intensity_scale``), so that the baseline is the same for data in any units."""
    from ..forward import intensity_scale

    return float(cfg.baseline.tv_mu) * intensity_scale(exp.ray_transform, exp.noisy_data_64)


def baselines(cfg: DictConfig, exp, out: Path) -> dict:
    """FBP and TV reconstructions from the noisy data (images: float64, volumes: the run's dtype, on the run's
    device, returned on the CPU as float64); cached in ``baselines.npz`` so that a resumed run does not recompute
    them. FBP and SIRT are linear in the data; TV's weight scales with them (:func:`tv_mu`). Volumes take the run's
    dtype: at 256^3 a float64 SIRT / TV iteration costs about twice a float32 one."""
    if not cfg.baseline.enabled:
        return {}
    b = cfg.baseline
    volume = exp.domain.ndim == 3
    mu = tv_mu(cfg, exp)
    key = np.array([b.fbp_filter.value, b.fbp_frequency_scaling, b.fbp_padding, repr(mu), b.tv_iterations,
                    b.sirt_iterations if volume else 0], dtype=str)
    cache = out / "baselines.npz"
    if cache.is_file():
        with np.load(cache) as z:
            if np.array_equal(z["key"], key):
                return {k: torch.from_numpy(z[k]) for k in z.files if k != "key"}
    from ..forward import fbp, sirt
    from ..forward.tv import tv_reconstruction

    t0 = time.perf_counter()
    T, g = exp.ray_transform, exp.noisy_data_64.to(exp.template.device, exp.template.dtype if volume else None)
    rec = {"fbp": fbp(T, g, filter=b.fbp_filter.value, frequency_scaling=b.fbp_frequency_scaling,
                      padding=b.fbp_padding)}
    if volume:  # electron tomography's iterative baseline
        rec["sirt"] = sirt(T, g, num_iter=b.sirt_iterations, nonneg=True)[0]
    rec["tv"] = tv_reconstruction(T, g, mu=mu, num_iter=b.tv_iterations)[0]
    rec = {k: v.detach().to("cpu", torch.float64) for k, v in rec.items()}
    log.info("baselines (%s) in %.1f s", ", ".join(rec).upper().replace(
        "TV", f"TV {b.tv_iterations} iterations, mu {mu:.4g} = {b.tv_mu:g} x the data's intensity unit"),
        time.perf_counter() - t0)
    np.savez(cache, key=key, **{k: v.numpy() for k, v in rec.items()})
    return rec


def _problem_config(plain: dict) -> dict:
    """The config keys that define the iterates (all but ``_RESUMABLE`` and ``solver.max_iter``)."""
    out = {k: v for k, v in plain.items() if k not in _RESUMABLE}
    out["solver"] = {k: v for k, v in out["solver"].items() if k != "max_iter"}
    return out


def _step_size(exp) -> float:
    """The configured step: Algorithm 1's (also solver=fast's inner one), else the optimiser's lr."""
    o = exp.options
    if hasattr(exp.solver, "step_sizes") or getattr(exp.solver, "inner", None) == "algorithm1":
        return float(exp.solver.step_size)
    return float(o["lr"] if o["lr"] is not None else 1.0)


def hyperparameters(cfg: DictConfig, exp) -> dict:
    """The run's parameters shown in TensorBoard's HParams tab and in metrics.json (the model adds its own)."""
    o = exp.options
    return {"gamma": float(o["gamma"]), "sigma": float(o["sigma"]), "N": int(o["num_steps"]), "model": o["model"],
            "step_size": _step_size(exp), "action": o["action"], "solver": o["solver"], "template": exp.label,
            "size": int(exp.domain.shape[0]), "max_iter": int(o["max_iter"]), "dtype": cfg.dtype.value,
            "seed": int(cfg.seed), **exp.problem.hparams()}


def _json_float(v):
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


class AppLoop(RegistrationLoop):
    """The shared registration loop plus the app's outputs: TensorBoard scalars every iteration; SSIM / PSNR
    (with a target) and the deformed template every ``logging.every``; a checkpoint every
    ``logging.checkpoint_every``; ``stop_after`` and SIGINT / SIGTERM stop it (``stopped`` / ``interrupted``)."""

    def __init__(self, cfg, exp, state, writer, path: Path, problem_cfg: dict, history, seconds):
        super().__init__(exp.problem, exp.solver, state, cfg.solver.max_iter, every=cfg.logging.every,
                         progress=cfg.logging.progress, desc=cfg.name, history=history, seconds=seconds,
                         validation=exp.validation)
        self.cfg, self.exp, self.writer, self.path, self.problem_cfg = cfg, exp, writer, path, problem_cfg
        self.stop = StopRequest()
        self._fom = ""

    def save_checkpoint(self) -> None:
        ckpt.save(self.path, {"iteration": self.state.iteration, "state": self.state.state_dict(),
                              "solver": self.solver.state_dict(), "rng": ckpt.rng_state(), "history": self.history,
                              "seconds": self.seconds, "problem": self.problem_cfg})

    def before_step(self):
        stop_after = self.cfg.stop_after
        return "stopped" if stop_after is not None and self.state.iteration >= stop_after else None

    def after_step(self, info: dict, done: bool):
        it, lg, exp = self.state.iteration, self.cfg.logging, self.exp
        self.writer.scalars(info, it)
        if "holdout_residual" in info:
            self.writer.validation(info["holdout_residual"], it)
        self._fom = ""
        if it % lg.every == 0 and not done:  # the last iterate is evaluated by finish()
            deformed = self.problem.reconstruction(self.state.iterate)
            if exp.target_64 is not None:
                fom = figures_of_merit(deformed, exp.target_64, exp.paper)
                self.writer.metrics(fom, it)
                self._fom = f", SSIM {fom['ssim']:.4f}, PSNR {fom['psnr']:.2f}"
            self.writer.image("images/deformed_template", deformed, it)
        if it % lg.checkpoint_every == 0:
            self.save_checkpoint()
        return "interrupted" if self.stop.signum is not None else None

    def describe(self, info: dict) -> str:
        return self._fom

    def run(self) -> str:
        self.stop.install()
        try:
            return super().run()
        finally:
            self.stop.restore()


def run(cfg: DictConfig, output_dir) -> dict:
    """Run (or resume) the experiment of ``cfg`` writing into ``output_dir``; returns ``metrics.json``'s dict.

    The dict has ``status``: ``completed`` (``max_iter`` reached), ``converged`` (``solver.grad_tol``),
    ``stalled`` (step halving collapsed the step: ``indreg.run.STALL_WINDOW``), ``diverged`` (finished with a
    relative data residual >= 1), ``failed`` (a non-finite objective or gradient: ``metrics.json`` and
    ``history.json`` hold the status, the iteration and the warning; the checkpoint keeps the last finite iterate),
    ``early_stopped`` (``validation.patience`` held-out evaluations without a new minimum), ``stopped``
    (``stop_after``) or ``interrupted`` (a signal; ``signal`` holds its number). Only ``completed``, ``converged``,
    ``stalled``, ``early_stopped`` and ``diverged`` runs write the final outputs. A bad config value, a bad data file,
    a bad run directory or a damaged / foreign / mismatched checkpoint raises ``ConfigError``, ``DataFileError`` or ``CheckpointError`` before any computing.
    """
    from .tblog import RunWriter

    validate(cfg)
    out = Path(output_dir)
    path = out / "checkpoint.pt"
    ckpt.check_location(path, cfg.resume)
    problem_cfg = _problem_config(to_plain(cfg))
    saved = _read_checkpoint(cfg, path, problem_cfg)
    seed_everything(cfg.seed)
    try:
        exp = build(cfg)  # reads and checks the data (files) before any computing
    except DataFileError:
        raise
    except (ValueError, TypeError) as e:  # the operators' input validation
        raise ConfigError(f"invalid configuration: {e}") from e
    problem = exp.problem
    log.info("%s | %s | %s", cfg.name, problem, exp.solver)
    rec = baselines(cfg, exp, out)

    state = initial_state(problem)
    history, seconds = [], 0.0
    if saved is not None:
        with ckpt.restoring(path):
            ckpt.check_state(saved, state, cfg.solver.max_iter)
            state.load_state_dict(saved["state"])
            state.iterate = tuple(t.to(device=exp.template.device, dtype=exp.template.dtype) for t in state.iterate)
            problem.check_iterate(state.iterate)
            exp.solver.load_state_dict(saved["solver"])
            ckpt.set_rng_state(saved["rng"])
            history, seconds = list(saved["history"]), float(saved["seconds"])
        log.info("resumed from %s at iteration %d", path, state.iteration)

    shown = exp.target_64 if exp.target_64 is not None else exp.template_64
    # a resumed run drops the events an interrupted one logged after its checkpoint
    writer = RunWriter(out / "tensorboard", state.iteration + 1 if state.iteration > 0 else None,
                       float(shown.min()), float(shown.max()), enabled=cfg.logging.tensorboard)
    if state.iteration == 0:
        writer.image("images/template", exp.template_64, 0)
        if exp.target_64 is not None:
            writer.image("images/target", exp.target_64, 0)
        for k, v in rec.items():
            writer.image(f"images/{k}", v, 0)
        writer.image("images/deformed_template", exp.template_64, 0)
        if exp.target_64 is not None:
            writer.metrics(figures_of_merit(exp.template_64, exp.target_64, exp.paper), 0)

    loop = AppLoop(cfg, exp, state, writer, path, problem_cfg, history, seconds)
    status = loop.run()
    if status == "failed":  # keep the last checkpoint: its iterate is finite
        writer.close()
        return _failed(out, loop.history)
    loop.save_checkpoint()
    if status in ("stopped", "interrupted"):
        writer.close()
        log.warning("%s at iteration %d; continue with resume=true (same run dir %s)", status, state.iteration, out)
        return {"status": status, "iteration": state.iteration, "signal": loop.stop.signum}
    result = finish(cfg, exp, state, rec, loop.history, loop.seconds, out, writer, status)
    writer.close()
    return result


def _read_checkpoint(cfg: DictConfig, path: Path, problem_cfg: dict):
    """With ``resume``: the verified checkpoint at ``path`` (None if there is none), refused if its problem
    differs from the config's or it is past ``solver.max_iter``."""
    if not cfg.resume:
        return None
    if not path.exists():
        log.warning("resume=true but there is no %s: starting at iteration 0", path)
        return None
    saved = ckpt.load(path, keys=("iteration", "state", "solver", "rng", "history", "seconds", "problem"))
    with ckpt.restoring(path):
        mismatch = ckpt.problem_mismatch(saved["problem"], problem_cfg)
        iteration = int(saved["iteration"])
    if mismatch:
        raise ConfigError("resume=true but the config differs from the checkpoint's: " + "; ".join(mismatch))
    if iteration > cfg.solver.max_iter:
        raise ckpt.CheckpointError(f"checkpoint {path} is at iteration {iteration}, past solver.max_iter="
                                   f"{cfg.solver.max_iter}: raise solver.max_iter to at least {iteration} or "
                                   "run without resume=true")
    return saved


def _failed(out: Path, history: list) -> dict:
    """A run whose objective or gradient became non-finite: ``metrics.json`` and ``history.json`` say so."""
    last = history[-1]
    result = {"status": "failed", "iteration": last["iteration"], "objective": last["objective"],
              "grad_norm": last["grad_norm"], "evaluations": last["evaluations"],
              "warning": last["warning"] or "non-finite gradient norm"}
    with open(out / "history.json", "w") as f:
        json.dump([{k: _json_float(v) for k, v in h.items()} for h in history], f)
    with open(out / "metrics.json", "w") as f:
        json.dump({k: _json_float(v) for k, v in result.items()}, f, indent=2)
    log.error("failed at iteration %d: %s (%s is not overwritten: it keeps the last periodic checkpoint, if any)",
              result["iteration"], result["warning"], out / "checkpoint.pt")
    return result


def finish(cfg, exp, state, rec, history, seconds, out: Path, writer, status: str) -> dict:
    """Final outputs: arrays, metrics.json, history.json, figure.png, TensorBoard images and hparams, from the
    result that ``indreg.register`` would return (``indreg.run.build_result``).

    Without a target (measured data) SSIM / PSNR, ``target.npy`` and ``data_clean.npy`` are absent; the relative
    data residual ``residual = ||T f - g|| / ||g||`` is always reported. The model's own outputs (e.g. a source and
    the parts of f(1)) are saved by name; those it scores (``problem.scored``) get SSIM / PSNR."""
    from .tblog import METRICS

    problem, it = exp.problem, state.iteration
    r = build_result(problem, state, history, seconds, status, units=exp.units, validation=exp.validation)
    target = exp.target_64
    result = {}
    if target is not None:
        def fom(image):
            return figures_of_merit(image, target, exp.paper)

        result.update(fom(r.deformed))
        for name, image in rec.items():
            result.update({f"{name}_{k}": v for k, v in fom(image).items()})
        result.update({f"template_{k}": v for k, v in fom(exp.template_64).items()})
        for name in problem.scored:
            result.update({f"{name}_{k}": v for k, v in fom(r.outputs[name]).items()})
    for name, truth in exp.targets.items():   # a model's outputs against their own ground truths
        if name in r.outputs:
            result.update({f"{name}_{k}": v for k, v in output_fom(r.outputs[name], truth, exp.domain.ndim).items()})
    result.update(r.terms)
    result.update({
        "status": r.status, "residual": r.residual, "iterations": it,
        "seconds_per_iteration": seconds / max(len(history), 1), "seconds": seconds, "min_jacobian": r.min_jacobian,
        "grad_norm": history[-1]["grad_norm"] if history else float("nan"),
        "evaluations": history[-1]["evaluations"] if history else 0,
        "warnings": r.warnings, "rejected_steps": count_rejected(history), "halvings": count_halvings(history),
        **exp.units.as_dict(), **({"tv_mu_absolute": tv_mu(cfg, exp)} if "tv" in rec else {}),
        "device": str(exp.template.device), "hparams": hyperparameters(cfg, exp), "config": to_plain(cfg)})
    result.update(r.holdout)
    if r.alignment:   # shifts per tilt and the tilt-axis angle (docs/alignment.md), and their plot
        from ..alignment import plot_shifts
        result["alignment"] = r.alignment
        plot_shifts(r.alignment, out / "alignment.png")
    result.update(exp.report)
    if exp.snr_db is not None:
        result.update({"snr_db": exp.snr_db, "snr_convention": cfg.noise.convention.value})
    arrays = {"final": r.deformed, "trajectory": r.trajectory, "velocity": r.velocity, "momentum": r.momentum,
              "deformation": r.deformation, "template": exp.template_64, "data": exp.noisy_data_64, **rec,
              **r.outputs}
    if target is not None:
        arrays["target"] = target
    if exp.clean_data_64 is not None:
        arrays["data_clean"] = exp.clean_data_64
    for name, a in arrays.items():
        np.save(out / f"{name}.npy", _numpy(a))
    if exp.domain.ndim == 3:  # the registered volume for IMOD / ChimeraX too (voxel size in the header)
        from ..io import write_volume
        write_volume(out / "final.mrc", _numpy(r.deformed), exp.domain)
    with open(out / "history.json", "w") as f:
        json.dump([{k: _json_float(v) for k, v in h.items()} for h in history], f)
    with open(out / "metrics.json", "w") as f:
        json.dump({k: _json_float(v) for k, v in result.items()}, f, indent=2)
    _figures(cfg, exp, r, rec, result, out, writer, it)
    writer.metrics(result, it)
    writer.hparams(result["hparams"], {k: result[k] for k in (*METRICS, "residual", "holdout_residual")
                                                        if k in result})
    done = f"{r.status}: {it} iterations" if r.status != "completed" else f"done: {it} iterations"
    if target is not None:
        paper = f" (paper convention {result['ssim_paper']:.4f} / {result['psnr_paper']:.2f})" if exp.paper else ""
        log.info("%s, SSIM %.4f, PSNR %.2f dB%s; FBP %s; TV %s; %d warnings", done, result["ssim"], result["psnr"],
                 paper, _pair(result, "fbp"), _pair(result, "tv") + (f"; SIRT {_pair(result, 'sirt')}" if "sirt" in rec
                                                                     else ""), result["warnings"])
    else:
        log.info("%s, objective %.6g, relative data residual %.4f, min Jacobian %.4g; %d warnings", done,
                 result["objective"], result["residual"], result["min_jacobian"], result["warnings"])
    if r.holdout:
        log.info("held-out angles %s: relative residual %.4f (least %.4f at iteration %s)", r.holdout["holdout_indices"],
                 r.holdout["holdout_residual"], r.holdout["holdout_best_residual"], r.holdout["holdout_best_iteration"])
    return result


def _figures(cfg, exp, r, rec: dict, result: dict, out: Path, writer, it: int) -> None:
    """figure.png (the paper's layout for images, orthogonal slices for volumes), parts.png when the model
    splits its reconstruction (``deformation_part`` / ``intensity_part``), and TensorBoard's final images."""
    from . import figures

    traj, target = _numpy(r.trajectory), exp.target_64
    volume = exp.domain.ndim == 3
    parts = (r.outputs["deformation_part"], r.outputs["intensity_part"]) \
        if {"deformation_part", "intensity_part"} <= set(r.outputs) else None
    quality = (f"SSIM {result['ssim']:.4f}, PSNR {result['psnr']:.2f} dB" if target is not None
               else f"relative data residual {result['residual']:.4f}")
    if cfg.logging.figure:
        figure = _ortho_figure if volume else _paper_figure
        figures.save(figure(exp, traj, rec, title=f"{cfg.name}: {quality}"), out / "figure.png")
        if parts is not None:
            figures.save(_parts_figure(exp, r.deformed, parts, title=f"{cfg.name}: {quality}"), out / "parts.png")
    n = traj.shape[0] - 1
    writer.strip("images/trajectory", [traj[0]] + [traj[i] for i in figures.time_indices(n)], it)
    writer.image("images/deformed_template", r.deformed, it)
    grid = _numpy(r.deformation)
    if volume:  # the xy plane through the centre: (x, y) of phi on the central z slice
        grid = grid[:2, :, :, grid.shape[-1] // 2]
    writer.figure("images/deformed_grid", figures.deformed_grid_figure(grid), it)
    if "frames" in r.outputs:   # several time points: the frames in a row, one image each, and a movie
        frames = _numpy(r.outputs["frames"])
        truth = exp.targets.get("frames")
        writer.strip("images/frames", list(frames), it)
        for k, f in enumerate(frames):
            writer.image(f"images/frames/{k:02d}", f, it)
        if cfg.logging.figure:
            shown = exp.target_64 if exp.target_64 is not None else frames[-1]
            figures.save(figures.frames_figure(frames, None if truth is None else _numpy(truth),
                                               title=f"{cfg.name}: frames (top), truth (bottom)"), out / "frames.png")
            figures.save_gif(frames, out / "frames.gif", float(shown.min()), float(shown.max()))
    if parts is not None:
        writer.image("images/deformation_part", parts[0], it)
        bound = max(float(parts[1].abs().max()), 1e-12)
        writer.image_scaled("images/intensity_part", parts[1], it, -bound, bound)
        writer.figure("images/parts", _parts_figure(exp, r.deformed, parts), it)


def _paper_figure(exp, traj, rec: dict, title: str):
    """``figures.paper_figure`` of a 2D run: the data panel shows the first row of the data against the
    detector coordinate where the geometry gives one (``det_points``), else against the bin index."""
    from . import figures

    noisy = exp.noisy_data_64.reshape(-1, exp.noisy_data_64.shape[-1])
    clean = None if exp.clean_data_64 is None else exp.clean_data_64.reshape(noisy.shape)[0].numpy()
    det = getattr(exp.geometry, "det_points", None)
    angles = getattr(exp.geometry, "angles", None)
    target = None if exp.target_64 is None else exp.target_64.numpy()
    return figures.paper_figure(exp.template_64.numpy(), traj, target,
                                np.arange(noisy.shape[-1]) if det is None else det.numpy(), clean, noisy[0].numpy(),
                                _numpy(rec["fbp"]) if "fbp" in rec else None,
                                _numpy(rec["tv"]) if "tv" in rec else None, extent=domain_extent(exp.domain),
                                title=title, angle_deg=0.0 if angles is None else float(angles[0]) * 180 / math.pi)


def _ortho_figure(exp, traj, rec: dict, title: str = ""):
    """A volume's run: orthogonal slices of the template, W(nu, I) at t = 0.5 and 1, target and baselines."""
    from . import figures

    n = traj.shape[0] - 1
    panels = [("template", exp.template_64.numpy()), ("t = 0.5", traj[n // 2]), ("t = 1", traj[n])]
    panels += [("target", None if exp.target_64 is None else exp.target_64.numpy())]
    panels += [(k.upper(), _numpy(v)) for k, v in rec.items()]
    shown = exp.target_64 if exp.target_64 is not None else exp.template_64
    return figures.ortho_figure(panels, float(shown.min()), float(shown.max()), title=title)


def _parts_figure(exp, final, parts, title: str = ""):
    """``figures.parts_figure`` of a run (volumes: ``parts_ortho_figure``): f(1), W(nu, I), f(1) - W(nu, I),
    target."""
    from . import figures

    target = None if exp.target_64 is None else exp.target_64.numpy()
    if exp.domain.ndim == 3:
        return figures.parts_ortho_figure(_numpy(final), _numpy(parts[0]), _numpy(parts[1]), target, title=title)
    return figures.parts_figure(_numpy(final), _numpy(parts[0]), _numpy(parts[1]), target,
                                extent=domain_extent(exp.domain), title=title)


def domain_extent(domain) -> tuple:
    """``imshow`` extent (x_min, x_max, y_min, y_max) of the domain."""
    (x0, y0), (x1, y1) = domain.min_pt, domain.max_pt
    return x0, x1, y0, y1


def _pair(result: dict, name: str) -> str:
    if f"{name}_ssim" not in result:
        return "off"
    return f"{result[f'{name}_ssim']:.4f} / {result[f'{name}_psnr']:.2f}"


_CONFIG_NAME = "config"
PROG = "indreg-register"
register_schema()


def _prefix_job_logs(cfg_hydra) -> None:
    """In a multirun, prefix every log line of this job with ``[job <hydra.job.num>]``."""
    from hydra.types import RunMode

    if cfg_hydra.mode != RunMode.MULTIRUN:
        return
    for handler in logging.getLogger().handlers:
        fmt = handler.formatter._fmt if handler.formatter is not None else "%(message)s"
        datefmt = handler.formatter.datefmt if handler.formatter is not None else None
        handler.setFormatter(logging.Formatter(f"[job {cfg_hydra.job.num}] {fmt}", datefmt))


def _task(cfg: DictConfig):
    """The Hydra task. Exit status: 0 done (completed, converged, stalled, early_stopped, stopped); 1 a user
    error (``ConfigError``, ``DataFileError``, ``CheckpointError``) or a failed or diverged run, with one line
    ``indreg-register: error: ...`` on stderr;
    128 + signal number after SIGINT / SIGTERM (checkpoint written)."""
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    _prefix_job_logs(hc)
    try:
        result = run(cfg, hc.runtime.output_dir)
    except (ConfigError, DataFileError, ckpt.CheckpointError) as e:  # user errors: one line, no traceback
        _log_to_file(str(e))
        _exit_error(str(e))
    if result["status"] == "interrupted":
        sys.exit(128 + int(result["signal"]))
    if result["status"] == "failed":
        _exit_error(f"the run failed at iteration {result['iteration']}: {result['warning']}")
    if result["status"] == "diverged":
        _exit_error(f"the run diverged: relative data residual {result['residual']:.4g} >= 1 after "
                    f"{result['iterations']} iterations (worse than a zero image); check the units of template and "
                    "data (data.template_scale=auto, data.background=auto) and the step (outputs in "
                    f"{hc.runtime.output_dir})")
    return result.get("ssim")


def _log_to_file(message: str) -> None:
    """``message`` as an error in the run's log file (the console gets the one-line error), so that a run
    directory never keeps an empty log."""
    record = logging.LogRecord(log.name, logging.ERROR, __file__, 0, " ".join(message.split()), None, None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def _exit_error(message: str) -> None:
    """``indreg-register: error: <message>`` on stderr (one line), exit status 1."""
    cli.exit_error(PROG, message)


def _check_config(cfg: DictConfig) -> None:
    """The config's values and (``data=files``) that its files exist, before any directory is created."""
    from .sources import check_files

    validate(cfg)
    check_files(cfg)


def preflight(argv) -> None:
    """Check the command line before Hydra creates the run directory (:func:`indreg.experiments.cli.preflight`:
    launcher plugin, composition, the config's values, the data files, the run directory), so that a problem
    ends in one line (``indreg-register: error: ...``, exit 1) with nothing written."""
    cli.preflight(argv, PROG, CONFIG_DIR, _CONFIG_NAME, validate=_check_config)


def main() -> None:
    """Console entry point ``indreg-register`` (Hydra parses ``sys.argv``); large freed arrays stay in the heap
    (``indreg._malloc``: 256^3 volumes are not page-faulted in afresh at every operation)."""
    import hydra

    from .._malloc import use_heap_allocator

    use_heap_allocator()
    preflight(sys.argv[1:])
    hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=_CONFIG_NAME)(_task)()


if __name__ == "__main__":
    main()
