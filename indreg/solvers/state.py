"""Solver state (for checkpoints) and the per-iteration report shared by the solvers."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class SolverState:
    """The iterate of a registration solver: momentum ``m`` (``nu = K m``) and the iteration count.

    Convention: ``momentum (N+1, 2, nx, ny)`` at ``t_i = i/N``. Solvers replace ``momentum`` by a new
    tensor at every accepted step (they never modify it in place). Optimizer internals (Adam moments,
    L-BFGS history, step size) live in ``solver.state_dict()``; save both to resume bit-identically.
    """

    momentum: torch.Tensor
    iteration: int = 0

    def state_dict(self) -> dict:
        return {"momentum": self.momentum.detach().clone(), "iteration": int(self.iteration)}

    def load_state_dict(self, d: dict) -> None:
        self.momentum = d["momentum"].detach().clone()
        self.iteration = int(d["iteration"])

    @classmethod
    def from_state_dict(cls, d: dict) -> "SolverState":
        state = cls(momentum=d["momentum"])
        state.load_state_dict(d)
        return state


def problems(objective: float, min_jacobian: float, previous: float | None = None) -> list:
    """Warnings for an iterate: non-finite objective, folding (min Jacobian <= 0; nan = not computed),
    increase over ``previous``."""
    out = []
    if not math.isfinite(objective):
        out.append(f"non-finite objective ({objective})")
    if min_jacobian <= 0:
        out.append(f"folding: min Jacobian determinant {min_jacobian:.4g} <= 0")
    if previous is not None and math.isfinite(objective) and objective > previous:
        out.append(f"objective increased from {previous:.10g} to {objective:.10g}")
    return out


def make_info(iteration, terms, grad_norm, min_jacobian, step_size, evaluations, rejected, warnings) -> dict:
    """The per-iteration report (python floats) returned by ``solver.step``."""
    return {"iteration": int(iteration), "objective": terms["objective"], "data_fit": terms["data_fit"],
            "regulariser": terms["regulariser"], "tv": terms["tv"], "grad_norm": float(grad_norm),
            "min_jacobian": float(min_jacobian), "step_size": float(step_size),
            "evaluations": int(evaluations), "rejected": bool(rejected), "warning": "; ".join(warnings)}


class IterativeSolver:
    """What every solver shares: the stopping rule and the loop. Subclasses set ``max_iter``, ``grad_tol``
    and implement ``step(state) -> info`` and ``report(state) -> info`` (the report at the current iterate,
    no step)."""

    max_iter: int
    grad_tol: float

    def failed(self, info: dict) -> bool:
        """True on a non-finite objective or gradient norm: the iteration broke down."""
        return not (math.isfinite(info["objective"]) and math.isfinite(info["grad_norm"]))

    def converged(self, info: dict) -> bool:
        """True when ``grad_norm <= grad_tol`` (``grad_tol > 0``) at a finite iterate."""
        return self.grad_tol > 0 and not self.failed(info) and info["grad_norm"] <= self.grad_tol

    def status(self, info: dict):
        """Why the loop stops after ``info``: "failed", "converged", "completed" (``max_iter``), or None."""
        if self.failed(info):
            return "failed"
        if self.converged(info):
            return "converged"
        return "completed" if info["iteration"] >= self.max_iter else None

    def run(self, state: SolverState, callback=None) -> dict:
        """Iterate ``step`` until ``status`` is not None; ``callback(state, info)`` after every step.

        Returns the last report with ``status`` added; without any step (``state.iteration >= max_iter``)
        the report of the current iterate (``report(state)``). Never raises on a non-finite objective: check
        ``info["status"] == "failed"``.
        """
        if state.iteration >= self.max_iter:
            info = self.report(state)
            return dict(info, status="failed" if self.failed(info) else "completed")
        while True:
            info = self.step(state)
            if callback is not None:
                callback(state, info)
            status = self.status(info)
            if status is not None:
                return dict(info, status=status)
