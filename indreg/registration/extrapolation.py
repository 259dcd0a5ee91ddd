"""Which volume to trust beyond the measured range: a validation that predicts extrapolation.

Held-out angles between the fitted ones (``holdout``) test interpolation: they can rank volumes in the wrong order
for the missing range (issue #49: a measured slice with its neighbour as the template scored residual model <
LDDMM < template alone on such angles, and the other way round on the missing range). Here the angles at the
edges of the measured range are held out instead (:func:`edge_split`: the outer ``edge_fraction`` of the range on
each side), every candidate is fitted to the inner ones, and each is scored on the edge ones, which lie in the
inner fit's missing range just as the missing range lies beyond the whole fit:

- the template alone (in the data's units, ``template_scale``);
- each model (``lddmm``, ``residual``), and between each and the template, where the data cannot see:
  ``f_alpha = f - alpha (N f - N I)``, ``N`` the prior-filled part of the inner fit (:func:`.parts.data_split`):
  the data-determined part of the registration and, for ``alpha = 1``, the template's prior-filled part; ``alpha``
  is how far the deformation may move the template there (its regularisation in the missing range), chosen among
  ``alphas``; every ``f_alpha`` fits the fitted angles as ``f`` does (``T N = 0``).

The least edge residual chooses (ties: the template, then smaller ``alpha``); the chosen model then runs on all the
angles, the chosen ``alpha`` is applied with the split of that fit (:func:`register_extrapolating`), or the template
alone is the answer. Measured in docs/evaluation.md.

Convention: ``angles`` (degrees) of the data's rows, from the operator's geometry when not given; the range's centre
is the angles' circular mean (a full-turn fan beam's limited range wraps through 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

__all__ = ["Extrapolation", "edge_split", "choose_extrapolation", "register_extrapolating", "blend", "row_angles",
           "EDGE_FRACTION", "ALPHAS", "MODELS"]

EDGE_FRACTION = 0.25
ALPHAS = (0.0, 0.25, 0.5, 0.75, 1.0)
MODELS = ("lddmm", "residual")


def row_angles(operator) -> np.ndarray:
    """The degrees of the operator's rows (parallel beam, tilt series, fan beam; alignment and restriction seen
    through); a one-line TypeError for an operator without angles."""
    from ..evaluation.parts import parallel_angles

    try:
        return np.degrees(parallel_angles(operator)[0].numpy())
    except TypeError:
        angles = getattr(getattr(operator, "geometry", None), "angles", None)
        if angles is None:
            raise TypeError(f"the edge validation needs the angles of {type(operator).__name__}: give angles=") \
                from None
        return np.degrees(torch.as_tensor(angles, dtype=torch.float64).cpu().numpy())


def edge_split(degrees, rows=None, fraction: float = EDGE_FRACTION) -> tuple:
    """``(inner, edge)`` sorted indices among ``rows`` (default all) of the angles ``degrees``: ``edge`` those whose
    circular distance from the range's centre (the circular mean) is at least ``1 - fraction`` of the largest, on
    each side at least the outermost one.

    Parameters
    ----------
    degrees : array_like
        The angles of the data's rows, in degrees.
    rows : iterable of int, optional
        The indices of ``degrees`` to split (default all).
    fraction : float
        The outer part of the range's half-width held out on each side, in (0, 1).

    Returns
    -------
    tuple
        ``(inner, edge)``: two sorted lists of row indices.

    Raises
    ------
    ValueError
        A fraction outside (0, 1), fewer than 4 rows, or fewer than 2 rows left to fit.
    """
    if not 0 < fraction < 1:
        raise ValueError(f"edge_fraction must be in (0, 1), got {fraction}")
    d = np.asarray(degrees, dtype=np.float64)
    rows = np.arange(len(d)) if rows is None else np.asarray(sorted(rows))
    if len(rows) < 4:
        raise ValueError(f"the edge validation needs at least 4 angles to fit and hold out, got {len(rows)}")
    a = np.radians(d[rows])
    centre = math.atan2(float(np.sin(a).mean()), float(np.cos(a).mean()))
    offset = np.degrees((a - centre + math.pi) % (2 * math.pi) - math.pi)
    reach = (1 - fraction) * np.abs(offset).max()
    edge = set(rows[np.abs(offset) >= reach - 1e-9].tolist())
    edge |= {int(rows[np.argmin(offset)]), int(rows[np.argmax(offset)])}
    inner = sorted(set(rows.tolist()) - edge)
    if len(inner) < 2:
        raise ValueError(f"edge_fraction {fraction} leaves {len(inner)} angle(s) to fit")
    return inner, sorted(edge)


@dataclass
class Extrapolation:
    """The choice (``"template"`` or a model), its ``alpha``, every candidate's edge residual (``{"template": r,
    model: {alpha: r}}``), the edge rows (indices of the data), and after :func:`register_extrapolating` the chosen
    ``volume``."""
    choice: str
    alpha: float
    edge_residuals: dict
    edge_rows: list
    volume: Optional[torch.Tensor] = field(default=None, repr=False)

    def summary(self) -> dict:
        """For ``result.extrapolation`` and ``metrics.json``."""
        return {"extrapolation_choice": self.choice, "extrapolation_alpha": self.alpha,
                "extrapolation_edge_residuals": {k: (v if isinstance(v, float) else {str(a): r for a, r in v.items()})
                                                 for k, v in self.edge_residuals.items()},
                "extrapolation_edge_rows": list(self.edge_rows)}


def _kept_rows(options: dict, count: int) -> list:
    from ..evaluation.validation import holdout_rows

    return list(range(count)) if options.get("holdout") is None else holdout_rows(options["holdout"], count)[0]


def subset(operator, rows: list):
    """The operator of ``rows`` (angles) of ``operator``: a ray transform or tilt series of those angles (what
    ``align`` can wrap), else ``indreg.forward.restrict``."""
    from ..forward.geometry import FanBeamGeometry, ParallelBeamGeometry
    from ..forward.ray_transform import RayTransform
    from ..forward.stacking import restrict
    from ..forward.tilt_series import TiltSeriesGeometry, TiltSeriesTransform

    g = getattr(operator, "geometry", None)
    if isinstance(operator, TiltSeriesTransform):
        geometry = TiltSeriesGeometry(g.angles[rows], g.det_count, g.det_min, g.det_max, g.tilt_axis,
                                      angle_unit="rad")
        return TiltSeriesTransform(operator.domain, geometry)
    if isinstance(operator, RayTransform) and isinstance(g, ParallelBeamGeometry):
        return RayTransform(operator.domain, ParallelBeamGeometry(det_count=g.det_count, det_min=g.det_min,
                                                                  det_max=g.det_max, angles=g.angles[rows],
                                                                  angle_unit="rad"))
    if isinstance(operator, RayTransform) and isinstance(g, FanBeamGeometry):
        return RayTransform(operator.domain, FanBeamGeometry(det_count=g.det_count, src_radius=g.src_radius,
                                                             det_radius=g.det_radius, det_min=g.det_min,
                                                             det_max=g.det_max, angles=g.angles[rows],
                                                             angle_unit="rad"))
    return restrict(operator, rows)


def _for_model(options: dict, model: str) -> dict:
    """``options`` without those of other models (``residual_tv`` does not go to an LDDMM trial)."""
    from ..options import all_options

    other = {o.name for o in all_options() if o.models is not None and model not in o.models}
    return {k: v for k, v in options.items() if k not in other}


def _trial(template, data, operator, model: str, options: dict, edge: list, alphas) -> tuple:
    """One model fitted to the inner rows: ``(edge residual of the template, {alpha: edge residual})``."""
    from .run import RegistrationLoop, build_result, initial_state, setup
    from ..evaluation.parts import data_split

    o = dict(_for_model(options, model), model=model, holdout=edge, patience=None, progress=False, callback=None,
             split=False, uncertainty=False)
    s = setup(template, data, operator, **o)
    loop = RegistrationLoop(s.problem, s.solver, initial_state(s.problem), s.options["max_iter"],
                            every=s.options["log_every"], validation=s.validation)
    status = loop.run()
    r = build_result(s.problem, loop.state, loop.history, loop.seconds, status, None, s.units, s.validation,
                     trajectory=False, solver=s.solver)
    f, I = r.deformed.detach(), s.problem.template
    T = s.problem.ray_transform
    move = data_split(f, T, max_iter=100).prior - data_split(I.to(f.dtype), T, max_iter=100).prior
    return s.validation.residual(I), {a: s.validation.residual(f - a * move) for a in alphas}


def choose_extrapolation(template, data, operator, models=MODELS, alphas=ALPHAS, edge_fraction: float = EDGE_FRACTION,
                         angles=None, **options) -> Extrapolation:
    """The edge validation (module docstring) with ``register()``'s ``options`` (the run's ``holdout`` rows are left
    out of the trials).

    Parameters
    ----------
    template, data, operator
        As ``indreg.register``.
    models : tuple
        The models tried (``register()``'s ``model`` names).
    alphas : tuple
        The fractions of the template's prior-filled part tried (0: the registration as it is).
    edge_fraction : float
        The outer part of the measured range held out on each side.
    angles : array, optional
        The rows' angles in degrees (default: the operator's).
    **options
        ``register()``'s options, passed to each trial (less ``holdout`` and ``extrapolation``); the rows of
        ``holdout`` are left out of the split.

    Returns
    -------
    Extrapolation
        Without ``volume`` (:func:`register_extrapolating` makes it).

    Raises
    ------
    ValueError
        Too few rows, a bad fraction; ``register()``'s errors.
    """
    count = int(operator.range_shape[0])
    degrees = row_angles(operator) if angles is None else np.asarray(angles, dtype=np.float64)
    kept = _kept_rows(options, count)
    inner, edge = edge_split(degrees, kept, edge_fraction)
    rows = sorted(inner + edge)
    sub_op = subset(operator, rows)
    sub_data = torch.as_tensor(data)[rows]
    positions = [rows.index(e) for e in edge]
    residuals, best = {}, ("template", 0.0, math.inf)
    for m in models:
        t, by_alpha = _trial(template, sub_data, sub_op, m, {k: v for k, v in options.items()
                                                             if k not in ("holdout", "extrapolation")},
                             positions, alphas)
        residuals.setdefault("template", t)
        residuals[m] = by_alpha
    best = ("template", 1.0, residuals["template"])
    for m in models:
        for a in sorted(alphas):
            if residuals[m][a] < best[2]:
                best = (m, float(a), residuals[m][a])
    return Extrapolation(best[0], best[1], residuals, edge)


def register_extrapolating(template, data, operator, models=MODELS, alphas=ALPHAS,
                           edge_fraction: float = EDGE_FRACTION, angles=None, **options):
    """``indreg.register`` with the edge validation first (:func:`choose_extrapolation`): the chosen model on all
    the angles (the template alone: no deformation, ``max_iter=0``), its volume moved by the chosen ``alpha``
    towards the template's prior-filled part; ``result.deformed`` is that volume, ``result.outputs["registered"]``
    the registration before it, ``result.extrapolation`` the report (:meth:`Extrapolation.summary`); the other
    fields (``holdout``, ``residual``, ``uncertainty``) are the registration's.

    Parameters
    ----------
    template, data, operator
        As ``indreg.register``.
    models : tuple
        The models tried (``register()``'s ``model`` names).
    alphas : tuple
        The fractions of the template's prior-filled part tried (0: the registration as it is).
    edge_fraction : float
        The outer part of the measured range held out on each side.
    angles : array, optional
        The rows' angles in degrees (default: the operator's).
    **options
        ``register()``'s options, for the trials (:func:`choose_extrapolation`) and the final run (less
        ``extrapolation``, and those of other models than the chosen one).

    Returns
    -------
    RegistrationResult
        The chosen run's result, with ``deformed``, ``outputs["registered"]`` and ``extrapolation`` as above.

    Raises
    ------
    ValueError
        Too few rows, a bad fraction; ``register()``'s errors.
    """
    from ..evaluation.parts import data_split
    from .once import register_once

    choice = choose_extrapolation(template, data, operator, models, alphas, edge_fraction, angles, **options)
    options = {k: v for k, v in options.items() if k != "extrapolation"}
    final = dict(_for_model(options, "lddmm"), model="lddmm", max_iter=0) if choice.choice == "template" else \
        dict(_for_model(options, choice.choice), model=choice.choice)
    result = register_once(template, data, operator, **final)
    f = result.deformed
    if choice.choice != "template" and choice.alpha > 0:
        f = blend(result, choice.alpha)
        result.outputs["registered"] = result.deformed
        result.deformed = f
        if result.data_part is not None:
            s = data_split(f.detach(), result.problem.ray_transform)
            result.data_part, result.prior_part = s.data, s.prior
    choice.volume = f
    result.extrapolation = choice.summary()
    return result


def blend(result, alpha: float) -> torch.Tensor:
    """``f - alpha (N f - N I)`` of a run's result (module docstring): ``N`` the prior-filled part of its fitted
    operator, ``I`` its template in the data's units."""
    from ..evaluation.parts import data_split

    f = result.deformed.detach()
    if alpha == 0:
        return f
    T, I = result.problem.ray_transform, result.problem.template.to(f.dtype)
    return f - alpha * (data_split(f, T).prior - data_split(I, T).prior)
