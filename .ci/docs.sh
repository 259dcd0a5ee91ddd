#!/usr/bin/env bash
# The documentation site in a fresh venv: docs/ and the docstrings (mkdocs.yml), warnings as errors (every internal
# link, anchor and API reference resolved). The API reference is read from the source (griffe), so neither torch nor
# indreg's other dependencies are installed: only the `docs` extra's packages (numpy among them: indreg.register's
# option entries come from the option table, imported without torch, docs/_hooks/register_options.py). Output: site/.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${DOCS_VENV:-.venv-docs-ci}"
rm -rf "$venv"
python3 -m venv "$venv"
# the `docs` extra of pyproject.toml (`pip install ".[docs]"` would also pull torch and the other dependencies)
mapfile -t extra < <("$venv/bin/python" -c "import tomllib; print(*tomllib.load(open('pyproject.toml', 'rb'))
['project']['optional-dependencies']['docs'], sep='\n')")
"$venv/bin/pip" install --quiet "${extra[@]}"
NO_MKDOCS_2_WARNING=1 "$venv/bin/mkdocs" build --strict
