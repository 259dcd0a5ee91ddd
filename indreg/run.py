"""One run of a registration, shared by ``indreg.register`` and the ``indreg-register`` app.

:func:`setup` validates the inputs and the options (``indreg.options``), builds the kernel, the model's problem
(``indreg.models``) and the solver; :class:`RegistrationLoop` iterates the solver (history, warnings, progress);
:func:`build_result` assembles a :class:`RegistrationResult` from the final iterate. Nothing here depends on the
model or on the operator type: a problem is used only through ``indreg.solvers.RegistrationProblem``'s protocol.
The app adds checkpoints, TensorBoard, figures and files around the same three steps.

Convention: ``template`` ``operator.domain.shape`` (axis 0 = x), ``data`` ``operator.range_shape``; torch tensors
or numpy arrays, real and finite; the run's dtype / device default to the template's (numpy: the CPU, float64
arrays stay float64, others become float32).
"""
from __future__ import annotations

import logging
import math
import sys
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from . import models, options as opts
from ._checks import as_tensor  # noqa: F401  (re-exported: indreg.run.as_tensor)
from .forward.operator import relative_residual  # noqa: F401  (re-exported: indreg.run.relative_residual)
from .solvers.state import rounding_tolerance

log = logging.getLogger("indreg")

#: Algorithm 1's step when none is given (the paper's suite-1 value).
ALGORITHM1_STEP = 0.02


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
    """``None``: the template's device (the CPU for arrays); ``"auto"``: CUDA when available, else the CPU."""
    if device is None:
        return template.device if isinstance(template, torch.Tensor) else torch.device("cpu")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        d = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be None, 'auto', 'cpu', 'cuda' or 'cuda:<index>', got {device!r}") from None
    if d.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={device!r} was requested but CUDA is not available")
    return d


# ---------------------------------------------------------------------------------------------------- units
#: Template and data agree in units when ``||T I|| / ||g||`` and ``c = <T I, g> / <T I, T I>`` lie in
#: ``[1 / UNIT_RANGE, UNIT_RANGE]`` (the paper's suites: 0.68-1.3); outside, a warning names both.
UNIT_RANGE = 3.0
#: Data look offset when the median of the detector's outermost columns (``border_level``) is away from zero, or
#: the median of all the data is below zero, by more than this fraction of the data's range.
OFFSET_FRACTION = 0.05
#: The factors by which file formats change units: the full scales of 8- to 16-bit integers (``2^b - 1``: images
#: are normalised by their type's maximum), the metric prefixes' 1e3 and 1e6, their reciprocals, and 1.
#: ``template_scale="auto"`` takes the nearest one when the fitted ``c`` lies within ``UNIT_SNAP`` of it
#: (relative), since the fit is biased low by the shapes' mismatch (the paper's suite 1: ``c = 0.9735`` for a
#: template in the data's units; the own-data example: 0.990). Factors of 10 are left out: a physical factor (one
#: over a voxel side of 10.5 nm: 0.095) lies near them as often as a unit change does.
UNIT_FACTORS = tuple(sorted({f ** e for f in [1e3, 1e6] + [float(2 ** b - 1) for b in (8, 10, 12, 14, 16)]
                             for e in (1, -1)} | {1.0}))
UNIT_SNAP = 0.05


@dataclass
class Units:
    """What :func:`prepare` did to the inputs, for the result and metrics.json.

    ``template_scale``: the factor applied to the template (1.0: none); ``background``: the offset subtracted
    from the data (0.0: none); ``projection_ratio`` = ``||T I|| / ||g||`` and ``scale_fit`` = the least-squares
    ``c = <T I, g> / <T I, T I>`` of the template as given and the data after the background (data inner product
    ``T.inner_data``)."""
    template_scale: float = 1.0
    background: float = 0.0
    projection_ratio: float = math.nan
    scale_fit: float = math.nan

    def as_dict(self) -> dict:
        return {"template_scale": self.template_scale, "background": self.background,
                "projection_ratio": self.projection_ratio, "scale_fit": self.scale_fit}


