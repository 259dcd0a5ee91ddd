"""In-the-fit corrections: parts of the data model re-estimated while the registration runs, as a registered
chain around the solver (the registry itself, :data:`CORRECTIONS`, lives in ``indreg.options``).

A correction is a :class:`Correction` entry and a ``RefitSolver`` subclass (``indreg.solvers.state``):

    - ``Correction(name, wrap, options=(...), model=None, start=None, check=None, plot=None, fixed=None)``: its
      own options (``indreg.options.Option``: keywords of ``register()`` and config keys), ``model(fit)`` when it
      estimates a part of the data model that must be in place before the problem is built (it sets
      ``fit.operator``, the alignment's ``T_s``, and keeps its own state in ``fit.states[name]``), ``start(fit,
      template, data)`` when it must act once the units are measured and before the template's factor is set (the
      alignment's scale fit), and ``wrap(solver, fit) -> solver``: ``solver`` itself where the options leave it
      off, else its ``RefitSolver`` around ``solver``. ``fit`` (:class:`Fit`) holds what it may need: the run's
      options, the data model after every ``model`` (before a ``holdout`` split), all the data, the units, the
      corrections' states.
    - its ``RefitSolver``: **when** it runs (``every``: before the steps at
      iterations ``0, every, 2 every, ...``), **what** it does (``refit(state)``: re-estimate at the current
      iterate and change the problem; the solver's cached evaluations are then dropped), its **outputs**
      (``report(info)``: entries of every iteration's report, so of the history and TensorBoard;
      ``summary()``: the final estimate, ``result.corrections[name]`` and metrics.json's ``name``), its
      **checkpoint state** (``state_dict()``: the inner solver's with its own entries added; ``load_state_dict``
      pops them and hands the rest on), and ``name``, the entry's.

:func:`chain` wraps the solver in every registered correction in order (the first registered is innermost: it
re-estimates first). Adding one is its module and one :func:`register_correction` call; neither
``indreg.registration.run`` nor the app names any (``docs/extending.md``).

Built in:

    alignment  ``indreg.alignment.correction``: per-projection shifts (and the tilt-axis angle) by projection
               matching against the current reconstruction (``align``, ``align_gauge``, ``align_interpolation``;
               docs/alignment.md)
    intensity  ``indreg.registration.intensity``: the template's factor (and offset) against the deformed template
               (``template_scale="fit"`` / ``"fit+offset"``; docs/units.md)
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..alignment import correction as _alignment  # noqa: F401  (registers the alignment: first, so innermost)
from ..options import CORRECTIONS, TEMPLATE_FITS, Correction, OptionError, register_correction

__all__ = ["Correction", "CORRECTIONS", "Fit", "register_correction", "chain", "data_model", "start", "summaries"]


@dataclass
class Fit:
    """What a correction's hooks may use: the run's resolved ``options``, ``label(name)`` (the option as the user
    named it: keyword or config key), the data model ``operator`` (after every correction's ``model``; all
    projections, before a ``holdout`` split), all the ``data`` (prepared: background removed), the ``units``
    (``indreg.units.Units``, which a correction may update), the ``problem`` built, and ``states``: each
    correction's own state by name (set by its ``model``)."""
    options: dict
    label: object
    operator: object
    data: object = None
    units: object = None
    problem: object = None
    states: dict = field(default_factory=dict)


def data_model(fit: Fit) -> object:
    """Every registered correction's ``model`` applied in order to ``fit.operator``; returns the data model."""
    for c in CORRECTIONS.values():
        if c.model is not None:
            c.model(fit)
    return fit.operator


def start(fit: Fit, template, data) -> None:
    """Every registered correction's ``start`` in order (the units measured, the template's factor not yet set)."""
    for c in CORRECTIONS.values():
        if c.start is not None:
            c.start(fit, template, data)


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


# ---------------------------------------------------------------------------------------------------- intensity
def _fit_intensity(solver, fit: Fit):
    from .intensity import wrap

    return wrap(solver, fit.options["template_scale"], fit.units)


def _check_intensity(o: dict, label) -> None:
    """Fitting with the deformation needs ``W(nu, c I + b) = c W(nu, I) + b``: lddmm with the geometric action."""
    if o["template_scale"] in TEMPLATE_FITS and (o["model"] != "lddmm" or o["action"] != "geometric"):
        raise OptionError(label("template_scale"), o["template_scale"], "None, 'auto' or a number with "
                          f"model={o['model']!r} and action={o['action']!r} (fitting with the deformation needs "
                          "lddmm with the geometric action)")


register_correction(Correction("intensity", _fit_intensity, check=_check_intensity,
                               doc="the template's factor and offset (template_scale='fit' / 'fit+offset')"))
