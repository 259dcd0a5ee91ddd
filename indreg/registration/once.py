"""One registration run from Python (``indreg.register`` without ``extrapolation``): the set-up, the loop and the
result (``indreg.registration.run``), with the run's warnings tallied by kind and, for ``progress=True`` off a
terminal with logging unset, the log lines on stderr. ``indreg.registration.api.register`` documents the options;
``indreg.registration.extrapolation`` runs it for each of its candidates."""
from __future__ import annotations

import logging
import sys

from ..options import OptionError
from .run import RegistrationLoop, RegistrationResult, build_result, initial_state, setup, shows_progress
from ..tally import has_output_handlers, tally_warnings

__all__ = ["register_once", "evaluation_options"]

log = logging.getLogger("indreg")


def register_once(template, data, operator, **options) -> RegistrationResult:
    """``indreg.register`` without the edge validation (``extrapolation``): one run.

    Parameters
    ----------
    template, data, operator
        As ``indreg.register``.
    **options
        ``indreg.register``'s options.

    Returns
    -------
    RegistrationResult
        The run's result.
    """
    with tally_warnings():   # the set-up's, the iterations' and the end's warnings, by kind (result.warnings)
        return _register(template, data, operator, options)


def _register(template, data, operator, options: dict) -> RegistrationResult:
    handler = _console_handler(options.get("progress") is True)   # before setup: sigma="auto" runs there
    try:
        try:
            s = setup(template, data, operator, **options)
        except OptionError as e:
            raise e.kind(str(e)) from None
        o, problem = s.options, s.problem
        state = initial_state(problem)
        log.info("%s | %s", problem, s.solver)
        loop = RegistrationLoop(problem, s.solver, state, o["max_iter"], every=o["log_every"],
                                progress=shows_progress(o["progress"]), callback=o["callback"],
                                validation=s.validation)
        status = loop.run()
    finally:
        if handler is not None:
            log.removeHandler(handler)
    result = build_result(problem, state, loop.history, loop.seconds, status, o["target"], s.units, s.validation,
                          orientation=s.orientation, solver=s.solver, box=s.box,
                          evaluation=evaluation_options(o))
    result.sigma, result.sigma_scores = float(o["sigma"]), s.sigma_scores
    return result


def evaluation_options(o: dict) -> dict:
    """The options of the result's evaluation (``indreg.evaluation.result.evaluate``) from the resolved ones.

    Parameters
    ----------
    o : dict
        The run's resolved options.

    Returns
    -------
    dict
        ``split``, ``uncertainty``, ``uncertainty_samples`` and ``uncertainty_noise``.
    """
    return {k: o[k] for k in ("split", "uncertainty", "uncertainty_samples", "uncertainty_noise")}


def _console_handler(progress: bool):
    """A stderr handler on the "indreg" logger for ``progress=True`` off a terminal when logging is unset."""
    if progress and not sys.stderr.isatty() and not has_output_handlers(log):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("[indreg] %(message)s"))
        log.addHandler(h)
        if log.level == logging.NOTSET or log.level > logging.INFO:
            log.setLevel(logging.INFO)
        return h
    return None