def border_level(data: torch.Tensor) -> float:
    """The median of the outermost ``max(1, n // 16)`` detector columns on each side (the last axis: bins of a
    sinogram, columns of a tilt series) over all angles (and rows): the level of the detector outside the
    object's shadow, 0 for projections of an object inside the field of view."""
    n = data.shape[-1]
    k = max(1, n // 16)
    border = torch.cat([data[..., :k].reshape(-1), data[..., n - k:].reshape(-1)]) if n > 1 else data.reshape(-1)
    return float(border.double().median())


def _ratio(a: float, b: float) -> float:
    return a / b if b != 0 else (math.nan if a == 0 else math.inf)


def check_offset(data: torch.Tensor, label: str) -> None:
    """Warn when the data look offset: their border level or their median is far from zero (a fraction
    ``OFFSET_FRACTION`` of their range) where projections of an object would be about zero outside it and
    mostly positive."""
    spread = float(data.max() - data.min())
    border, median = border_level(data), float(data.double().median())
    if spread > 0 and (abs(border) > OFFSET_FRACTION * spread or median < -OFFSET_FRACTION * spread):
        log.warning("the data look offset: the median of the outermost detector columns is %.4g and of all values "
                    "%.4g, with a range of %.4g (projections are about 0 outside the object); pass %s='auto' to "
                    "subtract the border level, or %s=<number>", border, median, spread, label, label)


def compare_units(template: torch.Tensor, data: torch.Tensor, operator) -> tuple:
    """``(||T I|| / ||g||, c = <T I, g> / <T I, T I>)`` in the data inner product ``operator.inner_data``."""
    with torch.no_grad():
        TI = operator(template)
        tt = float(operator.inner_data(TI, TI).sum())
        tg = float(operator.inner_data(TI, data).sum())
        gg = float(operator.inner_data(data, data).sum())
    return math.sqrt(_ratio(tt, gg)), _ratio(tg, tt)


def unit_factor(c: float) -> float:
    """The entry of ``UNIT_FACTORS`` nearest to ``c`` (in ratio) when within ``UNIT_SNAP`` of it, else ``c``."""
    nearest = min(UNIT_FACTORS, key=lambda f: abs(math.log(c / f)))
    return nearest if abs(c / nearest - 1) <= UNIT_SNAP else c


def _template_factor(template_scale, units: Units, key: str) -> float:
    """The template's factor for ``template_scale`` (None: 1 and a warning if the units look different)."""
    if template_scale == "auto":
        if not (math.isfinite(units.scale_fit) and units.scale_fit > 0):
            raise ValueError(f"{key}='auto' found no positive scale: c = <T I, g> / <T I, T I> = "
                             f"{units.scale_fit:.4g}; the template's projection does not resemble the data: check "
                             f"both, or give {key}=<number>")
        c = unit_factor(units.scale_fit)
        log.info("template scaled by %.6g (%s='auto': the fitted c = %.6g%s; ||T I|| / ||g|| was %.4g)", c, key,
                 units.scale_fit, "" if c == units.scale_fit else ", taken as the nearest unit factor",
                 units.projection_ratio)
        return c
    if template_scale is not None:
        return float(template_scale)
    if not all(1 / UNIT_RANGE <= v <= UNIT_RANGE for v in (units.projection_ratio, units.scale_fit)):
        log.warning("template and data look like different units: ||T I|| / ||g|| = %.4g and the least-squares "
                    "scale c = <T I, g> / <T I, T I> = %.4g (expected in [1/%g, %g]); pass %s='auto' to scale the "
                    "template by c, %s=<number>, or bring the template to the data's units", units.projection_ratio,
                    units.scale_fit, UNIT_RANGE, UNIT_RANGE, key, key)
    return 1.0


def prepare(template: torch.Tensor, data: torch.Tensor, operator, template_scale=None, background=None,
            label=lambda name: name) -> tuple:
    """Bring template and data to one unit before the run: ``(template, data, Units)``.

    ``background`` (None, ``"auto"``: :func:`border_level`, or a number) is subtracted from the data; without it
    a warning when the data look offset (:func:`check_offset`). Then :func:`compare_units` compares the
    template's projection with the data, and ``template_scale`` (None, ``"auto"``: ``c``, or a number) multiplies
    the template; without a scale a warning names both numbers when either is outside
    ``[1/UNIT_RANGE, UNIT_RANGE]`` (a template None, unknown, is returned as it is). ``label(name)`` names the
    option in messages (the app: its config key). Raises ValueError when ``"auto"`` finds no positive ``c`` (a
    template whose projection does not resemble the data)."""
    units = Units()
    if background is None:
        check_offset(data, label("background"))
    else:
        units.background = border_level(data) if background == "auto" else float(background)
        data = data - units.background
        log.info("subtracted the background %.6g from the data (%s=%r)", units.background, label("background"),
                 background)
    if template is None:   # unknown (reconstructed by the model): no units to compare
        return template, data, units
    units.projection_ratio, units.scale_fit = compare_units(template, data, operator)
    units.template_scale = _template_factor(template_scale, units, label("template_scale"))
    if units.template_scale != 1.0:
        template = template * units.template_scale
    return template, data, units


# ---------------------------------------------------------------------------------------------------- setup
def make_solver(problem, o: dict, solver_options: dict):
    """The solver of ``o["solver"]`` on ``problem``: ``Algorithm1``, ``MultilevelSolver`` (``"fast"``) or
    ``TorchOptimSolver`` (a torch.optim name), with the model's ``solver_options`` for its kind; a model's
    ``solver_options["wrap"]`` (a function of the solver) then wraps it."""
    wrap = solver_options.get("wrap")   # a model's solver around the one built here (e.g. an alternation)
    solver = _make_solver(problem, o, solver_options)
    return solver if wrap is None else wrap(solver)


def _make_solver(problem, o: dict, solver_options: dict):
    from .solvers import Algorithm1, MultilevelSolver, TorchOptimSolver
    from .solvers.multilevel import options as fast_options

    kind = models.solver_kind(o["solver"])
    extra = solver_options.get(kind, {})
    if kind == opts.FAST:
        unknown = sorted(set(o["optimizer_kwargs"]) - set(fast_options()))
        if unknown:
            raise TypeError(f"unknown optimizer_kwargs for solver='fast': {', '.join(unknown)}; valid: "
                            f"{', '.join(fast_options())}")
        return MultilevelSolver(problem, max_iter=o["max_iter"], grad_tol=o["grad_tol"], **o["optimizer_kwargs"],
                                **extra)
    if kind == opts.ALGORITHM1:
        return Algorithm1(problem, step_size=ALGORITHM1_STEP if o["step_size"] is None else o["step_size"],
                          max_iter=o["max_iter"], grad_tol=o["grad_tol"], step_halving=o["step_halving"],
                          max_halvings=o["max_halvings"], **extra)
    return TorchOptimSolver(problem, optimizer=o["solver"], lr=o["lr"], max_iter=o["max_iter"],
                            grad_tol=o["grad_tol"], **extra, **o["optimizer_kwargs"])


@dataclass
class Setup:
    """The problem and the solver built by :func:`setup`, with the run's (resolved) options, what :func:`prepare`
    did to the inputs, and ``validation``: the held-out angles (``indreg.validation.Validation``) when ``holdout``
    is set, else None."""
    problem: object
    solver: object
    options: dict
    units: Units = field(default_factory=Units)
    validation: object = None


def setup(template, data, operator, label=lambda o: o.name, strict: bool = True, **options) -> Setup:
    """Validate inputs and options (``indreg.options.resolve``) and build kernel, problem and solver.

    The inputs are first brought to one unit (:func:`prepare`: ``template_scale``, ``background``); with
    ``holdout`` the problem is then built on the operator and the prepared data restricted to the kept angles
    (``indreg.validation.split``) and the held-out ones become ``Setup.validation``.
    ``label`` / ``strict``: as ``indreg.options.resolve`` (the app names config keys and drops options of another
    solver). Errors: ``OptionError`` (a bad option), TypeError / ValueError (a bad input), naming it."""
    from . import alignment
    from ._checks import check_finite_in
    from .deform import GaussianKernel
    from .forward.operator import check_operator
    from .forward.time_series import as_time_series
    from .validation import split

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
    if o["interpolation"] is None:
        o["interpolation"] = "compose" if o["solver"] == opts.FAST or o["velocity_factor"] > 1 else "reinterpolate"
    for option in opts.all_options():   # a step must stay finite (and nonzero) in the run's dtype
        if option.name in ("step_size", "lr") and o[option.name] is not None:
            check_finite_in(o[option.name], label(option), dtype)
    names = {option.name: option for option in opts.all_options()}
    template, data, units = prepare(template, data, operator, o["template_scale"], o["background"],
                                    lambda name: label(names[name]))
    aligned = operator = alignment.aligned(operator, o["align"], label(names["align"]))   # T_s (docs/alignment.md)
    full_data, validation = data, None
    if o["holdout"] is not None:   # the split is of the prepared data (background removed)
        operator, data, validation = split(operator, data, o["holdout"], o["patience"], label(names["holdout"]))
    kernel = GaussianKernel(domain, o["sigma"])
    problem, solver_options = model.build(operator, template, data, kernel, o)
    solver = alignment.wrap(make_solver(problem, o, solver_options), aligned, full_data, label(names["align"]))
    return Setup(problem, solver, o, units, validation)


def initial_state(problem):
    """The solvers' starting iterate ``problem.zero_iterate()`` at iteration 0."""
    from .solvers import SolverState

    return SolverState.initial(problem)


# ---------------------------------------------------------------------------------------------------- the loop
def count_warnings(history) -> int:
    """Iterations whose report carries a warning (the count shown on screen and stored in metrics)."""
    return sum(1 for h in history if h.get("warning"))


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


def _held_out(info: dict) -> str:
    return f", held-out residual {info['holdout_residual']:.4g}" if "holdout_residual" in info else ""


class RegistrationLoop:
    """``info = solver.step(state)`` until done; history, warnings, progress log lines and a tqdm bar.

    Subclasses (the experiment app) hook in with :meth:`before_step` (may return a stop status),
    :meth:`after_step` (every iteration; may return a stop status) and :meth:`describe` (extra text for the
    log line printed every ``every`` iterations). ``run()`` returns the status: ``completed``,
    ``converged``, ``stalled`` (:data:`STALL_WINDOW`), ``failed`` (a non-finite objective or gradient; the state
    keeps the last iterate the solver accepted), ``early_stopped`` (``validation`` ran out of patience), or what a
    hook returned. ``callback(state, info)`` returning True stops it (``stopped``).

    ``validation`` (``indreg.validation.Validation``, from ``holdout``): every ``every`` iterations the held-out
    residual of the current reconstruction goes into ``info`` and the history as ``holdout_residual`` (before
    the hooks see ``info``) and into the log line.
    """

    def __init__(self, problem, solver, state, max_iter: int, every: int = 10, progress: bool = False,
                 desc: str = "indreg", history=None, seconds: float = 0.0, callback=None, validation=None):
        self.problem, self.solver, self.state = problem, solver, state
        self.max_iter, self.every, self.progress, self.desc = max_iter, every, progress, desc
        self.history = [] if history is None else history
        self.seconds = seconds
        self.callback = callback
        self.warnings = count_warnings(self.history)
        self.rtol = rounding_tolerance(state.iterate[0].dtype)
        self.validation = validation
        if validation is not None:
            validation.restore(self.history)

    def before_step(self) -> Optional[str]:
        return None

    def after_step(self, info: dict, done: bool) -> Optional[str]:
        if self.callback is not None and self.callback(self.state, info):
            return "stopped"
        return None

    def describe(self, info: dict) -> str:
        return ""

    def _warn(self, it: int, info: dict) -> None:
        """Count a warning; log the first one and then one every ``every`` iterations."""
        self.warnings += 1
        if self.warnings == 1 or it % self.every == 0:
            log.warning("iteration %d: %s (%d warnings so far)", it, info["warning"], self.warnings)

    def _validate(self, it: int, info: dict) -> Optional[str]:
        """Every ``every`` iterations: the held-out residual into ``info`` and the history; ``early_stopped`` when
        the validation's patience has run out."""
        v = self.validation
        if v is None or it % self.every:
            return None
        info["holdout_residual"] = self.history[-1]["holdout_residual"] = \
            v.record(it, self.problem.reconstruction(self.state.iterate))
        if not v.exhausted():
            return None
        best, value = v.best
        log.info("iteration %d: the held-out residual has not decreased in %d evaluations (least %.4g at "
                 "iteration %d); stopping", it, v.patience, value, best)
        return "early_stopped"

    def _stalled(self) -> bool:
        """Step halving has collapsed the step (:data:`STALL_WINDOW`)."""
        h, solver = self.history, self.solver
        if not (getattr(solver, "step_halving", False) and hasattr(solver, "step_sizes")) or len(h) <= STALL_WINDOW:
            return False
        old, new = h[-1 - STALL_WINDOW]["objective"], h[-1]["objective"]
        return any(x.get("halvings") for x in h) and old - new <= self.rtol * abs(old)

    def run(self) -> str:
        from tqdm import tqdm

        state, status = self.state, "completed"
        meter = Progress(self.max_iter, state.iteration)
        bar = tqdm(total=self.max_iter, initial=state.iteration, desc=self.desc, dynamic_ncols=True,
                   disable=not (self.progress and sys.stderr.isatty()))
        try:
            while state.iteration < self.max_iter:
                stop = self.before_step()
                if stop:
                    status = stop
                    break
                t0 = time.perf_counter()
                info = self.solver.step(state)
                dt = time.perf_counter() - t0
                self.seconds += dt
                it = state.iteration
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
                early = self._validate(it, info)
                stop = self.after_step(info, done) or early
                if it % self.every == 0 and not done:
                    log.info("%s: objective %.6g, data fit %.6g, min Jacobian %.4g%s%s%s", meter.line(it),
                             info["objective"], info["data_fit"], info["min_jacobian"], _regularisers(info),
                             _held_out(info), self.describe(info))
                bar.update(1)
                bar.set_postfix(objective=f"{info['objective']:.4g}")
                if stop:
                    status = stop
                    break
                if done:
                    status = reason
                    break
        finally:
            bar.close()
        rejected, halvings = count_rejected(self.history), count_halvings(self.history)
        if self.warnings:
            log.warning("%d of %d iterations reported a warning (%d rejected steps, %d step halvings)", self.warnings,
                        len(self.history), rejected, halvings)
        return status


# ---------------------------------------------------------------------------------------------------- the result
@dataclass
class RegistrationResult:
    """What a run returns (:func:`build_result`).

    Convention: ``deformed`` ``(nx, ny)`` = the reconstruction (LDDMM: W(nu, I); metamorphosis: f(1));
    ``trajectory`` ``(N+1, nx, ny)`` = the image path at ``t_i``; ``momentum`` and ``velocity`` ``(N+1, d, *shape)``
    (``nu = K m``, component 0 = x); ``deformation`` ``(d, *shape)`` = phi_{1,0} (points, physical units);
    tensors in the run's dtype / device. ``residual`` = ``||T f - g|| / ||g||`` in the data norm (on the fitted
    data, ``g`` after the background); ``history``: one dict per iteration (the solver's report plus ``seconds``);
    ``status``: ``completed`` (``max_iter``), ``converged`` (``grad_tol``), ``stalled`` (step halving collapsed the
    step, ``indreg.run.STALL_WINDOW``), ``early_stopped`` (``patience`` held-out evaluations without a new minimum),
    ``diverged`` (it ended with ``residual >= 1``: the result fits the data worse than a zero image), ``failed`` (a
    non-finite objective or gradient: see ``history[-1]["warning"]``) or ``stopped`` (the callback returned True).
    ``template_scale``, ``background``, ``projection_ratio``, ``scale_fit``: what was done to the inputs before the
    run (:class:`Units`). ``ssim`` / ``psnr`` only with a target. ``holdout`` (with ``holdout=``):
    ``holdout_residual`` (the final reconstruction's relative residual on the held-out angles),
    ``holdout_best_residual`` / ``holdout_best_iteration`` (the least on the curve, evaluated every ``log_every``
    iterations; the curve is in ``history``) and ``holdout_indices``; empty without. ``alignment`` (with
    ``align=``): the estimated shifts and tilt-axis angle (``indreg.alignment.summary``); empty without.
    ``outputs``: the model's
    own results by name (metamorphosis: ``source``, ``deformation_part`` = W(nu, I), ``intensity_part`` =
    f(1) - W(nu, I)), also readable as attributes (``result.source``).
    """
    deformed: torch.Tensor
    momentum: torch.Tensor
    velocity: torch.Tensor
    deformation: torch.Tensor
    trajectory: torch.Tensor
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
    template_scale: float = 1.0
    background: float = 0.0
    projection_ratio: float = math.nan
    scale_fit: float = math.nan
    holdout: dict = field(default_factory=dict)
    alignment: dict = field(default_factory=dict)

    def __getattr__(self, name):
        outputs = self.__dict__.get("outputs", {})
        if name in outputs:
            return outputs[name]
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")


def final_status(status: str, residual: float) -> str:
    """A finished run (``completed``, ``converged``, ``stalled``, ``early_stopped``) whose relative residual is ``>= 1`` (or not
    finite) has ``diverged``: its reconstruction fits the data worse than a zero image (a warning says so)."""
    if status in ("completed", "converged", "stalled", "early_stopped") and not residual < 1:
        log.warning("the run diverged: relative data residual ||T f - g|| / ||g|| = %.4g >= 1, worse than a zero "
                    "image; check the units of template and data (template_scale, background) and the step",
                    residual)
        return "diverged"
    return status


def build_result(problem, state, history: list, seconds: float, status: str, target=None,
                 units: Optional[Units] = None, validation=None) -> RegistrationResult:
    """The result at ``state``: reconstruction, trajectory, velocity, phi_{1,0}, terms, min Jacobian, residual
    (on the fitted data), the model's outputs, SSIM / PSNR of the reconstruction against ``target`` (float64, CPU)
    if given, and the held-out residuals of ``validation`` if given; ``status`` becomes ``diverged`` if the
    residual is ``>= 1`` (:func:`final_status`); ``units``: what :func:`prepare` did to the inputs."""
    from . import alignment, metrics

    x = state.iterate
    image = problem.reconstruction(x)
    with torch.no_grad():
        velocity = problem.velocity(x[0])
    terms = problem.evaluate_iterate(x)
    residual = problem.relative_residual(x)
    result = RegistrationResult(
        deformed=image, momentum=x[0], velocity=velocity, deformation=problem.deformation_field(velocity),
        trajectory=problem.image_trajectory(x), history=history, iterations=state.iteration,
        objective=terms["objective"], terms=terms, min_jacobian=problem.min_jacobian(velocity),
        residual=residual, status=final_status(status, residual), warnings=count_warnings(history), seconds=seconds,
        problem=problem, outputs=problem.outputs(x), alignment=alignment.summary(problem),
        **(units or Units()).as_dict())
    if target is not None:
        result.ssim, result.psnr = metrics.ssim(image, target), metrics.psnr(image, target)
    if validation is not None:
        result.holdout = validation.summary(image)
    return result
