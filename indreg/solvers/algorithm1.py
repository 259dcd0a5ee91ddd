"""Algorithm 1 of the paper (alg:GradientDescentAlgorithm_1): fixed-step V-gradient descent on the velocity field."""
from __future__ import annotations

import math

import torch

from .._checks import check_int, check_positive
from .objective import IndirectRegistration, check_nonnegative
from .state import IterativeSolver, SolverState, make_info, problems


class Algorithm1(IterativeSolver):
    """Gradient descent ``nu <- nu - alpha grad_V E(nu)`` (eq:gradientflow), as the authors' code.

    ``grad_V E(nu)(t_i) = gamma nu_i - K(|D phi_{t_i,1}| (grad_data o phi_{t_i,1}) grad(I o phi_{t_i,0}))``
    (eq:GradGoalFunctionalVRHKS in the code's scale, see ``objective``; the mass-preserving version
    eq:GradGoalFunctionalVRHKS_mp comes from the deformation's backward with the same assembly). With
    ``nu = K m`` and ``grad_V E = K h`` (``h`` = L2 gradient, ``IndirectRegistration.l2_gradient``) the
    update is linear, so it runs on the momentum: ``m <- m - alpha h``, ``nu = K m`` (identical iterates
    in exact arithmetic; the regulariser ``<m, K m>`` stays exact).

    Args:
        problem: an ``IndirectRegistration``.
        step_size: ``alpha > 0`` (the paper's 0.02 / 0.04 work unchanged).
        max_iter: maximum number of iterations ``K``.
        grad_tol: stop when the gradient norm (``problem.gradient_norm``: the ``L2([0,1], L2)`` norm of
            the L2 gradient ``h``) is ``<= grad_tol``; 0 disables the test.
        step_halving: reject a step whose objective is non-finite, larger than the current one, or
            folds (``min Jacobian <= 0``); halve the step and retry, at most ``max_halvings`` times
            (the halved step is kept for later iterations). If all retries fail the iterate is kept and
            ``info["rejected"]`` is True. Without it such steps are taken and reported in ``info["warning"]``.
        jacobian_every: compute ``min_jacobian`` (one extra Jacobian recursion, about the cost of the
            deformation's forward) every this many iterations, ``nan`` in between; with ``step_halving``
            it is computed at every step (folding must be checked).

    ``step(state)`` performs one iteration and returns the report at the new iterate: objective, data_fit,
    regulariser, tv, grad_norm, min_jacobian (of ``phi_{1,0}``), step_size, evaluations (cumulative
    forward/backward evaluations, one per tried step plus one at the start), rejected, warning.
    The gradient at the new iterate is kept for the next step, so an iteration costs one evaluation.
    ``report(state)`` is that report at the current iterate without a step. After ``load_state_dict`` the
    first evaluation recomputes the cached gradient of the saved iterate and is not counted, so
    ``evaluations`` continues as in an uninterrupted run.
    """

    def __init__(self, problem: IndirectRegistration, step_size: float = 0.02, max_iter: int = 200,
                 grad_tol: float = 0.0, step_halving: bool = False, max_halvings: int = 10,
                 jacobian_every: int = 1):
        if not isinstance(problem, IndirectRegistration):
            raise TypeError(f"problem must be an IndirectRegistration, got {type(problem).__name__}")
        self.problem = problem
        self.step_size = check_positive(step_size, "step_size")
        self.max_iter = check_int(max_iter, "max_iter", 0)
        self.grad_tol = check_nonnegative(grad_tol, "grad_tol")
        self.step_halving = bool(step_halving)
        self.max_halvings = check_int(max_halvings, "max_halvings", 0)
        self.jacobian_every = check_int(jacobian_every, "jacobian_every", 1)
        self.evaluations = 0
        self._current = None   # (momentum tensor, its _version, terms, h, nu) of the last evaluation
        self._recount = False  # the next evaluation at the iterate recomputes one already counted

    def __repr__(self):
        return (f"Algorithm1(step_size={self.step_size}, max_iter={self.max_iter}, grad_tol={self.grad_tol}, "
                f"step_halving={self.step_halving})")

    def _evaluate(self, m, counted: bool = True):
        terms, h, nu = self.problem.l2_gradient(m)
        self.evaluations += int(counted)
        return terms, h, nu

    def _at(self, state: SolverState):
        """Terms, L2 gradient and velocity at ``state.momentum`` (cached from the previous step)."""
        m = state.momentum
        c = self._current
        if c is None or c[0] is not m or c[1] != m._version:
            self.problem.check_momentum(m)
            self._current = (m, m._version, *self._evaluate(m, counted=not self._recount))
            self._recount = False
        return self._current[2:]

    def _min_jacobian(self, nu, iteration: int) -> float:
        if self.step_halving or iteration % self.jacobian_every == 0:
            return self.problem.min_jacobian(nu)
        return math.nan

    def report(self, state: SolverState) -> dict:
        """The report at ``state.momentum`` (no step; ``min_jacobian`` always computed)."""
        terms, h, nu = self._at(state)
        min_jac = self.problem.min_jacobian(nu)
        return make_info(state.iteration, terms, self.problem.gradient_norm(h), min_jac, self.step_size,
                         self.evaluations, False, problems(terms["objective"], min_jac))

    def step(self, state: SolverState) -> dict:
        """One iteration ``m <- m - alpha h`` (with optional step halving); mutates ``state``; returns the report."""
        terms, h, _ = self._at(state)
        retries = self.max_halvings if self.step_halving else 0
        for attempt in range(retries + 1):
            alpha = self.step_size
            m_new = torch.add(state.momentum, h, alpha=-alpha)
            new_terms, new_h, new_nu = self._evaluate(m_new)
            min_jac = self._min_jacobian(new_nu, state.iteration + 1)
            warnings = problems(new_terms["objective"], min_jac, terms["objective"])
            if not (self.step_halving and warnings):
                break
            if attempt < retries:
                self.step_size = alpha / 2
        rejected = bool(self.step_halving and warnings)
        if rejected:
            warnings = [f"step rejected after {retries} halvings (kept the iterate): " + "; ".join(warnings)]
            new_terms, new_h = terms, h
            min_jac = self._min_jacobian(self._current[4], state.iteration + 1)
        else:
            state.momentum = m_new
            self._current = (m_new, m_new._version, new_terms, new_h, new_nu)
        state.iteration += 1
        return make_info(state.iteration, new_terms, self.problem.gradient_norm(new_h), min_jac, alpha,
                         self.evaluations, rejected, warnings)

    def state_dict(self) -> dict:
        """Step size (it may have been halved), the evaluation counter and whether it counts the iterate's."""
        return {"step_size": self.step_size, "evaluations": self.evaluations,
                "evaluated": self._current is not None}

    def load_state_dict(self, d: dict) -> None:
        self.step_size = check_positive(d["step_size"], "step_size")
        self.evaluations = int(d["evaluations"])
        self._current = None
        self._recount = bool(d["evaluated"])
