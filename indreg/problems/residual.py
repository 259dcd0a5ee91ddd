"""LDDMM with an intensity residual (``model="residual"``): the template's shape, deformed, plus the intensities it
cannot fit, regularised by total variation (a template-anchored TV).

    E(nu, r) = (gamma/2) sum_i (1/N) ||nu_i||_V^2 + (1/2) ||T (W(nu, I) + r) - g||^2_data + mu TV_eps(r)

The reconstruction is ``f = W(nu, I) + r``. A TV reconstruction regularises ``f`` itself (``TV(f)``); here the
deformed template anchors it: where the data say nothing (a limited tilt range's missing wedge) ``r`` stays near 0
and ``f`` keeps the template's shape, where they disagree with every deformation of the template (an intensity the
template lacks) ``r`` fits them, piecewise constant. ``r = 0`` throughout (``mu`` infinite, or the residual frozen
for every iteration: ``residual_start >= max_iter``) is LDDMM.

Notes
-----
``r`` on ``image_domain`` (the template's grid), in the data's intensity units; ``mu`` (``tv_weight``
of the residual, ``residual_tv``) absolute; ``TV_eps`` the smoothed isotropic TV of ``indreg.forward.tv``
(``eps`` = ``smoothing``, an intensity per length); the L2 gradient in ``r`` is the torch gradient divided by
the cell volume. Algorithm 1's default step for ``r`` is ``1 / (||T||^2 + mu 4 d / (h^2 eps))`` (the data term's
and the smoothed TV's curvature bounds, ``h`` the smallest cell side).

The finish (:meth:`ResidualRegistration.finish`, run by ``indreg.registration.run.build_result`` after the loop): with the
deformation fixed, ``f = W(nu, I) + r`` is solved to its minimum by Chambolle-Pock (``tv_reconstruction`` with the
anchor ``W``, ``f >= 0``, the exact TV), since gradient steps on a smoothed TV converge slowly; its weight is chosen
among ``mu_candidates`` by the held-out angles when the run has them, as the TV baseline's weight is, and the loop's
own result is kept where it is better on them than every weight.
"""
from __future__ import annotations

import functools
import logging

import torch

from .._checks import check_nonnegative
from ..forward.operator import operator_norm
from ..forward.tv import total_variation, tv_reconstruction
from .lddmm import IndirectRegistration

__all__ = ["ResidualRegistration", "MAX_WIDEN"]

log = logging.getLogger("indreg")

#: The finish's weight grid is widened by a decade at most this many times while the best weight sits at its edge.
MAX_WIDEN = 3


def _say(info: dict, choosing: bool) -> None:
    """One log line: which result the finish kept, and the held-out residuals it compared."""
    u = info["unit"]
    tried = ", ".join(f"{m / u:.0e}: {v:.4g}" for m, v in info["holdout_by_weight"].items())
    wider = f", the grid widened to {', '.join(f'{m / u:.0e}' for m in info['widened'])}" if info["widened"] else ""
    if not choosing:
        log.info("the residual's finish at residual_tv %.0e (no held-out angles to compare it with the loop's "
                 "result)", info["residual_tv"] / u)
    elif info["chosen"] == "loop":
        log.info("the residual's finish kept the loop's result (held-out residual %.4g): every weight was worse "
                 "(%s%s)", info["holdout_loop"], tried, wider)
    else:
        log.info("the residual's finish at residual_tv %.0e won (held-out residual %.4g against the loop's %.4g; "
                 "%s%s)", info["residual_tv"] / u, info["holdout_by_weight"][info["residual_tv"]],
                 info["holdout_loop"], tried, wider)


