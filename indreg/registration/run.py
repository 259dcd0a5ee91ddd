"""One run of a registration, shared by ``indreg.register`` and the ``indreg-register`` app.

:func:`setup` validates the inputs and the options (``indreg.options``), builds the kernel, the model's problem
(``indreg.registration.models``) and the solver; :class:`RegistrationLoop` iterates the solver (history, warnings, progress);
:func:`build_result` assembles a :class:`RegistrationResult` from the final iterate. Nothing here depends on the
model or on the operator type: a problem is used only through ``indreg.solvers.RegistrationProblem``'s protocol.
The app adds checkpoints, TensorBoard, figures and files around the same three steps.

Notes
-----
``template`` ``operator.domain.shape`` (axis 0 = x), ``data`` ``operator.range_shape``; torch tensors
or numpy arrays, real and finite; the run's dtype / device default to the template's (numpy: the CPU, float64
arrays stay float64, others become float32).

Longer than 450 lines: the set-up, the loop and the result are one run, shared by ``indreg.register`` and the app;
the result's Attributes section alone is some 90 lines.
"""
from __future__ import annotations

import logging
import math
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from .. import metrics, options as opts
from .. import tally
from . import corrections, models
from .budget import result_pieces
from .._checks import as_tensor  # noqa: F401  (re-exported: indreg.registration.run.as_tensor)
from ..forward.operator import relative_residual  # noqa: F401  (re-exported: indreg.registration.run.relative_residual)
from ..kernel_width import default_sigma
from ..solvers.state import rounding_tolerance
from ..units import Units, apply_units, compare_units, data_term_scale, measure, noise_residual
from .specimen import plan_box

log = logging.getLogger("indreg")

# ---------------------------------------------------------------------------------------------------- inputs
def resolve_dtype(dtype, template) -> torch.dtype:
    if dtype is None:
        if isinstance(template, torch.Tensor) and template.is_floating_point():
            return template.dtype
        return torch.float64 if getattr(template, "dtype", None) == np.float64 else torch.float32
    d = getattr(torch, dtype, None) if isinstance(dtype, str) else dtype
    if d not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be 'float32' or 'float64' (or the torch dtype), got {dtype!r}")
    return d


def resolve_device(device, template=None) -> torch.device:
    """``None``: the template's device (the CPU for arrays); ``"auto"``: CUDA when available, else the CPU. Under
    ``torchrun`` (``WORLD_SIZE > 1``) ``"cuda"`` / ``"auto"`` is the GPU ``LOCAL_RANK``."""
    if device is None:
        return template.device if isinstance(template, torch.Tensor) else torch.device("cpu")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        d = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be None, 'auto', 'cpu', 'cuda' or 'cuda:<index>', got {device!r}") from None
    if d.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={device!r} was requested but CUDA is not available")
    if d.type == "cuda" and d.index is None and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        d = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(d)
    return d


# ---------------------------------------------------------------------------------------------------- setup
def make_solver(problem, o: dict, solver_options: dict):
    """The registered solver of ``o["solver"]`` (``indreg.registration.solver_registry``) on ``problem``, built with the model's
    ``solver_options`` under its name; a model's ``solver_options["wrap"]`` (a function of the solver) then wraps
    it."""
    entry = opts.solver(o["solver"])
    solver = entry.make(problem, o, solver_options.get(entry.name, {}))
    wrap = solver_options.get("wrap")   # a model's solver around the one built here (e.g. an alternation)
    return solver if wrap is None else wrap(solver)


@dataclass
class Setup:
    """The problem and the solver built by :func:`setup`, with the run's (resolved) options, what :func:`prepare`
    did to the inputs, ``validation``: the held-out angles (``indreg.evaluation.validation.Validation``) when ``holdout``
    is set, else None, ``orientation``: the orientation probe's warning (``indreg.io.orientation.check``), ``""``
    for none, ``box``: the wide box (``indreg.forward.wide_box.WideBox``) the problem lives on, None for the
    operator's own, and ``sigma_scores``: ``sigma="auto"``'s held-out residual of each width it tried (else
    empty)."""
    problem: object
    solver: object
    options: dict
    units: Units = field(default_factory=Units)
    validation: object = None
    orientation: str = ""
    box: object = None
    sigma_scores: dict = field(default_factory=dict)


