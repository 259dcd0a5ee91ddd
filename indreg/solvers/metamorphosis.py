"""The solvers of metamorphosis (``indreg.problems.metamorphosis``): Algorithm 1 on ``(nu, zeta)`` with the
source's own step (``MetamorphosisDescent``), and torch.optim on both (``MetamorphosisTorchOptim``).

Notes
-----
as :mod:`indreg.problems.metamorphosis` (the iterate ``x = (m, s)``).
"""
from __future__ import annotations

import torch

from ..options import default
from ..problems.metamorphosis import MetamorphosisRegistration
from .algorithm1 import Algorithm1
from .state import SolverState
from .torch_optim import TorchOptimSolver

__all__ = ["MetamorphosisState", "MetamorphosisDescent", "MetamorphosisTorchOptim"]


class MetamorphosisState(SolverState):
    """The iterate of a metamorphosis solver: momentum ``m`` (``nu = K m``), source iterate ``s`` (``(N+1, *shape)``;
    ``zeta = problem.source(s)``: ``s`` itself for the L2 source), iteration count (``SolverState`` with
    ``source``).

    Parameters
    ----------
    momentum : torch.Tensor
        ``m``, ``(N+1, d, *shape)``.
    iteration : int
        Iterations done.
    source : torch.Tensor, optional
        ``s``, ``(N+1, *shape)``.
    """

    def __init__(self, momentum: torch.Tensor, iteration: int = 0, source: torch.Tensor | None = None):
        super().__init__(momentum, iteration, source=source)

    @classmethod
    def zeros(cls, problem: MetamorphosisRegistration) -> "MetamorphosisState":
        return cls(problem.zero_momentum(), 0, problem.zero_source())


def _check_problem(problem):
    if not isinstance(problem, MetamorphosisRegistration):
        raise TypeError(f"problem must be a MetamorphosisRegistration, got {type(problem).__name__}")


class MetamorphosisDescent(Algorithm1):
    """``Algorithm1`` on ``x = (m, s)`` with separate step sizes for ``nu`` and ``zeta``:

    - ``m <- m - alpha h_nu`` (``nu = K m``: ``nu <- nu - alpha grad_V E``, as Algorithm 1);
    - ``s <- s - beta h_s`` (L2 gradient step on ``zeta = s``; with ``source_kernel``
      ``zeta <- zeta - beta K_s h_s``).

    Parameters
    ----------
    problem : MetamorphosisRegistration
        The objective.
    step_size : float, optional
        ``alpha > 0`` (the paper's Algorithm 1 step sizes work unchanged); None: relative to the data term (as
        ``Algorithm1``).
    source_step_size : float or "auto"
        ``beta > 0``, or ``"auto"``: ``1 / ((tau + ||T||^2) ||K_s||)`` (``problem.source_lipschitz``).
    max_iter, grad_tol : int, float
        As ``Algorithm1``; ``grad_norm`` is ``sqrt(|h_nu|^2 + |h_zeta|^2)`` (both ``L2([0,1], L2)`` norms), also
        reported separately (``velocity_grad_norm``, ``source_grad_norm``).
    step_halving, max_halvings : bool, int
        Reject a step whose objective is non-finite, larger than the current one, or folds; halve both step
        sizes and retry, at most ``max_halvings`` times (``StepControl``).
    jacobian_every : int
        Compute ``min_jacobian`` every this many iterations (always with ``step_halving``).
    source_start : int
        The source is kept fixed for the first ``source_start`` iterations (Algorithm 1 on ``nu`` alone: the
        deformation first explains what it can, then the source the remainder); 0 (default) updates both from
        the start.

    Raises
    ------
    TypeError
        ``problem`` is no ``MetamorphosisRegistration``.
    ValueError
        As ``Algorithm1``.
    """

    def __init__(self, problem: MetamorphosisRegistration, step_size: float | None = None, source_step_size="auto",
                 max_iter: int = default("max_iter"), grad_tol: float = default("grad_tol"),
                 step_halving: bool = default("step_halving", app=True), max_halvings: int = default("max_halvings"),
                 jacobian_every: int = 1, source_start: int = 0):
        _check_problem(problem)
        super().__init__(problem, step_size, max_iter, grad_tol, step_halving, max_halvings, jacobian_every,
                         steps={"source": None if source_step_size == "auto" else source_step_size},
                         frozen={"source": source_start})

    @property
    def source_step_size(self) -> float:
        return self.step_sizes[1]

    @property
    def source_start(self) -> int:
        return self.frozen.get(1, 0)


class MetamorphosisTorchOptim(TorchOptimSolver):
    """``TorchOptimSolver`` on ``x = (m, s)``: ``nu = K(c p)``, source iterate ``c q``, ``c = N / cell_volume``;
    ``lr`` applies to ``p``, ``source_lr`` (default ``lr``) to ``q`` (L-BFGS takes one parameter group, so it needs
    ``source_lr`` unset or equal to ``lr``).

    Parameters
    ----------
    problem : MetamorphosisRegistration
        The objective.
    optimizer, lr, max_iter, grad_tol, jacobian_every, **optimizer_kwargs
        As ``TorchOptimSolver``.
    source_lr : float, optional
        The source's learning rate (default ``lr``).
    backward : {"adjoint", "autograd"}
        The metamorphosis deformation's backward: the exact custom backward (default) or autograd.

    Raises
    ------
    TypeError
        ``problem`` is no ``MetamorphosisRegistration``.
    ValueError
        As ``TorchOptimSolver``.
    """

    def __init__(self, problem: MetamorphosisRegistration, optimizer="lbfgs", lr: float | None = None,
                 source_lr: float | None = None, max_iter: int = default("max_iter"),
                 grad_tol: float = default("grad_tol"),
                 backward: str = "adjoint", jacobian_every: int = 1, **optimizer_kwargs):
        _check_problem(problem)
        super().__init__(problem, optimizer, lr, max_iter, grad_tol, backward, jacobian_every,
                         lrs={"source": source_lr}, **optimizer_kwargs)

    @property
    def source_lr(self) -> float:
        return self.lrs[1]
