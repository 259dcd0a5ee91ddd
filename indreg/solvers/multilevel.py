"""Coarse-to-fine registration: the same objective solved on coarser grids first, then on the problem's grid.

The domain is physical, so a coarser grid of the same rectangle (box, in 3D) discretises the same problem: the
kernel width ``sigma``, ``gamma`` and the data ``g`` keep their meaning; only the template (area / volume
averages over the coarse cells), the forward operator (rebuilt on the coarse grid with the same geometry:
``RayTransform``, ``TiltSeriesTransform``) and the number of time steps change. A tilt series has one detector
row per slice along the tilt axis; a coarse slice is the average of the fine slices it covers, so it projects
to the average of their rows: the data are cell-averaged along the rows (``IndirectRegistration.coarsened``). Each level is solved by L-BFGS (``TorchOptimSolver``, strong Wolfe line search, exact gradient of
the discrete map) or by Algorithm 1, and its momentum is prolongated to the next level.
"""
from __future__ import annotations

import logging

import torch

from .._checks import check_bool, check_int, check_positive
from ..deform.lddmm import BACKWARDS
from ..options import default
from ..problems.grids import prolong, resample_time, restrict
from .algorithm1 import Algorithm1, check_problem
from .._checks import check_nonnegative
from .state import IterativeSolver, SolverState
from .torch_optim import TorchOptimSolver

INNER = ("lbfgs", "algorithm1")
log = logging.getLogger("indreg")


def options() -> tuple:
    """The keyword options of ``MultilevelSolver`` besides ``problem``, ``max_iter`` and ``grad_tol`` (what
    ``solver="fast"`` takes in ``optimizer_kwargs``)."""
    import inspect

    skip = ("self", "problem", "max_iter", "grad_tol")
    return tuple(k for k in inspect.signature(MultilevelSolver.__init__).parameters if k not in skip)


def _check_coarsenable(problem) -> None:
    """Coarse levels need ``problem.coarsened`` and an operator that rebuilds itself on a coarser grid."""
    T = problem.ray_transform
    if not hasattr(problem, "coarsened"):
        raise TypeError(f"coarse levels need a problem that can be coarsened (problem.coarsened); "
                        f"{type(problem).__name__} cannot: use levels=() or another solver")
    if not callable(getattr(T, "on_domain", None)):
        raise TypeError(f"coarse levels rebuild the forward operator on a coarser grid with T.on_domain(domain); "
                        f"a {type(T).__name__} has no on_domain: use levels=() (no coarse level) with this operator")