class ResidualRegistration(IndirectRegistration):
    """``min_{nu, r} E(nu, r)`` (module docstring); the iterate is ``x = (m, r)``, ``nu = K m``. Arguments as
    :class:`IndirectRegistration`, and ``residual_tv`` (``mu >= 0``), ``smoothing`` (``eps > 0``), the finish's
    ``finish_iter``, ``mu_candidates`` (chosen among by the held-out angles) and ``mu_unit`` (what the weights were
    relative to, for reports)."""

    iterate_names = ("momentum", "residual")
    output_kinds = {"deformation_part": "parts", "intensity_part": "parts"}

    def __init__(self, ray_transform, deformation, kernel, template, data, gamma, residual_tv: float,
                 smoothing: float, tv_weight: float = 0.0, finish_iter: int = 0, mu_candidates: tuple = (),
                 mu_unit: float = 1.0):
        super().__init__(ray_transform, deformation, kernel, template, data, gamma, tv_weight)
        self.residual_tv = check_nonnegative(residual_tv, "residual_tv", template.dtype)
        self.finish_iter, self.mu_candidates, self.mu_unit = int(finish_iter), tuple(mu_candidates), float(mu_unit)
        self.finish_info: dict = {}
        self.finish_norms = None   # the finish's step norms (||T||, ||grad||): computed once, kept for re-solves
        self.nonnegative = False   # the result is the finish's, f >= 0 (set by finish)
        self.smoothing = check_nonnegative(smoothing, "residual smoothing", template.dtype)
        if self.smoothing <= 0:
            raise ValueError(f"residual smoothing must be > 0 (the smoothed TV's eps), got {smoothing}")

    def __repr__(self):
        return (f"ResidualRegistration(domain={self.image_domain}, N={self.num_steps}, gamma={self.gamma}, "
                f"residual_tv={self.residual_tv}, smoothing={self.smoothing})")

    def with_deformation(self, deformation) -> "ResidualRegistration":
        return ResidualRegistration(self.ray_transform, deformation, self.kernel, self.template, self.data,
                                    self.gamma, self.residual_tv, self.smoothing, self.tv_weight, self.finish_iter,
                                    self.mu_candidates, self.mu_unit)

    def zero_residual(self) -> torch.Tensor:
        return torch.zeros(self.image_domain.shape, dtype=self.template.dtype, device=self.template.device)

    def residual_terms(self, m: torch.Tensor, r: torch.Tensor, nu: torch.Tensor | None = None) -> dict:
        """All terms as 0-dim tensors, differentiable through ``m`` (or ``nu``) and ``r``."""
        nu = self.velocity(m) if nu is None else nu
        out = self.matching(self.deformation(nu, self.template) + r)
        out["regulariser"] = self.regulariser(m, nu)
        out["residual_tv"] = self.residual_tv * total_variation(r, self.image_domain, self.smoothing)
        out["objective"] = out["data_fit"] + out["tv"] + out["regulariser"] + out["residual_tv"]
        return out

    # the registration-problem protocol (indreg.problems.problem): the iterate is x = (m, r)
    def zero_iterate(self) -> tuple:
        return self.zero_momentum(), self.zero_residual()

    def check_iterate(self, x: tuple) -> None:
        if not isinstance(x, tuple) or len(x) != 2:
            raise ValueError(f"the iterate must be a tuple of 2 tensors {self.iterate_names}")
        self.check_momentum(x[0])
        if tuple(x[1].shape) != tuple(self.image_domain.shape):
            raise ValueError(f"residual must have shape {tuple(self.image_domain.shape)}, got {tuple(x[1].shape)}")

    def gradient(self, x: tuple) -> tuple:
        """``(terms, (h_nu, h_r), nu)``: one forward / backward of ``W`` and ``T``; ``h_nu`` as LDDMM's (with the
        data residual of ``f = W + r``), ``h_r = T^*(T f - g) + mu grad TV_eps(r)`` in L2."""
        m, r = x
        with torch.no_grad():
            nu = self.velocity(m)
        with torch.enable_grad():
            nu_leaf, r_leaf = nu.detach().requires_grad_(True), r.detach().requires_grad_(True)
            t = self.residual_terms(m, r_leaf, nu_leaf)
            d_nu, d_r = torch.autograd.grad(t["data_fit"] + t["tv"] + t["residual_tv"], (nu_leaf, r_leaf))
        h_nu = d_nu.div_(self.time_weight).add_(m, alpha=self.gamma)
        h_r = d_r.div_(self.image_domain.cell_volume)
        return {k: float(v.detach()) for k, v in t.items()}, (h_nu, h_r), nu

    def differentiable(self, x: tuple) -> tuple:
        """Terms through ``(m, r)``, ``aux = (nu,)``; ``h_nu`` as LDDMM's, ``h_r`` the L2 gradient (``dx[1]`` is
        the gradient in ``r / s``, ``s = N / cell_volume``: ``h_r = dx[1] / N``)."""
        m, r = x
        nu = self.velocity(m)
        return self.residual_terms(m, r, nu), (nu,), lambda x, dx, daux: (
            daux[0] / self.time_weight + 0.5 * self.gamma * x[0], dx[1] / self.num_steps)

    def reconstruction(self, x: tuple) -> torch.Tensor:
        return self.deformed(x[0]) + x[1]

    def image_trajectory(self, x: tuple) -> torch.Tensor:
        """The deformed template's trajectory, the residual added at ``t = 1``."""
        out = self.trajectory(x[0])
        out[-1] += x[1]
        return out

    def evaluate_iterate(self, x: tuple) -> dict:
        self.check_iterate(x)
        with torch.no_grad():
            return {k: float(v) for k, v in self.residual_terms(*x).items()}

    def outputs(self, x: tuple) -> dict:
        """The parts of ``f``: ``deformation_part = W(nu, I)``, ``intensity_part = r``."""
        return {"deformation_part": self.deformed(x[0]), "intensity_part": x[1]}

    @functools.cached_property
    def operator_norm(self) -> float:
        """``||T||`` by 30 power iterations (computed once)."""
        return operator_norm(self.ray_transform, 30, self.template.dtype, self.template.device)

    def default_step(self, name: str) -> float:
        """The residual's step ``1 / (||T||^2 + mu 4 d / (h^2 eps))``."""
        if name != "residual":
            return super().default_step(name)
        h = min(self.image_domain.cell_sides)
        return 1.0 / (self.operator_norm ** 2 + self.residual_tv * 4 * self.image_domain.ndim / (h * h *
                                                                                                  self.smoothing))

    def for_line_search(self) -> "ResidualRegistration":
        return self.with_backward("exact") if self.deformation.backward == "paper" else self

    def finish(self, x: tuple, validation=None) -> tuple:
        """``(m, r')``: ``r' = f - W``, ``f = argmin_{f >= 0} (1/2)||T f - g||^2 + mu TV(f - W)`` with ``W = W(nu,
        I)`` fixed (``finish_iter`` Chambolle-Pock iterations from ``W + r``). With ``validation`` and
        ``mu_candidates`` the held-out angles choose among the loop's own result and the finish at each weight (the
        grid widened by a decade, at most :data:`MAX_WIDEN` times, while the best weight sits at its edge): the
        finish may keep ``x``. Without them the finish at ``residual_tv`` is taken. ``x`` unchanged when
        ``finish_iter`` is 0 or the weight is 0. Records the choice in ``finish_info`` (``chosen``: ``"loop"`` or
        ``"finish"``; the weights also in ``mu_unit``, the unit they were given in), whether the result is the
        finish's nonnegative one (``nonnegative``), and logs which won."""
        choosing = validation is not None and bool(self.mu_candidates)
        grid = sorted(self.mu_candidates) if choosing else [self.residual_tv]
        self.nonnegative = False
        if self.finish_iter == 0 or max(grid) <= 0:
            return x
        with torch.no_grad():
            W = self.deformed(x[0])
            solves = {}
            for mu in grid:
                solves[mu] = self._solve(W, x[1], mu, validation)
            widened = []
            while choosing and len(widened) < MAX_WIDEN:
                best = min(solves, key=lambda m: solves[m][1])
                step = best * 10 if best == max(solves) else best / 10 if best == min(solves) and best > 0 else None
                if step is None or step in solves:
                    break
                solves[step] = self._solve(W, x[1], step, validation)
                widened.append(step)
            mu = min(solves, key=lambda m: solves[m][1]) if choosing else grid[0]
            loop = validation.residual(W + x[1]) if choosing else float("nan")
        keep = choosing and loop <= solves[mu][1]
        self.nonnegative = not keep
        self.finish_info = {"residual_tv": mu, "holdout_by_weight": {m: v[1] for m, v in sorted(solves.items())},
                            "iterations": self.finish_iter, "unit": self.mu_unit, "holdout_loop": loop,
                            "chosen": "loop" if keep else "finish", "widened": widened}
        _say(self.finish_info, choosing)
        return x if keep else (x[0], solves[mu][0] - W)

    def _solve(self, W, r, mu, validation) -> tuple:
        """``(f, held-out residual)`` of the finish at weight ``mu`` (the steps' norms from the first solve, kept in
        ``finish_norms`` for re-solves on the same operator)."""
        f, history = tv_reconstruction(self.ray_transform, self.data, 2 * mu, self.finish_iter, x0=W + r,
                                       nonneg=True, anchor=W, norms=self.finish_norms)   # ||.||^2 + mu' TV: mu' = 2 mu
        self.finish_norms = history["norms"]
        return f, validation.residual(f) if validation is not None else float("nan")

    def hparams(self) -> dict:
        return {"residual_tv": self.residual_tv, "residual_smoothing": self.smoothing}

    def coarsened(self, *args, **kwargs):
        raise TypeError("model='residual' has no coarse-to-fine form: solver 'algorithm1' or a torch.optim name")
