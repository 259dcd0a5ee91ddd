"""``configs/README.md`` (= ``indreg/conf/README.md``) generated from the option table (``indreg.options``: one row per
registration key, its default and what it is), the registered data sources' keys and the config folders (one row
per group): ``python -m indreg.experiments.config_readme`` writes it, ``--check`` fails when the committed file
differs (``tests/experiments/test_config_readme.py`` runs the check in CI)."""
from __future__ import annotations

import sys

from .. import options
from ..conf import CONFIG_DIR
from . import schema  # noqa: F401  (registers the models, solvers, corrections and sources whose keys are listed)
from . import sources

__all__ = ["markdown", "main", "README"]

README = CONFIG_DIR / "README.md"
#: The longest "what" cell (characters): a longer doc is cut at a clause.
CELL = 110

#: The config groups, in order, with a short description.
GROUPS = {
    "experiment": "the paper's test suites and examples: every other group's choice (`experiment=...`)",
    "data": "where template and data come from: simulated (`phantom`), your files (`files`, docs/own_data.md), "
            "a breathing phantom (`dynamic`)",
    "phantom": "template and target (`indreg.phantoms`), grid size, `ndim` (3: volumes)",
    "geometry": "angles and detector bins (parallel, fan beam, tilt series)",
    "noise": "white noise: SNR in the code's dB convention, or a standard deviation",
    "deformation": "the deformation model and its discretisation (keys below)",
    "kernel": "the Gaussian kernel of V",
    "solver": "the solver and its steps (keys below); `solver.name=module:SOLVER` for a plug-in",
    "baseline": "FBP and TV (and SIRT for volumes) from the same data",
    "logging": "evaluation, image and checkpoint periods, TensorBoard, progress bar, figure",
    "validation": "(schema only) held-out angles and early stopping (keys below)",
    "sweep": "multirun presets",
    "hydra/launcher": "where multirun jobs run (`joblib`, `slurm`, `ray`: their plugins installed)",
}

INTRO = """# Experiment configs of `indreg-register`

Hydra 1.3 configs; their schema is `indreg.experiments.config.RegisterConfig` (typed: an unknown key, a wrong
type or an invalid value fails at start with a message naming the key). Print the composed config with
`indreg-register [overrides] --cfg job`; `indreg-register --help` lists the groups. The guide to the command-line
tools is `docs/cli.md` in the repository."""

TOP = """Top-level keys: `name`, `seed` (noise and torch), `dtype` (`float32` default, `float64`), `device` (`auto`, `cpu`,
`cuda`, `cuda:<i>`), `resume`, `stop_after`, `plugins` (modules imported first: a plug-in correction, solver,
model, source or file format)."""

TAIL = """## Commands

```bash
# one run (suite 1 by default); outputs in outputs/<name>/<date_time>/
indreg-register
indreg-register experiment=suite3_shepp_logan dtype=float64 device=cuda
python scripts/register.py experiment=suite2_six_objects          # same app without the console script

# resumable run: fix the run dir; after Ctrl-C / SIGTERM / a kill, the same command with resume=true continues
indreg-register experiment=suite4_extra_object hydra.run.dir=outputs/suite4_extra
indreg-register experiment=suite4_extra_object hydra.run.dir=outputs/suite4_extra resume=true

# the suite-3 table (30 runs) locally, 2 parallel worker processes (pip install "indreg[joblib]")
indreg-register -m sweep=suite3_table hydra/launcher=joblib hydra.launcher.n_jobs=2 hydra.sweep.dir=multirun/suite3_table
# ... on a SLURM cluster (pip install "indreg[submitit]"); resume=true lets requeued tasks continue
indreg-register -m sweep=suite3_table hydra/launcher=slurm hydra.launcher.partition=<partition> \
    hydra.sweep.dir=multirun/suite3_table resume=true
# an interrupted sweep: the same command with resume=true (same hydra.sweep.dir)

# the table, sigma rows x gamma columns, SSIM / PSNR next to the paper's numbers (table.md, table.csv)
indreg-sweep-table multirun/suite3_table

# TensorBoard: scalars, images, and the HParams tab to compare a sweep
tensorboard --logdir outputs            # or --logdir multirun/suite3_table
```

Outputs of a run: `metrics.json` (SSIM / PSNR of the result, FBP and TV, in two conventions: `ssim` / `psnr` with
the target's data range, `ssim_paper` / `psnr_paper` as the paper, for the paper's phantoms), `history.json`, `final.npy`, `trajectory.npy`
(W(nu, I)(t_i), i = 0..N), `velocity.npy`, `momentum.npy`, `deformation.npy` (phi_{1,0}), `target.npy`,
`template.npy`, `data.npy`, `data_clean.npy`, `fbp.npy`, `tv.npy`, `figure.png` (the paper's figure layout),
`tensorboard/`, `checkpoint.pt`, Hydra's `.hydra/` and log."""


