"""Checkpoints of a run, written atomically and read back without running code.

File format (version 2)::

    indreg-checkpoint 2 sha256=<64 hex digits> bytes=<n>\\n      one ASCII header line
    <n bytes>                                                    the payload: ``torch.save`` of a dict

The payload holds only tensors and plain data (dict, list, tuple, str, int, float, bool, None): :func:`save`
refuses anything else, and :func:`load` checks the header (format version, payload length, SHA-256 of the
payload) *before* unpickling, then unpickles with ``torch.load(..., weights_only=True)``, which builds
nothing but tensors and plain containers. A crafted file therefore cannot run code, and a damaged one
(truncated, empty, overwritten bytes, another format) is refused with one line naming the file, what is wrong
and what to do (:class:`CheckpointError`). Version 1 (a bare ``torch.save`` pickle) is refused likewise.

The registration app (``indreg.experiments.register``) stores::

    iteration, state (SolverState.state_dict), solver (solver.state_dict), rng (rng_state()),
    history (list of per-iteration info dicts), seconds (solver time so far), problem (the config keys that
    define the problem; resuming with different values is refused)

RNG states are stored as tensors and numbers: python's Mersenne Twister key (625 ints) and numpy's MT19937 key
(624 uint32) as int64 tensors, torch's CPU / CUDA states as their uint8 tensors.

Writing goes to a fresh file (``O_EXCL | O_NOFOLLOW``, in a new private directory beside ``<path>``:
``indreg._outfiles``), which is flushed, fsync'ed and moved over ``<path>`` with ``os.replace`` (then the directory
is fsync'ed), so a run killed while writing leaves the previous checkpoint intact, and a link planted at
``<path>`` or ``<path>.tmp`` is never written through. A run directory holding a link is refused
(:func:`check_location`).
"""
from __future__ import annotations

import hashlib
import io
import os
import random
import re
import tempfile
from collections import OrderedDict
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from .._outfiles import LinkError, check_no_links, open_replacing, remove_scratch

