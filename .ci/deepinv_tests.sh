#!/usr/bin/env bash
# The deepinv interop tests, in a second venv: deepinv imports torchvision, whose wheels reachable here are CUDA
# builds that need the matching CUDA torch (about 6 GB), so the main test venv (CPU torch) skips these tests.
# An installation that cannot be completed (no registry) is reported and skipped; failing tests fail CI.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=.venv-deepinv
if ! { python3 -m venv "$venv" && "$venv/bin/pip" install -q "torch==2.14.1" "torchvision==0.29.1" \
        && "$venv/bin/pip" install -q -e ".[test,deepinv]"; }; then
    echo "deepinv interop tests SKIPPED: could not install deepinv in $venv"
    exit 0
fi
OMP_NUM_THREADS=1 "$venv/bin/python" -m pytest -q -p no:cacheprovider tests/forward/test_deepinv.py \
    "tests/test_docstrings.py::test_docstring_examples[indreg.forward.deepinv]"