def _fit_budgets(schedule: list, max_iter: int) -> list:
    """Coarse levels whose budgets would use up ``max_iter`` (the problem's grid then reached only if they stall)
    get budgets scaled down in proportion to half of ``max_iter`` (at least 1 each), logged; others are kept."""
    coarse = sum(it for _, _, it in schedule[:-1])
    if coarse < max_iter or len(schedule) < 2:
        return schedule
    scaled = [(shape, n, max(1, it * (max_iter // 2) // coarse)) for shape, n, it in schedule[:-1]]
    log.info("solver='fast': the coarse levels' budgets (%d iterations in all) would use up max_iter=%d; scaled to "
             "%s so that the %s grid gets the rest", coarse, max_iter, [it for _, _, it in scaled],
             "x".join(map(str, schedule[-1][0])))
    return scaled + schedule[-1:]


class MultilevelSolver(IterativeSolver):
    """Coarse-to-fine minimisation of E (``IndirectRegistration``): grids ``n/f`` for ``f`` in ``levels``, then
    the problem's grid; ``solver="fast"`` of the app and of ``indreg.register``.

    Level ``l`` (coarse to fine) is the problem on a grid ``levels[l]`` times coarser with ``level_steps[l]``
    time steps (``problem.coarsened``); it starts from the previous level's momentum, prolongated as a
    piecewise-constant density in space (``prolong``: ``nu = K m`` is kept) and linearly in time
    (``resample_time``), and runs ``level_iter[l]`` iterations or until its objective stalls (``rtol``). The
    last level is the problem itself (its grid, N, action, interpolation) and runs until ``max_iter``
    iterations in all, ``grad_tol`` or ``rtol``. Levels whose grid would have fewer than ``min_size`` cells on
    an axis are skipped.

    Every iteration of every level counts as one iteration: ``step(state)`` runs one iteration of the current
    level, sets ``state.momentum`` to the current momentum prolongated to the problem's grid and N (so a
    checkpoint, the deformed template and the outputs are always those of the problem), and returns the
    level's report (objective, data_fit, ... of the level's problem: the same objective discretised on the
    level's grid, comparable across levels) with ``level`` (0 = coarsest; the last = the problem's grid) and
    ``grid`` (its size on axis 0) added; ``evaluations`` counts all levels.

    Parameters
    ----------
    problem : RegistrationProblem
        A problem whose iterate is the momentum (``IndirectRegistration``, 2D or 3D); with coarse levels it must
        have ``coarsened`` and its operator ``on_domain`` (``RayTransform``, ``TiltSeriesTransform``).
    levels : tuple of int
        Coarsening factors of the coarse levels, coarse to fine (e.g. ``(4, 2)``: 64^2 and 128^2 for a 256^2
        problem); ``()`` is the problem's grid only.
    level_steps : tuple of int
        Time steps N of each coarse level.
    level_iter : tuple of int
        Iteration budget of each coarse level.
    max_iter : int
        Iterations in all (coarse levels included).
    grad_tol : float
        Stop when the gradient norm of the problem's grid is ``<= grad_tol`` (0: never).
    rtol : float
        A level ends (the last one: the run converges) when its objective decreased at every one of its last
        ``window`` iterations, by less than ``rtol`` (relative) per iteration on average; 0 disables it.
    window : int
        See ``rtol``.
    inner : {"algorithm1", "lbfgs"}
        ``Algorithm1`` on every level with ``step_size``, ``step_halving``, ``max_halvings`` and the problem's
        deformation backward, or ``TorchOptimSolver`` (strong Wolfe line search, with the exact gradient of the
        discrete map, ``backward``, and ``history_size``).
    step_size : float
        Algorithm 1's step (the same on every level: the domain is physical); a new level starts at this step
        again.
    step_halving, max_halvings : bool, int
        Algorithm 1's safeguard (a step that increases the objective or folds is halved and the halved step kept
        for the level).
    backward : str
        The deformation's backward for ``"lbfgs"`` (an entry of ``LDDMMDeformation``'s ``BACKWARDS`` other than
        ``"paper"``).
    history_size : int
        L-BFGS memory.
    min_size : int
        Smallest grid of a coarse level.
    jacobian_every : int
        Compute ``min_jacobian`` every this many iterations of a level (``nan`` in between).

    Raises
    ------
    TypeError
        ``problem`` is no registration problem or its iterate is more than the momentum.
    ValueError
        An unknown ``inner``, a ``backward`` without the exact gradient for ``"lbfgs"``, levels and their
        budgets of different lengths, factors not > 1 and decreasing, a count out of range.

    Notes
    -----
    ``state.momentum`` ``(N+1, d, *shape)`` of the problem (``(N+1, 2, nx, ny)`` or ``(N+1, 3, nx, ny, nz)``);
    ``restrict`` / ``prolong`` act on the image axes (x, y[, z]), ``resample_time`` on axis 0 (``t_i = i/N``);
    a level's ``grid`` is its size on axis 0 (x).
    """

    def __init__(self, problem, levels=(4, 2), level_steps=(10, 10), level_iter=(40, 100),
                 max_iter: int = default("max_iter"), grad_tol: float = default("grad_tol"), rtol: float = 5e-4,
                 window: int = 5,
                 inner: str = "algorithm1", step_size: float = 0.08, step_halving: bool = True,
                 max_halvings: int = default("max_halvings"), backward: str = "exact", history_size: int = 10, min_size: int = 16,
                 jacobian_every: int = 1):
        check_problem(problem)
        if len(problem.iterate_names) != 1:
            raise TypeError(f"MultilevelSolver (solver='fast') takes a problem whose iterate is the momentum alone; "
                            f"{type(problem).__name__}'s is {problem.iterate_names}: use 'algorithm1' or a "
                            "torch.optim solver")
        if inner not in INNER:
            raise ValueError(f"inner must be one of {INNER}, got {inner!r}")
        if inner == "lbfgs" and (backward not in BACKWARDS or backward == "paper"):
            raise ValueError(f"backward must be one of {tuple(b for b in BACKWARDS if b != 'paper')} (the exact "
                             f"gradient a line search needs), got {backward!r}")
        levels, level_iter = tuple(levels), tuple(level_iter)
        level_steps = tuple(level_steps)
        if not len(levels) == len(level_steps) == len(level_iter):
            raise ValueError(f"levels, level_steps and level_iter must have one entry per coarse level, got "
                             f"{len(levels)}, {len(level_steps)} and {len(level_iter)} entries")
        if any(not check_positive(f, "levels entry") > 1 for f in levels) \
                or any(coarser <= finer for finer, coarser in zip(levels[1:], levels)):
            raise ValueError(f"levels must be coarsening factors > 1, decreasing (coarse to fine), got {levels}")
        self.problem = problem
        self.max_iter = check_int(max_iter, "max_iter", 0)
        self.grad_tol = check_nonnegative(grad_tol, "grad_tol")
        self.rtol = check_nonnegative(rtol, "rtol")
        self.window = check_int(window, "window", 1)
        self.inner, self.backward = inner, backward
        self.step_size = check_positive(step_size, "step_size", problem.template.dtype)
        self.step_halving = check_bool(step_halving, "step_halving")
        self.max_halvings = check_int(max_halvings, "max_halvings", 0)
        self.history_size = check_int(history_size, "history_size", 1)
        self.jacobian_every = check_int(jacobian_every, "jacobian_every", 1)
        min_size = check_int(min_size, "min_size", 1)
        self.schedule = []   # (grid shape, N, iterations) per level, coarse to fine; the last is the problem's
        for f, n, it in zip(levels, level_steps, level_iter):
            shape = tuple(max(1, round(s / f)) for s in problem.domain.shape)
            if min(shape) >= min_size:
                self.schedule.append((shape, check_int(n, "level_steps entry", 1),
                                      check_int(it, "level_iter entry", 0)))
        self.schedule.append((tuple(problem.domain.shape), problem.num_steps, None))
        if len(self.schedule) > 1:
            _check_coarsenable(problem)
            self.schedule = _fit_budgets(self.schedule, self.max_iter)
        self.level = -1          # index into schedule of the running level (-1: not started)
        self.level_start = 0     # the global iteration at which it started
        self.evaluations = 0     # of the finished levels (the running level's solver counts its own)
        self._solver = None      # the running level's solver and state
        self._state = None
        self._objectives = []    # the running level's objectives (for rtol)
        self._written = None     # (state.momentum written by the last step, its _version)
        self._pending = False    # resumed on the problem's grid: the level's momentum is the caller's state

    def reported_step(self) -> float:
        """Algorithm 1's step on every level (``inner="algorithm1"``), else L-BFGS's learning rate 1."""
        return float(self.step_size) if self.inner == "algorithm1" else 1.0

    def __repr__(self):
        grids = " -> ".join(f"{'x'.join(map(str, s))} N={n}" for s, n, _ in self.schedule)
        return (f"MultilevelSolver({grids}, inner={self.inner!r}, max_iter={self.max_iter}, "
                f"rtol={self.rtol}, grad_tol={self.grad_tol})")

    @property
    def on_problem_grid(self) -> bool:
        return self.level == len(self.schedule) - 1

    def _level_solver(self, level: int):
        shape, n, _ = self.schedule[level]
        if self.inner == "algorithm1":
            p = self.problem.coarsened(shape, n, self.problem.deformation.backward)
            return Algorithm1(p, step_size=self.step_size, max_iter=self.max_iter, step_halving=self.step_halving,
                              max_halvings=self.max_halvings, jacobian_every=self.jacobian_every)
        p = self.problem.coarsened(shape, n, self.backward)
        return TorchOptimSolver(p, "lbfgs", max_iter=self.max_iter, backward=self.backward,
                                jacobian_every=self.jacobian_every, history_size=self.history_size)

    def _to_level(self, m: torch.Tensor, level: int) -> torch.Tensor:
        shape, n, _ = self.schedule[level]
        d = len(shape)
        if tuple(m.shape[-d:]) == tuple(shape):
            return resample_time(m, n)
        if m.shape[-1] > shape[-1]:
            return resample_time(restrict(m, shape), n)
        return prolong(resample_time(m, n), shape).contiguous()

    def _start(self, level: int, m: torch.Tensor, iteration: int) -> None:
        self.level, self.level_start = level, iteration
        self._solver = self._level_solver(level)
        self._state = SolverState(self._to_level(m, level))
        self._objectives = []

    def _advance(self) -> None:
        """Close the running level and start the next one from its prolongated momentum."""
        self.evaluations += self._solver.evaluations
        self._start(self.level + 1, self._state.momentum, self.level_start + self._state.iteration)

    def _level_done(self) -> bool:
        _, _, budget = self.schedule[self.level]
        return self._state.iteration >= budget or self._stalled()

    def _stalled(self) -> bool:
        e, w = self._objectives[-self.window - 1:], self.window
        if self.rtol <= 0 or len(e) <= w:
            return False
        return all(b <= a for a, b in zip(e, e[1:])) and e[0] - e[-1] < self.rtol * w * abs(e[-1])

    def _sync(self, state: SolverState) -> None:
        """Start the first level from ``state.momentum`` (restricted), or check that it is still the solver's."""
        if self.level < 0:
            self.problem.check_momentum(state.momentum)
            self._start(0, state.momentum, state.iteration)
            return
        if self._pending:
            self.problem.check_momentum(state.momentum)
            self._state.momentum, self._pending = state.momentum, False
            return
        w = self._written
        if w is not None and w[0] is state.momentum and w[1] == state.momentum._version:
            return
        self.problem.check_momentum(state.momentum)
        if not torch.equal(state.momentum, self._fine_momentum()):
            raise ValueError("state.momentum is not the iterate of this MultilevelSolver (it was changed outside "
                             "the solver, or load_state_dict was given another run's solver state)")

    def _fine_momentum(self) -> torch.Tensor:
        m = self._state.momentum
        return m if self.on_problem_grid else self._to_level(m, len(self.schedule) - 1)

    def _info(self, info: dict, iteration: int) -> dict:
        shape = self.schedule[self.level][0]
        return dict(info, iteration=iteration, evaluations=self.evaluations + info["evaluations"],
                    level=self.level, grid=int(shape[0]))

    def report(self, state: SolverState) -> dict:
        """The report at the current iterate of the running level (no step; the first level if none ran)."""
        self._sync(state)
        return self._info(self._solver.report(self._state), state.iteration)

    def step(self, state: SolverState) -> dict:
        """One iteration of the running level (starting the next level first when it is done); mutates ``state``."""
        self._sync(state)
        while not self.on_problem_grid and self._level_done():
            self._advance()
        info = self._solver.step(self._state)
        self._objectives = (self._objectives + [info["objective"]])[-self.window - 1:]
        state.momentum = self._fine_momentum()
        state.iteration += 1
        self._written = (state.momentum, state.momentum._version)
        return self._info(info, state.iteration)

    def converged(self, info: dict) -> bool:
        """On the problem's grid: ``grad_norm <= grad_tol`` or a stalled objective (``rtol``)."""
        if not self.on_problem_grid or self.failed(info):
            return False
        return super().converged(info) or self._stalled()

    def state_dict(self) -> dict:
        """The running level, its solver's state and momentum (coarse levels), the evaluation counter."""
        if self.level < 0:
            return {"level": -1}
        d = {"level": self.level, "level_start": self.level_start, "evaluations": self.evaluations,
             "level_iteration": self._state.iteration, "objectives": list(self._objectives),
             "solver": self._solver.state_dict()}
        if not self.on_problem_grid:
            d["momentum"] = self._state.momentum.detach().clone()
        return d

    def load_state_dict(self, d: dict) -> None:
        level = int(d["level"])
        self._written = None
        if level < 0:
            self.level, self._solver, self._state = -1, None, None
            return
        if level >= len(self.schedule):
            raise ValueError(f"solver state is at level {level}, this MultilevelSolver has {len(self.schedule)}")
        self.level, self.level_start = level, int(d["level_start"])
        self._solver = self._level_solver(level)
        self._solver.load_state_dict(d["solver"])
        p = self._solver.problem
        m = d["momentum"] if "momentum" in d else None
        self._state = SolverState(p.zero_momentum() if m is None else m.to(p.template), int(d["level_iteration"]))
        self._objectives = [float(e) for e in d["objectives"]]
        self.evaluations = int(d["evaluations"])
        self._pending = m is None
