"""Every ``>>>`` example in the package's docstrings runs (doctest) and prints what it shows."""
import doctest
import importlib
import pkgutil
import re
from pathlib import Path

import pytest

import indreg

#: Modules whose examples need an optional extra: module -> the package it needs.
NEEDS = {"indreg.forward.deepinv": "deepinv"}


def _modules() -> list:
    return sorted(m.name for m in pkgutil.walk_packages(indreg.__path__, "indreg."))


def _examples(name: str) -> list:
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    return [t for t in finder.find(module, name, globs=vars(module).copy()) if t.examples]


def _modules_with_prompts() -> list:
    """Modules whose source has a ``>>>`` prompt line (found without doctest, to check the finder)."""
    root = Path(indreg.__file__).parent
    out = []
    for path in sorted(root.rglob("*.py")):
        if re.search(r"^\s*>>> ", path.read_text(), flags=re.M):
            rel = path.relative_to(root.parent).with_suffix("")
            out.append(".".join(p for p in rel.parts if p != "__init__"))
    return out


def test_every_prompt_is_found_by_doctest():
    """No example hides where doctest does not look (e.g. a comment or a nested function)."""
    prompts = _modules_with_prompts()
    assert prompts, "the package has examples"
    for name in prompts:
        source = Path(importlib.import_module(name).__file__).read_text()
        found = sum(len(t.examples) for t in _examples(name))
        assert found == len(re.findall(r"^\s*>>> ", source, flags=re.M)), name


@pytest.mark.parametrize("name", _modules_with_prompts())
def test_docstring_examples(name):
    if name in NEEDS:
        pytest.importorskip(NEEDS[name], reason=f"the examples of {name} need the optional extra {NEEDS[name]}")
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    report = []
    for test in _examples(name):
        runner.run(test, out=report.append)
    assert runner.tries > 0 and runner.failures == 0, "".join(report)


def test_modules_import_without_optional_extras():
    """Every module imports (the examples can be collected) whether or not the extras are installed."""
    for name in _modules():
        importlib.import_module(name)
