"""Any ``torch.optim`` optimizer on a parametrisation whose autograd gradient is the V-gradient."""
from __future__ import annotations

import copy
import math

import torch

from .._checks import check_int, check_positive
from .algorithm1 import check_problem
from .._checks import check_nonnegative
from ..options import default
from ..problems.problem import RegistrationProblem
from .state import IterativeSolver, SolverState, is_marked, make_info, mark, problems, rounding_tolerance

_DEFAULTS = {
    # one solver iteration = one L-BFGS iteration; stopping is ours (grad_tol, max_iter), not L-BFGS's
    # (max_eval bounds the evaluations of one step: 1 + line search; torch's default 1.25 max_iter would
    # leave the line search no evaluation to shrink a step with)
    # history_size 10 (scipy's default; torch's 100 would keep 200 copies of the parameter: 2 GiB at 256^2)
    torch.optim.LBFGS: {"max_iter": 1, "max_eval": 25, "history_size": 10, "line_search_fn": "strong_wolfe",
                        "tolerance_grad": 0.0, "tolerance_change": 0.0},
}


def _optimizer_class(optimizer):
    """The optimizer class of a name or class; the abstract base ``torch.optim.Optimizer`` is not one."""
    base = torch.optim.Optimizer
    if isinstance(optimizer, type) and issubclass(optimizer, base) and optimizer is not base:
        return optimizer
    names = {name.lower(): getattr(torch.optim, name) for name in dir(torch.optim)
             if isinstance(getattr(torch.optim, name), type) and getattr(torch.optim, name) is not base
             and issubclass(getattr(torch.optim, name), base)}
    if not isinstance(optimizer, str) or optimizer.lower() not in names:
        raise ValueError(f"optimizer must be a subclass of torch.optim.Optimizer (not the base class itself) or "
                         f"one of {sorted(names)}, got {optimizer!r}")
    return names[optimizer.lower()]


