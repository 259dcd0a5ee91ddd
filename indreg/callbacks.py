"""Callbacks of the registration loop (``indreg.registration.run.RegistrationLoop``), composable with ``&`` like ODL's.

A :class:`Callback` sees the loop at four moments: :meth:`~Callback.begin` (before the first step),
:meth:`~Callback.before` (before every step), :meth:`~Callback.after` (after every step, with the solver's report
``info``) and :meth:`~Callback.end`. ``before`` and ``after`` may return a status that stops the loop
(one of :data:`STOP_STATUSES`; anything else but ``None`` / ``False`` is a ``TypeError`` naming the callback);
:meth:`~Callback.describe` adds text to the progress log line. ``a & b`` runs ``a`` then ``b`` (:class:`Callbacks`):
every callback runs each time, the first status returned wins. Every ``end`` runs, also when a ``begin``, a step
or another ``end`` raised; the first exception is the one that propagates (later ones are logged).

``register(callback=...)`` takes a ``Callback``, a chain ``a & b``, a plain function ``fn(state, info)`` (returning
True stops the run: :class:`UserCallback`) or a list of these (:func:`as_callback`), the same loop as the app's.
Built in: :class:`UserCallback`,
:class:`HeldOut` (``holdout=``: the held-out residual every ``every`` iterations, early stopping). The app adds
TensorBoard, evaluation, checkpoints and its stop requests the same way (``indreg.experiments.runner``).

Notes
-----
``loop`` is the running ``RegistrationLoop`` (``loop.state``, ``loop.problem``, ``loop.solver``,
``loop.history``, ``loop.every``); ``info`` the solver's report of the step (a dict, also the last entry of
``loop.history``); iterations count from 1.
"""
from __future__ import annotations

import logging
from typing import Callable, Optional

__all__ = ["Callback", "Callbacks", "UserCallback", "HeldOut", "STOP_STATUSES", "as_callback"]

log = logging.getLogger("indreg")

#: The statuses a callback's ``before`` / ``after`` may return to stop the loop.
STOP_STATUSES = ("stopped", "early_stopped", "interrupted")


class Callback:
    """A hook of the registration loop (module docstring); the base does nothing."""

    def begin(self, loop) -> None:
        """Before the first step (after a resume too)."""

    def before(self, loop) -> Optional[str]:
        """Before every step: a status stops the loop before the step."""
        return None

    def after(self, loop, info: dict, done: bool) -> Optional[str]:
        """After every step (``done``: the solver ends here): a status stops the loop."""
        return None

    def describe(self, info: dict) -> str:
        """Text for the progress log line (``, SSIM 0.87``)."""
        return ""

    def end(self, loop) -> None:
        """After the last step, also when a step raised."""

    def __and__(self, other: "Callback") -> "Callbacks":
        return Callbacks(self, other)


class Callbacks(Callback):
    """Callbacks run in order (``a & b & c``); the first status any of them returns stops the loop."""

    def __init__(self, *callbacks: Callback):
        self.callbacks = []
        for c in callbacks:
            if not isinstance(c, Callback):
                raise TypeError(f"callbacks must be indreg.callbacks.Callback instances, got {type(c).__name__}")
            self.callbacks += c.callbacks if isinstance(c, Callbacks) else [c]

    def begin(self, loop) -> None:
        for c in self.callbacks:
            c.begin(loop)

    def before(self, loop) -> Optional[str]:
        return _first([(c, "before", c.before(loop)) for c in self.callbacks])

    def after(self, loop, info: dict, done: bool) -> Optional[str]:
        return _first([(c, "after", c.after(loop, info, done)) for c in self.callbacks])

    def describe(self, info: dict) -> str:
        return "".join(c.describe(info) for c in self.callbacks)

    def end(self, loop) -> None:
        """Every callback's ``end``, also after one raised; then the first exception is raised."""
        first = None
        for c in self.callbacks:
            try:
                c.end(loop)
            except Exception as e:
                if first is not None:
                    log.error("%s.end() failed too: %s: %s", type(c).__name__, type(e).__name__, e)
                first = first or e
        if first is not None:
            raise first

    def __repr__(self) -> str:
        return " & ".join(type(c).__name__ for c in self.callbacks) or "Callbacks()"


def _first(returned: list) -> Optional[str]:
    """The first status of ``(callback, method, value)`` triples; a value that is not ``None``, ``False`` or one
    of :data:`STOP_STATUSES` is a ``TypeError`` naming the callback."""
    for c, method, s in returned:
        if s is not None and s is not False and s not in STOP_STATUSES:
            raise TypeError(f"{type(c).__name__}.{method}() returned {s!r}: a callback returns None to go on or one "
                            f"of {', '.join(map(repr, STOP_STATUSES))} to stop the loop")
    return next((s for _, _, s in returned if s), None)


class UserCallback(Callback):
    """``fn(state, info)`` after every step; True stops the loop (``stopped``)."""

    def __init__(self, fn: Callable):
        self.fn = fn

    def after(self, loop, info: dict, done: bool) -> Optional[str]:
        return "stopped" if self.fn(loop.state, info) else None


def as_callback(value, label: str = "callback") -> Optional[Callback]:
    """``value`` as one :class:`Callback`: None; a ``Callback`` (or a chain ``a & b``) itself; a function
    ``fn(state, info)`` as a :class:`UserCallback`; a list or tuple of these in order (:class:`Callbacks`). Anything
    else is a one-line TypeError naming ``label``."""
    if value is None or isinstance(value, Callback):
        return value
    if isinstance(value, (list, tuple)):
        return Callbacks(*(as_callback(v, label) for v in value if v is not None))
    if callable(value):
        return UserCallback(value)
    raise TypeError(f"{label} must be callable(state, info), an indreg.callbacks.Callback or a list of them, "
                    f"got {type(value).__name__}")


class HeldOut(Callback):
    """Validation on held-out angles (``indreg.evaluation.validation.Validation``): every ``loop.every`` iterations the
    held-out residual of the current reconstruction goes into ``info`` and the history as ``holdout_residual``
    (put it first in a chain, so that the callbacks after it see it); ``early_stopped`` when the validation's
    patience has run out."""

    def __init__(self, validation):
        self.validation = validation

    def begin(self, loop) -> None:
        self.validation.restore(loop.history)   # a resumed run continues its curve

    def after(self, loop, info: dict, done: bool) -> Optional[str]:
        v, it = self.validation, loop.state.iteration
        if it % loop.every:
            return None
        info["holdout_residual"] = loop.history[-1]["holdout_residual"] = \
            v.record(it, loop.problem.reconstruction(loop.state.iterate))
        if not v.exhausted():
            return None
        best, value = v.best
        log.info("iteration %d: the held-out residual has not decreased in %d evaluations (least %.4g at "
                 "iteration %d); stopping", it, v.patience, value, best)
        return "early_stopped"

    def describe(self, info: dict) -> str:
        return f", held-out residual {info['holdout_residual']:.4g}" if "holdout_residual" in info else ""
