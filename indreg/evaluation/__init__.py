"""What a reconstruction owes to the data and what to the template, and how far to trust it (docs/evaluation.md).

- :mod:`~indreg.evaluation.validation`: held-out projections during a run.
- :mod:`~indreg.evaluation.parts`: the part of a volume the data determine and the part the prior fills
  (``data_split``: the range of the operator's adjoint by conjugate gradients, any operator; ``wedge_split``: the
  measured wedge in Fourier space, parallel tilt series and sinograms).
- :mod:`~indreg.evaluation.uncertainty`: a per-voxel standard deviation by perturbed re-optimisation with warm starts
  (``registration_uncertainty``; ``perturbed_solutions``, exact for a linear-Gaussian problem).
- :mod:`~indreg.evaluation.score`: any reconstruction scored on held-out tilts (``indreg-score``).

Which volume to trust beyond the measured range (tilts at the range's edges held out) is a choice among runs:
:mod:`indreg.registration.extrapolation` (``register(..., extrapolation=True)``).

The public names are imported on first use: ``import indreg.evaluation`` loads no torch.
"""
from __future__ import annotations

from .. import _lazy

#: public name -> the submodule that defines it
_HOME = {
    **dict.fromkeys(("Validation", "holdout_rows", "split"), "validation"),
    **dict.fromkeys(("Split", "data_split", "wedge_split", "wedge_mask"), "parts"),
    **dict.fromkeys(("Uncertainty", "perturbed_solutions", "registration_uncertainty", "coverage"), "uncertainty"),
    **dict.fromkeys(("relative_residual", "score_volumes", "score_table"), "score"),
}
__all__ = sorted(_HOME)

__getattr__, __dir__ = _lazy.attributes(__name__, _HOME, __all__)   # public names on first use
