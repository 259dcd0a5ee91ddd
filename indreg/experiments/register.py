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
``indreg.register`` (``indreg.registration.run.RegistrationLoop``) for ``solver.max_iter`` iterations: scalars to TensorBoard
every iteration; a progress line (``iteration i/total``, it/s, ETA), SSIM / PSNR (with a target) and the deformed
template every ``logging.every``; a checkpoint every ``logging.checkpoint_every`` and on SIGINT / SIGTERM (then
the process exits with 128 + signal number). ``resume=true`` continues from ``<run dir>/checkpoint.pt`` and ends
with the same numbers as an uninterrupted run. In a multirun every log line starts with ``[job <n>]``. Outputs in
the run dir: ``metrics.json``, ``history.json``, ``final.npy``, ``trajectory.npy``, ``velocity.npy``,
``momentum.npy``, ``deformation.npy`` (phi_{1,0}), ``target.npy``, ``template.npy``, ``data.npy``,
``data_clean.npy``, ``fbp.npy``, ``tv.npy``, ``figure.png``, ``tensorboard/``, ``checkpoint.pt`` (a model with
frames, ``spatiotemporal``: ``frames.npy``, ``frames.png`` and the movie ``frames.gif``; volumes also
``final.mrc``, with the voxel size in its header, and ``sirt.npy``; ``figure.png`` shows orthogonal slices);
measured data without a target have no ``target.npy`` / ``data_clean.npy`` and no SSIM / PSNR (``residual``, the
relative data misfit, is always in metrics.json).

This module is the entry point and the Hydra task; it imports no torch until a run starts (``--help`` answers at
once), and neither do the preflight's checks: a bad command line is refused, and the run's first line (its plan,
:func:`plan_line`) is logged, before torch is imported. The run itself: :mod:`indreg.experiments.runner` (loop,
resume, signals), :mod:`.baselines`, :mod:`.outputs` and :mod:`.run_figures`. ``run``, ``CONFIG_DIR`` and ``_CONFIG_NAME`` are also served from here (the latter two
with the config schema registered, for callers that compose the config themselves).
"""
from __future__ import annotations

import logging
import sys
from pathlib import Path

from omegaconf import DictConfig

from ..conf import CONFIG_DIR as _CONFIG   # = config.CONFIG_DIR, without importing its schema
from . import cli

__all__ = ["main", "preflight", "run", "plan_line", "where_line", "PROG", "CONFIG_DIR"]

log = logging.getLogger(__name__)

_CONFIG_FILE = "config"
_SCHEMA = "indreg_schema"   # = config.SCHEMA_NAME
PROG = "indreg-register"

#: Hydra's flags that only print text: the config schema is not needed (nor torch, which it imports).
_PRINT_ONLY = ("--help", "-h", "--hydra-help")
def _register_schema(argv=()) -> None:
    """The schema in Hydra's ConfigStore, with the options of the plug-in models named in ``argv``."""
    from .config import register_schema

    register_schema(argv)


def __getattr__(name: str):
    """``run`` (imports the app's modules and torch); ``CONFIG_DIR`` / ``_CONFIG_NAME`` with the schema registered."""
    if name == "run":
        from .runner import run
        return run
    if name in ("CONFIG_DIR", "_CONFIG_NAME"):
        _register_schema()
        return _CONFIG if name == "CONFIG_DIR" else _CONFIG_FILE
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
    log.info("%s", plan_line(cfg, Path(hc.runtime.output_dir)))   # the first line, before torch is imported

    from ..io import DataFileError
    from .checkpoint import CheckpointError
    from .config import ConfigError
    from .runner import run

    try:
        result = run(cfg, hc.runtime.output_dir)
    except (ConfigError, DataFileError, CheckpointError) as e:  # user errors: one line, no traceback
        _log_to_file(str(e))
        _exit_error(str(e))
    _say_where(result["status"], Path(hc.runtime.output_dir), result.get("layout"))
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


def plan_line(cfg: DictConfig, out: Path) -> str:
    """The run's first line: what will run (the run's name, model, solver, data, dtype and device) and where its
    outputs go; from the config alone, so that it is logged before torch is imported."""
    from .sources import describe

    s = cfg.solver
    solver = s.optimizer if s.name == "torch_optim" else s.name
    dtype = getattr(cfg.dtype, "value", cfg.dtype)
    resume = " (resume=true: from its checkpoint, if any)" if cfg.resume else ""
    return (f"{cfg.name}: model {cfg.deformation.model}, solver {solver} ({s.max_iter} iterations), data "
            f"{describe(cfg)}, {dtype} on device {cfg.device}; run dir {out.resolve()}{resume}")


def where_line(status: str, out: Path, layout: str | None = None) -> str:
    """The run's last line: where its outputs are (the figures by name; ``layout``: the files' convention the
    arrays are written in, ``indreg.experiments.outputs.as_given``), or where its checkpoint is."""
    if status in ("interrupted", "stopped"):
        return (f"checkpoint in {out / 'checkpoint.pt'}: continue with hydra.run.dir={out} resume=true")
    if status == "failed":
        return f"record of the failed run in {out} (metrics.json, history.json)"
    from .outputs import FIGURES

    shown = [name for name in FIGURES if (out / name).is_file()]
    where = f"outputs in {out}" + (f" (figures: {', '.join(shown)})" if shown else "")
    if layout:
        where += (f"; images and data in convention {layout}'s layout, as the files given (velocity, momentum "
                  "and deformation in indreg's: outputs.json)")
    return where


def _say_where(status: str, out: Path, layout: str | None = None) -> None:
    log.info("%s", where_line(status, out.resolve(), layout))


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
    from .config import validate
    from .sources import check_files

    validate(cfg)
    check_files(cfg)


def preflight(argv) -> None:
    """Check the command line before Hydra creates the run directory (:func:`indreg.experiments.cli.preflight`:
    launcher plugin, composition, the config's values, the data files, the run directory), so that a problem
    ends in one line (``indreg-register: error: ...``, exit 1) with nothing written."""
    cli.guard(argv, PROG)
    try:
        _register_schema(argv)   # plug-in models named on the command line: their options become keys
    except ValueError as e:      # e.g. a plug-in source's key declared with another type by another source
        _exit_error(str(e))
    cli.preflight(argv, PROG, _CONFIG, _CONFIG_FILE, validate=_check_config)


def main() -> None:
    """Console entry point ``indreg-register`` (Hydra parses ``sys.argv``); large freed arrays stay in the heap
    (``indreg._malloc``: 256^3 volumes are not page-faulted in afresh at every operation)."""
    import hydra

    from .._malloc import use_heap_allocator

    argv = sys.argv[1:]
    cli.guard(argv, PROG)   # --experimental-rerun and its prefixes, Hydra's callbacks, ...: exit 2
    if any(a in _PRINT_ONLY for a in argv):
        _stand_in_schema()
        if cli.answers(argv) and cli.print_help(_CONFIG, _CONFIG_FILE, argv):
            return
    else:
        use_heap_allocator()
        preflight(argv)
    hydra.main(version_base="1.3", config_path=str(_CONFIG), config_name=_CONFIG_FILE)(_task)()


def _stand_in_schema() -> None:
    """An empty node in the schema's place: enough for Hydra to compose the help text (it prints the config groups
    and unresolved values only), without importing the schema's modules and torch."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=_SCHEMA, node={})


if __name__ == "__main__":
    main()
