"""Every ``>>>`` example in the package's docstrings runs (doctest) and prints what it shows."""
import doctest
import inspect
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


# ------------------------------------------------------------------------------------------ the public API's sections
#: The packages whose public names are the API: name -> where its list lives (``__all__``; the three modules of
#: ``indreg.__all__`` that have none: every function and class they define without a leading underscore).
API_PACKAGES = ("indreg", "indreg.alignment", "indreg.evaluation", "indreg.io", "indreg.forward", "indreg.deform",
                "indreg.solvers", "indreg.problems", "indreg.learn")
API_MODULES = ("indreg.metrics", "indreg.noise", "indreg.phantoms")
#: The option registries of ``indreg.options`` (its other names are the table's internals).
OPTIONS_API = ("register_model", "register_solver", "register_correction", "Model", "Solver", "Correction", "Option",
               "check_value")
#: Public callables exempt from a section, with the reason: (name, section) -> reason.
EXEMPT = {}
#: Google-style section headers (the project writes numpydoc: a title underlined with dashes).
GOOGLE = re.compile(r"^\s*(Args|Arguments|Keyword Args|Returns|Return|Yields|Raises|Convention|Conventions|Example|"
                    r"Examples|Note|Notes|Attributes|Parameters|See Also|References):\s*$", flags=re.M)


def _public_api() -> dict:
    """Every public callable of the API: its first dotted name -> the object (one entry per object)."""
    names = []
    for package in API_PACKAGES:
        module = importlib.import_module(package)
        names += [(package, n) for n in module.__all__]
    for name in API_MODULES:
        module = importlib.import_module(name)
        names += [(name, n) for n, obj in vars(module).items() if not n.startswith("_") and
                  (inspect.isfunction(obj) or inspect.isclass(obj)) and obj.__module__ == name]
    names += [("indreg.options", n) for n in OPTIONS_API]
    out, seen = {}, set()
    for module, name in names:
        obj = getattr(importlib.import_module(module), name)
        if inspect.ismodule(obj) or not callable(obj) or id(obj) in seen:
            continue
        seen.add(id(obj))
        out[f"{module}.{name}"] = obj
    return out


def _sections(doc: str) -> dict:
    """numpydoc sections of a (cleaned) docstring: title -> its lines."""
    lines = doc.splitlines()
    out, title = {}, None
    for i, line in enumerate(lines):
        if i + 1 < len(lines) and line.strip() and re.fullmatch(r"-{3,}", lines[i + 1].strip()) \
                and not line.startswith(" "):
            title = line.strip()
            out[title] = []
        elif title is not None and not re.fullmatch(r"-{3,}", line.strip()):
            out[title].append(line)
    return out


def _documented(lines: list) -> set:
    """The names a Parameters section documents (``name : type`` or ``name`` at the section's indentation)."""
    out = set()
    for line in lines:
        m = re.match(r"^(\*{0,2}\w+(?:, \*{0,2}\w+)*)(\s*:.*)?$", line)
        if m:
            out.update(n.lstrip("*") for n in m.group(1).split(", "))
    return out


def _parameters(obj) -> list:
    """The parameters a caller passes (a class: its constructor's), without ``self``."""
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return []
    return [p for p in sig.parameters.values() if p.name not in ("self", "cls")]


def _returns_value(func) -> bool:
    """Whether ``func``'s own body has a ``return <value>`` (not ``return`` / ``return None``)."""
    import ast
    import textwrap

    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(func)))
    except (OSError, TypeError, SyntaxError):
        return False
    top = tree.body[0]

    def walk(node):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
                continue
            if isinstance(child, ast.Return) and child.value is not None and not (
                    isinstance(child.value, ast.Constant) and child.value.value is None):
                yield child
            yield from walk(child)
    return any(True for _ in walk(top))


API = _public_api()


def test_the_public_api_is_listed():
    assert len(API) > 100 and "indreg.register" in API and "indreg.options.check_value" in API


#: numpydoc's order of the sections.
ORDER = ("Parameters", "Attributes", "Returns", "Yields", "Raises", "Warns", "See Also", "Notes", "References",
         "Examples")


