#!/usr/bin/env bash
# The installed wheel must work like the checkout: build it, install it in a fresh venv, run both entry points
# from a temporary directory outside the repo (tiny problems, a few seconds each), and the sweep-table command.
set -euo pipefail
cd "$(dirname "$0")/.."
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
trap 'echo "wheel check FAILED at line $LINENO: $BASH_COMMAND" >&2' ERR
python3 -m pip wheel -q --no-deps -w "$work/dist" .
python3 -m venv "$work/venv"
"$work/venv/bin/pip" install -q "torch==2.13.0"
"$work/venv/bin/pip" install -q "$work"/dist/indreg-*.whl
cd "$work"
export OMP_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE
bin="$work/venv/bin"
help="$("$bin/indreg-register" --help)"
for preset in own_data_example suite1_jv suite3_shepp_logan suite4_missing_object_metamorphosis suite_et_3d; do
    grep -Eq "experiment:.*\b$preset\b" <<< "$help"
done
# the help describes the tool (not Hydra's stock text) and points to the docs and the sweep table
grep -q '^indreg-register: indirect image registration' <<< "$help"
grep -q 'docs/index.md' <<< "$help" && ! grep -q 'powered by Hydra' <<< "$help"
# the aligner's and the scorer's console scripts answer --help from the wheel; a missing stack is one line, exit 2
"$bin/indreg-align" --help | grep -q 'indreg-align'
"$bin/indreg-score" --help | grep -q '^usage: indreg-score'
if "$bin/indreg-score" "$work/missing.mrc" "$work/volume.mrc" 2> "$work/score.err"; then false; fi
grep -q 'no such file' "$work/score.err" && test "$(wc -l < "$work/score.err")" -eq 1
# a missing launcher plugin names its extra: one line, exit 1
if "$bin/indreg-register" -m hydra/launcher=slurm seed=0,1 2> "$work/launcher.err"; then false; fi
grep -q 'pip install "indreg\[submitit\]"' "$work/launcher.err" && test "$(wc -l < "$work/launcher.err")" -eq 1
"$bin/indreg-register" solver=lbfgs phantom.size=32 deformation.num_steps=4 solver.max_iter=2 baseline=none \
    logging=quiet hydra.run.dir="$work/run_lbfgs"
"$bin/indreg-register" deformation=mass_preserving noise=none phantom.size=32 deformation.num_steps=4 \
    solver.max_iter=2 baseline=none logging=quiet hydra.run.dir="$work/run_mp"
test -f "$work/run_lbfgs/metrics.json" && test -f "$work/run_mp/metrics.json"
# solver=fast, metamorphosis and a tiny 3D tilt-series run (final.mrc)
"$bin/indreg-register" solver=fast phantom.size=32 deformation.num_steps=4 solver.max_iter=3 baseline=none \
    logging=quiet hydra.run.dir="$work/run_fast"
"$bin/indreg-register" deformation=metamorphosis phantom.size=32 deformation.num_steps=4 solver.max_iter=2 \
    baseline=none logging=quiet hydra.run.dir="$work/run_meta"
"$bin/indreg-register" experiment=suite_et_3d phantom.size=16 geometry.det_count=16 geometry.tilt_step=20 \
    deformation.num_steps=3 solver.max_iter=2 baseline=none logging=quiet hydra.run.dir="$work/run_3d"
test -f "$work/run_fast/metrics.json" && test -f "$work/run_meta/metrics.json" && test -f "$work/run_3d/final.mrc"
# the shipped own-data example (files in the wheel's indreg/data, read through ${indreg_data:...})
"$bin/indreg-register" experiment=own_data_example solver.max_iter=5 baseline=none logging=quiet \
    hydra.run.dir="$work/run_own_data"
grep -q '"source": "files"' "$work/run_own_data/metrics.json"
grep -q '^indreg-train-momentum: learned LDDMM' <<< "$("$bin/indreg-train-momentum" --help)"
"$bin/indreg-train-momentum" domain.n=16 geometry.num_angles=6 geometry.det_count=24 shooting.num_steps=3 \
    data.num_train=4 data.num_val=2 model.width=4 model.levels=2 train.batch_size=2 train.steps=2 \
    train.eval_every=2 eval.algorithm1.num_samples=1 eval.algorithm1.max_iter=2 device=cpu \
    hydra.run.dir="$work/run_train"
test -f "$work/run_train/metrics.json"
# the sweep-table command: a usage error without arguments, then the table of a (one-run) multirun
grep -q '^usage: indreg-sweep-table' <<< "$("$bin/indreg-sweep-table" --help)"
if "$bin/indreg-sweep-table" 2> /dev/null; then false; fi
"$bin/indreg-register" -m kernel.sigma=2 phantom.size=32 deformation.num_steps=3 solver.max_iter=2 baseline=none \
    logging=quiet hydra.sweep.dir="$work/sweep"
grep -q '^| 2 |' <<< "$("$bin/indreg-sweep-table" "$work/sweep")"
test -f "$work/sweep/table.md" && test -f "$work/sweep/table.csv"
"$bin/python" -m indreg.experiments.sweep "$work/sweep" > /dev/null
test ! -e "$work/venv/lib/python3"*/site-packages/configs
echo "wheel check passed: the entry points ran from $work with the installed wheel"
