"""Hydra's ``--experimental-rerun FILE`` unpickles FILE (a crafted file runs code); its parser takes every
unambiguous prefix of the flag too. Every entry point refuses all of them in one line, exit 2, before Hydra
parses the command line: tested as a user would start it, a subprocess, with a pickle that creates a marker."""
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest

from indreg.experiments import cli

ROOT = Path(__file__).resolve().parents[2]
FLAG = "--experimental-rerun"


class _Opens:
    """Unpickling this creates ``marker``: the proof that the file was unpickled."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def _hydra_reads_rerun(args) -> bool:
    """Whether Hydra's own parser takes ``args`` as its rerun flag (the oracle of the guard)."""
    from hydra._internal.utils import get_args_parser

    try:
        parsed, _ = get_args_parser().parse_known_args(args)
    except SystemExit:   # ambiguous prefix (argparse's usage error)
        return False
    return parsed.experimental_rerun is not None


def _prefixes():
    return [FLAG[:n] for n in range(3, len(FLAG) + 1)]


@pytest.mark.parametrize("prefix", _prefixes())
def test_every_prefix_that_hydra_reads_as_rerun_is_refused(prefix):
    for args in ([prefix, "f.pickle"], [f"{prefix}=f.pickle"]):
        assert _hydra_reads_rerun(args), args      # the prefix is real: Hydra would unpickle f.pickle
        assert cli.loading_flag(["x=1", *args]) == args[0]


@pytest.mark.parametrize("args", [["--help"], ["--hydra-help"], ["--cfg", "job"], ["-m", "a=1,2"],
                                  ["--config-dir", "d"], ["--", "x=1"], ["model.lr=--experimental-rerun"],
                                  ["--e-x"], ["--experimental-rerunx=f"]])
def test_other_flags_pass(args):
    assert cli.loading_flag(args) is None and not _hydra_reads_rerun(args)


def _script(name: str) -> list:
    exe = Path(sys.executable).parent / name
    if not exe.exists():
        pytest.skip(f"{name} is not installed next to {sys.executable} (pip install -e .)")
    return [str(exe)]


ENTRY_POINTS = {
    "indreg-register": lambda: _script("indreg-register"),
    "indreg-train-momentum": lambda: _script("indreg-train-momentum"),
    "python -m indreg.experiments.register": lambda: [sys.executable, "-m", "indreg.experiments.register"],
    "python -m indreg.learn.train": lambda: [sys.executable, "-m", "indreg.learn.train"],
    "scripts/register.py": lambda: [sys.executable, str(ROOT / "scripts" / "register.py")],
    "scripts/train_momentum.py": lambda: [sys.executable, str(ROOT / "scripts" / "train_momentum.py")],
}
FORMS = {"indreg-register": ["--experimental-rer", "{f}"], "indreg-train-momentum": ["--experimental-rerun", "{f}"],
         "python -m indreg.experiments.register": ["--exp", "{f}", "--help"],
         "python -m indreg.learn.train": ["--experimental-r={f}"],
         "scripts/register.py": ["--experimental={f}"], "scripts/train_momentum.py": ["--e", "{f}"]}


@pytest.mark.slow   # a subprocess each: 1-15 s (torch import) on a loaded 2-core machine
@pytest.mark.parametrize("name", list(ENTRY_POINTS))
def test_entry_point_refuses_rerun_and_unpickles_nothing(tmp_path, name):
    evil, marker = tmp_path / "config.pickle", tmp_path / "unpickled"
    evil.write_bytes(pickle.dumps(_Opens(marker)))
    args = [a.format(f=evil) for a in FORMS[name]]
    proc = subprocess.run(ENTRY_POINTS[name]() + args, cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1"))
    assert not marker.exists(), f"{name} unpickled the file"
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"({FLAG}) is not supported" in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.pickle"]     # no run directory either
