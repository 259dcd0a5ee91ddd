"""Shared by the file modules (``indreg.io``, ``indreg.io.formats``, ``indreg.io.angle_files``, ``indreg.io.writers``):
the one-line error of a bad file (the ``file.npz:key`` path syntax: ``indreg.io.formats.split_path``).

Notes
-----
- Every problem with a file raises :class:`DataFileError`, one line ``"{name} file {path}: {problem}"``.
"""
from __future__ import annotations

import os
import re
import stat
import struct
from pathlib import Path

__all__ = ["DataFileError", "read_text", "MAX_TEXT_BYTES", "mrc_header_problem", "check_mrc_header"]

#: The largest text file indreg reads (angles, alignments, ``.mdoc`` metadata): 16 MiB, some 250,000 lines of an
#: ``.xf`` (a tilt series has hundreds); larger is refused before it is read, not parsed for minutes.
MAX_TEXT_BYTES = 16 * 2 ** 20


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


def read_text(path, name: str, max_bytes: int = MAX_TEXT_BYTES, errors: str = "strict") -> str:
    """The text of a small UTF-8 file (angles, alignments, metadata), checked before it is read: a regular file
    (a FIFO or device is never waited on) of at most ``max_bytes``. ``errors="strict"``: bytes that are not UTF-8
    are refused naming their offset and line; ``"replace"`` reads them as U+FFFD.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    name : str
        What the file is, for the message (``"angles"``, ``"alignment"``).
    max_bytes : int
        The largest size read.
    errors : str
        ``"strict"`` or ``"replace"``.

    Returns
    -------
    str
        The text.

    Raises
    ------
    DataFileError
        No such file, not a regular file, too large, not UTF-8 text, or unreadable (one line).
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


#: MRC modes and their bytes per value (mode 101: 4-bit, two values a byte).
_MRC_MODES = {0: 1, 1: 2, 2: 4, 3: 4, 4: 8, 6: 2, 12: 2, 101: 0.5}


def mrc_header_problem(head: bytes, size: int) -> str | None:
    """Why an MRC header (the file's first 1024 bytes ``head``) cannot belong to a file of ``size`` bytes: an
    extended header (``nsymbt``, word 24) that runs past the file's end, which ``mrcfile`` would try to read whole
    (a 2^31-byte claim: gigabytes allocated before the error). ``None`` if it fits (or the header is not one
    indreg can place: then ``mrcfile`` decides)."""
    if len(head) < 1024:
        return f"is {size} bytes, shorter than an MRC header (1024 bytes)"
    for order in "<>":
        nx, ny, nz, mode = struct.unpack(order + "4i", head[:16])
        if mode in _MRC_MODES and min(nx, ny, nz) >= 0:
            break
    else:
        return None
    nsymbt = struct.unpack(order + "i", head[92:96])[0]
    if nsymbt < 0 or 1024 + nsymbt > size:
        return (f"its header announces an extended header of {nsymbt} bytes, but the file has {size} bytes in all "
                "(a damaged or crafted MRC file)")
    return None


def check_mrc_header(path, name: str) -> None:
    """Raise :class:`DataFileError` (one line) if the MRC file ``path`` has a header that does not fit the file
    (:func:`mrc_header_problem`), before ``mrcfile`` reads it."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head, size = f.read(1024), os.fstat(f.fileno()).st_size
    except OSError as err:
        raise _fail(name, path, f"cannot be read ({type(err).__name__}: {err})") from None
    problem = mrc_header_problem(head, size)
    if problem:
        raise _fail(name, path, problem)