def setup(template, data, operator, label=lambda o: o.name, strict: bool = True, **options) -> Setup:
    """Validate inputs and options (``indreg.options.resolve``) and build kernel, problem and solver.

    The inputs are first brought to one unit (:func:`prepare`: ``template_scale``, ``background``); with
    ``holdout`` the problem is then built on the operator and the prepared data restricted to the kept angles
    (``indreg.evaluation.validation.split``) and the held-out ones become ``Setup.validation``.
    ``label`` / ``strict``: as ``indreg.options.resolve`` (the app names config keys and drops options of another
    solver). Errors: ``OptionError`` (a bad option), TypeError / ValueError (a bad input), naming it."""
    from ..io import orientation
    from .._checks import check_finite_in
    from ..deform import GaussianKernel
    from ..forward.operator import check_operator
    from ..forward.time_series import as_time_series
    from ..forward.tv import tv_weight_unit
    from ..evaluation.validation import split

    o = opts.resolve(options, label, strict)
    sigma_scores = {}
    if o["sigma"] == "auto":   # chosen from held-out angles first, then the run (indreg.kernel_width)
        sigma, sigma_scores = auto_sigma(template, data, operator, label, strict, options,
                                         shows_progress(o["progress"]))
        options = dict(options, sigma=sigma)
        o = opts.resolve(options, label, strict)
    operator, data = as_time_series(operator, data)   # sequences: one operator / data set per time point
    check_operator(operator, "operator")
    model = models.get(o["model"])
    if template is None and not model.template_optional:
        allowed = [m.name for m in models.MODELS.values() if m.template_optional]
        which = " or ".join(map(repr, allowed)) or "a model that reconstructs it"
        raise TypeError(f"template must be an image of shape {tuple(operator.domain.shape)}; None (an unknown "
                        f"template) only with model={which}")
    first = template if template is not None else data   # the run's dtype / device default to it
    dtype = resolve_dtype(o["dtype"], first)
    device = resolve_device(o["device"], first)
    domain = operator.domain
    if template is not None:
        template = as_tensor(template, "template", domain.shape, dtype, device)
    data = as_tensor(data, "data", operator.range_shape, dtype, device)
    if o["target"] is not None:
        o["target"] = as_tensor(o["target"], "target", domain.shape, torch.float64, torch.device("cpu"))
        if min(domain.shape) < metrics.SSIM_WINDOW:   # refused before the run, not after it
            raise ValueError(f"target: SSIM needs at least {metrics.SSIM_WINDOW} cells along every axis (its window), "
                             f"the image is {tuple(domain.shape)}: leave target out")
    if model.defaults is not None:   # the model's own rules for options left None
        model.defaults(o)
    names = {option.name: option for option in opts.all_options()}
    key = lambda name: label(names[name])   # noqa: E731  (the option as the user named it)
    fit = corrections.Fit(o, key, operator)
    fit.units = measure(template, data, operator, o["background"], key, o["transmission"])
    box = plan_box(template, fit.units.apply(None, data)[1], operator, o, fit.units, key)
    if box is not None:   # a specimen wider than the field of view: the problem on the wide box
        fit.operator = box.widen(operator)
        template = None if template is None else box.pad_image(template, o["template_padding"])
        if template is not None:   # the units compared on the wide box (Units.apply commutes with the padding)
            fit.units.projection_ratio, fit.units.scale_fit = compare_units(template, fit.units.apply(None, data)[1],
                                                                            fit.operator)
    corrections.data_model(fit)   # e.g. T_s (alignment)
    corrections.start(fit, template, fit.units.apply(None, data)[1])   # e.g. the scale through the alignment
    template, data, units = apply_units(template, data, fit.units, o["template_scale"], key)
    given = template if box is None or template is None else box.crop(template)   # on the operator's own box
    if o["target"] is not None and template is not None:   # SSIM / PSNR in the target's units
        units.locate_target(given, o["target"])
    probe = orientation.check(given, data, operator, o["orientation"], key("orientation"))
    operator, fit.data = fit.operator, data
    validation = None
    if o["holdout"] is not None:   # the split is of the prepared data (background removed)
        operator, data, validation = split(operator, data, o["holdout"], o["patience"], label(names["holdout"]))
    units.data_scale = data_term_scale(operator, data, max(domain.extent))   # the given box's side, wide or not
    units.noise_residual = noise_residual(data)
    opts.relative(o, units.data_scale, lambda: tv_weight_unit(operator, data))   # relative weights and step
    for name in ("step_size", "lr"):     # a step must stay finite (and nonzero) in the run's dtype
        if o[name] is not None:
            check_finite_in(o[name], label(names[name]), dtype)
    if o["sigma"] is None:
        o["sigma"] = default_sigma(domain)   # the given box's: the specimen's scale, not the wide box's
    kernel = GaussianKernel(box.domain if box is not None else domain, o["sigma"])
    problem, solver_options = model.make(operator, template, data, kernel, o)
    fit.problem = problem
    solver = corrections.chain(make_solver(problem, o, solver_options), fit)   # the in-the-fit corrections
    return Setup(problem, solver, o, units, validation, probe, box, sigma_scores)