def _problems(name: str, obj) -> list:
    """What ``obj``'s docstring lacks: a docstring, ``Parameters`` naming every parameter (a record class:
    ``Attributes``), ``Returns`` (``Yields`` for a generator) when the function returns a value, titles underlined
    with as many dashes and in numpydoc's order, the default first in a ``{a, b}`` type (the API reference shows the
    first as the default), no Google-style header."""
    doc = obj.__doc__
    if not (doc and doc.strip()):
        return [f"{name} has no docstring"]
    doc, out = inspect.cleandoc(doc), []
    lines = doc.splitlines()
    out += [f"{name}: underline of {lines[i - 1].strip()!r}" for i, line in enumerate(lines)
            if i and re.fullmatch(r"-{3,}", line.strip()) and lines[i - 1].strip()
            and len(line.strip()) != len(lines[i - 1].strip())]
    sections = _sections(doc)
    known = [t for t in sections if t in ORDER]
    if known != sorted(known, key=ORDER.index):
        out.append(f"{name}: sections {known} not in numpydoc's order")
    params = [] if getattr(obj, "_is_protocol", False) else _parameters(obj)   # a Protocol is not constructed
    if params and (name, "Parameters") not in EXEMPT:
        record = inspect.isclass(obj) and "Attributes" in sections and "Parameters" not in sections
        listed = _documented(sections.get("Attributes" if record else "Parameters", []))
        missing = [p.name for p in params if p.name not in listed]
        if missing:
            out.append(f"{name}: Parameters does not document {missing}")
        defaults = {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}
        for line in sections.get("Parameters", []):
            m = re.match(r"^(\w+) : \{([^}]*)\}", line)
            if m and m.group(1) in defaults and isinstance(defaults[m.group(1)], (str, int)) \
                    and m.group(2).split(",")[0].strip().strip("'\"") != str(defaults[m.group(1)]):
                out.append(f"{name}: list the default of {m.group(1)} first in its {{...}} type")
    if inspect.isfunction(obj) and (name, "Returns") not in EXEMPT:
        if inspect.isgeneratorfunction(obj) and "Yields" not in sections:
            out.append(f"{name} is a generator: a Yields section")
        elif not inspect.isgeneratorfunction(obj) and _returns_value(obj) and "Returns" not in sections:
            out.append(f"{name} returns a value: a Returns section")
    if GOOGLE.search(doc):
        out.append(f"{name}: a Google-style section header ({GOOGLE.search(doc).group(0).strip()})")
    return out


@pytest.mark.parametrize("name", sorted(API))
def test_public_docstring_has_its_sections(name):
    assert not _problems(name, API[name])


def test_exemptions_name_public_callables():
    assert {name for name, _ in EXEMPT} <= set(API) and all(reason for reason in EXEMPT.values())


def _bad(x, mode="b"):
    """Google style.

    Args:
        x: a value.
    """
    return x


def _good(x, mode="b"):
    """numpydoc.

    Parameters
    ----------
    x : int
        A value.
    mode : {"b", "a"}
        A choice, the default first.

    Returns
    -------
    int
        ``x``.
    """
    return x


def test_the_checks_fail_on_a_bad_docstring():
    """The checker is not vacuous: each defect of a docstring is reported."""
    assert _problems("good", _good) == []
    problems = " | ".join(_problems("bad", _bad))
    for what in ("does not document ['x', 'mode']", "a Returns section", "Google-style"):
        assert what in problems
    assert _problems("none", lambda: None) == ["none has no docstring"]

    def fake(doc):
        def f(x, mode="b"):
            return x
        f.__doc__ = doc
        return f
    wrong = fake("""Wrong default, short underline, Notes first.

    Notes
    -----
    x.

    Parameters
    ----------
    x : int
        A value.
    mode : {"a", "b"}
        The default listed second.

    Returns
    ------
    int
        ``x``.
    """)
    problems = " | ".join(_problems("wrong", wrong))
    for what in ("list the default of mode first", "underline of 'Returns'", "not in numpydoc's order"):
        assert what in problems


def test_no_google_style_sections_in_the_package():
    """One docstring style (numpydoc, mkdocs.yml's ``docstring_style``): no ``Args:`` / ``Raises:`` / ... blocks."""
    root = Path(indreg.__file__).parent
    found = [f"{p.relative_to(root.parent)}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0).strip()}"
             for p in sorted(root.rglob("*.py")) for text in [p.read_text()] for m in GOOGLE.finditer(text)]
    assert not found, "Google-style sections (write numpydoc: Parameters / Returns / Raises / Notes):\n" + \
        "\n".join(found)


def test_register_docstring_lists_every_option():
    """``help(indreg.register)``: a Parameters entry for every option of the table, generated from it."""
    from indreg import options

    entries = _sections(inspect.cleandoc(indreg.register.__doc__))["Parameters"]
    missing = {"template", "data", "operator", "options"} | {o.name for o in options.all_options()}
    assert not missing - _documented(entries), missing - _documented(entries)
    for o in options.all_options():
        line = next(e for e in entries if e.startswith(f"{o.name} : "))
        assert line.endswith(f", default {o.default!r}"), line
    assert "{options}" not in indreg.register.__doc__
