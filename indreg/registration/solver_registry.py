"""The solvers a registration can use, by name: the registry behind ``register(solver=...)`` and the app's
``solver.name`` (the registry itself, :data:`SOLVERS`, lives in ``indreg.options``, so that checking an option
never imports a solver).

A solver is a :class:`Solver`: its name, its own options (``indreg.options.Option`` with ``solvers=(name,)``; they
join ``register()``'s keywords and the app's config schema) and ``build(problem, options, model_kwargs) -> solver``,
``model_kwargs`` the model's ``solver_options[name]``. ``indreg.registration.run`` names none of them, so a new solver is its
module and one :func:`register_solver` call (``docs/extending.md``); the app takes a plug-in by its import path,
``solver.name=package.module:SOLVER``.

Built in (each builds its class on first use: the registry itself imports no solver):

    algorithm1  ``indreg.solvers.Algorithm1``: the paper's gradient descent with step control
    fast        ``indreg.solvers.MultilevelSolver``: coarse to fine (``optimizer_kwargs``: its options)
    torch       ``indreg.solvers.TorchOptimSolver``: every ``torch.optim`` optimizer, by its class name
                (``"lbfgs"``, ``"adam"``, ...; ``optimizer_kwargs``: its keywords)
"""
from __future__ import annotations

import inspect

from ..options import (ALGORITHM1, FAST, SOLVERS, TORCH, OptionError, Solver, register_solver,  # noqa: F401
                      solver, solver_kind)

__all__ = ["Solver", "SOLVERS", "register_solver", "get", "solver_kind"]


def get(name: str) -> Solver:
    """The registered solver serving ``name`` (``indreg.options.solver``: ``"package.module:attribute"`` imports one)."""
    return solver(name)


def _keys_within(o: dict, label, allowed, what: str) -> None:
    """Every ``optimizer_kwargs`` key is in ``allowed`` (``what`` names them in the one-line error)."""
    for key in o["optimizer_kwargs"]:
        if key not in allowed:
            raise OptionError(f"{label('optimizer_kwargs')}.{key}", o["optimizer_kwargs"][key],
                              f"{what}: {', '.join(sorted(allowed))})", TypeError)


# ---------------------------------------------------------------------------------------------------- algorithm1
def _algorithm1(problem, o: dict, model_kwargs: dict):
    from ..solvers import Algorithm1

    return Algorithm1(problem, step_size=o["step_size"], max_iter=o["max_iter"], grad_tol=o["grad_tol"],
                      step_halving=o["step_halving"], max_halvings=o["max_halvings"], **model_kwargs)


register_solver(Solver(ALGORITHM1, _algorithm1, doc="the paper's Algorithm 1: gradient descent in V with step control"))


# ---------------------------------------------------------------------------------------------------- fast
def _fast(problem, o: dict, model_kwargs: dict):
    from ..solvers import MultilevelSolver

    return MultilevelSolver(problem, max_iter=o["max_iter"], grad_tol=o["grad_tol"], **o["optimizer_kwargs"],
                            **model_kwargs)


def _check_fast(o: dict, label) -> None:
    from ..solvers.multilevel import options

    _keys_within(o, label, set(options()), "an option of solver='fast' (indreg.solvers.MultilevelSolver")


register_solver(Solver(FAST, _fast, check=_check_fast, doc="coarse to fine (MultilevelSolver)"))


# ---------------------------------------------------------------------------------------------------- torch.optim
def _optimizers() -> dict:
    """``torch.optim``'s optimizer classes by lower-case name."""
    import torch

    return {name.lower(): cls for name, cls in vars(torch.optim).items()
            if isinstance(cls, type) and issubclass(cls, torch.optim.Optimizer) and cls is not torch.optim.Optimizer}


def _optimizer_name(value: str):
    """``value`` lower-cased when it names a ``torch.optim`` optimizer, else None."""
    return value.lower() if value.lower() in _optimizers() else None


def _torch(problem, o: dict, model_kwargs: dict):
    from ..solvers import TorchOptimSolver

    return TorchOptimSolver(problem, optimizer=o["solver"], lr=o["lr"], max_iter=o["max_iter"],
                            grad_tol=o["grad_tol"], **model_kwargs, **o["optimizer_kwargs"])


def _check_torch(o: dict, label) -> None:
    cls = _optimizers()[o["solver"]]
    allowed = set(inspect.signature(cls.__init__).parameters) - {"self", "params", "lr"}
    _keys_within(o, label, allowed, f"a keyword of torch.optim {cls.__name__} (")


register_solver(Solver(TORCH, _torch, accepts=_optimizer_name, check=_check_torch,
                       expected="a torch.optim optimizer name (lbfgs, adam, sgd, ...)", family="a torch.optim solver",
                       doc="any torch.optim optimizer on the V-gradient's parametrisation (TorchOptimSolver)"))
