"""Modules that moved into a subpackage stay importable by their old names: ``import indreg.writers`` and ``from
indreg.writers import write_image`` give the module ``indreg.io.writers`` itself (one module object under both
names, so a patch of either is a patch of both). :data:`MOVED` maps each old name to its home."""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys

__all__ = ["MOVED", "install"]

#: old module name -> its home
MOVED = {
    "indreg._files": "indreg.io._files",
    "indreg.api": "indreg.registration.api",
    "indreg.corrections": "indreg.registration.corrections",
    "indreg.models": "indreg.registration.models",
    "indreg.option_checks": "indreg.options.checks",
    "indreg.run": "indreg.registration.run",
    "indreg.solver_registry": "indreg.registration.solver_registry",
    "indreg.angle_files": "indreg.io.angle_files",
    "indreg.conventions": "indreg.io.conventions",
    "indreg.writers": "indreg.io.writers",
    "indreg.alignment_files": "indreg.io.alignment_files",
    "indreg.volume_files": "indreg.io.volume_files",
}


class _Alias(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old name of :data:`MOVED` and loads it as its home module."""

    def find_spec(self, name, path=None, target=None):
        return importlib.util.spec_from_loader(name, self) if name in MOVED else None

    def create_module(self, spec):
        return importlib.import_module(MOVED[spec.name])

    def exec_module(self, module) -> None:
        """Nothing: the home module ran when it was imported."""


def install() -> None:
    """Put the alias finder first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, _Alias) for f in sys.meta_path):
        sys.meta_path.insert(0, _Alias())
