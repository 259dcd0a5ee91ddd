"""CPU seconds of the entry points' start-ups and of importing indreg (docs/benchmarks.md, "Start-up").

Each command runs ``--repeat`` times in a fresh process, the commands (and with ``--before``, the two checkouts)
taking turns, so that a change of load touches all alike; the table shows the median and the least of the CPU
seconds (user + system, less sensitive to other jobs than wall seconds) and the median wall seconds:

- ``python -c "import indreg"`` (the lazy top level) and ``python -c "from indreg import register"`` (torch
  and the registration stack), with ``python -c "import torch"`` for scale;
- ``indreg-register --help``, ``indreg-train-momentum --help`` and ``indreg-align --help``, to their exit (as
  ``python -m``, the modules their console scripts run);
- ``indreg-register kernel.sigma=-1`` to its one-line refusal (a bad option, refused before torch is imported);
- ``indreg-register`` (the default experiment, in a temporary run directory) to its first log line, the first
  INFO line from indreg a user sees (the run's plan, ``indreg.experiments.register.plan_line``, logged before torch
  is imported): the process reports its own CPU seconds there and exits (:data:`FIRST_LINE`); the line is printed
  below the table.

Every command imports the indreg of this checkout (``PYTHONPATH``), or with ``--before DIR`` also that of the
checkout ``DIR`` (an older commit: ``git worktree add DIR <commit>``), for a before / after table::

    python scripts/bench_startup.py                  # 5 repeats
    python scripts/bench_startup.py --repeat 9 --before ../indreg-main
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PYTHON = sys.executable
HERE = Path(__file__).resolve().parents[1]


def entry_point(root: Path, *modules: str) -> list:
    """``python -m module`` (what the console script runs) of the first of ``modules`` that the checkout ``root``
    has (an older one has no ``indreg.learn.entry``: its console script ran ``indreg.learn.train``)."""
    return [PYTHON, "-m", next(m for m in modules if (root / (m.replace(".", "/") + ".py")).is_file())]


def to_exit(cmd: list, env: dict) -> tuple:
    """(CPU seconds, wall seconds) of ``cmd`` run to its exit (in an empty directory: ``python -m`` puts the current
    one first on ``sys.path``)."""
    before, start = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, env=env, cwd=tmp)
    after, wall = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter() - start
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime, wall


def to_refusal(cmd: list, env: dict) -> tuple:
    """(CPU seconds, wall seconds) of ``cmd``, a command line the app refuses (exit status 1, one line on
    stderr), run to its exit."""
    before, start = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run(cmd + [f"hydra.run.dir={tmp}/run"], capture_output=True, text=True, env=env, cwd=tmp)
    after, wall = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter() - start
    if proc.returncode != 1 or len(proc.stderr.strip().splitlines()) != 1:
        raise RuntimeError(f"{' '.join(cmd)} was not refused with one line: {proc.stderr[-2000:]}")
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime, wall


#: ``indreg-register`` that ends at its first log record of level INFO or above from indreg, writing its own CPU
#: seconds and the line to stderr (``cpu <seconds>``, ``line <message>``): the process measures itself, so no time
#: passes between the line and the reading, however loaded the machine (the run would go on meanwhile).
FIRST_LINE = """
import logging, os, sys, time
make = logging.getLogRecordFactory()
def first(name, level, *args, **kwargs):
    record = make(name, level, *args, **kwargs)
    if level >= logging.INFO and name.startswith("indreg"):
        os.write(2, f"cpu {time.process_time()}\\nline {record.getMessage()}\\n".encode())
        os._exit(0)
    return record
