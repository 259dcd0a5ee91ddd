"""Any ``torch.optim`` optimizer on a parametrisation whose autograd gradient is the V-gradient."""
from __future__ import annotations

import copy
import math

import torch

from .._checks import check_int, check_positive
from ..deform.lddmm import BACKWARDS
from .objective import IndirectRegistration, check_nonnegative
from .state import IterativeSolver, SolverState, make_info, problems

_DEFAULTS = {
    # one solver iteration = one L-BFGS iteration; stopping is ours (grad_tol, max_iter), not L-BFGS's
    # (max_eval bounds the evaluations of one step: 1 + line search; torch's default 1.25 max_iter would
    # leave the line search no evaluation to shrink a step with)
    # history_size 10 (scipy's default; torch's 100 would keep 200 copies of the parameter: 2 GiB at 256^2)
    torch.optim.LBFGS: {"max_iter": 1, "max_eval": 25, "history_size": 10, "line_search_fn": "strong_wolfe",
                        "tolerance_grad": 0.0, "tolerance_change": 0.0},
}


def _optimizer_class(optimizer):
    if isinstance(optimizer, type) and issubclass(optimizer, torch.optim.Optimizer):
        return optimizer
    names = {name.lower(): getattr(torch.optim, name) for name in dir(torch.optim)
             if isinstance(getattr(torch.optim, name), type)
             and issubclass(getattr(torch.optim, name), torch.optim.Optimizer)}
    if not isinstance(optimizer, str) or optimizer.lower() not in names:
        raise ValueError(f"optimizer must be a torch.optim.Optimizer subclass or one of "
                         f"{sorted(n for n in names if n != 'optimizer')}, got {optimizer!r}")
    return names[optimizer.lower()]


def setup_common(solver, problem, optimizer, lr, max_iter, grad_tol, jacobian_every):
    """The attributes every ``torch.optim`` solver sets (``problem``, ``max_iter``, ``grad_tol``,
    ``jacobian_every``, ``scale = N / cell_volume``, ``lr``: 1.0 for L-BFGS, else required); returns the
    optimizer class."""
    solver.problem = problem
    solver.max_iter = check_int(max_iter, "max_iter", 0)
    solver.grad_tol = check_nonnegative(grad_tol, "grad_tol")
    solver.jacobian_every = check_int(jacobian_every, "jacobian_every", 1)
    solver.scale = problem.num_steps / problem.domain.cell_volume
    cls = _optimizer_class(optimizer)
    if lr is None and cls is not torch.optim.LBFGS:
        raise ValueError(f"lr is required for {cls.__name__} (see TorchOptimSolver for its scale)")
    solver.lr = check_positive(1.0 if lr is None else lr, "lr")
    return cls


