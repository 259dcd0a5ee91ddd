"""One run of the app: build the problem, the baselines, resume from a checkpoint, iterate (the shared loop with the
app's callbacks: TensorBoard, evaluation, checkpoints, ``stop_after``, SIGINT / SIGTERM), then the final outputs
(:mod:`indreg.experiments.outputs`).

Convention: ``run(cfg, output_dir)`` writes everything into ``output_dir`` (``checkpoint.pt``, ``baselines.npz``,
``tensorboard/`` and the outputs) and returns ``metrics.json``'s dict.
"""
from __future__ import annotations

import logging
import signal
import threading
from dataclasses import replace
from pathlib import Path

from omegaconf import DictConfig

from .._checks import StepOverflowError
from .._malloc import system_allocator
from ..callbacks import Callback
from ..io import DataFileError
from ..registration.run import RegistrationLoop, initial_state
from . import checkpoint as ckpt
from .baselines import baselines
from .build import build, seed_everything
from .config import ConfigError, to_plain, validate
from .outputs import failed, figures_of_merit, finish

__all__ = ["run", "StopRequest", "StopAfter", "Signals", "TensorBoard", "Evaluation", "Checkpoints"]

log = logging.getLogger("indreg.experiments.register")

# The app's own config keys that may change between an interrupted run and its resumption (the registration
# options that may are marked so in the option table: ``indreg.options.Option.resumable``).
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


def _problem_config(plain: dict) -> dict:
    """The config keys that define the iterates (all but ``_RESUMABLE`` and the options marked ``resumable``)."""
    from .. import options

    out = {k: v for k, v in plain.items() if k not in _RESUMABLE}
    for o in options.all_options():
        if o.resumable and isinstance(out.get(o.group), dict):
            out[o.group] = {k: v for k, v in out[o.group].items() if k != o.key}
    return out


class StopAfter(Callback):
    """``stop_after``: stop (``stopped``, checkpointed as if interrupted) once this many iterations are done."""

    def __init__(self, iterations):
        self.iterations = iterations

    def before(self, loop):
        return "stopped" if self.iterations is not None and loop.state.iteration >= self.iterations else None


class Signals(Callback):
    """SIGINT / SIGTERM (:class:`StopRequest`) end the loop after the running step (``interrupted``)."""

    def __init__(self):
        self.request = StopRequest()

    def begin(self, loop):
        self.request.install()

    def after(self, loop, info, done):
        return "interrupted" if self.request.signum is not None else None

    def end(self, loop):
        self.request.restore()


class TensorBoard(Callback):
    """The report's scalars every iteration, the held-out residual when it was evaluated (``tblog.RunWriter``)."""

    def __init__(self, writer):
        self.writer = writer

    def after(self, loop, info, done):
        it = loop.state.iteration
        self.writer.scalars(info, it)
        if "holdout_residual" in info:
            self.writer.validation(info["holdout_residual"], it)


class Evaluation(Callback):
    """Every ``every`` iterations (not the last: ``finish`` evaluates it): SSIM / PSNR against the target (to
    TensorBoard and the log line) and the reconstruction's image."""

    def __init__(self, exp, writer, every: int):
        self.exp, self.writer, self.every, self.text = exp, writer, every, ""

    def after(self, loop, info, done):
        it, exp = loop.state.iteration, self.exp
        self.text = ""
        if it % self.every or done:
            return
        deformed = exp.field(loop.problem.reconstruction(loop.state.iterate))
        if exp.target_64 is not None:
            fom = figures_of_merit(deformed, exp.target_64, exp.paper, exp.units)
            self.writer.metrics(fom, it)
            self.text = f", SSIM {fom['ssim']:.4f}, PSNR {fom['psnr']:.2f}"
        self.writer.image("images/deformed_template", deformed, it)

    def describe(self, info):
        return self.text


class Checkpoints(Callback):
    """A checkpoint every ``every`` iterations (:meth:`save`: iterate, solver, random state, history, time and the
    problem's config, which a resume checks)."""

    def __init__(self, path: Path, problem_cfg: dict, every: int):
        self.path, self.problem_cfg, self.every = path, problem_cfg, every

    def save(self, loop) -> None:
        ckpt.save(self.path, {"iteration": loop.state.iteration, "state": loop.state.state_dict(),
                              "solver": loop.solver.state_dict(), "rng": ckpt.rng_state(), "history": loop.history,
                              "seconds": loop.seconds, "problem": self.problem_cfg})

    def after(self, loop, info, done):
        if loop.state.iteration % self.every == 0:
            self.save(loop)


def run(cfg: DictConfig, output_dir) -> dict:
    """:func:`_run`, then the process group (under ``torchrun``) closed on every rank, so that no communication
    thread outlives the run (gloo's would abort the process at exit)."""
    from ..tally import tally_warnings

    try:
        with tally_warnings():   # the set-up's warnings too, by kind, in metrics.json and the last line
            return _run(cfg, output_dir)
    finally:
        import torch.distributed as dist
        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()