VERSION = 2
HINT = "delete it or run without resume=true"
_HEADER = re.compile(rb"indreg-checkpoint (\d+) sha256=([0-9a-f]{64}) bytes=(\d+)\n")
_MAX_HEADER = 128
_SCALARS = (str, int, float, bool, type(None))


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message (one line) names the file, the problem and the remedy."""


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _fail(path, what: str, hint: str):
    raise CheckpointError(f"checkpoint {path}: {_one_line(what)}; {hint}")


# ------------------------------------------------------------------ RNG states as tensors and numbers
def rng_state() -> dict:
    """The RNG states of python, numpy and torch (CPU and every CUDA device), as tensors and numbers."""
    version, key, gauss_next = random.getstate()
    name, mt, pos, has_gauss, cached = np.random.get_state()
    return {"python": {"version": int(version), "key": torch.tensor(key, dtype=torch.int64),
                       "gauss_next": gauss_next},
            "numpy": {"key": torch.from_numpy(np.asarray(mt, dtype=np.int64)), "pos": int(pos),
                      "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
            "torch": torch.get_rng_state(),
            "cuda": list(torch.cuda.get_rng_state_all()) if torch.cuda.is_available() else []}


def set_rng_state(state: dict) -> None:
    """Restore what :func:`rng_state` returned."""
    p, n = state["python"], state["numpy"]
    random.setstate((int(p["version"]), tuple(int(v) for v in p["key"].tolist()), p["gauss_next"]))
    np.random.set_state(("MT19937", n["key"].numpy().astype(np.uint32), int(n["pos"]), int(n["has_gauss"]),
                         float(n["cached_gaussian"])))
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# ------------------------------------------------------------------ writing
def check_plain(x, where: str = "payload") -> None:
    """Raise ``TypeError`` naming the entry of ``x`` that is not a tensor or plain data."""
    if type(x) in _SCALARS or type(x) in (torch.Tensor, torch.nn.Parameter):
        return
    if type(x) in (dict, OrderedDict):
        for k, v in x.items():
            if type(k) not in (str, int):
                raise TypeError(f"checkpoint {where} has a key of type {type(k).__name__}: only str and int keys")
            check_plain(v, f"{where}[{k!r}]")
        return
    if type(x) in (list, tuple):
        for i, v in enumerate(x):
            check_plain(v, f"{where}[{i}]")
        return
    raise TypeError(f"checkpoint {where} is a {type(x).__name__}: only tensors, numbers, strings, None, "
                    "lists, tuples and dicts are stored")


def encode(payload: dict) -> bytes:
    """Header line + ``torch.save(payload)`` (the file's bytes); ``TypeError`` for non-plain content."""
    if type(payload) is not dict:
        raise TypeError(f"checkpoint payload must be a dict, got {type(payload).__name__}")
    check_plain(payload)
    buf = io.BytesIO()
    torch.save(payload, buf)
    data = buf.getvalue()
    header = f"indreg-checkpoint {VERSION} sha256={hashlib.sha256(data).hexdigest()} bytes={len(data)}\n"
    return header.encode("ascii") + data


def save(path, payload: dict) -> None:
    """Atomically write ``payload`` to ``path``: a fresh file, fsync, ``os.replace``, fsync of the directory
    (:func:`indreg._outfiles.open_replacing`: no link is followed)."""
    blob = encode(payload)
    with open_replacing(path, "wb", fsync=True) as f:
        f.write(blob)


# ------------------------------------------------------------------ reading
def decode(blob: bytes, path, hint: str = HINT) -> dict:
    """Verify the header of a file's bytes, then unpickle the payload with ``weights_only=True``."""
    if not blob:
        _fail(path, "the file is empty", hint)
    end = blob.find(b"\n", 0, _MAX_HEADER)
    m = _HEADER.fullmatch(blob[:end + 1]) if end >= 0 else None
    if m is None:
        if blob.startswith(b"indreg-checkpoint "):
            _fail(path, "its header line is damaged", hint)
        _fail(path, f"not an indreg checkpoint of format version {VERSION} (no header line; damaged, or written "
                    "by an older indreg)", hint)
    version, digest, size = int(m[1]), m[2].decode(), int(m[3])
    if version != VERSION:
        _fail(path, f"format version {version}, this indreg reads version {VERSION}", hint)
    data = memoryview(blob)[end + 1:]
    if len(data) != size:
        _fail(path, f"{'truncated' if len(data) < size else 'has trailing bytes'}: the header announces {size} "
                    f"payload bytes, the file has {len(data)}", hint)
    if hashlib.sha256(data).hexdigest() != digest:
        _fail(path, "SHA-256 checksum mismatch (the file is damaged)", hint)
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as e:  # the unpickler refuses anything but tensors and plain data
        _fail(path, f"refused to unpickle its payload ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
                    " - only tensors and plain data are loaded", hint)
    if type(payload) is not dict:
        _fail(path, f"the payload is a {type(payload).__name__}, not a dict", hint)
    return payload


def load(path, keys=(), hint: str = HINT) -> dict:
    """Read a checkpoint written by :func:`save`; ``keys``: top-level keys that must be present.

    Raises :class:`CheckpointError` (one line naming ``path``, the problem and ``hint``) for an unreadable,
    damaged, foreign or incomplete file; nothing of the file is unpickled before its checksum is verified.
    """
    try:
        with open(path, "rb") as f:
            blob = f.read()
    except OSError as e:
        _fail(path, f"cannot be read ({e.strerror or e})", hint)
    payload = decode(blob, path, hint)
    missing = [k for k in keys if k not in payload]
    if missing:
        _fail(path, f"missing key(s) {', '.join(map(repr, missing))}", hint)
    return payload


@contextmanager
def restoring(path, hint: str = HINT):
    """Turn an error raised while applying a verified checkpoint's content (a key, shape or value this code
    does not expect) into a :class:`CheckpointError` naming ``path``."""
    try:
        yield
    except CheckpointError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError, AttributeError) as e:
        _fail(path, f"its content does not fit this run ({type(e).__name__}: {e})", hint)


