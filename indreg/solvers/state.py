"""Solver state (for checkpoints), step control and the per-iteration report shared by the solvers."""
from __future__ import annotations

import math

import torch


class SolverState:
    """The iterate ``x = (m, ...)`` of a registration solver and the iteration count.

    ``momentum`` is the first entry (``nu = K m``); further entries are named by the problem's ``iterate_names``
    and passed by name (metamorphosis: ``SolverState(m, 0, source=s)``), read and set as attributes
    (``state.source``). ``iterate`` is the tuple. Solvers replace entries by new tensors at every accepted step
    (never in place). Optimizer internals (Adam moments, L-BFGS history, step size) live in
    ``solver.state_dict()``; save both to resume bit-identically.

    Parameters
    ----------
    momentum : torch.Tensor
        ``m``, ``(N+1, d, *shape)`` at ``t_i = i/N``.
    iteration : int
        Iterations done.
    **rest : torch.Tensor
        The further entries of the iterate by name, in the problem's ``iterate_names`` order (as their problem
        says).
    """

    def __init__(self, momentum: torch.Tensor, iteration: int = 0, **rest):
        object.__setattr__(self, "names", ("momentum", *rest))
        object.__setattr__(self, "iterate", (momentum, *rest.values()))
        object.__setattr__(self, "iteration", int(iteration))

    @classmethod
    def initial(cls, problem) -> "SolverState":
        """``x = problem.zero_iterate()`` at iteration 0."""
        x = problem.zero_iterate()
        return cls(x[0], 0, **dict(zip(problem.iterate_names[1:], x[1:])))

    def __getattr__(self, name):
        names = self.__dict__.get("names", ())
        if name in names:
            return self.iterate[names.index(name)]
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")

    def __setattr__(self, name, value):
        if name in self.names:
            x = list(self.iterate)
            x[self.names.index(name)] = value
            value, name = tuple(x), "iterate"
        object.__setattr__(self, name, value)

    def __repr__(self):
        shapes = ", ".join(f"{n}={tuple(t.shape)}" for n, t in zip(self.names, self.iterate))
        return f"{type(self).__name__}({shapes}, iteration={self.iteration})"

    def state_dict(self) -> dict:
        return {"iteration": int(self.iteration), **{n: t.detach().clone() for n, t in zip(self.names, self.iterate)}}

    def load_state_dict(self, d: dict) -> None:
        self.iterate = tuple(d[n].detach().clone() for n in self.names)
        self.iteration = int(d["iteration"])

    @classmethod
    def from_state_dict(cls, d: dict) -> "SolverState":
        state = cls(d["momentum"], **{k: v for k, v in d.items() if k not in ("momentum", "iteration")})
        state.load_state_dict(d)
        return state


def rounding_tolerance(dtype: torch.dtype) -> float:
    """Relative objective changes within floating-point rounding: ``100 eps`` of the run's dtype (float32
    1.2e-5, float64 2.2e-14). The objective sums every data value and pixel, so its float32 rounding reaches
    about 1e-5 of its value: float32 cannot tell suite 1's increase from 183.6354 to 183.6369 (8e-6, paper's
    fixed step) from rounding."""
    return 100.0 * torch.finfo(dtype).eps


def problems(objective: float, min_jacobian: float, previous: float | None = None, rtol: float = 0.0) -> list:
    """Warnings for an iterate: non-finite objective, folding (min Jacobian <= 0; nan = not computed),
    increase over ``previous`` by more than ``rtol |previous|`` (``rounding_tolerance``: smaller increases are
    rounding, not a warning)."""
    out = []
    if not math.isfinite(objective):
        out.append(f"non-finite objective ({objective})")
    if min_jacobian <= 0:
        out.append(f"folding: min Jacobian determinant {min_jacobian:.4g} <= 0")
    if previous is not None and math.isfinite(objective) and objective > previous + rtol * abs(previous):
        out.append(f"objective increased from {previous:.10g} to {objective:.10g}")
    return out


def make_info(iteration, terms, grad_norms, min_jacobian, step_sizes, evaluations, rejected, warnings,
              names=("momentum",), halvings: int = 0) -> dict:
    """The per-iteration report (python floats) returned by ``solver.step``.

    ``grad_norm`` is the norm of the whole gradient (``hypot`` of the entries' ``L2([0,1], L2)`` norms) and
    ``step_size`` the momentum's step (``halvings``: how many times step control halved it in this iteration);
    an iterate of several entries adds ``velocity_grad_norm`` and, per further
    entry ``<name>``, ``<name>_grad_norm`` and ``<name>_step_size``. Every term of ``terms`` is reported.
    """
    grad_norms, step_sizes = tuple(grad_norms), tuple(step_sizes)
    info = {"iteration": int(iteration), "objective": terms["objective"], "data_fit": terms["data_fit"],
            "regulariser": terms["regulariser"], "tv": terms["tv"]}
    info.update({k: v for k, v in terms.items() if k not in info})
    info.update(grad_norm=float(math.hypot(*grad_norms)), min_jacobian=float(min_jacobian),
                step_size=float(step_sizes[0]), halvings=int(halvings), evaluations=int(evaluations),
                rejected=bool(rejected), warning="; ".join(warnings))
    if len(names) > 1:
        info["velocity_grad_norm"] = float(grad_norms[0])
        for name, g, s in zip(names[1:], grad_norms[1:], step_sizes[1:]):
            info[f"{name}_grad_norm"], info[f"{name}_step_size"] = float(g), float(s)
    return info


