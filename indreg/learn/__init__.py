"""Learned initial momenta for indirect registration (rem:AltLDDMM): networks (one-shot and unrolled), synthetic
data, loss, training.

The public names are imported on first use (PEP 562), so that the entry point ``indreg.learn.entry`` answers
``--help`` without torch; ``from indreg.learn import MomentumUNet`` works as ever."""
from __future__ import annotations

import importlib
import importlib.util

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


def __getattr__(name: str):
    """A public name (imported from its submodule on first use) or a submodule (``indreg.learn.train``, ...)."""
    if name in _HOME:
        value = getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
    elif importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list:
    return sorted({*globals(), *__all__})
