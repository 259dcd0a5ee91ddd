"""Public names imported on first use (PEP 562), for ``indreg`` and ``indreg.learn``: importing a light submodule
(an entry point answering ``--help``) loads no torch, and ``from indreg import register`` works as ever."""
from __future__ import annotations

import importlib
import importlib.util
import sys
from typing import Callable

__all__ = ["attributes"]


def attributes(package: str, home: dict, public: list) -> tuple[Callable, Callable]:
    """``(__getattr__, __dir__)`` of ``package``: a name of ``home`` (public name -> the submodule defining it) or a
    submodule of ``package``, imported on first use and kept in the package's namespace."""
    def __getattr__(name: str):
        if name in home:
            value = getattr(importlib.import_module(f".{home[name]}", package), name)
        elif importlib.util.find_spec(f"{package}.{name}") is not None:
            value = importlib.import_module(f".{name}", package)
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list:
        return sorted({*vars(sys.modules[package]), *public})

    return __getattr__, __dir__
