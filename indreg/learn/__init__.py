"""Learned initial momenta for indirect registration (rem:AltLDDMM): networks (one-shot and unrolled), synthetic
data, loss, training.

The public names are imported on first use (PEP 562), so that the entry point ``indreg.learn.entry`` answers
``--help`` without torch; ``from indreg.learn import MomentumUNet`` works as ever."""
from __future__ import annotations

from .. import _lazy

#: public name -> the submodule that defines it
_HOME = {
    **dict.fromkeys(("SyntheticDeformationDataset", "random_momentum", "random_template"), "dataset"),
    **dict.fromkeys(("UnrolledDescent", "descent_gradient", "descent_terms"), "descent"),
    "IndirectShootingLoss": "loss",
    "MomentumUNet": "unet",
    **dict.fromkeys(("UnrolledMomentum", "indirect_gradient"), "unrolled"),
}

__all__ = ["IndirectShootingLoss", "MomentumUNet", "SyntheticDeformationDataset", "UnrolledDescent", "UnrolledMomentum",
           "descent_gradient", "descent_terms", "indirect_gradient", "random_momentum", "random_template"]


__getattr__, __dir__ = _lazy.attributes(__name__, _HOME, __all__)   # public names on first use
