"""Alignment of projections: everything that estimates where the data lie on the detector.

The data model ``T_s f = S_{s, alpha} T f`` (:mod:`~indreg.alignment.operator`: per-projection shifts ``s`` and the
tilt-axis angle ``alpha``); its estimation by projection matching (:mod:`~indreg.alignment.fit`), in the fit of a
registration (:mod:`~indreg.alignment.solver`, registered as a correction by :mod:`~indreg.alignment.correction`)
or without a template (``projection_matching``, the ``indreg-align`` app: :mod:`~indreg.alignment.app`); the fit's
declared state (:mod:`~indreg.alignment.state`) and choices (:mod:`~indreg.alignment.modes`, importable without
torch); the tilt-axis angle from the stack alone (:mod:`~indreg.alignment.moments`) and the tilt axis in the
detector (:mod:`~indreg.alignment.tilt_axis`); other tools' alignment files (:mod:`~indreg.alignment.files`:
IMOD ``.xf``, AreTomo ``.aln``, indreg's ``align.json``); for a slab wider than the detector the stretched
cross-correlation (:mod:`~indreg.alignment.xcorr`), leave-one-out projection matching through the wide box
(:mod:`~indreg.alignment.slab`, ``indreg-align``'s path: :mod:`~indreg.alignment.slab_app`), the tilt axis by
common lines (:mod:`~indreg.alignment.axis_search`) and the gold beads' fit (:mod:`~indreg.alignment.fiducials`).
See docs/alignment.md.

The public names are imported on first use: ``import indreg.alignment`` loads no torch.
"""
from __future__ import annotations

from .. import _lazy

#: public name -> the submodule that defines it
_HOME = {
    **dict.fromkeys(("ALIGN_MODES", "ALIGN_GAUGES", "INTERPOLATIONS", "EDGES", "ALIGN_EVERY", "MAX_SHIFT_FRACTION",
                     "MAX_ANGLE_DEG", "MAX_ANGLE_SE_DEG", "MIN_PROJECTIONS"), "modes"),
    "AlignmentState": "state",
    "AlignedOperator": "operator",
    **dict.fromkeys(("aligned", "angle_uncertainty", "bounds", "coarse_shifts", "estimate", "first_start",
                     "fit_scale", "gauge", "projection_matching", "turn_projection"), "fit"),
    **dict.fromkeys(("AlignmentSolver", "find_aligned", "hold_stack_angle", "operator_summary", "plot_shifts",
                     "stack_angle", "summary", "wrap"), "solver"),
    **dict.fromkeys(("AxisEstimate", "estimate_axis_angle"), "moments"),
    **dict.fromkeys(("Alignment", "read_alignment", "write_alignment", "to_operator", "from_operator"), "files"),
    **dict.fromkeys(("CoarseAlignment", "axis_frame", "coarse_alignment"), "xcorr"),
    **dict.fromkeys(("SlabAlignment", "slab_projection_matching"), "slab"),
    **dict.fromkeys(("AxisSearch", "search_axis_angle"), "axis_search"),
    **dict.fromkeys(("FiducialAlignment", "fiducial_alignment"), "fiducials"),
}
__all__ = sorted(_HOME)

__getattr__, __dir__ = _lazy.attributes(__name__, _HOME, __all__)   # public names on first use
