"""The house rules of the package's size (issue #45): a module over 450 lines says why at the end of its docstring
(``Longer than 450 lines: ...``), a function over 80 lines (its docstring aside) in a comment at the top of its body
(``# Longer than 80 lines: ...``)."""
import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "indreg"
MAX_MODULE, MAX_FUNCTION = 450, 80


def _modules():
    return sorted(PACKAGE.rglob("*.py"))


def _body_lines(fn) -> tuple:
    """``(first line of the body after the docstring, its length in lines)``."""
    body = fn.body
    if isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) and \
            isinstance(body[0].value.value, str) and len(body) > 1:
        body = body[1:]
    return body[0].lineno, fn.end_lineno - body[0].lineno + 1


def test_a_long_module_says_why():
    unexplained = []
    for path in _modules():
        text = path.read_text()
        if text.count("\n") + 1 > MAX_MODULE and "Longer than 450 lines:" not in (ast.get_docstring(ast.parse(text))
                                                                                  or ""):
            unexplained.append(str(path.relative_to(PACKAGE.parent)))
    assert not unexplained, unexplained


def test_a_long_function_says_why():
    unexplained = []
    for path in _modules():
        text = path.read_text()
        lines = text.splitlines()
        for fn in ast.walk(ast.parse(text)):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                start, length = _body_lines(fn)
                comment = "\n".join(lines[max(start - 4, 0):start])
                if length > MAX_FUNCTION and "# Longer than 80 lines:" not in comment:
                    unexplained.append(f"{path.relative_to(PACKAGE.parent)}:{fn.name} ({length} lines)")
    assert not unexplained, unexplained
