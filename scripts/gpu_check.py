"""GPU readiness in one call: the CUDA tests, then the speed and memory benchmarks on one GPU, then one table.

Run from the repository root with a Python that has torch with CUDA and indreg's dependencies (the checkout is put
on ``PYTHONPATH``, so nothing needs installing): ``bash scripts/gpu_check.sh [OUTDIR]``. Every step runs in a
subprocess with its own time limit (all of them together under 8 minutes on one H100-class GPU); their full
output goes to ``OUTDIR`` (default ``gpu_check_out``), the summary table to stdout and ``OUTDIR/summary.md``.

Steps:
    tests       ``pytest -k cuda``: every test with a CUDA path (``tests/test_cuda.py``: whole registrations on the
                GPU equal to the CPU in float64; the operators', deformations' and losses' CUDA tests)
    register    ``scripts/bench_coarse_velocity.py`` at 256^3 (``velocity_factor`` 4, the ``suite_et_3d_256``
                settings), CPU and CUDA rows: seconds per iteration, peak memory
    slabs       ``scripts/bench_slabs.py --device cuda --tables whole big``: the slab-wise data term against the
                whole volume at 256^3, and one iteration at 1024 x 1024 x 256
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def steps(quick: bool) -> list:
    """``(name, argv, seconds allowed, pattern of the output lines the table keeps)``."""
    py = sys.executable
    size = "64" if quick else "256"
    out = [("tests", [py, "-m", "pytest", "-q", "-k", "cuda", "-p", "no:cacheprovider", "tests"], 200,
            r"^\d+ (passed|failed|skipped|error)|\d+ (passed|failed|skipped) in"),
           ("register", [py, "scripts/bench_coarse_velocity.py", "--sizes", size, "--factors", "4", "--rounds", "1",
                         "--iters", "2", "--warmup", "1", "--threads", "8"], 200, r"^\|.*\| (cpu|cuda) \|")]
    if (ROOT / "scripts" / "bench_slabs.py").exists():
        tables = ["--tables", "whole", "--n", "64", "--reps", "1", "--rounds", "1"] if quick else \
            ["--tables", "whole", "big", "--rounds", "1", "--big-iters", "4", "--max-memory", "8e9"]
        out.append(("slabs", [py, "scripts/bench_slabs.py", "--device", "cuda" if not quick else "cpu", *tables], 300,
                    r"^\|.*(cuda|cpu|slab|whole)"))
    return out


def run_step(name: str, argv: list, limit: int, keep: str, outdir: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    start = time.perf_counter()
    try:
        p = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=limit)
        text, status = p.stdout + p.stderr, "ok" if p.returncode == 0 else f"rc {p.returncode}"
    except subprocess.TimeoutExpired as e:
        text, status = f"{e.stdout or ''}{e.stderr or ''}", f"timed out after {limit} s"
        text = text.decode() if isinstance(text, bytes) else text
    (outdir / f"{name}.txt").write_text(text)
    lines = [ln.strip() for ln in text.splitlines() if re.search(keep, ln)]
    return {"name": name, "status": status, "seconds": time.perf_counter() - start, "lines": lines[-6:]}


def device_line() -> str:
    import torch

    if not torch.cuda.is_available():
        return f"torch {torch.__version__}: no CUDA device"
    p = torch.cuda.get_device_properties(0)
    return f"torch {torch.__version__}, CUDA {torch.version.cuda}: {p.name}, {p.total_memory / 2 ** 30:.0f} GiB"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("outdir", nargs="?", default="gpu_check_out")
    parser.add_argument("--quick", action="store_true", help="small sizes (a dry run of the script itself)")
    args = parser.parse_args()
    outdir = Path(args.outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    rows = [run_step(*s, outdir) for s in steps(args.quick)]
    table = [f"GPU check: {device_line()}", "", "| step | status | seconds | result |", "|---|---|---|---|"]
    for r in rows:
        cells = [" · ".join(c.strip() for c in ln.strip("|").split("|")) for ln in r["lines"]]
        result = "<br>".join(cells) or "(see the log)"
        table.append(f"| {r['name']} | {r['status']} | {r['seconds']:.0f} | {result} |")
    text = "\n".join(table)
    print(text)
    (outdir / "summary.md").write_text(text + "\n")
    return 0 if all(r["status"] == "ok" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
