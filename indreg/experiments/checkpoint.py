"""Checkpoints of a run: solver state, solver internals, RNG states and history, written atomically.

A checkpoint is ``torch.save`` of a dict::

    version, iteration, state (SolverState.state_dict), solver (solver.state_dict), rng (python, numpy, torch,
    cuda), history (list of per-iteration info dicts), seconds (solver time so far), problem (the config keys
    that define the problem; resuming with different values is refused)

It is written to ``<path>.tmp`` then moved over ``<path>`` with ``os.replace``, so a run killed while writing
leaves the previous checkpoint intact.
"""
from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch

VERSION = 1


def rng_state() -> dict:
    """The RNG states of python, numpy and torch (CPU and every CUDA device)."""
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save(path, payload: dict) -> None:
    """Atomically write ``payload`` (plus ``version``) to ``path``: tmp file, fsync, ``os.replace``."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            torch.save(dict(payload, version=VERSION), f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def load(path) -> dict:
    """Read a checkpoint written by :func:`save` (own file: full unpickling for the numpy RNG state)."""
    payload = torch.load(Path(path), map_location="cpu", weights_only=False)
    if payload.get("version") != VERSION:
        raise ValueError(f"checkpoint {path} has version {payload.get('version')!r}, expected {VERSION}")
    return payload


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
