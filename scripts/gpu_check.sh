#!/usr/bin/env bash
# GPU readiness in one call (docs/benchmarks.md): the CUDA tests and the benchmarks' CUDA rows, one table.
# Usage, from anywhere: bash scripts/gpu_check.sh [OUTDIR] [--quick]   (PYTHON=... picks the interpreter)
set -uo pipefail
cd "$(dirname "$0")/.."
exec "${PYTHON:-python3}" scripts/gpu_check.py "$@"