class TorchOptimSolver(IterativeSolver):
    """Minimise E with a ``torch.optim`` optimizer over ``p``, where ``nu = K(s p)``, ``s = N / cell_volume``.

    Why this parametrisation: with ``m = s p`` the torch gradient is ``dE/dm = (cell_volume/N) K h``
    (``K`` is a symmetric matrix, ``h`` the L2 gradient of E w.r.t. ``nu``, see ``IndirectRegistration``),
    so ``dE/dp = s dE/dm = K h = grad_V E`` as a field: autograd's gradient is the V-gradient of
    Algorithm 1, and E(p) is an honest function of ``p``, so line searches (L-BFGS ``strong_wolfe``) see
    consistent values and directional derivatives. Plain SGD on ``p`` is ``nu <- nu - lr s K grad_V E``:
    V-gradient descent preconditioned once more by ``s K`` (not Algorithm 1; use ``Algorithm1`` for that),
    so its ``lr`` is much smaller than the paper's step sizes.

    Args:
        problem: an ``IndirectRegistration``.
        optimizer: "lbfgs", "adam", "sgd" (any ``torch.optim`` class name, case-insensitive) or a class.
        lr: learning rate (default 1.0 for L-BFGS; required otherwise).
        max_iter: number of solver iterations (one ``optimizer.step`` each; L-BFGS does one iteration
            per step: ``max_iter=1``, ``max_eval=25``, ``history_size=10`` are passed to it, with
            ``line_search_fn="strong_wolfe"`` and zero tolerances unless overridden in ``optimizer_kwargs``).
        grad_tol: stop when ``grad_norm`` (as ``Algorithm1``) is ``<= grad_tol``; 0 disables the test.
        backward: the deformation's backward; the problem's deformation is rebuilt with it if it differs.
            "exact" (default): the hand-written adjoint of the discrete forward map, the exact gradient at
            about the paper's cost; "autograd": the same gradient through autograd (about 2x the time and
            memory); "paper": the paper's continuous-gradient formula, whose mismatch with the discrete
            forward (e.g. ``nu(t_0)`` unused by eq:ODEflow1b) can make a line search fail.
        jacobian_every: compute ``min_jacobian`` every this many iterations (``nan`` in between).
        **optimizer_kwargs: passed to the optimizer.

    Evaluations (forward + backward of W and T) are counted by the closure; a closure call at a point
    already evaluated (L-BFGS re-evaluates the accepted line-search point) reuses the stored result. After
    ``load_state_dict`` the first evaluation recomputes the stored result at the saved parameter and is not
    counted, so ``evaluations`` continues as in an uninterrupted run. ``report(state)`` is the report at the
    current iterate without a step.
    """

    def __init__(self, problem: IndirectRegistration, optimizer="lbfgs", lr: float | None = None,
                 max_iter: int = 100, grad_tol: float = 0.0, backward: str = "exact", jacobian_every: int = 1,
                 **optimizer_kwargs):
        if not isinstance(problem, IndirectRegistration):
            raise TypeError(f"problem must be an IndirectRegistration, got {type(problem).__name__}")
        if backward not in BACKWARDS:
            raise ValueError(f"backward must be one of {BACKWARDS}, got {backward!r}")
        if backward != problem.deformation.backward:
            W = problem.deformation
            problem = problem.with_deformation(type(W)(W.domain, W.num_steps, W.action, backward,
                                                       W.interpolation, W.scheme))
        cls = setup_common(self, problem, optimizer, lr, max_iter, grad_tol, jacobian_every)
        self.parameter = torch.nn.Parameter(problem.zero_momentum())
        kwargs = {**_DEFAULTS.get(cls, {}), **optimizer_kwargs}
        self.optimizer = cls([self.parameter], lr=self.lr, **kwargs)
        self.evaluations = 0
        self._cache = None      # (p clone, terms, grad, h, nu) of the last evaluation
        self._synced = None     # (momentum tensor, its _version) written by the last step
        self._recount = None    # a saved parameter whose evaluation was already counted

    def __repr__(self):
        return (f"TorchOptimSolver(optimizer={type(self.optimizer).__name__}, lr={self.lr}, "
                f"max_iter={self.max_iter}, grad_tol={self.grad_tol})")

    def _evaluate(self):
        """Objective and ``dE/dp`` at the current parameter (cached by value)."""
        p = self.parameter
        c = self._cache
        if c is not None and torch.equal(c[0], p.detach()):
            return c[1:]
        with torch.enable_grad():
            m = self.scale * p
            nu = self.problem.velocity(m)
            terms = self.problem.terms(m, nu)
            # dE/dnu at fixed m is (cell_volume/N)(gamma/2 m + L2 gradient of the matching term)
            grad, dnu = torch.autograd.grad(terms["objective"], (p, nu))
        m = m.detach()
        h = dnu / self.problem.time_weight + 0.5 * self.problem.gamma * m
        terms = {k: float(v.detach()) for k, v in terms.items()}
        recount = self._recount is not None and torch.equal(self._recount, p.detach())
        self.evaluations += int(not recount)
        self._recount = None
        self._cache = (p.detach().clone(), terms, grad, h, nu.detach())
        return self._cache[1:]

    def _closure(self):
        terms, grad, _, _ = self._evaluate()
        self.parameter.grad = grad.clone()
        return torch.tensor(terms["objective"], dtype=self.parameter.dtype)

    def _sync(self, state: SolverState) -> None:
        """Set ``p = m / s`` unless ``state.momentum`` is the one this solver wrote (bit-identical resume)."""
        m = state.momentum
        if self._synced is not None and self._synced[0] is m and self._synced[1] == m._version:
            return
        self.problem.check_momentum(m)
        p = self.parameter.detach()
        if not torch.equal(self.scale * p, m):
            with torch.no_grad():
                p.copy_(m / self.scale)

    def report(self, state: SolverState) -> dict:
        """The report at ``state.momentum`` (no step; ``min_jacobian`` always computed)."""
        self._sync(state)
        terms, _, h, nu = self._evaluate()
        min_jac = self.problem.min_jacobian(nu)
        return make_info(state.iteration, terms, self.problem.gradient_norm(h), min_jac, self.lr,
                         self.evaluations, False, problems(terms["objective"], min_jac))

    def step(self, state: SolverState) -> dict:
        """One ``optimizer.step``; mutates ``state``; returns the report at the new iterate."""
        self._sync(state)
        previous = self._evaluate()[0]["objective"]
        self.optimizer.step(self._closure)
        terms, _, h, nu = self._evaluate()
        if (state.iteration + 1) % self.jacobian_every == 0:
            min_jac = self.problem.min_jacobian(nu)
        else:
            min_jac = math.nan
        warnings = problems(terms["objective"], min_jac, previous)
        state.momentum = (self.scale * self.parameter).detach()
        self._synced = (state.momentum, state.momentum._version)
        state.iteration += 1
        step_size = self.optimizer.state[self.parameter].get("t", self.lr) \
            if isinstance(self.optimizer, torch.optim.LBFGS) else self.lr
        return make_info(state.iteration, terms, self.problem.gradient_norm(h), min_jac, step_size,
                         self.evaluations, False, warnings)

    def state_dict(self) -> dict:
        """Optimizer internals (Adam moments, L-BFGS history), the parameter ``p`` and the evaluation counter."""
        return {"optimizer": copy.deepcopy(self.optimizer.state_dict()),
                "parameter": self.parameter.detach().clone(), "evaluations": self.evaluations,
                "evaluated": self._cache is not None and torch.equal(self._cache[0], self.parameter.detach())}

    def load_state_dict(self, d: dict) -> None:
        with torch.no_grad():
            self.parameter.copy_(d["parameter"])
        self.optimizer.load_state_dict(copy.deepcopy(d["optimizer"]))
        self.evaluations = int(d["evaluations"])
        self._cache = None
        self._synced = None
        self._recount = self.parameter.detach().clone() if d["evaluated"] else None
