"""The intertwined solver of the spatiotemporal model with an unknown template (``indreg.problems.spatiotemporal``):
every outer iteration a TV reconstruction of the template from all frames pulled back through the current motion,
then Algorithm 1's steps on the momentum.

Notes
-----
as :mod:`indreg.problems.spatiotemporal` (the iterate ``x = (m, I)``).
"""
from __future__ import annotations

import torch

from ..problems.spatiotemporal import FramesOfTemplate

__all__ = ["IntertwinedSolver"]


class IntertwinedSolver:
    """The intertwined scheme for an unknown template (``SpatiotemporalRegistration`` with iterate ``(m, I)``):
    every ``registration_steps`` iterations (an *outer iteration*) the template is reconstructed from all frames
    pulled back through the current deformations, ``I <- argmin (1/2) sum_k ||T_k W(phi_{0,t_k}, I) - g_k||^2 +
    template_tv_weight TV(I)`` by ``template_steps`` Chambolle-Pock iterations (equal steps) warm-started at the
    current ``I`` (``tv_reconstruction`` on :class:`FramesOfTemplate`; ``mu = 2 template_tv_weight``: its objective
    is twice ours), then ``registration_steps`` Algorithm 1 steps move the momentum with ``I`` fixed.

    Wraps ``inner``, an ``Algorithm1`` on the same problem whose ``cycle`` keeps the template fixed, whose report,
    stopping rule and state (step sizes, evaluations) are this solver's: a checkpoint of it resumes the same
    sequence (the template steps are deterministic and fall on ``iteration % registration_steps == 0``).

    Notes
    -----
    the iterate ``(m, I)`` as ``SpatiotemporalRegistration``'s (template unknown); one iteration of
    this solver is one Algorithm 1 step, an outer iteration ``registration_steps`` of them.
    """

    def __init__(self, inner, template_steps: int = 50, registration_steps: int = 10, template_tv_weight=0.0):
        from .._checks import check_int

        if inner.moving(0) != {0}:
            raise ValueError("inner must be an Algorithm1 that moves only the momentum (cycle=((('momentum',), 1),))")
        self.inner = inner
        self.problem, self.max_iter, self.grad_tol = inner.problem, inner.max_iter, inner.grad_tol
        self.template_steps = check_int(template_steps, "template_steps", 1)
        self.registration_steps = check_int(registration_steps, "registration_steps", 1)
        self.mu = 2.0 * float(template_tv_weight)

    def reported_step(self) -> float:
        return self.inner.reported_step()

    def __repr__(self):
        return (f"IntertwinedSolver(TV reconstruction of the template: {self.template_steps} iterations, mu="
                f"{self.mu:g}, then {self.registration_steps} steps of {self.inner!r})")

    @property
    def step_size(self) -> float:
        return self.inner.step_size

    @property
    def step_sizes(self) -> list:
        return self.inner.step_sizes

    @property
    def step_halving(self) -> bool:
        return self.inner.step_halving

    @property
    def halves_steps(self) -> bool:
        return self.inner.halves_steps

    def reconstruct_template(self, x: tuple) -> torch.Tensor:
        """The template step at ``x = (m, I)``: ``template_steps`` Chambolle-Pock iterations from ``I``."""
        from ..forward.tv import tv_reconstruction

        A = FramesOfTemplate(self.problem, self.problem.velocity(x[0]))
        if self.mu > 0:
            # equal steps: the few warm-started iterations per outer step were tuned with them (the balanced ones,
            # duals restarted at 0 each time, move the template less: SSIM 0.585 against 0.692, docs/spatiotemporal.md)
            return tv_reconstruction(A, self.problem.data, self.mu, self.template_steps, x0=x[1], opnorm_iter=20,
                                     balanced=False)[0]
        step = 1.0 / (1.1 * _norm(A)) ** 2           # plain least squares: Landweber
        template = x[1]
        for _ in range(self.template_steps):
            template = template - step * A.adjoint(A(template) - self.problem.data)
        return template

    def step(self, state) -> dict:
        if state.iteration % self.registration_steps == 0:
            with torch.no_grad():
                state.template = self.reconstruct_template(state.iterate)
        return self.inner.step(state)

    def report(self, state) -> dict:
        return self.inner.report(state)

    def status(self, info: dict):
        return self.inner.status(info)

    def failed(self, info: dict) -> bool:
        return self.inner.failed(info)

    def state_dict(self) -> dict:
        return self.inner.state_dict()

    def load_state_dict(self, d: dict) -> None:
        self.inner.load_state_dict(d)


def _norm(A) -> float:
    """``||A||`` by 20 power iterations."""
    from ..forward.operator import operator_norm

    return operator_norm(A, 20, A.problem.data.dtype, A.problem.data.device)