logging.setLogRecordFactory(first)
sys.argv = ["indreg-register", *sys.argv[1:]]
from indreg.experiments.register import main
main()
"""


#: The first log line of the last run of :func:`to_first_line`, by checkout (``PYTHONPATH``).
FIRST_LINES: dict = {}


def to_first_line(cmd: list, env: dict) -> tuple:
    """(CPU seconds, wall seconds) of ``cmd`` (:data:`FIRST_LINE`) until its first log line (kept in
    :data:`FIRST_LINES`)."""
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run(cmd + [f"hydra.run.dir={tmp}/run"], capture_output=True, text=True, cwd=tmp, env=env)
    wall = time.perf_counter() - start
    lines = [line for line in proc.stderr.splitlines() if line.startswith("cpu ")]
    if not lines:
        raise RuntimeError(f"{' '.join(cmd[:2])} ended without a log line: {proc.stderr[-2000:]}")
    FIRST_LINES[env["PYTHONPATH"]] = next((ln[5:] for ln in proc.stderr.splitlines() if ln.startswith("line ")), "")
    return float(lines[-1].split()[1]), wall


def cases(root: Path) -> list:
    """(label, measure, command) of each start-up, for the checkout ``root``."""
    register = entry_point(root, "indreg.experiments.register")
    train = entry_point(root, "indreg.learn.entry", "indreg.learn.train")
    return [("`python -c \"import torch\"` (for scale)", to_exit, [PYTHON, "-c", "import torch"]),
            ("`python -c \"import indreg\"`", to_exit, [PYTHON, "-c", "import indreg"]),
            ("`python -c \"from indreg import register\"`", to_exit, [PYTHON, "-c", "from indreg import register"]),
            ("`indreg-register --help`", to_exit, register + ["--help"]),
            ("`indreg-train-momentum --help`", to_exit, train + ["--help"]),
            ("`indreg-align --help`", to_exit, [PYTHON, "-m", "indreg.alignment.app", "--help"]),
            ("`indreg-register kernel.sigma=-1` to its one-line refusal", to_refusal, register + ["kernel.sigma=-1"]),
            ("`indreg-register` to its first log line", to_first_line, [PYTHON, "-c", FIRST_LINE])]


def measure(roots: list, repeat: int) -> dict:
    """{(label, root): [(CPU s, wall s), ...]}, the commands and the checkouts taking turns."""
    runs = {}
    for _ in range(repeat):
        for label, how, _ in cases(roots[0]):
            for root in roots:
                cmd = next(c for lab, _, c in cases(root) if lab == label)
                env = dict(os.environ, PYTHONPATH=str(root), OMP_NUM_THREADS="1")
                runs.setdefault((label, root), []).append(how(cmd, env))
    return runs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=5, help="runs of each command (median and least shown)")
    p.add_argument("--before", type=Path, help="another indreg checkout, measured by turns with this one")
    args = p.parse_args()
    if args.repeat < 1:
        p.error(f"--repeat {args.repeat}: at least one run")
    if args.before is not None and not (args.before / "indreg" / "__init__.py").is_file():
        p.error(f"--before {args.before}: not an indreg checkout (no indreg/__init__.py)")
    roots = [args.before.resolve(), HERE] if args.before is not None else [HERE]
    print(f"load average before: {os.getloadavg()[0]:.1f}\n")
    runs = measure(roots, args.repeat)
    names = ["before", "after"] if len(roots) == 2 else [""]
    head = " | ".join(f"{n} CPU s, median of {args.repeat} | {n} least | {n} wall s, median".strip() for n in names)
    print(f"| command | {head} |\n|---|" + "---|" * 3 * len(roots))
    for label, _, _ in cases(HERE):
        cells = []
        for root in roots:
            cpu, wall = [t[0] for t in runs[label, root]], [t[1] for t in runs[label, root]]
            cells += [f"{statistics.median(cpu):.2f}", f"{min(cpu):.2f}", f"{statistics.median(wall):.2f}"]
        print(f"| {label} | {' | '.join(cells)} |")
    print(f"\nload average after: {os.getloadavg()[0]:.1f}")
    for name, root in zip(names, roots):
        print(f"\n{name + ': ' if name else ''}first log line: {FIRST_LINES.get(str(root), '')}")


if __name__ == "__main__":
    main()
