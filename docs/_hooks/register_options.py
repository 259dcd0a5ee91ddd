"""griffe extension (mkdocs.yml, mkdocstrings' ``extensions``): ``indreg.register``'s docstring in the API reference
with its option entries, as ``help(indreg.register)`` shows them. The reference is read from the source, where the
docstring holds the placeholder line ``{options}`` that ``indreg/registration/api.py`` fills at import; this fills it
with the same generator (``indreg.options.docs.fill``), from the option table and the registries, which import
without torch (numpy only: the ``docs`` extra has it)."""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

import griffe

ROOT = Path(__file__).resolve().parents[2]
#: The objects whose docstrings hold the placeholder.
FILLED = ("indreg.registration.api.register",)
#: The modules that fill the registries whose options ``register`` takes (models, solvers, corrections).
REGISTRIES = ("indreg.registration.models", "indreg.registration.solver_registry", "indreg.registration.corrections")


class RegisterOptions(griffe.Extension):
    def on_function_instance(self, *, func, **kwargs) -> None:
        if func.path in FILLED and func.docstring is not None:
            if str(ROOT) not in sys.path:
                sys.path.insert(0, str(ROOT))
            for name in REGISTRIES:
                importlib.import_module(name)
            fill = importlib.import_module("indreg.options.docs").fill
            func.docstring.value = fill(func.docstring.value)
