"""What the alignment fit knows besides the data model's parameters: the operator ``T_s``
(``indreg.alignment.operator.AlignedOperator``) holds the shifts, the angle and the per-tilt matrices; the fit's
own state (its mode and gauge, its estimates so far, what is held and how well it is determined) is an
:class:`AlignmentState`, owned by the fit (``indreg.alignment.solver.AlignmentSolver``, the template's scale fit,
``indreg.alignment.fit.projection_matching``), never set on the operator."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from .modes import ALIGN_GAUGES

__all__ = ["AlignmentState"]


@dataclass
class AlignmentState:
    """The alignment fit's state.

    Parameters
    ----------
    mode : str
        ``"shifts"`` or ``"shifts+axis"`` (``indreg.alignment.modes.ALIGN_MODES``).
    gauge : str
        What the shifts leave to the deformation (``ALIGN_GAUGES``).
    started : bool
        The first estimate starts from the operator's own shifts (an imported alignment, or the template's scale
        fit), not from the cross-correlation peaks.
    records : list
        ``(iteration, shifts, angle)`` per estimate in the fit.
    at_bound : int
        Parameters at their bound after the last estimate.
    stack_tried : bool
        The angle was looked for in the stack alone (``indreg.alignment.solver.hold_stack_angle``), once per fit.
    stack_estimate : object
        Its ``indreg.alignment.moments.AxisEstimate`` (None: not applicable, or not tried).
    held : bool
        The stack's angle is held in the fit (it determines the angle).
    angle_se : float
        The standard error (degrees) of the tilt-axis angle (``inf``: not estimated, or not determined).
    prior : tuple or None
        ``(angle, sd)`` (radians): a Gaussian prior of the fit's angle (the stack's estimate where it does not
        determine the angle, ``indreg.alignment.solver.UNDETERMINED = "prior"``), else None.
    """
    mode: str
    gauge: str = ALIGN_GAUGES[0]
    started: bool = False
    records: list = field(default_factory=list)
    at_bound: int = 0
    stack_tried: bool = False
    stack_estimate: object = None
    held: bool = False
    angle_se: float = math.inf
    prior: tuple | None = None

    @property
    def axis(self) -> bool:
        """Whether the fit estimates the tilt-axis angle (mode ``"shifts+axis"`` and the angle not held)."""
        return self.mode == "shifts+axis" and not self.held

    def state_dict(self) -> dict:
        """The checkpoint entries of the fit (with the operator's shifts and angle, ``AlignmentSolver``)."""
        return {"alignment_records": list(self.records), "alignment_angle_se": float(self.angle_se),
                "alignment_angle_held": bool(self.held),
                "alignment_angle_prior": None if self.prior is None else [float(v) for v in self.prior]}

    def load_state_dict(self, d: dict) -> None:
        """Pop :meth:`state_dict`'s entries from ``d`` (a checkpoint's dict, changed in place)."""
        self.records = list(d.pop("alignment_records"))
        self.angle_se = float(d.pop("alignment_angle_se", math.inf))
        self.held = bool(d.pop("alignment_angle_held", False))
        prior = d.pop("alignment_angle_prior", None)
        self.prior = None if prior is None else tuple(float(v) for v in prior)
