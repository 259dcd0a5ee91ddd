"""The alignment as an in-the-fit correction (``indreg.registration.corrections``): its options, the data model
``T_s`` it puts in place before the problem is built, the template's scale fitted through it, and the solver it
wraps around the registration's (``indreg.alignment.solver.AlignmentSolver``). Importing this module registers
it; it loads no torch (the option table is read before torch)."""
from __future__ import annotations

from ..options import Correction, Option, choice, register_correction
from .modes import ALIGN_GAUGES, ALIGN_MODES, INTERPOLATIONS

__all__ = ["ALIGNMENT"]

#: The values of ``template_scale`` fitted before the run (through the alignment when it is on).
_FITTED = ("auto", "fit", "fit+offset")


def _model(fit) -> None:
    """``fit.operator`` becomes ``T_s`` for ``align`` (``indreg.alignment.fit.aligned``), its fit's state
    ``fit.states["alignment"]``."""
    from .fit import aligned

    o, label = fit.options, fit.label
    fit.operator, state = aligned(fit.operator, o["align"], label("align"), o["align_gauge"],
                                  o["align_interpolation"])
    if state is not None:
        fit.states["alignment"] = state


def _start(fit, template, data) -> None:
    """With a fitted ``template_scale``: the template's scale through the alignment of its projection to the data
    (``indreg.alignment.fit.fit_scale``; the stack's own angle first, it needs no template), whose shifts then start
    the first in-fit estimate; ``fit.units.scale_fit`` becomes it."""
    state = fit.states.get("alignment")
    if state is None or template is None or fit.options["template_scale"] not in _FITTED:
        return
    from .fit import fit_scale
    from .solver import hold_stack_angle

    op = fit.operator
    hold_stack_angle(op, state, data)
    c, op.shifts, op.angle, _ = fit_scale(op, state, template, data)
    state.started = True
    fit.units.fit_through_alignment(c)


def _wrap(solver, fit):
    """``solver`` in an ``AlignmentSolver`` where ``align`` is on, else itself."""
    state = fit.states.get("alignment")
    if state is None:
        return solver
    from .solver import wrap

    return wrap(solver, fit.operator, state, fit.data, fit.label("align"))


def _plot(summary: dict, path) -> None:
    from .solver import plot_shifts

    plot_shifts(summary, path)


def _fixed(problem) -> dict:
    from .solver import summary

    return summary(problem)


ALIGNMENT = register_correction(Correction(
    "alignment", _wrap, model=_model, start=_start, plot=_plot, fixed=_fixed,
    doc="per-projection shifts and the tilt-axis angle (docs/alignment.md)", options=(
        Option("align", "data", "align", ALIGN_MODES[0], choice(ALIGN_MODES),
               "alignment in the fit: 'none', 'shifts' (per-projection shifts) or 'shifts+axis' (and the tilt-axis "
               "angle of a tilt series), re-estimated against the reconstruction's projection (docs/alignment.md)",
               str),
        Option("align_gauge", "data", "align_gauge", ALIGN_GAUGES[0], choice(ALIGN_GAUGES),
               "what the shifts of align leave to the deformation: 'offset+translation' (a constant across the axis "
               "and an object translation), 'translation' (the axis' offset estimated too) or 'none' (the template "
               "fixes the frame; docs/alignment.md)", str),
        Option("align_interpolation", "data", "align_interpolation", INTERPOLATIONS[0], choice(INTERPOLATIONS),
               "how align moves a projection image: 'linear' (bilinear) or 'cubic' (Keys' cubic convolution: no "
               "blur at fractional shifts; docs/alignment.md)", str),
    )))
