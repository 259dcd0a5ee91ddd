"""Shared by the file modules (``indreg.io``, ``indreg.io.angle_files``, ``indreg.io.writers``): the one-line error of
a bad file and the ``file.npz:key`` path syntax.

Convention:
    - Every problem with a file raises :class:`DataFileError`, one line ``"{name} file {path}: {problem}"``.
"""
from __future__ import annotations

import os
import re
import stat
from pathlib import Path

__all__ = ["DataFileError", "split_path", "read_text", "MAX_TEXT_BYTES"]

#: The largest text file indreg reads (angles, alignments, ``.mdoc`` metadata): 16 MiB, some 250,000 lines of an
#: ``.xf`` (a tilt series has hundreds); larger is refused before it is read, not parsed for minutes.
MAX_TEXT_BYTES = 16 * 2 ** 20

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


def read_text(path, name: str, max_bytes: int = MAX_TEXT_BYTES, errors: str = "strict") -> str:
    """The text of a small UTF-8 file (angles, alignments, metadata), checked before it is read: a regular file
    (a FIFO or device is never waited on) of at most ``max_bytes``. ``errors="strict"``: bytes that are not UTF-8
    are refused naming their offset and line; ``"replace"`` reads them as U+FFFD.

    Raises:
        DataFileError: no such file, not a regular file, too large, not UTF-8 text, or unreadable (one line).
    """
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise _fail(name, path, "no such file") from None
    except OSError as err:
        raise _fail(name, path, f"cannot be read ({type(err).__name__}: {err})") from None
    if not stat.S_ISREG(st.st_mode):
        raise _fail(name, path, "is not a regular file")
    if st.st_size > max_bytes:
        raise _fail(name, path, f"is {st.st_size} bytes, more than the {max_bytes} indreg reads of such a text file "
                                "(a tilt series' angles or alignment is a few kB): is it the right file?")
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as err:
        raise _fail(name, path, f"cannot be read ({type(err).__name__}: {err})") from None
    try:
        return data.decode("utf-8", errors=errors)
    except UnicodeDecodeError as err:
        line = data.count(b"\n", 0, err.start) + 1
        raise _fail(name, path, f"is not UTF-8 text: byte 0x{data[err.start]:02x} at offset {err.start} (line "
                                f"{line})") from None