class TorchOptimSolver(IterativeSolver):
    """Minimise E with a ``torch.optim`` optimizer over ``p = (p_0, p_1, ...)``, iterate ``x_k = s p_k``,
    ``s = N / cell_volume`` (LDDMM: ``nu = K(s p)``).

    Why this parametrisation: with ``m = s p`` the torch gradient is ``dE/dm = (cell_volume/N) K h``
    (``K`` is a symmetric matrix, ``h`` the L2 gradient of E w.r.t. ``nu``, see ``IndirectRegistration``),
    so ``dE/dp = s dE/dm = K h = grad_V E`` as a field: autograd's gradient is the V-gradient of
    Algorithm 1, and E(p) is an honest function of ``p``, so line searches (L-BFGS ``strong_wolfe``) see
    consistent values and directional derivatives (metamorphosis' source likewise: ``dE/dq`` is its L2 gradient,
    or its RKHS gradient with a source kernel). Plain SGD on ``p`` is ``nu <- nu - lr s K grad_V E``:
    V-gradient descent preconditioned once more by ``s K`` (not Algorithm 1; use ``Algorithm1`` for that),
    so its ``lr`` is much smaller than the paper's step sizes.

    Parameters
    ----------
    problem : RegistrationProblem
        The objective to minimise.
    optimizer : str or type
        ``"lbfgs"``, ``"adam"``, ``"sgd"`` (any ``torch.optim`` class name, case-insensitive) or a subclass of
        ``torch.optim.Optimizer``.
    lr : float, optional
        Learning rate of the momentum (default 1.0 for L-BFGS; required otherwise).
    max_iter : int
        Number of solver iterations (one ``optimizer.step`` each; L-BFGS does one iteration per step:
        ``max_iter=1``, ``max_eval=25``, ``history_size=10`` are passed to it, with
        ``line_search_fn="strong_wolfe"`` and zero tolerances unless overridden in ``optimizer_kwargs``).
    grad_tol : float
        Stop when ``grad_norm`` (as ``Algorithm1``) is ``<= grad_tol``; 0 disables the test.
    backward : str, optional
        The deformation's backward; None (default): ``problem.for_line_search()`` (LDDMM's ``"paper"`` becomes
        ``"exact"``, the hand-written adjoint of the discrete forward map: the exact gradient at about the
        paper's cost); ``"autograd"``: the same gradient through autograd (about 2x the time and memory); LDDMM's
        ``"paper"`` (the continuous-gradient formula, whose mismatch with the discrete forward can make a line
        search fail) only when asked for.
    jacobian_every : int
        Compute ``min_jacobian`` every this many iterations (``nan`` in between).
    lrs : dict, optional
        Learning rates of the entries after the momentum by name (default ``lr``; L-BFGS takes one parameter
        group, so they must equal ``lr``).
    **optimizer_kwargs
        Passed to the optimizer.

    Raises
    ------
    TypeError
        ``problem`` is no registration problem.
    ValueError
        An unknown optimizer, no ``lr`` for an optimizer other than L-BFGS, a rate that is not positive,
        ``lrs`` naming no entry after the momentum or differing from ``lr`` with L-BFGS, a count out of range.

    Notes
    -----
    Evaluations (forward + backward of W and T) are counted by the closure; a closure call at a point
    already evaluated (L-BFGS re-evaluates the accepted line-search point) reuses the stored result. After
    ``load_state_dict`` the first evaluation recomputes the stored result at the saved parameters and is not
    counted, so ``evaluations`` continues as in an uninterrupted run. ``report(state)`` is the report at the
    current iterate without a step.
    """

    def __init__(self, problem: RegistrationProblem, optimizer="lbfgs", lr: float | None = None,
                 max_iter: int = default("max_iter"), grad_tol: float = default("grad_tol"),
                 backward: str | None = None, jacobian_every: int = 1,
                 lrs: dict | None = None, **optimizer_kwargs):
        check_problem(problem)
        if backward is None:
            problem = problem.for_line_search()
        elif backward != problem.deformation.backward:
            problem = problem.with_backward(backward)
        self.problem = problem
        self.names = tuple(problem.iterate_names)
        self.max_iter = check_int(max_iter, "max_iter", 0)
        self.grad_tol = check_nonnegative(grad_tol, "grad_tol")
        self.jacobian_every = check_int(jacobian_every, "jacobian_every", 1)
        self.scale = problem.num_steps / problem.domain.cell_volume
        cls = _optimizer_class(optimizer)
        if lr is None and cls is not torch.optim.LBFGS:
            raise ValueError(f"lr is required for {cls.__name__} (see TorchOptimSolver for its scale)")
        self.lr = check_positive(1.0 if lr is None else lr, "lr", problem.template.dtype)
        lrs = dict(lrs or {})
        for key in lrs:
            if key not in self.names[1:]:
                raise ValueError(f"lrs name entries of the iterate after the momentum {self.names[1:]}, got {key!r}")
        self.lrs = [self.lr] + [self.lr if lrs.get(n) is None else check_positive(lrs[n], f"{n}_lr", problem.template.dtype)
                                for n in self.names[1:]]
        self.parameters = [torch.nn.Parameter(x) for x in problem.zero_iterate()]
        if cls is torch.optim.LBFGS:
            if any(r != self.lr for r in self.lrs):
                raise ValueError(f"L-BFGS takes one parameter group: the learning rates of {self.names} must be "
                                 f"equal, got {self.lrs}")
            groups = [{"params": self.parameters}]
        else:
            groups = [{"params": [p], "lr": r} for p, r in zip(self.parameters, self.lrs)]
        self.optimizer = cls(groups, lr=self.lr, **{**_DEFAULTS.get(cls, {}), **optimizer_kwargs})
        self.evaluations = 0
        self._cache = None      # (p clones, terms, grads, h, nu) of the last evaluation
        self._synced = None     # mark of the iterate written by the last step
        self._recount = None    # saved parameters whose evaluation was already counted

    @property
    def parameter(self) -> torch.nn.Parameter:
        """The momentum's parameter ``p_0 = m / s``."""
        return self.parameters[0]

    def reported_step(self) -> float:
        return float(self.lr)

    def __repr__(self):
        return (f"TorchOptimSolver(optimizer={type(self.optimizer).__name__}, lr={self.lr}, "
                f"max_iter={self.max_iter}, grad_tol={self.grad_tol})")

    def _at_cache(self, c) -> bool:
        return c is not None and all(torch.equal(a, p.detach()) for a, p in zip(c, self.parameters))

    def _evaluate(self):
        """Objective, ``dE/dp``, the L2 gradients and ``nu`` at the current parameters (cached by value)."""
        if self._at_cache(None if self._cache is None else self._cache[0]):
            return self._cache[1:]
        k = len(self.parameters)
        with torch.enable_grad():
            x = tuple(self.scale * p for p in self.parameters)
            terms, aux, l2 = self.problem.differentiable(x)
            grads = torch.autograd.grad(terms["objective"], (*self.parameters, *aux))
        h = l2(tuple(t.detach() for t in x), grads[:k], grads[k:])
        terms = {key: float(v.detach()) for key, v in terms.items()}
        self.evaluations += int(not self._at_cache(self._recount))
        self._recount = None
        self._cache = (tuple(p.detach().clone() for p in self.parameters), terms, grads[:k], h, aux[0].detach())
        return self._cache[1:]

    def _closure(self):
        terms, grads, _, _ = self._evaluate()
        for p, g in zip(self.parameters, grads):
            p.grad = g.clone()
        return torch.tensor(terms["objective"], dtype=self.parameter.dtype)

    def _sync(self, state: SolverState) -> None:
        """Set ``p = x / s`` unless ``state.iterate`` is the one this solver wrote (bit-identical resume)."""
        x = state.iterate
        if is_marked(x, self._synced):
            return
        self.problem.check_iterate(x)
        with torch.no_grad():
            for p, xk in zip(self.parameters, x):
                if not torch.equal(self.scale * p, xk):
                    p.copy_(xk / self.scale)

    def _info(self, iteration, terms, h, min_jac, step_size, previous=None) -> dict:
        return make_info(iteration, terms, [self.problem.gradient_norm(g) for g in h], min_jac,
                         [step_size, *self.lrs[1:]], self.evaluations, False,
                         problems(terms["objective"], min_jac, previous, rounding_tolerance(self.parameter.dtype)),
                         self.names)

    def report(self, state: SolverState) -> dict:
        """The report at ``state.iterate`` (no step; ``min_jacobian`` always computed)."""
        self._sync(state)
        terms, _, h, nu = self._evaluate()
        return self._info(state.iteration, terms, h, self.problem.min_jacobian(nu), self.lr)

    def step(self, state: SolverState) -> dict:
        """One ``optimizer.step``; mutates ``state``; returns the report at the new iterate."""
        self._sync(state)
        previous = self._evaluate()[0]["objective"]
        self.optimizer.step(self._closure)
        terms, _, h, nu = self._evaluate()
        min_jac = self.problem.min_jacobian(nu) if (state.iteration + 1) % self.jacobian_every == 0 else math.nan
        state.iterate = tuple((self.scale * p).detach() for p in self.parameters)
        self._synced = mark(state.iterate)
        state.iteration += 1
        step_size = self.optimizer.state[self.parameter].get("t", self.lr) \
            if isinstance(self.optimizer, torch.optim.LBFGS) else self.lr
        return self._info(state.iteration, terms, h, min_jac, step_size, previous)

    def state_dict(self) -> dict:
        """Optimizer internals (Adam moments, L-BFGS history), the parameters ``p`` and the evaluation counter."""
        return {"optimizer": copy.deepcopy(self.optimizer.state_dict()),
                "parameters": [p.detach().clone() for p in self.parameters], "evaluations": self.evaluations,
                "evaluated": self._cache is not None and self._at_cache(self._cache[0])}

    def load_state_dict(self, d: dict) -> None:
        with torch.no_grad():
            for p, saved in zip(self.parameters, d["parameters"]):
                p.copy_(saved)
        self.optimizer.load_state_dict(copy.deepcopy(d["optimizer"]))
        self.evaluations = check_int(d["evaluations"], "evaluations", 0)
        self._cache = None
        self._synced = None
        self._recount = tuple(p.detach().clone() for p in self.parameters) if d["evaluated"] else None
