"""CPU seconds of the entry points' start-ups and of importing indreg (docs/benchmarks.md, "Start-up").

Each command runs ``--repeat`` times in a fresh process; the table shows the least CPU seconds (user + system,
less sensitive to other jobs than wall seconds) and the wall seconds of that run:

- ``python -c "import indreg"`` (the lazy top level) and ``python -c "from indreg import register"`` (torch
  and the registration stack), with ``python -c "import torch"`` for scale;
- ``indreg-register --help`` and ``indreg-train-momentum --help``, to their exit (as ``python -m``, the modules
  their console scripts run);
- ``indreg-register`` (the default experiment, in a temporary run directory) to its first log line: the process
  is stopped there and its CPU seconds read from ``/proc/<pid>/stat`` (Linux).

    python scripts/bench_startup.py               # 3 repeats
    python scripts/bench_startup.py --repeat 5
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PYTHON = sys.executable


def entry_point(*modules: str) -> list:
    """``python -m module`` (what the console script runs) of the first of ``modules`` that this indreg has (an
    older one has no ``indreg.learn.entry``: its console script ran ``indreg.learn.train``)."""
    return [PYTHON, "-m", next(m for m in modules if importlib.util.find_spec(m) is not None)]


def to_exit(cmd: list) -> tuple:
    """(CPU seconds, wall seconds) of ``cmd`` run to its exit."""
    before, start = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    after, wall = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter() - start
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime, wall


def to_first_line(cmd: list) -> tuple:
    """(CPU seconds, wall seconds) of ``cmd`` until it writes its first line (stdout and stderr together)."""
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.Popen(cmd + [f"hydra.run.dir={tmp}/run"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                cwd=tmp)
        try:
            if not proc.stdout.readline():
                raise RuntimeError(f"{cmd[0]} ended without a line")
            wall = time.perf_counter() - start
            fields = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")   # utime, stime
        finally:
            proc.kill()
            proc.wait()
    return cpu, wall


def cases() -> list:
    register = entry_point("indreg.experiments.register")
    train = entry_point("indreg.learn.entry", "indreg.learn.train")
    return [("`python -c \"import torch\"` (for scale)", to_exit, [PYTHON, "-c", "import torch"]),
            ("`python -c \"import indreg\"`", to_exit, [PYTHON, "-c", "import indreg"]),
            ("`python -c \"from indreg import register\"`", to_exit, [PYTHON, "-c", "from indreg import register"]),
            ("`indreg-register --help`", to_exit, register + ["--help"]),
            ("`indreg-train-momentum --help`", to_exit, train + ["--help"]),
            ("`indreg-register` to its first log line", to_first_line, register)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=3, help="runs of each command (the least CPU time is shown)")
    args = p.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f}\n")
    print("| command | CPU s | wall s |\n|---|---|---|")
    for label, measure, cmd in cases():
        cpu, wall = min(measure(cmd) for _ in range(args.repeat))
        print(f"| {label} | {cpu:.2f} | {wall:.2f} |", flush=True)
    print(f"\nload average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
