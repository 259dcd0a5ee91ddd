"""Algorithm 1 of the paper (alg:GradientDescentAlgorithm_1): gradient descent on the velocity field, on any
registration problem's iterate (LDDMM: the momentum; metamorphosis: momentum and source)."""
from __future__ import annotations

import math

import torch

from .._checks import check_bool, check_int, check_positive
from .._checks import StepOverflowError, check_nonnegative
from ..options import default
from ..units import STEP_REL, data_term_scale
from ..problems.problem import RegistrationProblem
from .state import (IterativeSolver, SolverState, StepControl, is_marked, make_info, mark, problems,
                    rounding_tolerance)


def check_problem(problem) -> None:
    if not isinstance(problem, RegistrationProblem):
        raise TypeError(f"problem must be a registration problem (indreg.solvers.RegistrationProblem: "
                        f"IndirectRegistration, MetamorphosisRegistration, ...), got {type(problem).__name__}")


class Algorithm1(IterativeSolver):
    """Gradient descent ``x_k <- x_k - alpha_k h_k`` on every entry of the iterate (eq:gradientflow).

    LDDMM (``x = (m,)``): ``grad_V E(nu)(t_i) = gamma nu_i - K(|D phi_{t_i,1}| (grad_data o phi_{t_i,1})
    grad(I o phi_{t_i,0}))`` (eq:GradGoalFunctionalVRHKS in the code's scale, see ``objective``; the
    mass-preserving version eq:GradGoalFunctionalVRHKS_mp comes from the deformation's backward with the same
    assembly). With ``nu = K m`` and ``grad_V E = K h`` (``h`` = L2 gradient, ``problem.gradient``) the update is
    linear, so it runs on the momentum: ``m <- m - alpha h``, ``nu = K m`` (identical iterates in exact
    arithmetic; the regulariser ``<m, K m>`` stays exact). Metamorphosis (``x = (m, s)``) descends the source
    with its own step ``beta`` (eq:Metam:ODE's gradient in ``zeta``).

    Parameters
    ----------
    problem : RegistrationProblem
        The objective to descend.
    step_size : float, optional
        ``alpha > 0`` for the momentum (the paper's values work unchanged); None: relative to the data term,
        ``step_rel / S`` (``indreg.units``; ``step_rel``: ``indreg.units.STEP_REL``).
    max_iter : int
        Maximum number of iterations ``K`` (>= 0).
    grad_tol : float
        Stop when the gradient norm (``hypot`` of the entries' ``L2([0,1], L2)`` norms) is ``<= grad_tol``; 0
        disables the test.
    step_halving, max_halvings : bool, int
        ``StepControl``: reject a step whose objective is non-finite, larger than the current one, or folds
        (``min Jacobian <= 0``); halve every step and retry, at most ``max_halvings`` times (the halved steps are
        kept for later iterations; ``info["halvings"]`` counts them). If all retries fail the iterate is kept and
        ``info["rejected"]`` is True. Without it such steps are taken and reported in ``info["warning"]`` (an
        increase only beyond float rounding, ``rounding_tolerance``).
    jacobian_every : int
        Compute ``min_jacobian`` (one extra Jacobian recursion, about the cost of the deformation's forward)
        every this many iterations, ``nan`` in between; with ``step_halving`` it is computed at every step
        (folding must be checked).
    steps : dict, optional
        Step sizes of the entries after the momentum by name (``None`` or absent:
        ``problem.default_step(name)``).
    frozen : dict, optional
        Iterations during which an entry is kept fixed, by name (e.g. ``{"source": 300}``).
    cycle : tuple, optional
        Block-alternating descent: ``((names, iterations), ...)``, e.g. ``((("template",), 5),
        (("momentum",), 5))``: the first 5 iterations move only the template, the next 5 only the momentum, and
        so on (iteration ``i`` at position ``i mod 10`` of the cycle); step halving halves the block's steps
        only. None (default): every entry moves.

    Raises
    ------
    TypeError
        ``problem`` is no registration problem, or an argument of the wrong type.
    ValueError
        A step that is not positive and finite in the problem's dtype, ``steps`` / ``frozen`` / ``cycle`` naming
        no entry of the iterate after the momentum, a count out of range.

    Notes
    -----
    ``step(state)`` performs one iteration and returns the report at the new iterate (``make_info``):
    objective and its terms, grad_norm, min_jacobian (of ``phi_{1,0}``), step_size, evaluations (cumulative
    forward/backward evaluations, one per tried step plus one at the start), rejected, warning. The gradient
    at the new iterate is kept for the next step, so an iteration costs one evaluation. ``report(state)`` is
    that report at the current iterate without a step. After ``load_state_dict`` the first evaluation
    recomputes the cached gradient of the saved iterate and is not counted, so ``evaluations`` continues as in
    an uninterrupted run.
    """

    def __init__(self, problem: RegistrationProblem, step_size: float | None = None,
                 max_iter: int = default("max_iter"), grad_tol: float = default("grad_tol"),
                 step_halving: bool = default("step_halving", app=True), max_halvings: int = default("max_halvings"),
                 jacobian_every: int = 1, steps: dict | None = None, frozen: dict | None = None,
                 cycle: tuple | None = None):
        check_problem(problem)
        self.problem = problem
        self.names = tuple(problem.iterate_names)
        steps, frozen = dict(steps or {}), dict(frozen or {})
        for key in (*steps, *frozen):
            if key not in self.names[1:]:
                raise ValueError(f"steps / frozen name entries of the iterate after the momentum "
                                 f"{self.names[1:]}, got {key!r}")
        dtype = problem.template.dtype   # steps must stay finite and nonzero in the run's dtype
        if step_size is None:   # relative to the data term (indreg.units): step_rel / S
            step_size = STEP_REL / data_term_scale(problem.ray_transform, problem.data)
        self.step_sizes = [check_positive(step_size, "step_size", dtype)]
        for name in self.names[1:]:
            s = steps.get(name)
            self.step_sizes.append(check_positive(problem.default_step(name) if s is None else s,
                                                  f"{name}_step_size", dtype))
        self.frozen = {self.names.index(k): check_int(v, f"{k}_start", 0) for k, v in frozen.items()}
        self.cycle = self._check_cycle(cycle)
        self.max_iter = check_int(max_iter, "max_iter", 0)
        self.grad_tol = check_nonnegative(grad_tol, "grad_tol")
        self.control = StepControl(check_bool(step_halving, "step_halving"), check_int(max_halvings, "max_halvings", 0))
        self.jacobian_every = check_int(jacobian_every, "jacobian_every", 1)
        self.evaluations = 0
        self._current = None   # (mark of the iterate, terms, h, nu) of the last evaluation
        self._recount = False  # the next evaluation at the iterate recomputes one already counted

    @property
    def step_size(self) -> float:
        """The momentum's step (it may have been halved)."""
        return self.step_sizes[0]

    @property
    def halves_steps(self) -> bool:
        return self.control.halving

    def reported_step(self) -> float:
        return float(self.step_size)

    @step_size.setter
    def step_size(self, value: float) -> None:
        self.step_sizes[0] = check_positive(value, "step_size")

    @property
    def step_halving(self) -> bool:
        return self.control.halving

    @property
    def max_halvings(self) -> int:
        return self.control.max_halvings

    def __repr__(self):
        extra = "".join(f", {n}_step_size={s:.4g}" for n, s in zip(self.names[1:], self.step_sizes[1:]))
        return (f"{type(self).__name__}(step_size={self.step_size}{extra}, max_iter={self.max_iter}, "
                f"grad_tol={self.grad_tol}, step_halving={self.step_halving})")

    def _evaluate(self, x: tuple, counted: bool = True):
        terms, h, nu = self.problem.gradient(x)
        self.evaluations += int(counted)
        return terms, h, nu

    def _at(self, state: SolverState):
        """Terms, L2 gradients and velocity at ``state.iterate`` (cached from the previous step)."""
        x = state.iterate
        if self.problem.at_iteration(state.iteration):   # the objective changed (a staged problem)
            self._current = None
        if self._current is None or not is_marked(x, self._current[0]):
            self.problem.check_iterate(x)
            self._current = (mark(x), *self._evaluate(x, counted=not self._recount))
            self._recount = False
        return self._current[1:]

    def _min_jacobian(self, nu, iteration: int) -> float:
        if self.step_halving or iteration % self.jacobian_every == 0:
            return self.problem.min_jacobian(nu)
        return math.nan

    def _info(self, iteration, terms, h, min_jac, steps, rejected, warnings, halvings=0) -> dict:
        return make_info(iteration, terms, [self.problem.gradient_norm(g) for g in h], min_jac, steps,
                         self.evaluations, rejected, warnings, self.names, halvings)

    def report(self, state: SolverState) -> dict:
        """The report at ``state.iterate`` (no step; ``min_jacobian`` always computed)."""
        terms, h, nu = self._at(state)
        min_jac = self.problem.min_jacobian(nu)
        return self._info(state.iteration, terms, h, min_jac, self.step_sizes, False,
                          problems(terms["objective"], min_jac))

    def _check_cycle(self, cycle) -> tuple | None:
        """``cycle`` as ``((entry indices, iterations), ...)``; one-line ValueError for unknown names."""
        if cycle is None:
            return None
        out = []
        for names, count in cycle:
            unknown = [n for n in names if n not in self.names]
            if unknown or not names:
                raise ValueError(f"cycle must name entries of the iterate {self.names}, got {tuple(names)!r}")
            out.append((frozenset(self.names.index(n) for n in names), check_int(count, "cycle iterations", 1)))
        return tuple(out)

    def _block(self, iteration: int) -> set:
        """The entries (indices) of the ``cycle``'s block at ``iteration`` (all without a cycle)."""
        if self.cycle is None:
            return set(range(len(self.names)))
        position = iteration % sum(count for _, count in self.cycle)
        for block, count in self.cycle:
            if position < count:
                return set(block)
            position -= count

    def moving(self, iteration: int) -> set:
        """The entries (indices) that move at ``iteration``: not ``frozen``, and in the ``cycle``'s block."""
        return {k for k in self._block(iteration) if iteration >= self.frozen.get(k, 0)}

    def _moved(self, x: tuple, h: tuple, steps: tuple, iteration: int) -> tuple:
        """``x_k - alpha_k h_k`` for every entry that moves at ``iteration`` (:meth:`moving`)."""
        moving = self.moving(iteration)
        return tuple(torch.add(xk, hk, alpha=-a) if k in moving else xk
                     for k, (xk, hk, a) in enumerate(zip(x, h, steps)))

    def step(self, state: SolverState) -> dict:
        """One iteration (with optional step halving); mutates ``state``; returns the report."""
        terms, h, nu = self._at(state)
        it = state.iteration

        block = sorted(self._block(it))   # step control halves only the steps of the cycle's block

        def with_block(sizes) -> list:
            steps = list(self.step_sizes)
            for k, a in zip(block, sizes):
                steps[k] = a
            return steps

        def trial(sizes):
            steps = with_block(sizes)
            x_new = self._moved(state.iterate, h, steps, it)
            try:
                new = self._evaluate(x_new)
            except ValueError as e:   # the step overflowed the dtype (the momentum or its velocity)
                if "non-finite" not in str(e):
                    raise
                if self.control.halving:
                    return None, math.inf, math.nan
                raise StepOverflowError(steps[0], x_new[0].dtype, str(e)) from None
            return (x_new, new, tuple(steps)), new[0]["objective"], self._min_jacobian(new[2], it + 1)

        rtol = rounding_tolerance(state.iterate[0].dtype)
        sizes = [self.step_sizes[k] for k in block]
        result, min_jac, tried, warnings, rejected, halvings = self.control.search(
            sizes, terms["objective"], trial, rtol)
        for k, a in zip(block, sizes):
            self.step_sizes[k] = a
        if rejected:   # every trial failed (possibly each overflowed: no result at all); the iterate stays
            new, steps = (terms, h, nu), tuple(with_block(tried))
            min_jac = self._min_jacobian(nu, it + 1)
        else:
            x_new, new, steps = result
            state.iterate = x_new
            self._current = (mark(x_new), *new)
        state.iteration += 1
        return self._info(state.iteration, new[0], new[1], min_jac, steps, rejected, warnings, halvings)

    def state_dict(self) -> dict:
        """Step sizes (they may have been halved), the evaluation counter and whether it counts the iterate's."""
        d = {"step_size": self.step_sizes[0], "evaluations": self.evaluations, "evaluated": self._current is not None}
        d.update({f"{n}_step_size": s for n, s in zip(self.names[1:], self.step_sizes[1:])})
        return d

    def load_state_dict(self, d: dict) -> None:
        self.step_sizes = [check_positive(d["step_size"], "step_size")] + \
            [check_positive(d[f"{n}_step_size"], f"{n}_step_size") for n in self.names[1:]]
        self.evaluations = check_int(d["evaluations"], "evaluations", 0)
        self._current = None
        self._recount = bool(d["evaluated"])
