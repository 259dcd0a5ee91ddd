"""Renamed modules: the old names that stay warn (a DeprecationWarning naming the new path and the release that
removes them) and give the new module itself; the others are gone; nothing in the repository uses an old name."""
import importlib
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from indreg._lazy import DEPRECATED, REMOVED_IN

ROOT = Path(__file__).resolve().parents[1]
#: Every module name that moved (the deprecated ones and those moved without an alias).
OLD = sorted({*DEPRECATED, "indreg._files", "indreg.api", "indreg.corrections", "indreg.option_checks", "indreg.run",
              "indreg.solver_registry", "indreg.align_app", "indreg.forward.shift", "indreg.io.alignment_files",
              "indreg.intensity", "indreg.orientation", "indreg.validation", "indreg._moved"})
#: Where old names may be written: the table of deprecated names, this test, the list of renames.
ALLOWED = {"indreg/_lazy.py", "tests/test_deprecated.py", "docs/changes.md"}


@pytest.mark.parametrize("old", sorted(DEPRECATED))
def test_deprecated_name_warns_and_is_the_new_module(old):
    code = (f"import warnings, importlib\nwarnings.simplefilter('error', DeprecationWarning)\n"
            f"try:\n    importlib.import_module({old!r})\nexcept DeprecationWarning as w:\n    print(w)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert f"{old} is deprecated" in out and DEPRECATED[old] in out and REMOVED_IN in out, out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        assert importlib.import_module(old) is importlib.import_module(DEPRECATED[old])


def test_the_warning_points_at_the_importing_line(tmp_path):
    script = tmp_path / "user_script.py"
    script.write_text("import warnings\nwarnings.simplefilter('always')\nimport indreg.writers\n")
    err = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, check=True).stderr
    assert "user_script.py:3: DeprecationWarning: indreg.writers is deprecated" in err, err


@pytest.mark.parametrize("old", sorted(set(OLD) - set(DEPRECATED)))
def test_removed_names_are_gone(old):
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(old)


def test_no_old_name_in_the_repository():
    files = subprocess.run(["git", "ls-files", "*.py", "*.md", "*.yaml", "*.sh", "*.toml"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    patterns = [re.compile(r"\bindreg\.(" + "|".join(re.escape(n[len("indreg."):]) for n in OLD) + r")\b(?![\w/])"),
                *(re.compile(rf"\bfrom {re.escape(parent)} import [^\n]*\b{leaf}\b")
                  for parent, leaf in (name.rsplit(".", 1) for name in OLD)),
                re.compile(r"\bindreg/(" + "|".join(re.escape(n[len("indreg."):].replace(".", "/")) for n in OLD)
                           + r")\.py\b")]
    found = [f"{f}:{i}: {line.strip()}" for f in files if f not in ALLOWED and (ROOT / f).is_file()
             for i, line in enumerate((ROOT / f).read_text(errors="replace").splitlines(), 1)
             if any(p.search(line) for p in patterns)]
    assert not found, "old module names:\n" + "\n".join(found[:30])
