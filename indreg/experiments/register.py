"""``indreg-register``: run one indirect registration experiment of the paper (a Hydra app).

Usage (configs in ``indreg/conf/``, the checkout's ``configs/``; every key can be overridden as ``key=value``)::

    indreg-register                                   # suite 1 (J -> V), the default experiment
    indreg-register experiment=suite3_shepp_logan dtype=float64 device=cuda
    indreg-register hydra.run.dir=outputs/suite1      # a fixed run dir, so that it can be resumed:
    indreg-register hydra.run.dir=outputs/suite1 resume=true
    # the suite-3 table as one multirun: locally in 2 worker processes, or as a SLURM array job
    indreg-register -m sweep=suite3_table hydra/launcher=joblib hydra.launcher.n_jobs=2 \
        hydra.sweep.dir=multirun/suite3_table
    indreg-register -m sweep=suite3_table hydra/launcher=slurm hydra.launcher.partition=<partition> \
        hydra.sweep.dir=multirun/suite3_table resume=true
    python scripts/sweep_table.py multirun/suite3_table          # the paper's table (table.md, table.csv)
    tensorboard --logdir outputs                      # or the multirun dir (HParams tab compares the sweep)

A fixed ``hydra.run.dir`` / ``hydra.sweep.dir`` (the defaults contain the date and time) is what makes a run or
a sweep resumable: rerun the same command with ``resume=true``. See configs/README.md.

A run builds the problem (:mod:`indreg.experiments.build`), computes the FBP and TV baselines from the same
data, then loops ``info = solver.step(state)`` for ``solver.max_iter`` iterations: scalars to TensorBoard every
iteration; SSIM / PSNR and the deformed template every ``logging.every``; a checkpoint every
``logging.checkpoint_every`` and on SIGINT / SIGTERM (then the process exits with 128 + signal number).
``resume=true`` continues from ``<run dir>/checkpoint.pt`` and ends with the same numbers as an uninterrupted
run. Outputs in the run dir: ``metrics.json``, ``history.json``, ``final.npy``, ``trajectory.npy``,
``velocity.npy``, ``momentum.npy``, ``deformation.npy`` (phi_{1,0}), ``target.npy``, ``template.npy``,
``data.npy``, ``data_clean.npy``, ``fbp.npy``, ``tv.npy``, ``figure.png``, ``tensorboard/``, ``checkpoint.pt``.
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

from ..api import RegistrationLoop, count_warnings, relative_residual
from . import checkpoint as ckpt
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


def figures_of_merit(image, target_64) -> dict:
    """SSIM / PSNR against the target: data range of the target, and the paper's convention (PAPER_NOTES)."""
    from .. import metrics

    x = image.detach().to("cpu", torch.float64)
    return {"ssim": metrics.ssim(x, target_64), "psnr": metrics.psnr(x, target_64),
            "ssim_paper": metrics.ssim_paper(x, target_64), "psnr_paper": metrics.psnr_paper(x, target_64)}


def baselines(cfg: DictConfig, exp, out: Path) -> dict:
    """FBP and TV reconstructions from the noisy data (float64 on the run's device, returned on the CPU);
    cached in ``baselines.npz`` so that a resumed run does not recompute them."""
    if not cfg.baseline.enabled:
        return {}
    b = cfg.baseline
    key = np.array([b.fbp_filter.value, b.fbp_frequency_scaling, b.fbp_padding, b.tv_mu, b.tv_iterations],
                   dtype=str)
    cache = out / "baselines.npz"
    if cache.is_file():
        with np.load(cache) as z:
            if np.array_equal(z["key"], key):
                return {"fbp": torch.from_numpy(z["fbp"]), "tv": torch.from_numpy(z["tv"])}
    from ..forward import fbp
    from ..forward.tv import tv_reconstruction

    t0 = time.perf_counter()
    T, g = exp.ray_transform, exp.noisy_data_64.to(exp.template.device)
    rec = {"fbp": fbp(T, g, filter=b.fbp_filter.value, frequency_scaling=b.fbp_frequency_scaling,
                      padding=b.fbp_padding),
           "tv": tv_reconstruction(T, g, mu=b.tv_mu, num_iter=b.tv_iterations)[0]}
    rec = {k: v.detach().to("cpu", torch.float64) for k, v in rec.items()}
    log.info("baselines (FBP, TV %d iterations) in %.1f s", b.tv_iterations, time.perf_counter() - t0)
    np.savez(cache, key=key, **{k: v.numpy() for k, v in rec.items()})
    return rec


