#!/usr/bin/env bash
# The installed wheel must work like the checkout: build it, install it in a fresh venv, run both entry points
# from a temporary directory outside the repo (tiny problems, a few seconds each).
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
"$bin/indreg-train-momentum" --help > /dev/null
"$bin/indreg-train-momentum" domain.n=16 geometry.num_angles=6 geometry.det_count=24 shooting.num_steps=3 \
    data.num_train=4 data.num_val=2 model.width=4 model.levels=2 train.batch_size=2 train.steps=2 \
    train.eval_every=2 eval.algorithm1.num_samples=1 eval.algorithm1.max_iter=2 device=cpu \
    hydra.run.dir="$work/run_train"
test -f "$work/run_train/metrics.json"
test ! -e "$work/venv/lib/python3"*/site-packages/configs
echo "wheel check passed: both entry points ran from $work with the installed wheel"