def _short(text: str) -> str:
    """``text`` (its pipes escaped) cut at the last clause boundary within :data:`CELL` characters."""
    text = " ".join(text.split())
    if len(text) > CELL:
        ends = [i for sep in ("; ", ". ", " (", ": ", ", ") for i in _positions(text, sep)
                if 30 <= i <= CELL and text[:i].count("(") == text[:i].count(")")]
        text = text[:max(ends)] if ends else text[:CELL - 4].rsplit(" ", 1)[0] + " ..."
    return text.replace("|", "\\|")


def _positions(text: str, sep: str) -> list:
    out, i = [], text.find(sep)
    while i >= 0:
        out.append(i)
        i = text.find(sep, i + 1)
    return out


def _cell(value) -> str:
    return f"`{value!r}`".replace("|", "\\|")


#: A group with more choices lists this many, then points to its folder.
CHOICES = 8


def _group_rows() -> list:
    rows = ["| group | choices (`configs/<group>/`) | what |", "|---|---|---|"]
    for group, what in GROUPS.items():
        folder = CONFIG_DIR / group
        names = sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []
        shown = names if len(names) <= CHOICES else names[:CHOICES - 2]
        choices = ", ".join(f"`{n}`" for n in shown) or "keys only"
        if len(shown) < len(names):
            choices += f" and {len(names) - len(shown)} more"
        rows.append(f"| `{group}` | {choices} | {what} |")
    return rows


def _builtin(function) -> bool:
    """Whether ``function`` is indreg's (a plug-in registered in this process is not listed)."""
    return getattr(function, "__module__", "").startswith("indreg.")


def listed_options() -> list:
    """The options with a config key that indreg itself declares (the core's, its models', solvers' and
    corrections')."""
    entries = (*options.MODELS.values(), *options.SOLVERS.values(), *options.CORRECTIONS.values())
    plugged = {id(o) for e in entries if not _builtin(getattr(e, "build", None) or e.wrap) for o in e.options}
    return [o for o in options.all_options() if o.group != "run" and id(o) not in plugged]


def _option_rows() -> list:
    rows = ["| key | default | only with | what |", "|---|---|---|---|"]
    for o in listed_options():
        rows.append(f"| `{o.config_key}` | {_cell(o.schema_default)} | {o.where() or ''} | {_short(o.doc)} |")
    for source in (s for s in sources.SOURCES.values() if _builtin(s.load)):
        for key, _, default in source.options:
            value = getattr(default, "value", default)
            rows.append(f"| `data.{key}` | {_cell(value)} | data.source={source.name!r} | a key of the source "
                        f"`{source.name}` ({_short(source.doc)}) |")
    return rows


def markdown() -> str:
    """The README's text."""
    return "\n".join([
        "<!-- generated by `python -m indreg.experiments.config_readme` from indreg.options: edit there -->",
        INTRO, "", *_group_rows(), "", TOP, "",
        "## Registration keys",
        "",
        "Generated from the option table (`indreg.options`; the full texts: `indreg.register`'s docstring). The app's",
        "defaults are the paper's where they differ from `indreg.register`'s (`solver.step_halving`, `solver.lr`).",
        "",
        *_option_rows(), "", TAIL, ""])


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = markdown()
    if "--check" in argv:
        if README.read_text() != text:
            print(f"{README} is not what the option table generates: run python -m indreg.experiments.config_readme",
                  file=sys.stderr)
            return 1
        return 0
    from .._outfiles import open_replacing

    with open_replacing(README, "w") as f:   # as every file indreg writes: no link followed
        f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