def shows_progress(progress) -> bool:
    """The ``progress`` option resolved: None (the default) is a bar on a terminal only (stderr a tty), so that
    scripts, pipes and tests stay quiet.

    Parameters
    ----------
    progress : bool or None
        The option's value.

    Returns
    -------
    bool
        Whether to show progress.
    """
    return sys.stderr.isatty() if progress is None else bool(progress)


def auto_sigma(template, data, operator, label, strict: bool, options: dict, progress: bool = False) -> tuple:
    """``sigma="auto"``: ``(sigma, {width: held-out residual})``, the width of ``indreg.kernel_width.candidates``
    whose registration (the run's options, its ``holdout`` or every ``AUTO_HOLDOUT``-th angle held out, no early
    stop) predicts the held-out angles best. With ``progress`` each trial run shows a bar on a terminal and each
    width's score is said as it comes (``indreg.kernel_width.choose_sigma``)."""
    from ..kernel_width import AUTO_HOLDOUT, candidates, choose_sigma

    trial = dict(options, holdout=options.get("holdout") or AUTO_HOLDOUT, patience=None, callback=None,
                 progress=False, target=None)
    widths = candidates(getattr(operator, "domain", None) or operator[0].domain)

    def held_out(sigma: float) -> float:
        s = setup(template, data, operator, label, strict, **dict(trial, sigma=sigma))
        o = s.options
        k, state = widths.index(sigma) + 1, initial_state(s.problem)
        RegistrationLoop(s.problem, s.solver, state, o["max_iter"], every=o["log_every"],
                         validation=s.validation, progress=progress,
                         desc=f"sigma='auto' {k}/{len(widths)}: sigma {sigma:.4g}").run()
        if not s.validation.curve:   # fewer iterations than log_every: the held-out residual of the last one
            s.validation.record(state.iteration, s.problem.reconstruction(state.iterate))
        return s.validation.best[1]

    return choose_sigma(held_out, widths, say=_say if progress else None)


def _say(message: str) -> None:
    """A line of progress: logged (INFO), and written above the bars on a terminal where no logging is set up
    (where INFO lines would not show)."""
    log.info("%s", message)
    if sys.stderr.isatty() and not log.hasHandlers():
        from tqdm import tqdm
        tqdm.write(f"[indreg] {message}", file=sys.stderr)


def initial_state(problem):
    """The solvers' starting iterate ``problem.zero_iterate()`` at iteration 0."""
    from ..solvers import SolverState

    return SolverState.initial(problem)


# ---------------------------------------------------------------------------------------------------- the loop
def count_warnings(history) -> int:
    """Iterations whose report carries a warning (the count shown on screen and stored in metrics)."""
    return sum(1 for h in history if h.get("warning"))


def count_rises(history) -> int:
    """Iterations of a fixed step whose objective rose (``objective_rose``: the paper's step takes every step,
    :class:`RegistrationLoop`), counted apart from the warnings.

    Parameters
    ----------
    history : list of dict
        The run's reports.

    Returns
    -------
    int
        How many rose.
    """
    return sum(1 for h in history if h.get("objective_rose"))


#: How the step control words an objective that rose (``indreg.solvers.state.problems``).
_RISE = "objective increased from"


def count_rejected(history) -> int:
    """Iterations whose step was rejected after every halving (the iterate kept)."""
    return sum(1 for h in history if h.get("rejected"))


def count_halvings(history) -> int:
    """Step halvings in all (the sum of the counts in the "step size halved" log lines)."""
    return sum(int(h.get("halvings", 0)) for h in history)


