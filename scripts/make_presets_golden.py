"""Record the golden numbers of every experiment preset (tests/data/presets_golden.json).

Runs the ``indreg-register`` app in-process (``register.run``) for every preset in ``indreg/conf/experiment/``,
unchanged except a few iterations (``MAX_ITER``, default ``DEFAULT_MAX_ITER``), no baselines, no TensorBoard /
figure / progress bar, on the CPU; ``suite_et_3d`` also on a 32^3 grid with a 32-column detector (``SHRINK``: its
64^3 grid takes about 50 s for 2 iterations on a 2-core CPU). Then ``VARIANTS``: suite 1 with the other solvers and
deformation models, and a metamorphosis preset with its source updated from iteration 2 (the presets freeze it
for their first 300-600 iterations); the L-BFGS variant in float64 (in float32 its line search turns rounding
differences, e.g. of the thread count, into 1e-3 relative differences within 3 iterations). Then
``indreg.register`` on suite 1 (README, "Example") with ``API_CASES`` (float64: the phantoms' dtype).

Stores, per case, the overrides (options) and the scalars of the metrics (result) but timings, config and device
(``golden_helpers``); ``tests/experiments/test_presets_golden.py`` re-runs every case and compares.

    python scripts/make_presets_golden.py            # writes tests/data/presets_golden.json
    python scripts/make_presets_golden.py --out /tmp/golden.json
    python scripts/make_presets_golden.py --only app:suite1_jv-metamorphosis api:metamorphosis
                                                     # only these cases, the others kept as stored
    python scripts/make_presets_golden.py --floors   # the quality floors of the quick cases (below)

Floors (``--floors [KIND:NAME ...]``): each case run again at its converged iteration count (the preset's own
``solver.max_iter``, or the API's 200), its SSIM stored with ``floor = SSIM - FLOOR_MARGIN``: whoever changes the
numerics on purpose re-records the golden numbers and keeps the floors
(``tests/experiments/test_presets_floors.py``). Without names: ``FLOOR_CASES``, the cases that converge in seconds.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "experiments")]  # this checkout's indreg and test helpers

import torch  # noqa: E402

from golden_helpers import GOLDEN, api_numbers, app_numbers  # noqa: E402

PRESETS = ROOT / "indreg" / "conf" / "experiment"
COMMON = ["baseline.enabled=false", "logging.tensorboard=false", "logging.figure=false", "logging.progress=false",
          "device=cpu"]
DEFAULT_MAX_ITER = 3                       # 256^2 and 438^2 presets: 0.3-1 s per iteration
MAX_ITER = {"suite1_jv": 10, "own_data_example": 10, "suite_et_3d": 2, "suite_et_3d_128": 2, "suite_et_3d_256": 2,
            "suite_et_3d_slab": 2, "suite_et_3d_1024_slab": 2}
# same [-16, 16]^3, 1-unit voxels / columns (the 128^3 / 256^3 variants: their config path at a testable size)
SHRINK = {name: ["phantom.size=32", "geometry.det_count=32"] for name in ("suite_et_3d", "suite_et_3d_128",
                                                                          "suite_et_3d_256")}
SHRINK["suite_et_3d_slab"] = ["phantom.size=32", "phantom.thickness=12", "geometry.det_count=32"]
# 0.5-unit voxels as the shrunk cubes, the preset's aspect (x : z = 4 : 1, 8 rows), slab-wise in 2 slabs
SHRINK["suite_et_3d_1024_slab"] = ["phantom.size=64", "phantom.rows=8", "phantom.thickness=16", "geometry.det_count=64",
                                   "deformation.slab_size=4"]
VARIANTS = {
    # float64: L-BFGS's line search in float32 amplifies rounding (1 vs 2 threads: 1e-3 apart after 3 iterations)
    "suite1_jv-lbfgs": ["experiment=suite1_jv", "solver=lbfgs", "solver.max_iter=10", "dtype=float64"],
    # level_iter 3, 3: both coarse levels and the problem's grid within 9 iterations
    "suite1_jv-fast": ["experiment=suite1_jv", "solver=fast", "solver.max_iter=9",
                       "solver.optimizer_kwargs.level_iter=[3,3]"],
    "suite1_jv-adam": ["experiment=suite1_jv", "solver=adam", "solver.lr=1e-4", "solver.max_iter=10"],  # 1e-3 folds
    "suite1_jv-mass_preserving": ["experiment=suite1_jv", "deformation=mass_preserving", "solver.max_iter=10"],
    "suite1_jv-metamorphosis": ["experiment=suite1_jv", "deformation=metamorphosis", "solver.max_iter=10"],
    "suite1_jv-backward_exact": ["experiment=suite1_jv", "deformation.backward=exact", "solver.max_iter=10"],
    "suite4_missing_object_metamorphosis-source_start_1": [
        "experiment=suite4_missing_object_metamorphosis", "solver.source_start=1", "solver.max_iter=3"],
}
#: The cases whose converged run takes seconds (64^2): their floors are recorded and checked in CI.
FLOOR_CASES = ("app:suite1_jv", "app:own_data_example", "app:suite_dynamic_2d", "app:suite_dynamic_2d_unknown",
               "app:suite1_jv-backward_exact", "app:suite1_jv-mass_preserving", "app:suite1_jv-metamorphosis",
               "app:suite1_jv-fast", "api:default", "api:fast", "api:metamorphosis", "api:defaults")
FLOOR_MARGIN = 0.01
API_CONVERGED = 200
#: register()'s defaults before the kernel width relative to the box and compose (indreg.kernel_width): the cases
#: recorded with them keep them; "defaults" runs the defaults of today.
BEFORE = {"sigma": 6.0, "interpolation": "reinterpolate"}
API_CASES = {
    "default": {"max_iter": 10, **BEFORE},
    "lbfgs": {"solver": "lbfgs", "max_iter": 5, **BEFORE},
    "fast": {"solver": "fast", "max_iter": 9, "optimizer_kwargs": {"level_iter": [3, 3]}, "sigma": 6.0},
    "metamorphosis": {"model": "metamorphosis", "max_iter": 10, **BEFORE},
    "defaults": {"max_iter": 10},
}


def app_cases() -> dict:
    """Case name -> overrides: every preset of the directory, then ``VARIANTS``."""
    cases = {}
    for path in sorted(PRESETS.glob("*.yaml")):
        name = path.stem
        cases[name] = ([f"experiment={name}", f"solver.max_iter={MAX_ITER.get(name, DEFAULT_MAX_ITER)}"]
                       + SHRINK.get(name, []))
    cases.update(VARIANTS)
    return {k: v + COMMON for k, v in cases.items()}


def _commit() -> str:
    """The last commit that changed ``indreg/`` (``-dirty``: with uncommitted changes there)."""
    def git(*args):
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True).stdout.strip()

    commit = git("log", "-1", "--format=%h", "--", "indreg") or "unknown"
    return commit + ("-dirty" if git("status", "--porcelain", "--", "indreg") else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=GOLDEN)
    ap.add_argument("--only", nargs="+", metavar="KIND:NAME", default=None,
                    help="regenerate only these cases (app:NAME / api:NAME) and keep the others as stored in --out")
    ap.add_argument("--floors", nargs="*", metavar="KIND:NAME", default=None,
                    help="record the quality floors of these cases (default: FLOOR_CASES) at their converged "
                         "iteration count, keeping the golden numbers")
    args = ap.parse_args()
    if args.floors is not None:
        return record_floors(args.out, args.floors or FLOOR_CASES)
    cases = {"app": app_cases(), "api": API_CASES}
    if args.only is None:
        floors = json.loads(args.out.read_text()).get("floors", {}) if args.out.exists() else {}
        golden = {"about": {"indreg_commit": _commit(), "torch": torch.__version__,
                            "python": platform.python_version(), "threads": torch.get_num_threads()},
                  "app": {}, "api": {}, "floors": floors}   # the floors are kept: they are re-recorded apart
        chosen = [(kind, name) for kind in cases for name in cases[kind]]
    else:
        golden = json.loads(args.out.read_text())
        chosen = [tuple(spec.split(":", 1)) for spec in args.only]
        unknown = [f"{k}:{n}" for k, n in chosen if n not in cases.get(k, {})]
        if unknown:
            ap.error(f"unknown case(s) {', '.join(unknown)}")
    rows = []
    for kind, name in chosen:
        t0 = time.perf_counter()
        if kind == "app":
            with tempfile.TemporaryDirectory() as out_dir:
                numbers = app_numbers(cases[kind][name], out_dir)
            golden["app"][name] = {"overrides": cases[kind][name], "metrics": numbers}
        else:
            numbers = api_numbers(cases[kind][name])
            golden["api"][name] = {"options": cases[kind][name], "result": numbers}
        rows.append((kind, name, time.perf_counter() - t0, numbers))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(golden, indent=2, sort_keys=True) + "\n")
    print("| kind | case | seconds | status | iterations | objective | SSIM |\n|---|---|---|---|---|---|---|")
    for kind, name, seconds, m in rows:
        print(f"| {kind} | {name} | {seconds:.1f} | {m['status']} | {m['iterations']} | {m['objective']:.6g} | "
              f"{m.get('ssim', float('nan')):.4f} |")
    print(f"\nwrote {args.out} ({len(rows)} cases)")


def converged(kind: str, case):
    """The case at its converged iteration count: the app's overrides without ``solver.max_iter`` (the preset's
    own), the API's options with ``max_iter`` ``API_CONVERGED``."""
    if kind == "app":
        return [o for o in case if not o.startswith("solver.max_iter=")]
    return dict(case, max_iter=API_CONVERGED)


def record_floors(out: Path, chosen) -> None:
    """SSIM of each case at its converged iteration count, stored under ``floors`` with ``SSIM - FLOOR_MARGIN``."""
    golden = json.loads(out.read_text())
    cases = {"app": app_cases(), "api": API_CASES}
    print("| case | iterations | SSIM | floor | seconds |\n|---|---|---|---|---|")
    for spec in chosen:
        kind, name = spec.split(":", 1)
        run = converged(kind, cases[kind][name])
        t0 = time.perf_counter()
        if kind == "app":
            with tempfile.TemporaryDirectory() as out_dir:
                numbers = app_numbers(run, out_dir)
        else:
            numbers = api_numbers(run)
        ssim = numbers["ssim"]
        seconds = time.perf_counter() - t0
        golden.setdefault("floors", {})[spec] = {"run": run, "ssim": ssim, "seconds": round(seconds, 1),
                                                 "floor": math.floor((ssim - FLOOR_MARGIN) * 1000) / 1000}
        print(f"| {spec} | {numbers['iterations']} | {ssim:.4f} | {golden['floors'][spec]['floor']:.3f} | "
              f"{seconds:.1f} |", flush=True)
    out.write_text(json.dumps(golden, indent=2, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
