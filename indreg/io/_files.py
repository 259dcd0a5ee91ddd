"""Shared by the file modules (``indreg.io``, ``indreg.io.angle_files``, ``indreg.io.writers``): the one-line error of
a bad file and the ``file.npz:key`` path syntax.

Convention:
    - Every problem with a file raises :class:`DataFileError`, one line ``"{name} file {path}: {problem}"``.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

__all__ = ["DataFileError", "split_path"]

_KEYED = re.compile(r"^(.*\.(?:npy|npz|h5|hdf5|hspy|mrc|st|ali|png|tif|tiff)):(.*)$", re.IGNORECASE)


class DataFileError(ValueError):
    """A file that cannot be used: the message is one line naming the file and the problem."""


class _Problem(Exception):
    """Internal: a problem found while reading, turned into a ``DataFileError`` naming the file."""


def _one_line(text) -> str:
    return re.sub(r"\s*[\r\n]+\s*", " ", str(text)).strip()


def _fail(name: str, spec, problem) -> DataFileError:
    return DataFileError(_one_line(f"{name} file {spec}: {problem}"))


def _as_path(spec, name: str) -> Path:
    """``spec`` as a ``Path``; anything but a str / ``os.PathLike`` is a ``DataFileError`` naming ``name``."""
    if not isinstance(spec, (str, os.PathLike)):
        raise DataFileError(f"{name} path must be a str or os.PathLike, got {type(spec).__name__}")
    return Path(spec)


def split_path(spec, name: str = "data") -> tuple:
    """``(path, key)`` of a path ``file.npz:key`` / ``file.h5:/group/dataset`` (key ``None`` if not given)."""
    text = str(_as_path(spec, name))
    match = _KEYED.match(text)
    if match and not Path(text).exists():
        return Path(match.group(1)), (match.group(2) or None)
    return Path(text), None
