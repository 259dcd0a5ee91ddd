"""Names resolved on first use: the public names of ``indreg`` and ``indreg.learn`` (PEP 562: importing a light
submodule, an entry point answering ``--help``, loads no torch, and ``from indreg import register`` works as
ever), and the deprecated module names of :data:`DEPRECATED`, which import their new home with a
``DeprecationWarning`` until :data:`REMOVED_IN`."""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings
from typing import Callable

__all__ = ["DEPRECATED", "REMOVED_IN", "attributes", "install_deprecated"]

#: The release that removes the names of :data:`DEPRECATED`.
REMOVED_IN = "0.2.0"
#: Old module name -> its home. The names kept are those of the file and plug-in modules that user scripts
#: import (docs/file_formats.md, docs/extending.md, docs/alignment.md); internal modules moved without an alias.
DEPRECATED = {
    "indreg.models": "indreg.registration.models",
    "indreg.writers": "indreg.io.writers",
    "indreg.conventions": "indreg.io.conventions",
    "indreg.angle_files": "indreg.io.angle_files",
    "indreg.volume_files": "indreg.io.volume_files",
    "indreg.alignment_files": "indreg.alignment.files",
    "indreg.axis_moments": "indreg.alignment.moments",
    "indreg.tilt_axis": "indreg.alignment.tilt_axis",
}


def attributes(package: str, home: dict, public: list) -> tuple[Callable, Callable]:
    """``(__getattr__, __dir__)`` of ``package``.

    Parameters
    ----------
    package : str
        The package's name.
    home : dict
        Public name -> the submodule (relative to ``package``) that defines it.
    public : list
        The package's ``__all__``.

    Returns
    -------
    tuple
        ``__getattr__`` (a name of ``home`` or a submodule of ``package``, imported on first use and kept in the
        package's namespace) and ``__dir__``.
    """
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


def _stacklevel() -> int:
    """The ``stacklevel`` of the first frame outside the import machinery and this module (the importer's line);
    ``warnings`` itself skips the frames of ``importlib._bootstrap`` when it counts."""
    frame, level = sys._getframe(2), 1   # the frame above the one that warns
    while frame is not None:
        name = frame.f_code.co_filename
        if not ("importlib" in name and "_bootstrap" in name):
            level += 1
            if "importlib" not in name and name != __file__:
                return level
        frame = frame.f_back
    return 1


class _Deprecated(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old name of :data:`DEPRECATED` and loads its home module (one module object under both names),
    warning once per process."""

    def find_spec(self, name, path=None, target=None):
        return importlib.util.spec_from_loader(name, self) if name in DEPRECATED else None

    def create_module(self, spec):
        warnings.warn(f"{spec.name} is deprecated and will be removed in indreg {REMOVED_IN}; import "
                      f"{DEPRECATED[spec.name]} instead", DeprecationWarning, stacklevel=_stacklevel())
        return importlib.import_module(DEPRECATED[spec.name])

    def exec_module(self, module) -> None:
        """Nothing: the home module ran when it was imported."""


def install_deprecated() -> None:
    """Put the finder of the deprecated names first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, _Deprecated) for f in sys.meta_path):
        sys.meta_path.insert(0, _Deprecated())
