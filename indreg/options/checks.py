"""The value checks of the option table (``indreg.options``): each ``check(value, label)`` returns the value
normalised or raises :class:`OptionError` naming ``label`` (the keyword or the config key), the value and what was
expected.

Notes
-----
``label`` is the name shown to the user; ``OptionError.kind`` is the exception type ``register()``
raises (TypeError for a wrong type, ValueError else).
"""
from __future__ import annotations

import math
import numbers
from typing import Callable

__all__ = ["OptionError", "number", "choice", "boolean", "optional", "mapping", "auto_or", "anything", "holdout",
           "ALGORITHM1", "FAST", "TORCH"]

#: The built-in solvers' registry names (``indreg.registration.solver_registry``): the options of the table name them; ``TORCH``
#: is the family of the torch.optim optimizers (``register()`` names each by its class name: ``"lbfgs"``, ...).
ALGORITHM1, FAST, TORCH = "algorithm1", "fast", "torch"


class OptionError(ValueError):
    """An invalid option value: ``label`` (keyword or config key), the value and what was expected.
    ``kind`` is the exception type ``register()`` raises (TypeError for a wrong type, ValueError else)."""

    def __init__(self, label: str, value, expected: str, kind=ValueError):
        self.label, self.value, self.expected, self.kind = label, value, expected, kind
        super().__init__(f"{label} must be {expected}, got {value!r}")


def number(lo: float = -math.inf, strict: bool = False, integer: bool = False) -> Callable:
    """A real (or integer) scalar ``>= lo`` (``> lo`` if ``strict``), finite; bools and strings are refused."""
    what = ("an integer" if integer else "a finite number") + \
        ("" if lo == -math.inf else f" {'>' if strict else '>='} {lo:g}")

    def check(v, label):
        if isinstance(v, (bool, str)) or not isinstance(v, numbers.Real) \
                or (integer and not isinstance(v, numbers.Integral)):
            raise OptionError(label, v, what, TypeError)
        if not math.isfinite(float(v)) or (v <= lo if strict else v < lo):
            raise OptionError(label, v, what)
        return int(v) if integer else float(v)
    return check


def choice(values: Callable | tuple) -> Callable:
    """One of ``values`` (a tuple, or a function returning one when the check runs, e.g. the registered models)."""
    def check(v, label):
        allowed = values() if callable(values) else values
        if v not in allowed:
            raise OptionError(label, v, f"one of {', '.join(map(repr, allowed))}")
        return v
    return check


def boolean(v, label):
    if not isinstance(v, bool):
        raise OptionError(label, v, "True or False", TypeError)
    return v


def optional(check: Callable) -> Callable:
    return lambda v, label: None if v is None else check(v, label)


def mapping(v, label):
    if v is None:
        return {}
    if not hasattr(v, "keys"):
        raise OptionError(label, v, "a dict of keyword arguments", TypeError)
    return dict(v)


def auto_or(check: Callable, what: str, words: tuple = ("auto",)) -> Callable:
    """None, one of ``words`` (``"auto"``) or a value that passes ``check`` (``what`` names it in the message)."""
    expected = f"None, {', '.join(map(repr, words))} or {what}"

    def checked(v, label):
        if v is None or v in words:
            return v
        if isinstance(v, str):
            raise OptionError(label, v, expected)
        try:
            return check(v, label)
        except OptionError as e:
            raise OptionError(label, v, expected, e.kind) from None
    return checked


def anything(v, label):
    return v


def holdout(v, label):
    """None, an integer k >= 2 (every k-th angle) or a non-empty list of distinct indices >= 0 (their range is
    checked against the data by ``indreg.evaluation.validation.holdout_rows``)."""
    if v is None:
        return None
    if hasattr(v, "tolist") and not isinstance(v, (bool, str)):   # numpy / torch indices
        v = v.tolist()
    if isinstance(v, numbers.Integral) and not isinstance(v, bool):
        if v < 2:
            raise OptionError(label, v, "an integer k >= 2 (every k-th angle; 1 leaves no angle to fit) or a list "
                                        "of indices")
        return int(v)
    if not isinstance(v, (list, tuple)) or not v or not all(
            isinstance(i, numbers.Integral) and not isinstance(i, bool) for i in v):
        raise OptionError(label, v, "None, an integer k >= 2 (every k-th angle) or a non-empty list of indices",
                          TypeError if not isinstance(v, (list, tuple)) or v else ValueError)
    out = [int(i) for i in v]
    if min(out) < 0 or len(set(out)) != len(out):
        raise OptionError(label, v, "a list of distinct indices >= 0")
    return out
