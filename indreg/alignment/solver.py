"""Alignment in the fit: the solver that re-estimates the shifts (and the tilt-axis angle) of the data model
``T_s`` every :data:`~indreg.alignment.modes.ALIGN_EVERY` iterations against the current reconstruction's
projection (``indreg.alignment.fit``), the tilt-axis angle from the stack alone before the fit
(``indreg.alignment.moments``), and the fit's summary (``result.alignment``, ``align.png``)."""
from __future__ import annotations

import logging
import math
from pathlib import Path

import torch

from ..solvers.state import RefitSolver
from .fit import angle_uncertainty, bounds, estimate, first_start
from .modes import ALIGN_EVERY, MAX_ANGLE_DEG, MAX_ANGLE_SE_DEG
from .operator import AlignedOperator, projection_frame
from .state import AlignmentState

__all__ = ["STACK_ANGLE", "UNDETERMINED", "UNDETERMINED_POLICIES", "AlignmentSolver", "find_aligned", "hold_stack_angle", "operator_summary", "plot_shifts",
           "stack_angle", "summary", "wrap"]

log = logging.getLogger("indreg")

#: ``"shifts+axis"`` first estimates the angle from the stack alone (:func:`stack_angle`) and, where that
#: determines it, holds it in the fit; ``False``: the angle is estimated in the fit only (docs/alignment.md).
STACK_ANGLE = True
#: Where the stack does not determine the angle (its standard error above ``MAX_ANGLE_SE_DEG``): ``"hold"`` holds the
#: stack's estimate (a finite standard error) or else the given angle, and reports the stack's standard error (inf:
#: none), which covers the valley the fit would wander along; ``"prior"`` fits it with the stack's estimate as a
#: Gaussian prior; ``"fit"`` fits it freely (before: the angle followed the turn the deformation took up, 0.30 for
#: a true 3 degrees, reported with a standard error of 0.011). Measured on held-out tilts (docs/alignment.md).
UNDETERMINED = "hold"
UNDETERMINED_POLICIES = ("hold", "prior", "fit")


def stack_angle(op: AlignedOperator, data: torch.Tensor, started: bool = False):
    """The tilt-axis angle of ``data`` from the stack alone, by the moment conditions of every detector row
    (``indreg.alignment.moments.estimate_axis_angle``): no reconstruction, so no turn of the object about the beam can
    take part of it up. ``None`` where it does not apply: pixels not square, a given alignment (``started``: the fit
    starts from imported shifts; an angle, per-tilt matrices).

    Parameters
    ----------
    op : AlignedOperator
        The data model (a tilt series).
    data : torch.Tensor
        The stack, ``op.range_shape``.
    started : bool
        The fit starts from imported shifts (then None).

    Returns
    -------
    AxisEstimate or None
        The estimate; :meth:`~indreg.alignment.moments.AxisEstimate.refused` (not determined, with the reason)
        for a stack that cannot tell the angle (too few tilts whose specimen stays on the detector, too few
        rows); None where it does not apply.
    """
    from .moments import MAX_PIXELS, AxisEstimate, estimate_axis_angle

    _, K, R, D, _, det_cell, row_cell = projection_frame(op.operator)
    if started or op.matrices is not None or float(op.angle) != 0:
        return None
    if data.numel() != K * R * D:
        log.info("tilt-axis angle from the stack: skipped (data of shape %s, not one stack)", tuple(data.shape))
        return None
    if abs(det_cell / row_cell - 1) > 1e-6:
        log.info("tilt-axis angle from the stack: skipped (pixels %.4g x %.4g are not square)", det_cell, row_cell)
        return None
    log.info("tilt-axis angle from the stack's moment conditions: estimating (%d tilts of %d x %d px, binned to at "
             "most %d px a side; measured 14 s at 64^2, 78 s at 128^2 on two cores)", K, R, D, MAX_PIXELS)
    try:
        return estimate_axis_angle(data.detach().double().cpu().reshape(K, R, D).numpy(),
                                   op.operator.geometry.angles.double().cpu().numpy(), scan_deg=MAX_ANGLE_DEG)
    except ValueError as e:
        return AxisEstimate.refused(str(e), K)


