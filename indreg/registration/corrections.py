"""In-the-fit corrections: parts of the data model re-estimated while the registration runs, as a registered
chain around the solver (the registry itself, :data:`CORRECTIONS`, lives in ``indreg.options``).

A correction is a :class:`Correction` entry and a ``RefitSolver`` subclass (``indreg.solvers.state``):

    - ``Correction(name, wrap, options=(...), model=None, check=None, plot=None)``: its own options
      (``indreg.options.Option``: keywords of ``register()`` and config keys), ``model(operator, options, label)
      -> operator`` when it estimates a part of the data model that must be in place before the problem is built
      (the alignment's ``T_s``), and ``wrap(solver, fit) -> solver``: ``solver`` itself where the options leave it
      off, else its ``RefitSolver`` around ``solver``. ``fit`` (:class:`Fit`) holds what it may need: the
      run's options, the data model after every ``model`` (before a ``holdout`` split), all the data, the units.
    - its ``RefitSolver``: **when** it runs (``every``: before the steps at
      iterations ``0, every, 2 every, ...``), **what** it does (``refit(state)``: re-estimate at the current
      iterate and change the problem; the solver's cached evaluations are then dropped), its **outputs**
      (``report(info)``: entries of every iteration's report, so of the history and TensorBoard;
      ``summary()``: the final estimate, ``result.corrections[name]`` and metrics.json's ``name``), its
      **checkpoint state** (``state_dict()``: the inner solver's with its own entries added; ``load_state_dict``
      pops them and hands the rest on), and ``name``, the entry's.

:func:`chain` wraps the solver in every registered correction in order (the first registered is innermost: it
re-estimates first). Adding one is its module and one :func:`register_correction` call; neither
``indreg.run`` nor the app names any (``docs/extending.md``).

Built in:

    alignment  ``indreg.alignment``: per-projection shifts (and the tilt-axis angle) by projection matching against
               the current reconstruction (``align``, ``align_gauge``, ``align_interpolation``; docs/alignment.md)
    intensity  ``indreg.intensity``: the template's factor (and offset) against the deformed template
               (``template_scale="fit"`` / ``"fit+offset"``; docs/units.md)
"""
from __future__ import annotations

from dataclasses import dataclass

from ..options import CORRECTIONS, Correction, Option, OptionError, choice, register_correction

__all__ = ["Correction", "CORRECTIONS", "Fit", "register_correction", "aligned_scale", "chain", "data_model",
           "summaries"]


@dataclass
class Fit:
    """What a correction's ``wrap`` may use: the run's resolved ``options``, ``label(name)`` (the option as the
    user named it: keyword or config key), the data model ``operator`` (after every correction's ``model``; all
    projections, before a ``holdout`` split), all the ``data`` (prepared: background removed), the ``units``
    (``indreg.units.Units``, which a correction may update) and the ``problem`` built."""
    options: dict
    label: object
    operator: object
    data: object
    units: object
    problem: object = None


def data_model(operator, o: dict, label):
    """``operator`` with every registered correction's ``model`` applied in order."""
    for c in CORRECTIONS.values():
        if c.model is not None:
            operator = c.model(operator, o, label)
    return operator


def chain(solver, fit: Fit):
    """``solver`` wrapped by every registered correction in order (each returns it unchanged when off)."""
    for c in CORRECTIONS.values():
        solver = c.wrap(solver, fit)
    return solver


def summaries(solver, problem=None) -> dict:
    """``{name: summary}`` of the corrections around ``solver`` (innermost first), those with one; with ``problem``
    also the ``fixed`` summaries of corrections that did not run (an imported alignment used as it is)."""
    from ..solvers.state import RefitSolver

    out = {}
    while isinstance(solver, RefitSolver):
        out[solver.name] = solver.summary()
        solver = solver.inner
    out = {name: s for name, s in reversed(out.items()) if s}
    for c in CORRECTIONS.values():
        if problem is not None and c.fixed is not None and c.name not in out:
            fixed = c.fixed(problem)
            if fixed:
                out[c.name] = fixed
    return out


# ---------------------------------------------------------------------------------------------------- alignment
def _aligned(operator, o: dict, label):
    from ..alignment import aligned

    return aligned(operator, o["align"], label("align"), o["align_gauge"], o["align_interpolation"])


def _align(solver, fit: Fit):
    from ..alignment import wrap

    return wrap(solver, fit.operator, fit.data, fit.label("align"))


def aligned_scale(operator):
    """``indreg.units.prepare``'s ``aligned_scale`` for the data model ``operator`` (after :func:`data_model`): the
    template's scale fitted jointly with the alignment of its projection to the data (``indreg.alignment.fit_scale``),
    whose shifts then start the first in-fit estimate; None when ``operator`` has no alignment to estimate."""
    from ..alignment import fit_scale, hold_stack_angle
    from ..forward.shift import AlignedOperator

    if not isinstance(operator, AlignedOperator) or not hasattr(operator, "mode"):   # none, or a fixed alignment
        return None

    def fit(template, data) -> float:
        hold_stack_angle(operator, data)   # the stack's own angle first: it needs no template
        c, operator.shifts, operator.angle, _ = fit_scale(operator, template, data)
        operator.started = True
        return c

    return fit


def _plot_shifts(summary: dict, path) -> None:
    from ..alignment import plot_shifts

    plot_shifts(summary, path)


def _fixed_alignment(problem) -> dict:
    from ..alignment import summary

    return summary(problem)


register_correction(Correction("alignment", _align, model=_aligned, plot=_plot_shifts, fixed=_fixed_alignment,
                               doc="per-projection shifts and the tilt-axis angle (docs/alignment.md)", options=(
    Option("align", "data", "align", "none", choice(("none", "shifts", "shifts+axis")),
           "alignment in the fit: 'none', 'shifts' (per-projection shifts) or 'shifts+axis' (and the tilt-axis "
           "angle of a tilt series), re-estimated against the reconstruction's projection (docs/alignment.md)", str),
    Option("align_gauge", "data", "align_gauge", "offset+translation",
           choice(("offset+translation", "translation", "none")),
           "what the shifts of align leave to the deformation: 'offset+translation' (a constant across the axis and "
           "an object translation), 'translation' (the axis' offset estimated too) or 'none' (the template fixes "
           "the frame; docs/alignment.md)", str),
    Option("align_interpolation", "data", "align_interpolation", "linear", choice(("linear", "cubic")),
           "how align moves a projection image: 'linear' (bilinear) or 'cubic' (Keys' cubic convolution: no blur "
           "at fractional shifts; docs/alignment.md)", str),
)))


# ---------------------------------------------------------------------------------------------------- intensity
_FITS = ("fit", "fit+offset")   # indreg.intensity.FITS (not imported: the registry imports no correction)


def _fit_intensity(solver, fit: Fit):
    from ..intensity import wrap

    return wrap(solver, fit.options["template_scale"], fit.units)


def _check_intensity(o: dict, label) -> None:
    """Fitting with the deformation needs ``W(nu, c I + b) = c W(nu, I) + b``: lddmm with the geometric action."""
    if o["template_scale"] in _FITS and (o["model"] != "lddmm" or o["action"] != "geometric"):
        raise OptionError(label("template_scale"), o["template_scale"], "None, 'auto' or a number with "
                          f"model={o['model']!r} and action={o['action']!r} (fitting with the deformation needs "
                          "lddmm with the geometric action)")


register_correction(Correction("intensity", _fit_intensity, check=_check_intensity,
                               doc="the template's factor and offset (template_scale='fit' / 'fit+offset')"))
