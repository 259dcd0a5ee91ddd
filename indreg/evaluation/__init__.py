"""Evaluation of a reconstruction against the data: held-out projections during a run
(:mod:`~indreg.evaluation.validation`).

The public names are imported on first use: ``import indreg.evaluation`` loads no torch.
"""
from __future__ import annotations

from .. import _lazy

#: public name -> the submodule that defines it
_HOME = dict.fromkeys(("Validation", "holdout_rows", "split"), "validation")
__all__ = sorted(_HOME)

__getattr__, __dir__ = _lazy.attributes(__name__, _HOME, __all__)   # public names on first use
