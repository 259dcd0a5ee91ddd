"""The template's intensities fitted with the deformation (``template_scale="fit"`` / ``"fit+offset"``,
docs/units.md).

A template in other units than the data (a picture in grey levels, an atlas in its own scale) is brought to them
by a factor ``c`` and an offset ``b``: the object is modelled as ``c W(nu, I) + b`` (for the geometric action
``W(nu, c I + b) = c W(nu, I) + b``, so the registration of ``c I + b`` is that model). ``template_scale="auto"``
fits ``c`` once, before the run, by least squares of ``c T I`` to ``g``: the shapes' mismatch biases it (20 % low
on a limited-angle case). ``"fit"`` re-fits ``c`` every :data:`FIT_EVERY` iterations against the *deformed* template,
whose shapes match the data better as the registration proceeds, ``"fit+offset"`` ``c`` and ``b``:

    min_{c, b} (1/2) || c T W(nu_k, I) + b T 1 - g ||^2_data        (two normal equations; b = 0 for "fit")

then registers ``c I + b`` on (Algorithm 1's or torch.optim's cached evaluations are dropped: they belong to
the old template). The first fit (iteration 0) is the ``"auto"`` fit (with the offset). The offset is optional:
it fills the whole box, where an object on an empty background has none, and SSIM against such a target punishes
a small one hard (a fitted -0.008 took the limited-angle Shepp-Logan case from 0.626 to 0.555).

Notes
-----
``I`` the template as prepared (``indreg.units.prepare``: the first factor applied); ``c`` and ``b``
in the data's units; the result's ``units.template_scale`` / ``units.template_offset`` are the final ones
(``template_scale`` relative to the template as given).
"""
from __future__ import annotations

import logging
import math

import torch

from ..options import TEMPLATE_FITS as FITS  # the values of template_scale that fit with the deformation
from ..solvers.state import RefitSolver

__all__ = ["FITS", "FIT_EVERY", "fit_intensity", "IntensityFitSolver", "wrap"]

log = logging.getLogger("indreg")

#: Iterations between two fits of the template's factor and offset.
FIT_EVERY = 10


def fit_intensity(P: torch.Tensor, Q, g: torch.Tensor, inner) -> tuple:
    """``(c, b)`` minimising ``||c P + b Q - g||^2`` in the data inner product ``inner`` (float64 normal equations);
    ``b = 0`` when ``Q`` is None or (nearly) parallel to ``P``."""
    def dot(x, y):
        return float(inner(x.double(), y.double()).sum())

    pp, pg = dot(P, P), dot(P, g)
    if pp <= 0:
        return math.nan, 0.0
    if Q is None:
        return pg / pp, 0.0
    pq, qq, qg = dot(P, Q), dot(Q, Q), dot(Q, g)
    det = pp * qq - pq * pq
    if det <= 1e-9 * pp * qq:
        return pg / pp, 0.0
    return (pg * qq - qg * pq) / det, (qg * pp - pg * pq) / det


class IntensityFitSolver(RefitSolver):
    """A solver that re-fits the template's factor (and offset) every ``every`` iterations (module docstring), then
    takes ``inner``'s step. ``units`` (``indreg.units.Units``) receives the fitted values: ``template_scale`` (times
    the factor ``prepare`` applied first) and ``template_offset``."""

    name = "intensity"

    def __init__(self, inner, units, offset: bool = False, every: int = FIT_EVERY):
        super().__init__(inner, every)
        self.units, self.with_offset = units, offset
        self.what = "factor and offset" if offset else "factor"
        self.template = self.problem.template            # I, as prepared
        self.first = units.template_scale                # the factor prepare applied
        self.scale, self.offset, self.records = 1.0, 0.0, []
        with torch.no_grad():   # T 1, the offset's projection
            self.ones = self.problem.ray_transform(torch.ones_like(self.template)) if offset else None

    def refit(self, state) -> None:
        """Fit ``(c, b)`` at ``state.iterate`` and register ``c I + b`` from here on."""
        p = self.problem
        with torch.no_grad():
            deformed = (p.reconstruction(state.iterate) - self.offset) / self.scale   # W(nu, I)
            c, b = fit_intensity(p.ray_transform(deformed), self.ones, p.data, p.ray_transform.inner_data)
        if not (math.isfinite(c) and c > 0 and math.isfinite(b)):
            log.warning("iteration %d: the template's factor fit gave c = %.4g; keeping c = %.4g, b = %.4g",
                        state.iteration, c, self.scale, self.offset)
            return
        self.scale, self.offset = c, b
        self.records.append((state.iteration, c, b))
        self._apply()

    def _apply(self) -> None:
        self.problem.template = self.scale * self.template + self.offset
        self.units.template_scale, self.units.template_offset = self.first * self.scale, self.offset

    def report(self, info: dict) -> dict:
        info["template_scale"], info["template_offset"] = self.first * self.scale, self.offset
        return info

    def summary(self) -> dict:
        """The fits: ``(iteration, factor, offset)`` each (the factor relative to the template as prepared)."""
        return {"every": self.every, "fits": [list(r) for r in self.records]}

    def state_dict(self) -> dict:
        return dict(self.inner.state_dict(), intensity_fit=(self.scale, self.offset, list(self.records)))

    def load_state_dict(self, d: dict) -> None:
        d = dict(d)
        self.scale, self.offset, records = d.pop("intensity_fit")
        self.records = list(records)
        self._apply()
        self.inner.load_state_dict(d)


def wrap(solver, template_scale, units):
    """``solver`` wrapped in an :class:`IntensityFitSolver` when ``template_scale`` is ``"fit"`` or
    ``"fit+offset"`` (``indreg.options`` allows them only for ``model="lddmm"`` with the geometric action:
    ``W(nu, c I + b) = c W(nu, I) + b`` holds only there)."""
    if template_scale not in FITS:
        return solver
    return IntensityFitSolver(solver, units, offset=template_scale == "fit+offset")