def hold_stack_angle(op: AlignedOperator, state: AlignmentState, data: torch.Tensor) -> bool:
    """Estimate the angle from the stack (:func:`stack_angle`), once per fit, before anything else fits the
    alignment (the template's scale, ``indreg.alignment.fit.fit_scale``, or the first in-fit estimate), and set it
    on ``op``; else a warning, and the fit estimates it.

    Parameters
    ----------
    op : AlignedOperator
        The data model (its ``angle`` is set).
    state : AlignmentState
        The fit's state (``stack_tried``, ``stack_estimate``, ``held``, ``angle_se`` are set).
    data : torch.Tensor
        The stack.

    Returns
    -------
    bool
        ``state.held``: the data determine the angle and the fit holds it (False for a mode other than
        ``"shifts+axis"``).
    """
    if state.mode != "shifts+axis":
        return False
    if state.stack_tried:
        return state.held
    state.stack_tried = True
    e = state.stack_estimate = stack_angle(op, data, state.started) if STACK_ANGLE else None
    state.held = e is not None and e.determined
    if e is None:
        return False
    log.info(e.describe())
    if state.held:
        op.angle = torch.tensor(math.radians(e.angle_deg), dtype=torch.float64)
        state.angle_se = e.se_deg
        return True
    return _undetermined(op, state, e)


def _undetermined(op: AlignedOperator, state: AlignmentState, e) -> bool:
    """The stack's estimate ``e`` does not determine the angle: :data:`UNDETERMINED`'s policy, in one warning."""
    why = e.reason or (f"s.e. {e.se_deg:.3f} deg" if math.isfinite(e.se_deg) else "s.e. inf deg")
    usable = not e.reason and math.isfinite(e.se_deg) and math.isfinite(e.angle_deg)
    head = f"tilt-axis angle not determined by the data ({why}, from the stack's moment conditions)"
    tail = "measure it beforehand and rotate the stack, or use align='shifts'"
    if UNDETERMINED == "fit":
        log.warning("%s: it is estimated in the fit, where a turn of the object about the beam can take part of it "
                    "up; %s", head, tail)
        return False
    if UNDETERMINED == "prior" and usable:
        state.prior = (math.radians(e.angle_deg), math.radians(e.se_deg))
        log.warning("%s: estimated in the fit with the stack's %.3f +- %.3f deg as its prior; %s", head, e.angle_deg,
                    e.se_deg, tail)
        return False
    if usable:
        op.angle = torch.tensor(math.radians(e.angle_deg), dtype=torch.float64)
    state.held, state.angle_se = True, e.se_deg if usable else math.inf
    log.warning("%s: the %s angle %.3f deg is held in the fit with a standard error of %s deg (a turn of the object "
                "about the beam would take up any other); %s", head, "stack's" if usable else "given",
                math.degrees(float(op.angle)), f"{e.se_deg:.3f}" if usable else "inf", tail)
    return True


