"""Writing a run's outputs without following links: every output file is written under a fresh name and then
renamed over its target, and a run directory holding links is refused.

Why: a run directory may be shared or handed over (to resume a run); a planted link ``metrics.json ->
/elsewhere/victim`` would make a plain ``open(path, "w")`` write the victim. Here the new content goes to a file
created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` in a fresh private directory (``mkdtemp``: mode 0700, a new
random name) inside the run directory, and ``os.replace`` renames it over the target: a link at the target is
replaced, never followed, and a reader sees the old file or the new one, never a half-written one.
"""
from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["replacing", "open_replacing", "remove_scratch", "links_in", "check_no_links", "LinkError"]

_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


class LinkError(ValueError):
    """A run directory that holds a symbolic link (the message, one line, names it)."""


@contextmanager
def replacing(path, fsync: bool = False) -> Iterator[Path]:
    """A fresh path (same file name, in a new private directory beside ``path``) for a writer that takes a path
    (``np.save``, ``mrcfile``, ``savefig``); once the block ends without an exception it is renamed over
    ``path`` (``fsync``: its data and the directory are flushed to disk first and after). On an exception the
    new file is discarded and ``path`` is left as it was."""
    path = Path(path)
    scratch = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    new = scratch / path.name
    try:
        yield new
        if fsync:
            _fsync(new, os.O_RDONLY)
        _install(new, path, scratch)
        if fsync:
            _fsync(path.parent, os.O_RDONLY)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _install(new: Path, path: Path, scratch: Path) -> None:
    """Rename ``new`` over ``path``. A directory written as a whole (OME-Zarr), or one replacing a file or a link,
    cannot be renamed over it: what is at ``path`` (a link itself, never its target) is first moved into the
    scratch directory, which is then removed with it (``shutil.rmtree`` unlinks links, never follows them)."""
    try:
        os.replace(new, path)
    except OSError:
        if not (new.is_dir() or (os.path.lexists(path) and path.is_dir() and not path.is_symlink())):
            raise
        if os.path.lexists(path):
            os.rename(path, scratch / ".replaced")
        os.rename(new, path)


@contextmanager
def open_replacing(path, mode: str = "wb", fsync: bool = False):
    """``open(path, mode)`` for writing (``"w"`` / ``"wb"``), through :func:`replacing`: the file is created
    with ``O_EXCL | O_NOFOLLOW`` and renamed over ``path`` when the block ends."""
    if mode not in ("w", "wb"):
        raise ValueError(f"open_replacing: mode must be 'w' or 'wb', got {mode!r}")
    with replacing(path, fsync) as new:
        with os.fdopen(os.open(new, _FLAGS, 0o666), mode) as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())


def _fsync(path, flags: int) -> None:
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


#: The private directories :func:`replacing` makes (``tempfile.mkdtemp``: ``.<name>.<8 random characters>.tmp``).
_SCRATCH = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def remove_scratch(directory) -> list:
    """Remove what a writer killed mid-write (``kill -9``) left in ``directory``: the private directories of
    :func:`replacing` (by name, not links: a link is left for :func:`check_no_links` to refuse). Returns their
    names. The finished outputs are never among them (they were renamed out before the scratch was removed)."""
    removed = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    for entry in entries:
        if _SCRATCH.fullmatch(entry.name) and entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path, ignore_errors=True)
            removed.append(entry.name)
    return sorted(removed)


def links_in(directory) -> list:
    """The symbolic links in ``directory`` and below (links are not followed), sorted; ``[]`` if it does not
    exist."""
    found = []
    for root, dirs, files in os.walk(directory, followlinks=False):
        found += [Path(root) / n for n in dirs + files if os.path.islink(os.path.join(root, n))]
    return sorted(found)


def check_no_links(directory, what: str = "run directory", remedy: str = "choose another hydra.run.dir") -> None:
    """Raise :class:`LinkError` (one line) if ``directory`` holds a symbolic link: outputs are never written
    through one, and a directory with planted links is refused rather than cleaned."""
    found = links_in(directory)
    if found:
        link = found[0]
        more = f" (and {len(found) - 1} more)" if len(found) > 1 else ""
        raise LinkError(f"{what} {directory}: {link.relative_to(directory)} is a symbolic link (to "
                        f"{os.readlink(link)}){more}; indreg never writes through links: remove it or {remedy}")
