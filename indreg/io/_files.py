"""Shared by the file modules (``indreg.io``, ``indreg.io.formats``, ``indreg.io.angle_files``, ``indreg.io.writers``):
the one-line error of a bad file (the ``file.npz:key`` path syntax: ``indreg.io.formats.split_path``).

Notes
-----
- Every problem with a file raises :class:`DataFileError`, one line ``"{name} file {path}: {problem}"``.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

__all__ = ["DataFileError"]


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