class StepControl:
    """Safeguarded descent steps on any iterate (a tuple of tensors).

    ``search(steps, objective, trial, rtol)`` calls ``trial(steps) -> (result, new_objective, min_jacobian)``;
    with ``halving`` a trial whose objective is non-finite, larger than ``objective``, or whose deformation folds
    (``min_jacobian <= 0``) is rejected, every step size halved and the trial repeated, at most ``max_halvings``
    times (the halved sizes are kept for later iterations). Without ``halving`` the first trial is taken and its
    problems are only reported, an increase only when larger than ``rtol |objective|`` (``rounding_tolerance``).

    ``search`` returns ``(result, min_jacobian, steps_tried, warnings, rejected, halvings)``: ``rejected`` when
    every trial failed (the caller keeps its iterate); ``steps_tried`` are the sizes of the last trial;
    ``halvings`` how many times the sizes were halved.

    Parameters
    ----------
    halving : bool
        Halve and retry rejected steps.
    max_halvings : int
        The most halvings in one search.
    """

    def __init__(self, halving: bool, max_halvings: int):
        self.halving, self.max_halvings = bool(halving), int(max_halvings)

    def search(self, steps: list, objective: float, trial, rtol: float = 0.0) -> tuple:
        retries = self.max_halvings if self.halving else 0
        for attempt in range(retries + 1):
            tried = tuple(steps)
            result, new_objective, min_jac = trial(tried)
            warnings = problems(new_objective, min_jac, objective)
            if not (self.halving and warnings):
                return result, min_jac, tried, problems(new_objective, min_jac, objective, rtol), False, attempt
            if attempt < retries:
                steps[:] = [s / 2 for s in steps]
        return result, min_jac, tried, [f"step rejected after {retries} halvings (kept the iterate): "
                                        + "; ".join(warnings)], True, retries


class IterativeSolver:
    """What every solver shares: the stopping rule and the loop. Subclasses set ``max_iter``, ``grad_tol``
    and implement ``step(state) -> info`` and ``report(state) -> info`` (the report at the current iterate,
    no step)."""

    max_iter: int
    grad_tol: float
    #: Whether the solver halves its steps (step control): the run loop then watches for a collapsed step
    #: (status ``stalled``, ``indreg.registration.run.STALL_WINDOW``).
    halves_steps: bool = False

    def reported_step(self) -> float:
        """The step this solver reports (hyperparameters, metrics.json): a step size or a learning rate."""
        return math.nan

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


class RefitSolver:
    """A solver around ``inner`` that re-estimates part of the data model every ``every`` iterations (before the
    step at iteration ``0, every, 2 every, ...``: :meth:`refit`, which subclasses implement), drops what ``inner``
    cached of the old model, then takes ``inner``'s step; :meth:`report` adds the estimate to the step's report,
    :meth:`summary` the final one to the result (``result.corrections[name]``). Checkpoints: a subclass's
    ``state_dict`` is ``inner``'s with its own entries added, ``load_state_dict`` pops them and hands the rest on.
    Everything else (step sizes, step halving, status, ...) is ``inner``'s. Subclasses: ``indreg.alignment``'s and
    ``indreg.registration.intensity``'s (the in-the-fit corrections of ``indreg.registration.corrections``)."""

    #: the correction's name (``indreg.registration.corrections``): the key of its summary in the result and metrics.json
    name = ""

    def __init__(self, inner, every: int):
        self.inner, self.every = inner, every
        self.problem, self.max_iter, self.grad_tol = inner.problem, inner.max_iter, inner.grad_tol

    def __getattr__(self, name):
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    #: what is re-estimated, for the repr
    what = "the data model"

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.what} every {self.every} iterations, then {self.inner!r})"

    def refit(self, state) -> None:
        raise NotImplementedError

    def report(self, info: dict) -> dict:
        return info

    def summary(self) -> dict:
        """The final estimate for the result (``{}``: nothing to add)."""
        return {}

    def step(self, state) -> dict:
        if state.iteration % self.every == 0:
            self.refit(state)
            forget_evaluations(self.inner)   # its cached objective / gradient belong to the old model
        return self.report(self.inner.step(state))


def forget_evaluations(solver) -> None:
    """Drop what ``solver`` cached of its last evaluation (Algorithm 1's objective and gradient, torch.optim's
    closure and optimizer memory): after a change of the problem (its data model, its template) they are stale."""
    for attr in ("_current", "_cache"):
        if hasattr(solver, attr):
            setattr(solver, attr, None)
    optimizer = getattr(solver, "optimizer", None)
    if optimizer is not None:
        optimizer.state.clear()


def mark(x: tuple) -> tuple:
    """A token for the tensors of ``x`` as they are now (the tensors and their in-place versions)."""
    return tuple(x), tuple(t._version for t in x)


def is_marked(x: tuple, token) -> bool:
    """Whether ``x`` holds the same tensors, unchanged, as when ``token = mark(...)`` was taken."""
    return token is not None and len(x) == len(token[0]) and all(a is b for a, b in zip(x, token[0])) \
        and tuple(t._version for t in x) == token[1]