def _run(cfg: DictConfig, output_dir) -> dict:
    """Run (or resume) the experiment of ``cfg`` writing into ``output_dir``; returns ``metrics.json``'s dict.

    The dict has ``status``: ``completed`` (``max_iter`` reached), ``converged`` (``solver.grad_tol``),
    ``stalled`` (step halving collapsed the step: ``indreg.registration.run.STALL_WINDOW``), ``diverged`` (finished with a
    relative data residual >= 1), ``failed`` (a non-finite objective or gradient: ``metrics.json`` and
    ``history.json`` hold the status, the iteration and the warning; the checkpoint keeps the last finite iterate),
    ``early_stopped`` (``validation.patience`` held-out evaluations without a new minimum), ``stopped``
    (``stop_after``) or ``interrupted`` (a signal; ``signal`` holds its number). Only ``completed``, ``converged``,
    ``stalled``, ``early_stopped`` and ``diverged`` runs write the final outputs. A bad config value, a bad data file,
    a bad run directory or a damaged / foreign / mismatched checkpoint raises ``ConfigError``, ``DataFileError`` or
    ``CheckpointError`` before any computing.
    """
    validate(cfg, registration=False)   # the registration options: resolved once, by build's setup
    rank, output_dir = _distributed(cfg, output_dir)
    out = Path(output_dir)
    path = out / "checkpoint.pt"
    ckpt.check_location(path, cfg.resume)
    problem_cfg = _problem_config(to_plain(cfg))
    saved = _read_checkpoint(cfg, path, problem_cfg)
    seed_everything(cfg.seed)
    try:
        with system_allocator():   # the data's float64 temporaries go back to the system (indreg._malloc)
            exp = build(cfg)  # reads and checks the data (files) before any computing
    except DataFileError:
        raise
    except (ValueError, TypeError) as e:  # the operators' input validation
        raise ConfigError(f"invalid configuration: {e}") from e
    problem = exp.problem
    _check_split(problem)
    if rank != 0:   # it writes nothing: it keeps the template and data its slabs read, no ground truths
        exp.data = replace(exp.data, target_64=None, clean_64=None, targets={})
    log.info("%s | %s | %s", cfg.name, problem, exp.solver)
    rec = baselines(cfg, exp, out)   # every rank takes its rows of a split run; rank 0 gets the volumes

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

    from .tblog import RunWriter   # TensorBoard imported after the first log line

    shown = exp.target_64 if exp.target_64 is not None else exp.template_64
    # a resumed run drops the events an interrupted one logged after its checkpoint
    writer = RunWriter(out / "tensorboard", state.iteration + 1 if state.iteration > 0 else None,
                       float(shown.min()), float(shown.max()), enabled=cfg.logging.tensorboard and rank == 0)
    if state.iteration == 0 and writer.enabled:   # rank 0 alone; its SSIM of volumes costs ~1 GiB at 256^3
        writer.image("images/template", exp.template_64, 0)
        if exp.target_64 is not None:
            writer.image("images/target", exp.target_64, 0)
        for k, v in rec.items():
            writer.image(f"images/{k}", v, 0)
        writer.image("images/deformed_template", exp.template_64, 0)
        if exp.target_64 is not None:
            writer.metrics(figures_of_merit(exp.template_64, exp.target_64, exp.paper, exp.units), 0)

    checkpoints, signals = Checkpoints(path, problem_cfg, cfg.logging.checkpoint_every), Signals()
    callbacks = StopAfter(cfg.stop_after) & signals
    if rank == 0:   # outputs and checkpoints once (the iterates are the same on every rank)
        callbacks = callbacks & TensorBoard(writer) & Evaluation(exp, writer, cfg.logging.every) & checkpoints
    loop = RegistrationLoop(exp.problem, exp.solver, state, cfg.solver.max_iter, every=cfg.logging.every,
                            progress=cfg.logging.progress and rank == 0, desc=cfg.name, history=history,
                            seconds=seconds, validation=exp.validation, callbacks=callbacks)
    try:
        status = loop.run()
    except StepOverflowError as e:   # found only in the run: one line naming the config key
        writer.close()
        raise ConfigError(f"invalid configuration: {e.message(_config_key)}") from None
    if rank != 0:   # its part of rank 0's build_result (its collectives, in order): the final sums, its frames' slabs
        if status not in ("failed", "stopped", "interrupted"):
            problem.evaluate_iterate(state.iterate), problem.relative_residual(state.iterate)
            for _ in problem.image_frames(state.iterate):
                pass
        return {"status": status, "iteration": state.iteration, "rank": rank}
    if status == "failed":  # keep the last checkpoint: its iterate is finite
        writer.close()
        return failed(out, loop.history)
    checkpoints.save(loop)
    if status in ("stopped", "interrupted"):
        writer.close()
        log.warning("%s at iteration %d; continue with resume=true (same run dir %s)", status, state.iteration, out)
        return {"status": status, "iteration": state.iteration, "signal": signals.request.signum}
    result = finish(cfg, exp, state, rec, loop.history, loop.seconds, out, writer, status)
    writer.close()
    return result


def _config_key(option: str) -> str:
    """The config key of the registration option ``option`` (``step_size`` -> ``solver.step_size``)."""
    from .. import options

    return next((o.config_key for o in options.all_options() if o.name == option), option)


def _distributed(cfg: DictConfig, output_dir) -> tuple:
    """``(rank, output_dir)``: under ``torchrun`` (``WORLD_SIZE > 1``, or ``deformation.distributed``) the process
    group is started and every rank writes where rank 0 does (Hydra's dated dirs may differ between ranks)."""
    from ..ranks import process_group
    from ..registration.run import resolve_device

    group = process_group(cfg.deformation.get("distributed"), resolve_device(cfg.device))
    if group is None:
        return 0, output_dir
    import torch.distributed as dist

    holder = [str(output_dir)]
    dist.broadcast_object_list(holder, src=0, group=group)
    return dist.get_rank(group), holder[0]


def _check_split(problem) -> None:
    """One line when several processes run a registration that is not split between them."""
    from ..ranks import default_group

    group = default_group()
    if group is not None and not getattr(problem, "splits_over_ranks", False):
        import torch.distributed as dist
        raise ConfigError(f"{dist.get_world_size(group)} processes (torchrun) need a registration that splits into "
                          f"slabs (model lddmm, a tilt series, deformation.velocity_factor > 1, solver algorithm1, no "
                          f"TV): run {type(problem).__name__} in one process")


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