#: A run with step halving stalls (status ``stalled``) when the step was halved and the objective then decreased
#: by less than float rounding (``rounding_tolerance``, relative) over this many iterations: the step has
#: collapsed (the own-data example stalls at iteration 130 of 200 with a step of 4.7e-12; run on, it halves it to
#: 4e-14 and keeps one objective for 70 iterations).
STALL_WINDOW = 10


class Progress:
    """``iteration i/total``, rate (it/s) and ETA for log lines, measured over this process's iterations."""

    def __init__(self, total: int, start: int):
        self.total, self.start, self.t0 = total, start, time.perf_counter()

    def line(self, iteration: int) -> str:
        done = iteration - self.start
        elapsed = time.perf_counter() - self.t0
        rate = done / elapsed if elapsed > 0 and done > 0 else math.nan
        eta = (self.total - iteration) / rate if rate > 0 else math.nan
        eta_s = "?" if not math.isfinite(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        return f"iteration {iteration}/{self.total} ({rate:.3g} it/s, ETA {eta_s})"


def _regularisers(info: dict) -> str:
    """Every regulariser of the report beyond the velocity's, for the log line."""
    extra = [k for k in info if k.endswith("_regulariser")]
    if not extra:
        return ""
    return ", regularisers " + " / ".join(f"{k} {info[k]:.4g}" for k in ("regulariser", *extra))


class RegistrationLoop:
    """``info = solver.step(state)`` until done; history, warnings, progress log lines and a tqdm bar.

    ``callbacks`` (``indreg.callbacks.Callback``, composed with ``&``) hook in before and after every step (either
    may return a status that stops the loop) and add text to the log line printed every ``every`` iterations; the
    app adds TensorBoard, evaluation, checkpoints and its stop requests so, ``indreg.register(callback=...)`` the
    user's: ``callback`` here, after ``callbacks`` (``indreg.callbacks.as_callback``: a function
    ``callback(state, info)`` returning True stops the loop, ``stopped``; a ``Callback``; a list of them).
    ``validation`` (``indreg.evaluation.validation.Validation``, from ``holdout``) puts ``indreg.callbacks.HeldOut`` first in
    the chain (the held-out residual every ``every`` iterations, in ``info``, the history and the log line; early
    stopping). ``run()`` returns the status: ``completed``, ``converged``, ``stalled`` (:data:`STALL_WINDOW`),
    ``failed`` (a non-finite objective or gradient; the state keeps the last iterate the solver accepted),
    ``early_stopped`` (``validation`` ran out of patience), or what a callback returned.
    """

    def __init__(self, problem, solver, state, max_iter: int, every: int = 10, progress: bool = False,
                 desc: str = "indreg", history=None, seconds: float = 0.0, callback=None, validation=None,
                 callbacks=None):
        from ..callbacks import Callbacks, HeldOut, as_callback

        self.problem, self.solver, self.state = problem, solver, state
        self.max_iter, self.every, self.progress, self.desc = max_iter, every, progress, desc
        self.history = [] if history is None else history
        self.seconds = seconds
        self.warnings = count_warnings(self.history)
        self.rtol = rounding_tolerance(state.iterate[0].dtype)
        chain = [HeldOut(validation)] if validation is not None else []
        chain += [c for c in (as_callback(callbacks, "callbacks"), as_callback(callback)) if c is not None]
        self.callbacks = Callbacks(*chain)

    def _warn(self, it: int, info: dict) -> None:
        """Count a warning; log the first one and then one every ``every`` iterations."""
        self.warnings += 1
        if self.warnings == 1 or it % self.every == 0:
            log.warning("iteration %d: %s (%d warnings so far)", it, info["warning"], self.warnings,
                        extra=tally.COUNTED)

    def _rose(self, it: int, info: dict) -> None:
        """A fixed step (no step halving, as the paper's presets) takes every step, so its objective may rise:
        what the paper's step does, not a warning. The report's ``warning`` moves to ``objective_rose``; the
        first rise is said once, the others only counted (metrics.json's ``objective_rises``)."""
        info["objective_rose"], info["warning"] = info["warning"], ""
        if count_rises(self.history) == 0:
            log.warning("iteration %d: %s: the fixed step (step_halving off, as the paper's presets) takes every step, "
                        "so the objective may rise; further rises are counted (objective_rises), not printed "
                        "(step_halving=true, indreg.register's default, rejects such steps)", it,
                        info["objective_rose"], extra=tally.COUNTED)

    def _fixed_step(self) -> bool:
        """Algorithm 1's step control with step halving off: every step is taken."""
        control = getattr(self.solver, "control", None)
        return control is not None and not control.halving

    def _stalled(self) -> bool:
        """Step halving has collapsed the step (:data:`STALL_WINDOW`)."""
        h = self.history
        if not self.solver.halves_steps or len(h) <= STALL_WINDOW:
            return False
        old, new = h[-1 - STALL_WINDOW]["objective"], h[-1]["objective"]
        return any(x.get("halvings") for x in h) and old - new <= self.rtol * abs(old)

    def _end(self, error) -> None:
        """Every callback's ``end`` (``Callbacks.end``); while ``error`` (of ``begin`` or a step) propagates, an
        ``end`` that raises too is logged, not raised: the first exception is the one reported."""
        try:
            self.callbacks.end(self)
        except Exception as e:
            if error is None:
                raise
            log.error("a callback's end() failed while %s propagated: %s: %s", type(error).__name__,
                      type(e).__name__, e)

    def run(self) -> str:
        from tqdm import tqdm

        state, status = self.state, "completed"
        meter = Progress(self.max_iter, state.iteration)
        bar = tqdm(total=self.max_iter, initial=state.iteration, desc=self.desc, dynamic_ncols=True,
                   disable=not (self.progress and sys.stderr.isatty()))
        error = None
        try:
            self.callbacks.begin(self)
            while state.iteration < self.max_iter:
                stop = self.callbacks.before(self)
                if stop:
                    status = stop
                    break
                t0 = time.perf_counter()
                info = self.solver.step(state)
                dt = time.perf_counter() - t0
                self.seconds += dt
                it = state.iteration
                if self._fixed_step() and info.get("warning", "").startswith(_RISE) and ";" not in info["warning"]:
                    self._rose(it, info)
                self.history.append(dict(info, iteration=it, seconds=dt))
                if info.get("warning"):
                    self._warn(it, info)
                if info.get("halvings"):
                    log.info("iteration %d: step size halved %d time(s) to %.4g (the longer step increased the "
                             "objective or folded)", it, info["halvings"], info["step_size"])
                reason = self.solver.status(info)   # failed / converged / completed / None
                if reason is None and self._stalled():
                    reason = "stalled"
                    log.warning("iteration %d: stalled: the objective decreased by less than %.2g (relative) over the "
                                "last %d iterations while step halving shrank the step to %.4g; stopping", it,
                                self.rtol, STALL_WINDOW, info["step_size"])
                if reason == "failed":              # non-finite: stop before any hook saves this iterate
                    status = reason
                    log.error("iteration %d: non-finite objective or gradient (%s); stopping", it,
                              info.get("warning") or "grad_norm is not finite")
                    break
                done = reason is not None
                stop = self.callbacks.after(self, info, done)
                if it % self.every == 0 and not done:
                    log.info("%s: objective %.6g, data fit %.6g, min Jacobian %.4g%s%s", meter.line(it),
                             info["objective"], info["data_fit"], info["min_jacobian"], _regularisers(info),
                             self.callbacks.describe(info))
                bar.update(1)
                bar.set_postfix(objective=f"{info['objective']:.4g}")
                if stop:
                    status = stop
                    break
                if done:
                    status = reason
                    break
        except BaseException as e:
            error = e
            raise
        finally:
            bar.close()
            self._end(error)
        rejected, halvings = count_rejected(self.history), count_halvings(self.history)
        if self.warnings:
            log.warning("%d of %d iterations reported a warning (%d rejected steps, %d step halvings)",
                        self.warnings, len(self.history), rejected, halvings, extra=tally.COUNTED)
        return status


# ---------------------------------------------------------------------------------------------------- the result
@dataclass
class RegistrationResult:
    """What a run returns (:func:`build_result`): ``indreg.register``'s result, the app's ``final.npy`` and
    metrics. Tensors are in the run's dtype / device; ``d`` is the domain's dimension.

    Attributes
    ----------
    deformed : torch.Tensor
        ``(nx, ny)`` (3D: ``(nx, ny, nz)``): the reconstruction (LDDMM: W(nu, I); metamorphosis: f(1)).
    momentum, velocity : torch.Tensor
        ``(N+1, d, *shape)``, ``nu = K m``, component 0 = x.
    deformation : torch.Tensor or None
        ``(d, *shape)``: phi_{1,0} (points, physical units). A slab-wise run keeps ``deformation`` and
        ``trajectory`` only where they fit in ``max_memory`` (else None, and a log line says so:
        ``indreg.registration.budget``).
    trajectory : torch.Tensor or None
        ``(N+1, *shape)``: the image path at ``t_i``.
    history : list of dict
        One dict per iteration (the solver's report plus ``seconds``).
    iterations : int
        Iterations run.
    objective : float
        The final objective.
    terms : dict
        Its terms (``data_fit``, ``regulariser``, ``tv``, a model's own).
    min_jacobian : float
        The least Jacobian determinant of the final map (folding when <= 0).
    residual : float
        ``||T f - g|| / ||g||`` in the data norm (on the fitted data, ``g`` after the background).
    status : str
        ``completed`` (``max_iter``), ``converged`` (``grad_tol``), ``stalled`` (step halving collapsed the
        step, ``indreg.registration.run.STALL_WINDOW``), ``early_stopped`` (``patience`` held-out evaluations
        without a new minimum), ``diverged`` (it ended with ``residual >= 1``: the result fits the data worse
        than a zero image), ``failed`` (a non-finite objective or gradient: see ``history[-1]["warning"]``) or
        ``stopped`` (the callback returned True).
    warnings : int
        The warnings of the run: the iterations that reported one, the set-up's and the end's
        (``indreg.tally``).
    warnings_by_kind : dict
        The same by kind.
    objective_rises : int
        The iterations of a fixed step (``step_halving=False``) whose objective rose, which that step allows (not
        warnings: said once).
    sigma : float
        The kernel's width used.
    sigma_scores : dict
        ``{width: held-out residual}`` when ``sigma="auto"`` chose it; empty otherwise.
    seconds : float
        Wall time of the loop.
    problem : RegistrationProblem
        The problem that was solved.
    outputs : dict
        The model's own results by name (``problem.outputs``, their kinds in ``problem.output_kinds``;
        docs/metamorphosis.md, docs/spatiotemporal.md), also readable as attributes (``result.<name>``).
    ssim, psnr : float or None
        Only with a target, in its units: the data's, or the template's as given (the reconstruction divided
        by ``template_scale``: ``Units.locate_target``).
    units : indreg.units.Units
        What was done to the inputs before the run (``template_scale``, ``background``), what was measured
        (``projection_ratio``, ``scale_fit``) and the data-term scale ``data_scale`` of the relative options.
    holdout : dict
        With ``holdout=``: ``holdout_residual`` (the final reconstruction's relative residual on the held-out
        angles), ``holdout_best_residual`` / ``holdout_best_iteration`` (the least on the curve, evaluated every
        ``log_every`` iterations; the curve is in ``history``) and ``holdout_indices``; empty without.
    alignment : dict
        With ``align=``: the estimated shifts and tilt-axis angle (``indreg.alignment.summary``); empty without.
    poor_fit : str
        The warning of a run that ended far above what the data's noise explains (:func:`poor_fit`: a layout
        mistake, an offset, a wrong scale, or too few iterations), ``""`` for none; the status stays.
    corrections : dict
        The final estimates of the in-the-fit corrections by name (``indreg.registration.corrections``:
        ``alignment``, ``intensity``, a plug-in's), those that ran.
    box : indreg.forward.wide_box.WideBox or None
        The wide box of a specimen wider than the field of view (option ``wide_box``), None without: the images are
        then on ``box.domain``, ``box.crop(result.deformed)`` is the field of view (where SSIM / PSNR score against
        a target given on the operator's box).
    data_part, prior_part : torch.Tensor or None
        Option ``split``: ``deformed`` split into the part the fitted data determine and the part the prior fills
        (``indreg.evaluation.parts``); None when off.
    uncertainty : torch.Tensor or None
        Option ``uncertainty``: the per-voxel standard deviation (``indreg.evaluation.uncertainty``); None when off.
    evaluation : dict
        Their numbers (``split_*``, ``uncertainty_*``; docs/evaluation.md).
    extrapolation : dict
        Option ``extrapolation``: the edge validation's choice (``indreg.registration.extrapolation``), empty without.
    """
    deformed: torch.Tensor
    momentum: torch.Tensor
    velocity: torch.Tensor
    deformation: Optional[torch.Tensor]
    trajectory: Optional[torch.Tensor]
    history: list
    iterations: int
    objective: float
    terms: dict
    min_jacobian: float
    residual: float
    status: str
    warnings: int
    seconds: float
    problem: object = field(repr=False)
    outputs: dict = field(default_factory=dict, repr=False)
    ssim: Optional[float] = None
    psnr: Optional[float] = None
    units: Units = field(default_factory=Units)
    holdout: dict = field(default_factory=dict)
    alignment: dict = field(default_factory=dict)
    poor_fit: str = ""
    corrections: dict = field(default_factory=dict)
    box: object = None
    objective_rises: int = 0
    sigma: Optional[float] = None
    sigma_scores: dict = field(default_factory=dict)
    warnings_by_kind: dict = field(default_factory=dict)
    data_part: Optional[torch.Tensor] = field(default=None, repr=False)
    prior_part: Optional[torch.Tensor] = field(default=None, repr=False)
    uncertainty: Optional[torch.Tensor] = field(default=None, repr=False)
    evaluation: dict = field(default_factory=dict)
    extrapolation: dict = field(default_factory=dict)

    def __getattr__(self, name):
        outputs = self.__dict__.get("outputs", {})
        if name in outputs:
            return outputs[name]
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")


#: A finished run of more than :data:`STALL_WINDOW` iterations that ends at a relative residual above
#: ``POOR_FIT[0] * noise + POOR_FIT[1]`` (``noise``: what the data's noise explains, ``indreg.units.noise_residual``)
#: is reported as a poor fit: levelled off (its objective decreased by less than ``POOR_FIT[2]``, relative, over the
#: last ``STALL_WINDOW`` iterations) the model cannot explain the data (measured: angles and bins swapped, a template
#: at half the data's units); still falling, it may need more iterations or be offset (measured: a template + 0.3).
POOR_FIT = (2.0, 0.1, 0.02)
#: What to check when a run fits far worse than its noise.
_CHECK = ("check the layout (angles and detector bins swapped? the template transposed or flipped?), an offset "
          "(background, template_scale='fit+offset') and the template's scale (template_scale)")


def levelled_off(history: list) -> bool:
    """The objective decreased by less than ``POOR_FIT[2]`` (relative) over the last ``STALL_WINDOW`` iterations."""
    if len(history) <= STALL_WINDOW:
        return False
    old, new = history[-1 - STALL_WINDOW]["objective"], history[-1]["objective"]
    return old - new <= POOR_FIT[2] * abs(new)


def final_status(status: str, residual: float) -> str:
    """A finished run (``completed``, ``converged``, ``stalled``, ``early_stopped``) whose relative residual is ``>= 1``
    (or not finite) has ``diverged``: its reconstruction fits the data worse than a zero image (a warning says so)."""
    finished = status in ("completed", "converged", "stalled", "early_stopped")
    if finished and not residual < 1:
        log.warning("the run diverged: relative data residual ||T f - g|| / ||g|| = %.4g >= 1, worse than a zero "
                    "image; check the units of template and data (template_scale, background) and the step",
                    residual)
        return "diverged"
    return status


def wider_hint(units: Units, box) -> str:
    """What a poor fit's warning says of a specimen wider than the box.

    Parameters
    ----------
    units : Units
        The run's (its ``border``).
    box : WideBox or None
        The run's wide box.

    Returns
    -------
    str
        Where the detector's border is specimen: that the material outside the box adds to the data, and what to
        give; ``""`` otherwise.
    """
    if units.border != "specimen":
        return ""
    if box is None:
        return ("; the detector's outermost columns are specimen, not vacuum: the object is wider than the box and "
                "adds to the data from outside it: widen the box (wide_box=True, slab_thickness, slab_extent)")
    return (f"; the detector's outermost columns are specimen and the wide box ({box.width_factor:.3g} x) may still be "
            "too narrow or too thin for it (slab_extent, slab_thickness), or the template's padding unlike it "
            "(template_padding)")


def poor_fit(status: str, residual: float, noise: float, history: list, held_out: Optional[float] = None,
             orientation: str = "", wider: str = "") -> str:
    """The poor-fit warning of a finished run (:data:`POOR_FIT`), ``""`` for none; the larger of the fitted and the
    ``held_out`` residual counts. ``orientation``: the probe's warning before the run (``indreg.io.orientation``), which
    makes any finished run a poor fit (the residual cannot tell: a mis-read run may end below the right reading's).
    ``wider``: :func:`wider_hint`, appended where the data point to an object wider than the box. The status stays
    what it was: the warning is the word that goes with it."""
    if status not in ("completed", "converged", "stalled", "early_stopped"):
        return ""
    if orientation:
        return f"poor fit: the run fitted data that were probably read wrongly ({orientation})"
    if len(history) <= STALL_WINDOW:
        return ""
    value, where = (held_out, " on the held-out angles") if held_out is not None and held_out > residual else \
        (residual, "")
    if not value > POOR_FIT[0] * noise + POOR_FIT[1]:
        return ""
    far = f"a relative data residual{where} {value:.4g}, far above the {noise:.4g} that the data's noise explains"
    if levelled_off(history):
        return f"poor fit: the objective levelled off at {far}; {_CHECK}{wider}"
    return f"poor fit: the run ended at {far}, its objective still falling: more iterations (max_iter) may fit " \
           f"better; if not, {_CHECK}{wider}"


def build_result(problem, state, history: list, seconds: float, status: str, target=None,
                 units: Optional[Units] = None, validation=None, trajectory: bool = True,
                 orientation: str = "", solver=None, box=None,
                 evaluation: Optional[dict] = None) -> RegistrationResult:
    """The result at ``state``: reconstruction, trajectory (None if not ``trajectory``: a caller taking the frames
    one at a time, ``problem.image_frames``), velocity, phi_{1,0}, terms, min Jacobian, residual (on the fitted
    data), the model's outputs, SSIM / PSNR against ``target`` (float64, CPU) if given, the held-out residuals of
    ``validation`` if given, the summaries of the in-the-fit corrections around ``solver`` if given
    (``indreg.registration.corrections``); ``status`` becomes ``diverged`` if the residual is ``>= 1`` (:func:`final_status`);
    ``orientation``: the orientation probe's warning (``Setup.orientation``), repeated as the poor-fit warning;
    ``box``: the wide box (``Setup.box``): SSIM / PSNR on its field of view.
    A problem with a ``finish(x, validation)`` method (``indreg.problems.residual``) replaces the final iterate by
    its result first. ``evaluation``: the options ``split``, ``uncertainty``, ``uncertainty_samples``
    (``indreg.evaluation.result.evaluate``; None: none of it)."""
    units = units or Units()
    fitted = corrections.summaries(solver, problem)
    finish = getattr(problem, "finish", None)   # a model's last step after the loop (model="residual")
    if finish is not None and status != "failed":
        state.iterate = finish(state.iterate, validation)
    x = state.iterate
    keep_deformation, trajectory = result_pieces(problem, trajectory)   # within max_memory (slab-wise)
    image = problem.reconstruction(x)
    with torch.no_grad():
        velocity = problem.velocity(x[0])
    terms = problem.evaluate_iterate(x)
    residual = problem.relative_residual(x)
    result = RegistrationResult(
        deformed=image, momentum=x[0], velocity=velocity,
        deformation=problem.deformation_field(velocity) if keep_deformation else None,
        trajectory=problem.image_trajectory(x) if trajectory else None, history=history, iterations=state.iteration,
        objective=terms["objective"], terms=terms, min_jacobian=problem.min_jacobian(velocity),
        residual=residual, status=final_status(status, residual), warnings=count_warnings(history),
        objective_rises=count_rises(history), seconds=seconds,
        problem=problem, outputs=problem.outputs(x), units=units, corrections=fitted,
        alignment=fitted.get("alignment", {}), box=box)
    if target is not None:
        scored = units.to_target_units(image)   # the target's units (template_scale: maybe the template's)
        if box is not None and tuple(scored.shape) != tuple(target.shape):   # the field of view
            scored = box.crop(scored)
        result.ssim, result.psnr = metrics.ssim(scored, target), metrics.psnr(scored, target)
    if validation is not None:
        result.holdout = validation.summary(image)
    if evaluation is not None and status != "failed":
        from ..evaluation.result import evaluate

        e = evaluate(problem, x, image, solver, evaluation, validation)
        result.data_part, result.prior_part, result.uncertainty = e["data_part"], e["prior_part"], e["uncertainty"]
        result.evaluation = e["summary"]
    result.poor_fit = poor_fit(result.status, residual, units.noise_residual, history,
                               result.holdout.get("holdout_residual"), orientation, wider_hint(units, box))
    if result.poor_fit:
        log.warning("%s", result.poor_fit)
    result.warnings, result.warnings_by_kind = tally.warning_kinds(history, tally.current())
    return result
