"""One call from Python: ``indreg.register(template, data, operator, **options) -> RegistrationResult``.

It validates the options (``indreg.options``: the same table as the app's config), builds the kernel of V, the
model's objective (``indreg.models``: the built-in ones or one you register) and a solver, runs the
shared loop and returns the reconstruction with the deformation and a report (``indreg.run``). The
``indreg-register`` app runs the same code, adding checkpoints, TensorBoard, figures and files.

Convention:
    - ``template`` ``operator.domain.shape`` (``(nx, ny)`` or ``(nx, ny, nz)``, axis 0 = x), ``data``
      ``operator.range_shape`` (``(num_angles, det_count)`` for a ray transform); torch tensors or numpy arrays,
      real and finite. Results' fields follow the domain's dimension (``momentum (N+1, d, *shape)``, ...).
    - Defaults are the paper's suite-1 values (``sigma`` 6, ``gamma`` 1e-6, N = 20, step 0.02, 200
      iterations) except ``step_halving=True``: a step that increases the objective or folds the
      deformation is halved until it does not, so data of any intensity scale are safe (the paper's fixed
      step is ``step_halving=False``).
    - Warnings (folding, objective increase, rejected steps) and progress go through ``logging`` (logger
      ``"indreg"``); ``result.warnings`` counts the iterations that reported one.
"""
from __future__ import annotations

import logging
import sys

from .options import OptionError
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


def register(template, data, operator, **options) -> RegistrationResult:
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
        sigma: width of the Gaussian kernel of V (physical units), 6.0.
        gamma: regularisation weight, 1e-6. num_steps: time steps N, 20.
        action: "geometric" or "mass_preserving". interpolation: "reinterpolate" or "compose" (default
            "compose" with ``solver="fast"``, else "reinterpolate", the paper's).
        backward: None: the model's default (LDDMM: "paper", Algorithm 1's gradient); LDDMM also "exact" (the
            exact gradient of the discrete map by its hand-written adjoint, about the paper's cost; torch.optim
            solvers use it in place of "paper") or "autograd" (the same exact gradient, about 2x the cost).
        model: "lddmm" (default), another name in ``indreg.models.MODELS`` or a model added with
            ``indreg.models.register_model``; a model's own options (``indreg.models``, e.g. ``tau``) are
            keywords too, and an option of another model or solver given a value is an error.
        solver: "algorithm1" (default), "fast" (coarse-to-fine, ``indreg.solvers.MultilevelSolver``; its
            options in ``optimizer_kwargs``), "lbfgs", or any ``torch.optim`` optimizer name (case-insensitive).
        max_iter: 200. grad_tol: stop when the gradient norm is below it (0: never).
        step_size: Algorithm 1's step, 0.02. lr: the torch.optim learning rate (1.0 for L-BFGS; required
            for the others). optimizer_kwargs: passed to the torch.optim optimizer.
        step_halving: True (default): reject and halve steps that increase the objective or fold.
        max_halvings: 20: halvings tried within one iteration (2^-20: intensities up to ~1000x the paper's
            0..1 are handled in the first iteration); the halved step is kept for later iterations.
        tv_weight: weight of a TV term on the deformed template, 0.
        template_scale: None (default: the template is used as given; a warning before the run when
            ``||T I|| / ||g||`` or the least-squares scale ``c = <T I, g> / <T I, T I>`` is outside [1/3, 3]),
            "auto" (the template is multiplied by ``c``) or a number > 0 (the template is multiplied by it).
        background: None (default; a warning when the data look offset), "auto" (the median of the detector's
            outermost columns over all angles) or a number: subtracted from the data before the run. What was
            applied is in ``result.template_scale`` / ``result.background`` (with ``projection_ratio``,
            ``scale_fit``).
        device, dtype: default the template's (numpy input: CPU; float64 arrays stay float64, others float32).
        callback: ``callback(state, info)`` after every iteration; returning True stops the run.
        progress: True shows a tqdm bar on a terminal, else progress lines on the "indreg" logger
            (a stderr handler is added for the call if logging is not configured). log_every: 10.
        target: optional ground truth: adds ``ssim`` and ``psnr`` to the result.
        holdout: validation without a ground truth (``indreg.validation``): every k-th angle (an integer k >= 2,
            indices k // 2, k // 2 + k, ...) or a list of indices is left out of the fit; its relative residual
            is evaluated every ``log_every`` iterations (``history``'s ``holdout_residual``) and reported in
            ``result.holdout``. patience: with holdout, stop (``early_stopped``) after this many evaluations
            without a new minimum.

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
    return build_result(problem, state, loop.history, loop.seconds, status, o["target"], s.units, s.validation)
