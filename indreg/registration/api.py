"""One call from Python: ``indreg.register(template, data, operator, **options) -> RegistrationResult``.

It validates the options (``indreg.options``: the same table as the app's config), builds the kernel of V, the
model's objective (``indreg.registration.models``: the built-in ones or one you register) and a solver, runs the
shared loop and returns the reconstruction with the deformation and a report (``indreg.registration.run``). The
``indreg-register`` app runs the same code, adding checkpoints, TensorBoard, figures and files.

Convention:
    - ``template`` ``operator.domain.shape`` (``(nx, ny)`` or ``(nx, ny, nz)``, axis 0 = x), ``data``
      ``operator.range_shape`` (``(num_angles, det_count)`` for a ray transform); torch tensors or numpy arrays,
      real and finite. Results' fields follow the domain's dimension (``momentum (N+1, d, *shape)``, ...).
    - Defaults are the paper's suite-1 values (``sigma`` 6, N = 20, 200 iterations), with ``gamma`` and the
      step relative to the data term (``gamma_rel``, ``step_rel``: suite 1's 1e-6 and 0.02 at its scale; the same
      run for data in any intensity or length unit, ``indreg.units``) and ``step_halving=True``: a step that
      increases the objective or folds the deformation is halved until it does not (the paper's fixed absolute
      step: ``gamma=1e-6, step_size=0.02, step_halving=False``).
    - Warnings (folding, objective increase, rejected steps) and progress go through ``logging`` (logger
      ``"indreg"``); ``result.warnings`` counts the iterations that reported one.
"""
from __future__ import annotations

import logging
import sys
import textwrap

from ..options import OptionError, all_options
from .run import (Progress, RegistrationLoop, RegistrationResult, Setup, build_result, initial_state,  # noqa: F401
                  relative_residual, resolve_device, setup)

log = logging.getLogger("indreg")


def _console_handler(progress: bool):
    """A stderr handler on the "indreg" logger for ``progress=True`` off a terminal when logging is unset."""
    if progress and not sys.stderr.isatty() and not log.hasHandlers():
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("[indreg] %(message)s"))
        log.addHandler(h)
        if log.level == logging.NOTSET or log.level > logging.INFO:
            log.setLevel(logging.INFO)
        return h
    return None


def register(template, data, operator, **options) -> RegistrationResult:  # noqa: D417 (options: the table)
    """Deform ``template`` until ``operator(deformed)`` matches ``data`` (indirect LDDMM registration).

    Args:
        template: the template image I, ``operator.domain.shape`` (torch tensor or numpy array).
        data: the data g, ``operator.range_shape`` (e.g. a sinogram ``(num_angles, det_count)``).
        operator: the forward operator T: ``indreg.RayTransform(domain, geometry)`` (parallel or fan beam),
            ``indreg.TiltSeriesTransform`` or any linear operator with ``domain``, ``range_shape``, ``__call__``,
            ``adjoint`` and ``inner_data`` (``indreg.forward.check_operator``; ``docs/extending.md``).
            Data at several time points (``model="spatiotemporal"``, ``docs/spatiotemporal.md``): a list of
            operators, one per time point, with a list of data sets (or an ``indreg.forward.TimeSeriesOperator``
            and the data stacked ``(K, *range_shape)``), ``times=[t_1, ..., t_K]``, and ``template=None`` when the
            template is unknown (reconstructed: ``result.template``; the frames: ``result.frames``).
        **options: keywords from the option table ``indreg.options`` (the app's config keys in brackets; an
            option of another solver or model given a value is an error), generated from it:

{options}
    Raises:
        TypeError: an unknown option (the message lists the valid ones), a wrong type, an option of another
            solver or model given a value.
        ValueError: a shape mismatch, non-finite values, an invalid value; the message names the argument.

    Example:
        >>> import indreg
        >>> from indreg import phantoms
        >>> domain = indreg.ImageDomain.paper(16)
        >>> T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(6, 24))
        >>> result = indreg.register(phantoms.get("j", domain), T(phantoms.get("v", domain)), T, max_iter=3,
        ...                          num_steps=4)
        >>> result.status, result.iterations
        ('completed', 3)
    """
    if options.get("extrapolation"):   # the edge validation, then the chosen run (indreg.evaluation.extrapolation)
        from ..evaluation.extrapolation import register_extrapolating

        return register_extrapolating(template, data, operator, **options)
    try:
        s = setup(template, data, operator, **options)
    except OptionError as e:
        raise e.kind(str(e)) from None
    o, problem = s.options, s.problem
    state = initial_state(problem)
    handler = _console_handler(o["progress"])
    try:
        log.info("%s | %s", problem, s.solver)
        loop = RegistrationLoop(problem, s.solver, state, o["max_iter"], every=o["log_every"],
                                progress=o["progress"], callback=o["callback"], validation=s.validation)
        status = loop.run()
    finally:
        if handler is not None:
            log.removeHandler(handler)
    return build_result(problem, state, loop.history, loop.seconds, status, o["target"], s.units, s.validation,
                        orientation=s.orientation, solver=s.solver, evaluation=evaluation_options(o))


def evaluation_options(o: dict) -> dict:
    """The options of the result's evaluation (``indreg.evaluation.result.evaluate``) from the resolved ones."""
    return {k: o[k] for k in ("split", "uncertainty", "uncertainty_samples")}


def option_docs(indent: int = 12) -> str:
    """The option table as ``register()``'s docstring lists it: ``name [config key]: doc; default value``."""
    pad = " " * indent
    lines = []
    for o in all_options():
        key = "" if o.group == "run" else f" [{o.config_key}]"
        where = f" Only with {o.where()}." if o.where() else ""
        lines.append(textwrap.fill(f"{o.name}{key}: {o.doc}; default {o.default!r}.{where}", 116,
                                   initial_indent=pad, subsequent_indent=pad + "    "))
    return "\n".join(lines)


register.__doc__ = register.__doc__.replace("{options}", option_docs())