class AlignmentSolver(RefitSolver):
    """A solver that re-estimates the alignment of ``operator`` (an ``AlignedOperator`` in ``inner.problem``) every
    ``every`` iterations from the image of the current iterate, then takes ``inner``'s step.

    Parameters
    ----------
    inner : Solver
        The solver whose steps it takes.
    operator : AlignedOperator
        The data model whose shifts (and angle) it estimates.
    state : AlignmentState
        The fit's state (mode, gauge, estimates, held angle), owned by this solver.
    data : torch.Tensor
        The data the shifts are fitted to (``operator``'s range; all projections, held-out ones included).
    every : int
        Iterations between two estimates.

    Notes
    -----
    After an estimate the inner solver's cached objective and gradient (and a torch.optim optimizer's memory) are
    dropped: they belong to the old data model.
    """

    name = "alignment"

    def __init__(self, inner, operator: AlignedOperator, state: AlignmentState, data: torch.Tensor,
                 every: int = ALIGN_EVERY):
        super().__init__(inner, every)
        self.operator, self.state, self.data = operator, state, data

    def refit(self, state) -> None:
        """Estimate the alignment at ``state.iterate`` and set it on the operator."""
        op, fit = self.operator, self.state
        with torch.no_grad():
            image = self.problem.reconstruction(state.iterate)
            P = op.operator(image)
            start = op.shifts
            if not fit.records:   # first estimate: the given alignment, else the cross-correlation peak
                hold_stack_angle(op, fit, self.data)
                start = first_start(op, fit, P, self.data)
            axis = fit.axis
            op.shifts, op.angle, fit.at_bound = estimate(op, P, self.data, start, op.angle, axis, kind=fit.gauge,
                                                         prior=fit.prior)
            if axis:   # with a prior, no less uncertain than it: the data's own curvature misses the valley
                fit.angle_se = angle_uncertainty(op, image, self.data)
                if fit.prior is not None:
                    fit.angle_se = max(fit.angle_se, math.degrees(fit.prior[1]))
        fit.records.append((state.iteration, op.shifts.clone(), float(op.angle)))
        if fit.at_bound:
            log.warning("iteration %d: %d alignment parameter(s) at their bound (|s| <= %s px, |alpha| <= %g deg): "
                        "the data may be misaligned beyond it, or the template too unlike the data", state.iteration,
                        fit.at_bound, [round(float(b), 2) for b in bounds(op)], MAX_ANGLE_DEG)

    def report(self, info: dict) -> dict:
        info["alignment_rms"] = float(self.operator.shifts.pow(2).sum(1).mean().sqrt())
        return info

    def summary(self) -> dict:
        return operator_summary(self.operator, self.state, self.every)

    def state_dict(self) -> dict:
        return dict(self.inner.state_dict(), alignment_shifts=self.operator.shifts.clone(),
                    alignment_angle=float(self.operator.angle), **self.state.state_dict())

    def load_state_dict(self, d: dict) -> None:
        d = dict(d)
        self.operator.shifts = d.pop("alignment_shifts").double()
        self.operator.angle = torch.tensor(float(d.pop("alignment_angle")), dtype=torch.float64)
        self.state.load_state_dict(d)
        self.inner.load_state_dict(d)


def find_aligned(operator) -> AlignedOperator | None:
    """The ``AlignedOperator`` in ``operator`` (itself, or under a ``RestrictedOperator``).

    Parameters
    ----------
    operator : LinearOperator or None
        An operator.

    Returns
    -------
    AlignedOperator or None
        The aligned operator found by following ``.operator``, else None.
    """
    while operator is not None and not isinstance(operator, AlignedOperator):
        operator = getattr(operator, "operator", None)
    return operator


def summary(problem) -> dict:
    """``result.alignment`` of a run on ``problem`` whose alignment was not estimated (an imported alignment used as
    it is).

    Parameters
    ----------
    problem : RegistrationProblem
        The problem (its ``ray_transform``).

    Returns
    -------
    dict
        :func:`operator_summary` of its ``AlignedOperator`` with mode ``fixed``; ``{}`` without one.
    """
    op = find_aligned(getattr(problem, "ray_transform", None))
    return {} if op is None else operator_summary(op)


def operator_summary(op: AlignedOperator, state: AlignmentState | None = None, every: int = ALIGN_EVERY) -> dict:
    """The summary of the aligned operator ``op``.

    Parameters
    ----------
    op : AlignedOperator
        The data model.
    state : AlignmentState, optional
        The fit's state; None: an alignment used as it is (mode ``fixed``, ``indreg.alignment.files``).
    every : int
        Iterations between two estimates.

    Returns
    -------
    dict
        The mode, gauge, interpolation, shifts (px, per projection), tilt angles (deg), the tilt-axis angle (deg),
        the number of estimates and of parameters at their bound; with ``"shifts+axis"`` also the angle's source,
        standard error and whether the data determine it (a warning when its standard error is above
        ``MAX_ANGLE_SE_DEG``).
    """
    out = {"mode": "fixed" if state is None else state.mode, "gauge": None if state is None else state.gauge,
           "interpolation": op.interpolation,
           "tilt_angles_deg": [math.degrees(float(t)) for t in op.operator.geometry.angles],
           "shifts_px": op.shifts.tolist(), "components": ["across", "along"][:op.components],
           "axis_angle_deg": math.degrees(float(op.angle)), "estimates": 0 if state is None else len(state.records),
           "every": every, "at_bound": 0 if state is None else state.at_bound}
    if state is not None and state.mode == "shifts+axis" and state.records:
        out.update(_angle_summary(op, state))
    return out


