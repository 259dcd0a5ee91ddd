"""Fixtures and options of the whole suite.

- Every test starts from the same random state (``random``, numpy's and torch's global generators seeded with 0):
  a test's random inputs do not depend on the tests that ran before it, and a failure repeats.
- The tests marked ``slow`` (end-to-end runs, seconds to minutes each) run only when asked for: ``pytest -m slow``
  (those alone), ``pytest -m ""`` (everything), any other ``-m`` expression, or a test named by its node id
  (``pytest tests/x.py::test_y``). A plain ``pytest`` runs the rest and reports the slow ones as deselected; CI
  (``.ci/run``) runs both.
- On a machine with two cores or more the tests run in parallel (pytest-xdist, one worker a core up to 8, work stealing),
  unless ``-n``/``--dist``/``--tx`` is given, xdist is off (``-p no:xdist``), ``--pdb``/``--collect-only``, or the
  tests are named by node id. ``-n 0`` runs them in this process. Each worker, and each process a test starts,
  gets its share of the cores as torch threads (``OMP_NUM_THREADS``, unless already set), so that the workers do
  not oversubscribe the machine.
"""
import os
import random

import numpy as np
import pytest
import torch


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _parallel_by_default(config) -> bool:
    """xdist is there, this is not one of its workers, and nothing on the command line chose otherwise."""
    option = config.option
    if not config.pluginmanager.hasplugin("xdist") or "PYTEST_XDIST_WORKER" in os.environ or _cores() < 2:
        return False
    if option.numprocesses is not None or option.dist != "no" or option.tx or option.distload:
        return False
    return not (option.usepdb or option.collectonly or any("::" in str(a) for a in config.args))


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    """Runs before xdist reads ``-n`` (tryfirst, and a conftest's hooks run before the plugins' ones)."""
    if _parallel_by_default(config):
        config.option.numprocesses, config.option.dist = min(_cores(), 8), "worksteal"
    workers = getattr(config.option, "numprocesses", None) or 0
    workers = _cores() if workers in ("auto", "logical") else workers
    if workers > 0 and "OMP_NUM_THREADS" not in os.environ:   # read by torch in the workers and their children
        os.environ["OMP_NUM_THREADS"] = str(max(1, _cores() // workers))


@pytest.fixture(autouse=True)
def _seeded():
    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)


@pytest.fixture
def error_without_torch(tmp_path):
    """``error_without_torch(script, *args)``: the one stderr line of ``python script *args`` run where ``torch``
    cannot be imported (a package of that name that raises, first on ``PYTHONPATH``), and asserted to exit 1 with
    that one line: what a script says before it imports torch (a walk-through's missing data)."""
    import subprocess
    import sys

    fake = tmp_path / "unimportable"
    (fake / "torch").mkdir(parents=True)
    (fake / "torch" / "__init__.py").write_text("raise ImportError('torch was imported')\n")

    def run(script, *args) -> str:
        done = subprocess.run([sys.executable, str(script), *map(str, args)], capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": str(fake)}, timeout=120)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 1 and len(lines) == 1, done.stderr[-2000:]
        return lines[0]
    return run


def _asked_for_slow(config) -> bool:
    """``-m`` given (even empty), or a test named by its node id on the command line."""
    args = [str(a) for a in config.invocation_params.args]
    return (bool(config.option.markexpr) or any(a.startswith("-m") for a in args)
            or any("::" in str(a) for a in config.args))


def pytest_collection_modifyitems(config, items):
    if _asked_for_slow(config):
        return
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if item.get_closest_marker("slow") is None]
