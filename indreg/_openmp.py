"""OpenMP start-up policy, applied before torch is first imported.

With ``OMP_WAIT_POLICY`` unset, the OpenMP threads of torch spin-wait for each other: when another process keeps
one of the cores busy, a 2-thread run slows down 2.5x-18x (measured on a 2-core machine: suite 3 at 0.095 s
per iteration idle, 0.24 s with one core busy). ``PASSIVE`` makes idle threads sleep, and the same run then
loses only what the busy core costs. The variable is read once, when the OpenMP runtime loads (on
``import torch``), so it must be set before that; indreg sets it when it is imported first, and never
overrides a value the user set. A library user who imports torch before indreg should export
``OMP_WAIT_POLICY=PASSIVE`` in the shell (or set ``os.environ`` before ``import torch``).
"""
from __future__ import annotations

import os
import sys

DEFAULT_WAIT_POLICY = "PASSIVE"


def configure() -> bool:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` unless the user chose a policy or torch is already loaded.

    Returns True when the policy now in force for this process is the one in ``os.environ``."""
    if "torch" in sys.modules:
        return "OMP_WAIT_POLICY" in os.environ
    os.environ.setdefault("OMP_WAIT_POLICY", DEFAULT_WAIT_POLICY)
    return True