def _angle_summary(op: AlignedOperator, state: AlignmentState) -> dict:
    """The tilt-axis angle's source, standard error and determination (:func:`operator_summary`)."""
    se, stack = state.angle_se, state.stack_estimate
    determined = stack is not None and stack.determined
    source = ("stack" if determined else "stack (not determined)" if math.isfinite(se) else "given") \
        if state.held else ("fit with the stack's prior" if state.prior is not None else "fit")
    out = {"axis_angle_source": source}
    if stack is not None:
        out["axis_angle_stack_deg"] = stack.angle_deg if math.isfinite(stack.angle_deg) else None
        out["axis_angle_stack_se_deg"] = stack.se_deg if math.isfinite(stack.se_deg) else None
    out["axis_angle_se_deg"] = se if math.isfinite(se) else None
    out["axis_angle_determined"] = se <= MAX_ANGLE_SE_DEG and (stack is None or stack.determined)
    if se > MAX_ANGLE_SE_DEG and not state.held:   # a held angle's warning was given when it was held
        log.warning("the tilt-axis angle is not determined by the data: %.3f deg with a standard error of %s deg "
                    "(above %g; the data cannot tell a turn of the axis from a turn of the object about the "
                    "beam): measure the angle beforehand and rotate the stack, or use align='shifts'",
                    math.degrees(float(op.angle)), f"{se:.3f}" if math.isfinite(se) else "inf", MAX_ANGLE_SE_DEG)
    return out


def plot_shifts(alignment: dict, path: str | Path) -> None:
    """Shifts (px) against the tilt angle (deg), one line per component, the axis angle in the title when it was
    estimated (a mode with ``axis``).

    Parameters
    ----------
    alignment : dict
        A summary (:func:`operator_summary`, ``result.alignment``).
    path : str or pathlib.Path
        The figure's file (PNG).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    shifts = torch.tensor(alignment["shifts_px"])
    for i, name in enumerate(alignment["components"]):
        ax.plot(alignment["tilt_angles_deg"], shifts[:, i].numpy(), "o-", ms=3, label=f"{name} the tilt axis")
    ax.set_xlabel("tilt angle (deg)")
    ax.set_ylabel("shift (px)")
    angle = f": tilt-axis angle {alignment['axis_angle_deg']:.3f} deg" if "axis" in alignment["mode"] else \
        " (tilt-axis angle not estimated)"
    ax.set_title(f"alignment ({alignment['mode']}){angle}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def wrap(solver, operator: AlignedOperator, state: AlignmentState, data: torch.Tensor, label: str = "align"):
    """``solver`` with the alignment of ``operator`` in the fit: an :class:`AlignmentSolver` owning ``state``.

    Parameters
    ----------
    solver : IterativeSolver
        The registration's solver.
    operator : AlignedOperator
        The data model.
    state : AlignmentState
        The fit's state.
    data : torch.Tensor
        The data the alignment is fitted to.
    label : str
        The option's name in messages.

    Returns
    -------
    AlignmentSolver
        The solver with the alignment re-estimated every ``ALIGN_EVERY`` iterations.

    Raises
    ------
    ValueError
        One line for solver='fast' (its coarse levels have no aligned operator).
    """
    from ..solvers import MultilevelSolver

    if isinstance(solver, MultilevelSolver):
        raise ValueError(f"{label}={state.mode!r} needs solver='algorithm1' or a torch.optim solver, not 'fast'")
    return AlignmentSolver(solver, operator, state, data)
