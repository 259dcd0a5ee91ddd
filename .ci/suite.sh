#!/usr/bin/env bash
# README's test command in a fresh venv: bash .ci/suite.sh VENV PINS [EXTRA [WHEELS]]. PINS: a pip constraints file
# naming the torch (and what it needs: numpy's major version); torch is installed first from it (with torchvision
# when EXTRA is deepinv, from the folder WHEELS if given, where .ci/run downloaded them), then README's command from
# `pip install -e ".[test]"` on (the extra EXTRA added), the pins kept. Prints torch's version, the venv's size and
# the times of the installation and of each pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=$1 pins=$2 extra=${3:-} wheels=${4:-}
export PIP_CONSTRAINT="$PWD/$pins"
rm -rf "$venv"
t0=$SECONDS
python3 -m venv "$venv"
. "$venv/bin/activate"
torch=(torch)
[ "$extra" = deepinv ] && torch+=(torchvision)
if [ -n "$wheels" ]; then pip install -q --no-index --find-links "$wheels" "${torch[@]}"; else pip install -q "${torch[@]}"; fi
t1=$SECONDS
pip install -q -e ".[test${extra:+,$extra}]"
t2=$SECONDS
pytest -q -p no:cacheprovider || exit 1   # (set -e alone does not stop inside an && list, README's form)
t3=$SECONDS
pytest -q -p no:cacheprovider -m slow || exit 1
t4=$SECONDS
echo "[ci] $venv: torch $(python -c 'import torch; print(torch.__version__)'), $(du -sh "$venv" | cut -f1);" \
     "torch $((t1 - t0)) s, indreg$extra $((t2 - t1)) s, pytest $((t3 - t2)) s, pytest -m slow $((t4 - t3)) s"