def check_location(path, resume: bool, hint: str = HINT) -> None:
    """Before any computing: the directory of ``path`` can be created and written and holds no symbolic link
    (outputs are never written through one), ``path`` is not a directory, and with ``resume`` an existing
    ``path`` is readable and writable (it will be replaced). What a writer killed mid-write left there (an empty
    ``.checkpoint.pt.<random>.tmp``) is removed."""
    path = Path(path)
    out = path.parent
    try:
        check_no_links(out)
    except LinkError as e:
        raise CheckpointError(str(e)) from None
    remove_scratch(out)   # a writer's private directory left by kill -9 (indreg._outfiles.replacing)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".write-test-"):
            pass
    except OSError as e:
        raise CheckpointError(f"run directory {out} is not writable ({e.strerror or e}): fix its permissions or "
                              "choose another hydra.run.dir") from None
    if path.exists() and not path.is_file():
        _fail(path, "exists but is not a regular file",
              hint if resume else "delete it (the run writes its checkpoint there)")
    if resume and path.is_file() and not os.access(path, os.R_OK | os.W_OK):
        _fail(path, "is not readable and writable (resuming replaces it)", "fix its permissions, " + hint)


def problem_mismatch(saved: dict, current: dict, prefix: str = "") -> list:
    """Keys (dotted) whose values differ between two nested config dicts."""
    keys = sorted(set(saved) | set(current))
    out = []
    for k in keys:
        a, b = saved.get(k), current.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += problem_mismatch(a, b, f"{prefix}{k}.")
        elif a != b:
            out.append(f"{prefix}{k}: checkpoint {a!r}, config {b!r}")
    return out


def check_state(saved: dict, state, max_iter: int) -> None:
    """The loaded checkpoint against the run's schema, not only its bytes: ``iteration`` an integer in
    ``[0, max_iter]`` equal to the state's, the state's entries (``state.names``) floating-point tensors of the
    current iterate's shapes, ``history`` one report per iteration, ``seconds`` a finite number >= 0. Raises
    ``ValueError`` naming the field (``restoring`` turns it into a ``CheckpointError`` naming the file)."""
    it = saved["iteration"]
    if isinstance(it, bool) or not isinstance(it, int) or not 0 <= it <= max_iter:
        raise ValueError(f"iteration {it!r} is not an integer in [0, solver.max_iter={max_iter}]")
    s = saved["state"]
    if not isinstance(s, dict) or s.get("iteration") != it:
        raise ValueError(f"state.iteration {s.get('iteration') if isinstance(s, dict) else s!r} differs from "
                         f"iteration {it}")
    for name, current in zip(state.names, state.iterate):
        t = s.get(name)
        if not isinstance(t, torch.Tensor) or not t.is_floating_point() or tuple(t.shape) != tuple(current.shape):
            what = f"a {t.dtype} tensor of shape {tuple(t.shape)}" if isinstance(t, torch.Tensor) else repr(type(t))
            raise ValueError(f"state.{name} is {what}; this run needs a floating-point tensor of shape "
                             f"{tuple(current.shape)}")
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"state.{name} contains non-finite values")
    history, seconds = saved["history"], saved["seconds"]
    if not isinstance(history, list) or len(history) != it or not all(isinstance(h, dict) for h in history):
        raise ValueError(f"history has {len(history) if isinstance(history, list) else '?'} entries, expected one "
                         f"report per iteration ({it})")
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 <= seconds < float("inf"):
        raise ValueError(f"seconds {seconds!r} is not a finite number >= 0")