def _problem_config(plain: dict) -> dict:
    """The config keys that define the iterates (all but ``_RESUMABLE`` and ``solver.max_iter``)."""
    out = {k: v for k, v in plain.items() if k not in _RESUMABLE}
    out["solver"] = {k: v for k, v in out["solver"].items() if k != "max_iter"}
    return out


def hyperparameters(cfg: DictConfig, exp) -> dict:
    """The run's parameters shown in TensorBoard's HParams tab and in metrics.json."""
    return {"gamma": float(cfg.solver.gamma), "sigma": float(cfg.kernel.sigma),
            "N": int(cfg.deformation.num_steps),
            "step_size": float(cfg.solver.step_size if cfg.solver.name.value == "algorithm1" else cfg.solver.lr),
            "action": cfg.deformation.action.value, "solver": cfg.solver.name.value,
            "template": exp.label, "size": int(exp.domain.shape[0]),
            "max_iter": int(cfg.solver.max_iter), "dtype": cfg.dtype.value, "seed": int(cfg.seed)}


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
                         progress=cfg.logging.progress, desc=cfg.name, history=history, seconds=seconds)
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
        self._fom = ""
        if it % lg.every == 0 and not done:  # the last iterate is evaluated by finish()
            deformed = self.problem.deformed(self.state.momentum)
            if exp.target_64 is not None:
                fom = figures_of_merit(deformed, exp.target_64)
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

    The dict has ``status``: ``completed`` (``max_iter`` reached), ``converged`` (``solver.grad_tol`` or a
    non-finite objective), ``stopped`` (``stop_after``) or ``interrupted`` (a signal; ``signal`` holds its
    number). Only ``completed`` and ``converged`` runs write the final outputs. Input errors (config values,
    data files) are raised before anything is written.
    """
    from ..solvers import SolverState
    from .tblog import RunWriter

    validate(cfg)
    seed_everything(cfg.seed)
    exp = build(cfg)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    problem = exp.problem
    log.info("%s | %s | %s", cfg.name, problem, exp.solver)
    problem_cfg = _problem_config(to_plain(cfg))
    rec = baselines(cfg, exp, out)

    state = SolverState(momentum=problem.zero_momentum(), iteration=0)
    history, seconds = [], 0.0
    path = out / "checkpoint.pt"
    if cfg.resume and path.is_file():
        saved = ckpt.load(path)
        mismatch = ckpt.problem_mismatch(saved["problem"], problem_cfg)
        if mismatch:
            raise ConfigError("resume=true but the config differs from the checkpoint's: " + "; ".join(mismatch))
        state.load_state_dict(saved["state"])
        state.momentum = state.momentum.to(device=exp.template.device, dtype=exp.template.dtype)
        exp.solver.load_state_dict(saved["solver"])
        ckpt.set_rng_state(saved["rng"])
        history, seconds = saved["history"], saved["seconds"]
        log.info("resumed from %s at iteration %d", path, state.iteration)
    elif cfg.resume:
        log.warning("resume=true but there is no %s: starting at iteration 0", path)

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
            writer.metrics(figures_of_merit(exp.template_64, exp.target_64), 0)

    loop = AppLoop(cfg, exp, state, writer, path, problem_cfg, history, seconds)
    status = loop.run()
    loop.save_checkpoint()
    if status in ("stopped", "interrupted"):
        writer.close()
        log.warning("%s at iteration %d; continue with resume=true (same run dir %s)", status, state.iteration, out)
        return {"status": status, "iteration": state.iteration, "signal": loop.stop.signum}
    result = finish(cfg, exp, state, rec, loop.history, loop.seconds, out, writer, status)
    writer.close()
    return result


def finish(cfg, exp, state, rec, history, seconds, out: Path, writer, status: str) -> dict:
    """Final outputs: arrays, metrics.json, history.json, figure.png, TensorBoard images and hparams.

    Without a target (measured data) SSIM / PSNR, ``target.npy`` and ``data_clean.npy`` are absent; the relative
    data residual ``residual = ||T f - g|| / ||g||`` is always reported."""
    from . import figures
    from .tblog import METRICS

    problem, m, it = exp.problem, state.momentum, state.iteration
    final = problem.deformed(m)
    trajectory = problem.trajectory(m)
    with torch.no_grad():
        velocity = problem.velocity(m)
        phi = problem.deformation.deformation(velocity)
    terms = problem.evaluate(m)
    target = exp.target_64
    result = {}
    if target is not None:
        result.update(figures_of_merit(final, target))
        for name, image in rec.items():
            result.update({f"{name}_{k}": v for k, v in figures_of_merit(image, target).items()})
        result.update({f"template_{k}": v for k, v in figures_of_merit(exp.template_64, target).items()})
    result.update(terms)
    result.update({
        "status": status, "residual": relative_residual(exp.ray_transform, final, problem.data), "iterations": it,
        "seconds_per_iteration": seconds / max(len(history), 1), "seconds": seconds,
        "min_jacobian": problem.min_jacobian(velocity),
        "grad_norm": history[-1]["grad_norm"] if history else float("nan"),
        "evaluations": history[-1]["evaluations"] if history else 0,
        "warnings": count_warnings(history), "rejected_steps": sum(1 for h in history if h.get("rejected")),
        "device": str(exp.template.device), "hparams": hyperparameters(cfg, exp), "config": to_plain(cfg)})
    if exp.snr_db is not None:
        result.update({"snr_db": exp.snr_db, "snr_convention": cfg.noise.convention.value})
    arrays = {"final": final, "trajectory": trajectory, "velocity": velocity, "momentum": m, "deformation": phi,
              "template": exp.template_64, "data": exp.noisy_data_64, **rec}
    if target is not None:
        arrays["target"] = target
    if exp.clean_data_64 is not None:
        arrays["data_clean"] = exp.clean_data_64
    for name, a in arrays.items():
        np.save(out / f"{name}.npy", _numpy(a))
    with open(out / "history.json", "w") as f:
        json.dump([{k: _json_float(v) for k, v in h.items()} for h in history], f)
    with open(out / "metrics.json", "w") as f:
        json.dump({k: _json_float(v) for k, v in result.items()}, f, indent=2)

    traj = _numpy(trajectory)
    if cfg.logging.figure:
        quality = (f"SSIM {result['ssim']:.4f}, PSNR {result['psnr']:.2f} dB" if target is not None
                   else f"relative data residual {result['residual']:.4f}")
        fig = figures.paper_figure(exp.template_64.numpy(), traj, None if target is None else target.numpy(),
                                   exp.geometry.det_points.numpy(),
                                   None if exp.clean_data_64 is None else exp.clean_data_64[0].numpy(),
                                   exp.noisy_data_64[0].numpy(),
                                   _numpy(rec["fbp"]) if "fbp" in rec else None,
                                   _numpy(rec["tv"]) if "tv" in rec else None, extent=domain_extent(exp.domain),
                                   title=f"{cfg.name}: {quality}",
                                   angle_deg=float(exp.geometry.angles[0]) * 180 / math.pi)
        figures.save(fig, out / "figure.png")
    n = traj.shape[0] - 1
    writer.strip("images/trajectory", [traj[0]] + [traj[i] for i in figures.time_indices(n)], it)
    writer.image("images/deformed_template", final, it)
    writer.figure("images/deformed_grid", figures.deformed_grid_figure(_numpy(phi)), it)
    writer.metrics(result, it)
    writer.hparams(hyperparameters(cfg, exp), {k: result[k] for k in (*METRICS, "residual") if k in result})
    if target is not None:
        log.info("done: %d iterations, SSIM %.4f, PSNR %.2f dB (paper convention %.4f / %.2f); FBP %s; TV %s; "
                 "%d warnings", it, result["ssim"], result["psnr"], result["ssim_paper"], result["psnr_paper"],
                 _pair(result, "fbp"), _pair(result, "tv"), result["warnings"])
    else:
        log.info("done: %d iterations, objective %.6g, relative data residual %.4f, min Jacobian %.4g; %d warnings",
                 it, result["objective"], result["residual"], result["min_jacobian"], result["warnings"])
    return result


def domain_extent(domain) -> tuple:
    """``imshow`` extent (x_min, x_max, y_min, y_max) of the domain."""
    (x0, y0), (x1, y1) = domain.min_pt, domain.max_pt
    return x0, x1, y0, y1


def _pair(result: dict, name: str) -> str:
    if f"{name}_ssim" not in result:
        return "off"
    return f"{result[f'{name}_ssim']:.4f} / {result[f'{name}_psnr']:.2f}"


_CONFIG_NAME = "config"
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
    from hydra.core.hydra_config import HydraConfig

    from ..io import DataFileError

    hc = HydraConfig.get()
    _prefix_job_logs(hc)
    try:
        result = run(cfg, hc.runtime.output_dir)
    except (ConfigError, DataFileError) as e:  # bad input: one line, no traceback
        print(f"indreg-register: error: {e}", file=sys.stderr)
        sys.exit(1)
    if result["status"] == "interrupted":
        sys.exit(128 + int(result["signal"]))
    return result.get("ssim")


def main() -> None:
    """Console entry point ``indreg-register`` (Hydra parses ``sys.argv``)."""
    import hydra

    hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=_CONFIG_NAME)(_task)()


if __name__ == "__main__":
    main()
