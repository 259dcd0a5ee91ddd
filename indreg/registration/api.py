"""One call from Python: ``indreg.register(template, data, operator, **options) -> RegistrationResult``.

It validates the options (``indreg.options``: the same table as the app's config), builds the kernel of V, the
model's objective (``indreg.registration.models``: the built-in ones or one you register) and a solver, runs the
shared loop and returns the reconstruction with the deformation and a report (``indreg.registration.run``). The
``indreg-register`` app runs the same code, adding checkpoints, TensorBoard, figures and files.

Notes
-----
- ``template`` ``operator.domain.shape`` (``(nx, ny)`` or ``(nx, ny, nz)``, axis 0 = x), ``data``
  ``operator.range_shape`` (``(num_angles, det_count)`` for a ray transform); torch tensors or numpy arrays,
  real and finite. Results' fields follow the domain's dimension (``momentum (N+1, d, *shape)``, ...).
- Defaults are the paper's suite-1 values (``sigma`` 6, N = 20, 200 iterations), with ``gamma`` and the
  step relative to the data term (``gamma_rel``, ``step_rel``: suite 1's 1e-6 and 0.02 at its scale; the same
  run for data in any intensity or length unit, ``indreg.units``) and ``step_halving=True``: a step that
  increases the objective or folds the deformation is halved until it does not (the paper's fixed absolute
  step: ``gamma=1e-6, step_size=0.02, step_halving=False``).
- Warnings (folding, objective increase, rejected steps) and progress go through ``logging`` (logger
  ``"indreg"``); ``result.warnings`` counts them, the set-up's and the end's included, and
  ``result.warnings_by_kind`` by kind (``indreg.tally``; a fixed step's objective rises apart:
  ``result.objective_rises``, said once). ``progress`` (default None): a bar on a terminal, for the run
  and for each of ``sigma="auto"``'s trial runs (with a line per width and its held-out residual, and the
  width chosen: ``result.sigma``); nothing in scripts, pipes and tests; ``progress=True`` off a terminal: log
  lines on stderr.
"""
from __future__ import annotations

from ..options.docs import fill
from .once import evaluation_options, register_once  # noqa: F401 (evaluation_options: the app's)
from .run import (Progress, RegistrationLoop, RegistrationResult, Setup, build_result, initial_state,  # noqa: F401
                  relative_residual, resolve_device, setup, shows_progress)


def register(template, data, operator, **options) -> RegistrationResult:
    """Deform ``template`` until ``operator(deformed)`` matches ``data`` (indirect LDDMM registration).

    Parameters
    ----------
    template : torch.Tensor or numpy.ndarray or None
        The template image I, ``operator.domain.shape``. None (unknown: reconstructed, ``result.template``) only
        with ``model="spatiotemporal"``.
    data : torch.Tensor or numpy.ndarray or list
        The data g, ``operator.range_shape`` (e.g. a sinogram ``(num_angles, det_count)``); with several time
        points a list of data sets, one per operator (or stacked ``(K, *range_shape)``).
    operator : LinearOperator or list of LinearOperator
        The forward operator T: ``indreg.RayTransform(domain, geometry)`` (parallel or fan beam),
        ``indreg.TiltSeriesTransform`` or any linear operator with ``domain``, ``range_shape``, ``__call__``,
        ``adjoint`` and ``inner_data`` (``indreg.forward.check_operator``; ``docs/extending.md``). Data at several
        time points (``model="spatiotemporal"``, ``docs/spatiotemporal.md``): a list of operators, one per time
        point (or an ``indreg.forward.TimeSeriesOperator``), with ``times=[t_1, ..., t_K]``; the frames:
        ``result.frames``.
    **options
        Keywords of the option table ``indreg.options`` (the same as the app's config keys), listed below,
        generated from it. An unknown keyword, or an option of another solver or model given a value, is an
        error.
    {options}

    Returns
    -------
    RegistrationResult
        The reconstruction (``deformed``), the momentum, velocity and deformation, the iteration history and a
        report (``status``, ``residual``, ``warnings``, ``units``, the corrections' estimates).

    Raises
    ------
    TypeError
        An unknown option (the message lists the valid ones), a wrong type, an option of another solver or model
        given a value.
    ValueError
        A shape mismatch, non-finite values, an invalid value; the message names the argument.

    Examples
    --------
    >>> import indreg
    >>> from indreg import phantoms
    >>> domain = indreg.ImageDomain.paper(16)
    >>> T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(6, 24))
    >>> result = indreg.register(phantoms.get("j", domain), T(phantoms.get("v", domain)), T, max_iter=3,
    ...                          num_steps=4)
    >>> result.status, result.iterations
    ('completed', 3)
    """
    if options.get("extrapolation"):   # the edge validation, then the chosen run (indreg.registration.extrapolation)
        from .extrapolation import register_extrapolating

        return register_extrapolating(template, data, operator, **options)
    return register_once(template, data, operator, **options)


register.__doc__ = fill(register.__doc__)   # the options' entries, from the table (indreg.options.docs)
