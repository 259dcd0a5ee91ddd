"""One call from Python: ``indreg.register(template, data, operator, **options) -> RegistrationResult``.

It builds the Gaussian kernel of V, the LDDMM deformation, the objective (``IndirectRegistration``) and a
solver from keyword options, iterates, and returns the deformed template with the deformation and a report.
``model="metamorphosis"`` (with ``tau``) builds the metamorphosis operator, objective and solvers instead
(``indreg.deform.MetamorphosisDeformation``, ``indreg.solvers.MetamorphosisRegistration``): the result's image
is then ``f(1)``, with its pure-deformation and intensity parts.
The ``indreg-register`` app runs the same code (:func:`setup`, :class:`RegistrationLoop`), adding checkpoints,
TensorBoard, figures and files.

Convention:
    - ``template`` ``(nx, ny)`` on ``operator.domain`` (axis 0 = x), ``data`` ``operator.range_shape``
      (``(num_angles, det_count)`` for a ray transform); torch tensors or numpy arrays, real and finite.
    - 3D: any operator whose ``domain`` is 3D, ``template (nx, ny, nz)``; the result's fields get a third
      component / axis (``momentum (N+1, 3, nx, ny, nz)``, ...). ``model="lddmm"`` with ``solver="algorithm1"`` or a
      torch.optim name; ``solver="fast"``, ``model="metamorphosis"``, ``tv_weight > 0`` and ``target`` are 2D only
      (a clear error).
    - Defaults are the paper's suite-1 values (``sigma`` 6, ``gamma`` 1e-6, N = 20, step 0.02, 200
      iterations) except ``step_halving=True``: a step that increases the objective or folds the
      deformation is halved until it does not, so data of any intensity scale are safe (the paper's fixed
      step is ``step_halving=False``).
    - Warnings (folding, objective increase, rejected steps) and progress go through ``logging`` (logger
      ``"indreg"``); ``result.warnings`` counts the iterations that reported one.
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

log = logging.getLogger("indreg")

MODELS = ("lddmm", "metamorphosis")
#: Default ``tau`` of ``model="metamorphosis"`` (the source penalty, in the objective's scale).
METAMORPHOSIS_TAU = 1.0
#: Options of :func:`register` and their defaults (``None``: see :func:`register`).
DEFAULTS = {
    "sigma": 6.0, "gamma": 1e-6, "num_steps": 20, "action": "geometric", "interpolation": None,
    "backward": None, "model": "lddmm", "tau": METAMORPHOSIS_TAU, "source_sigma": None, "source_mask": None, "source_step_size": None,
    "source_lr": None, "source_start": 0, "solver": "algorithm1", "max_iter": 200, "step_size": None, "lr": None,
    "step_halving": True, "max_halvings": 20, "grad_tol": 0.0, "tv_weight": 0.0, "optimizer_kwargs": None, "device": None,
    "dtype": None, "callback": None, "progress": False, "log_every": 10, "target": None,
}
ALGORITHM1_STEP = 0.02


@dataclass
class RegistrationResult:
    """What :func:`register` returns.

    Convention: ``deformed`` ``(nx, ny)`` = W(nu, I); ``trajectory`` ``(N+1, nx, ny)`` = W(nu, I)(t_i);
    ``momentum`` and ``velocity`` ``(N+1, 2, nx, ny)`` (``nu = K m``, component 0 = x); ``deformation``
    ``(2, nx, ny)`` = phi_{1,0} (points, physical units); tensors in the run's dtype / device.
    ``residual`` = ``||T f - g|| / ||g||`` in the data norm; ``history``: one dict per iteration (the
    solver's report plus ``seconds``); ``status``: ``completed`` (``max_iter``), ``converged`` (``grad_tol``),
    ``failed`` (a non-finite objective or gradient: see ``history[-1]["warning"]``) or ``stopped`` (the
    callback returned True). ``ssim`` / ``psnr`` only with
    ``target=``. ``model="metamorphosis"``: ``deformed`` = f(1), ``trajectory`` = f(t_i), ``source`` = zeta
    ``(N+1, nx, ny)``, ``deformation_part`` = W(nu, I) and ``intensity_part`` = f(1) - W(nu, I) (else None).
    """
    deformed: torch.Tensor
    momentum: torch.Tensor
    velocity: torch.Tensor
    deformation: torch.Tensor
    trajectory: torch.Tensor
    history: list
    iterations: int
    objective: float
    min_jacobian: float
    residual: float
    status: str
    warnings: int
    seconds: float
    problem: object = field(repr=False)
    ssim: Optional[float] = None
    psnr: Optional[float] = None
    source: Optional[torch.Tensor] = None
    deformation_part: Optional[torch.Tensor] = None
    intensity_part: Optional[torch.Tensor] = None


def _unknown(options: dict) -> None:
    unknown = sorted(set(options) - set(DEFAULTS))
    if unknown:
        raise TypeError(f"unknown option(s) {', '.join(unknown)}; valid options: {', '.join(sorted(DEFAULTS))}")


def _resolve_dtype(dtype, template) -> torch.dtype:
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
    d = torch.device(device)
    if d.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={device!r} was requested but CUDA is not available")
    return d


def as_array(x, name: str, shape: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``x`` (tensor or array-like) as a real, finite tensor of ``shape`` in ``dtype`` / ``device``;
    errors name the argument."""
    if isinstance(x, torch.Tensor):
        t = x.detach()
    else:
        a = np.asarray(x)
        if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
            raise TypeError(f"{name} must be a numeric array or torch tensor, got {type(x).__name__} of {a.dtype}")
        t = torch.from_numpy(np.ascontiguousarray(a))
    if t.is_complex():
        raise TypeError(f"{name} must be real, got the complex dtype {t.dtype}")
    if tuple(t.shape) != tuple(shape):
        raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {tuple(shape)}")
    t = t.to(device=device, dtype=dtype)
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains non-finite values (nan or inf)")
    return t


def make_solver(problem, solver: str, max_iter: int, step_size, lr, step_halving: bool, max_halvings: int,
                grad_tol: float, optimizer_kwargs: dict | None, source_step_size=None, source_lr=None,
                source_start: int = 0):
    """``Algorithm1`` (``solver="algorithm1"``, ``step_size``), ``MultilevelSolver`` (``solver="fast"``) or
    ``TorchOptimSolver`` (a ``torch.optim`` name, case-insensitive, ``lr``); for a metamorphosis problem
    ``MetamorphosisDescent`` (``source_step_size``, None: ``1 / (tau + ||T||^2)``) or ``MetamorphosisTorchOptim``
    (``source_lr``, None: ``lr``)."""
    from .solvers import Algorithm1, MetamorphosisDescent, MetamorphosisTorchOptim, MultilevelSolver, TorchOptimSolver
    from .solvers.multilevel import options as fast_options

    if not isinstance(solver, str):
        raise TypeError(f"solver must be 'algorithm1', 'fast' or a torch.optim optimizer name, got {solver!r}")
    if solver.lower() == "fast":
        if is_metamorphosis(problem):
            raise TypeError("solver='fast' is for model='lddmm'; metamorphosis takes 'algorithm1' or a torch.optim name")
        if lr is not None or step_size is not None:
            raise TypeError("solver='fast' takes neither lr nor step_size (its options go in optimizer_kwargs: "
                            f"{', '.join(fast_options())})")
        unknown = sorted(set(optimizer_kwargs or {}) - set(fast_options()))
        if unknown:
            raise TypeError(f"unknown optimizer_kwargs for solver='fast': {', '.join(unknown)}; valid: "
                            f"{', '.join(fast_options())}")
        return MultilevelSolver(problem, max_iter=max_iter, grad_tol=grad_tol, **(optimizer_kwargs or {}))
    if solver.lower() == "algorithm1":
        if lr is not None:
            raise TypeError("lr is the torch.optim learning rate; solver='algorithm1' takes step_size")
        if optimizer_kwargs:
            raise TypeError("optimizer_kwargs apply to torch.optim solvers, not solver='algorithm1'")
        step = ALGORITHM1_STEP if step_size is None else step_size
        if is_metamorphosis(problem):
            return MetamorphosisDescent(problem, step_size=step, max_iter=max_iter, grad_tol=grad_tol,
                                        source_step_size="auto" if source_step_size is None else source_step_size,
                                        step_halving=step_halving, max_halvings=max_halvings,
                                        source_start=source_start)
        return Algorithm1(problem, step_size=step, max_iter=max_iter, grad_tol=grad_tol, step_halving=step_halving,
                          max_halvings=max_halvings)
    if step_size is not None:
        raise TypeError(f"step_size is Algorithm 1's; solver={solver!r} (torch.optim) takes lr")
    if source_start:
        raise TypeError("source_start is an option of solver='algorithm1' (metamorphosis)")
    if is_metamorphosis(problem):
        return MetamorphosisTorchOptim(problem, optimizer=solver, lr=lr, source_lr=source_lr, max_iter=max_iter,
                                       grad_tol=grad_tol, **(optimizer_kwargs or {}))
    # a line search needs the gradient of the function it evaluates: the paper's backward becomes "exact"
    backward = "exact" if problem.deformation.backward == "paper" else problem.deformation.backward
    return TorchOptimSolver(problem, optimizer=solver, lr=lr, max_iter=max_iter, grad_tol=grad_tol, backward=backward,
                            **(optimizer_kwargs or {}))


@dataclass
class Setup:
    """The objective and the solver built by :func:`setup`, with the run's options."""
    problem: object
    solver: object
    options: dict


def setup(template, data, operator, **options) -> Setup:
    """Validate the inputs and build kernel, deformation, objective and solver (options as :func:`register`)."""
    from .deform import GaussianKernel, LDDMMDeformation, MetamorphosisDeformation
    from .forward.operator import check_operator
    from .solvers import IndirectRegistration, MetamorphosisRegistration

    _unknown(options)
    o = {**DEFAULTS, **options}
    check_operator(operator, "operator")
    dtype = _resolve_dtype(o["dtype"], template)
    device = resolve_device(o["device"], template)
    domain = operator.domain
    template = as_array(template, "template", domain.shape, dtype, device)
    data = as_array(data, "data", operator.range_shape, dtype, device)
    if o["target"] is not None:
        o["target"] = as_array(o["target"], "target", domain.shape, torch.float64, torch.device("cpu"))
    if o["callback"] is not None and not callable(o["callback"]):
        raise TypeError(f"callback must be callable(state, info), got {o['callback']!r}")
    if o["interpolation"] is None:
        fast = isinstance(o["solver"], str) and o["solver"].lower() == "fast"
        o["interpolation"] = "compose" if fast else "reinterpolate"
    _check_model(o)
    kernel = GaussianKernel(domain, o["sigma"])
    if o["model"] == "metamorphosis":
        deformation = MetamorphosisDeformation(domain, num_steps=o["num_steps"], backward=o["backward"] or "adjoint",
                                               interpolation=o["interpolation"])
        source_kernel = None if o["source_sigma"] is None else GaussianKernel(domain, o["source_sigma"])
        problem = MetamorphosisRegistration(operator, deformation, kernel, template, data, o["gamma"], o["tau"],
                                            tv_weight=o["tv_weight"], source_kernel=source_kernel,
                                            source_mask=_source_mask(o["source_mask"], template, domain))
    else:
        deformation = LDDMMDeformation(domain, num_steps=o["num_steps"], action=o["action"],
                                       backward=o["backward"] or "paper", interpolation=o["interpolation"])
        problem = IndirectRegistration(operator, deformation, kernel, template, data, o["gamma"],
                                       tv_weight=o["tv_weight"])
    solver = make_solver(problem, o["solver"], o["max_iter"], o["step_size"], o["lr"], o["step_halving"],
                         o["max_halvings"], o["grad_tol"], o["optimizer_kwargs"], o["source_step_size"],
                         o["source_lr"], o["source_start"])
    return Setup(problem, solver, o)


def _check_model(o: dict) -> None:
    """``model`` and the options that only one model takes."""
    if o["model"] not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {o['model']!r}")
    if o["model"] == "lddmm":
        for key in ("source_sigma", "source_mask", "source_step_size", "source_lr", "source_start"):
            if o[key] is not DEFAULTS[key] and o[key] != DEFAULTS[key]:
                raise TypeError(f"{key} is an option of model='metamorphosis' (the source term's step)")
    elif o["action"] != "geometric":
        raise ValueError(f"model='metamorphosis' uses the geometric action, got action={o['action']!r}")


def _source_mask(mask, template: torch.Tensor, domain):
    """``source_mask`` option: None, ``"template"`` (the template's support, ``template_support``) or an array."""
    from .solvers.metamorphosis import template_support

    if mask is None:
        return None
    if isinstance(mask, str):
        if mask != "template":
            raise ValueError(f"source_mask must be None, 'template' or an array (nx, ny), got {mask!r}")
        return template_support(template, domain)
    return as_array(mask, "source_mask", domain.shape, template.dtype, template.device)


def is_metamorphosis(problem) -> bool:
    """Whether ``problem`` is a metamorphosis problem (iterate: momentum and source)."""
    from .solvers import MetamorphosisRegistration

    return isinstance(problem, MetamorphosisRegistration)


def initial_state(problem):
    """The solvers' starting iterate: ``m = 0`` (and ``zeta = 0`` for metamorphosis)."""
    from .solvers import MetamorphosisState, SolverState

    return MetamorphosisState.zeros(problem) if is_metamorphosis(problem) else SolverState(problem.zero_momentum())


def final_image(problem, state) -> torch.Tensor:
    """The reconstruction at ``state``: ``W(nu, I)`` (LDDMM) or ``f(1)`` (metamorphosis)."""
    if is_metamorphosis(problem):
        return problem.image(state.momentum, state.source)
    return problem.deformed(state.momentum)


def image_trajectory(problem, state) -> torch.Tensor:
    """``W(nu, I)(t_i)`` or ``f(t_i)``, ``(N+1, nx, ny)``."""
    if is_metamorphosis(problem):
        return problem.trajectory(state.momentum, state.source)
    return problem.trajectory(state.momentum)


def evaluate(problem, state) -> dict:
    """The objective's terms at ``state`` (python floats)."""
    if is_metamorphosis(problem):
        return problem.evaluate(state.momentum, state.source)
    return problem.evaluate(state.momentum)


def count_warnings(history) -> int:
    """Iterations whose report carries a warning (the count shown on screen and stored in metrics)."""
    return sum(1 for h in history if h.get("warning"))


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


class RegistrationLoop:
    """``info = solver.step(state)`` until done; history, warnings, progress log lines and a tqdm bar.

    Subclasses (the experiment app) hook in with :meth:`before_step` (may return a stop status),
    :meth:`after_step` (every iteration; may return a stop status) and :meth:`describe` (extra text for the
    log line printed every ``every`` iterations). ``run()`` returns the status: ``completed``,
    ``converged``, ``failed`` (a non-finite objective or gradient; the state keeps the last iterate the solver
    accepted), or what a hook returned.
    """

    def __init__(self, problem, solver, state, max_iter: int, every: int = 10, progress: bool = False,
                 desc: str = "indreg", history=None, seconds: float = 0.0):
        self.problem, self.solver, self.state = problem, solver, state
        self.max_iter, self.every, self.progress, self.desc = max_iter, every, progress, desc
        self.history = [] if history is None else history
        self.seconds = seconds
        self.warnings = count_warnings(self.history)

    def before_step(self) -> Optional[str]:
        return None

    def after_step(self, info: dict, done: bool) -> Optional[str]:
        return None

    def describe(self, info: dict) -> str:
        return ""

    def _warn(self, it: int, info: dict) -> None:
        """Count a warning; log the first one and then one every ``every`` iterations."""
        self.warnings += 1
        if self.warnings == 1 or it % self.every == 0:
            log.warning("iteration %d: %s (%d warnings so far)", it, info["warning"], self.warnings)

    def _halved(self) -> bool:
        """Whether Algorithm 1's step halving shortened the step in the last iteration."""
        h = self.history
        return (getattr(self.solver, "step_halving", False) and len(h) > 1
                and h[-1]["step_size"] < h[-2]["step_size"])

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
                if self._halved():
                    log.info("iteration %d: step size halved to %.4g (the longer step increased the objective or "
                             "folded)", it, info["step_size"])
                reason = self.solver.status(info)   # failed / converged / completed / None
                if reason == "failed":              # non-finite: stop before any hook saves this iterate
                    status = reason
                    log.error("iteration %d: non-finite objective or gradient (%s); stopping", it,
                              info.get("warning") or "grad_norm is not finite")
                    break
                done = reason is not None
                stop = self.after_step(info, done)
                if it % self.every == 0 and not done:
                    log.info("%s: objective %.6g, data fit %.6g, min Jacobian %.4g%s%s", meter.line(it),
                             info["objective"], info["data_fit"], info["min_jacobian"], _source_terms(info),
                             self.describe(info))
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
        rejected = sum(1 for h in self.history if h.get("rejected"))
        if self.warnings:
            log.warning("%d of %d iterations reported a warning (%d rejected steps)", self.warnings,
                        len(self.history), rejected)
        return status


def _source_terms(info: dict) -> str:
    """Metamorphosis: both regularisers for the log line."""
    if "source_regulariser" not in info:
        return ""
    return f", regularisers nu {info['regulariser']:.4g} / zeta {info['source_regulariser']:.4g}"


class _ApiLoop(RegistrationLoop):
    def __init__(self, *args, callback=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.callback = callback

    def after_step(self, info, done):
        if self.callback is not None and self.callback(self.state, info):
            return "stopped"
        return None


def relative_residual(operator, deformed: torch.Tensor, data: torch.Tensor) -> float:
    """``||T f - g|| / ||g||`` in the data norm (``operator.inner_data``)."""
    with torch.no_grad():
        r = operator(deformed) - data
        return math.sqrt(float(operator.inner_data(r, r).sum()) / float(operator.inner_data(data, data).sum()))


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
        operator: the forward operator T: ``indreg.RayTransform(domain, geometry)`` (parallel or fan beam) or
            any ``indreg.LinearOperator`` (``domain``, ``range_shape``, ``__call__``, ``adjoint``, ``inner_data``).
        sigma: width of the Gaussian kernel of V (physical units), 6.0.
        gamma: regularisation weight, 1e-6. num_steps: time steps N, 20.
        action: "geometric" or "mass_preserving". interpolation: "reinterpolate" or "compose" (default
            "compose" with ``solver="fast"``, else "reinterpolate", the paper's).
        backward: LDDMM: "paper" (Algorithm 1's gradient, the default), "exact" (the exact gradient of the
            discrete map by its hand-written adjoint, about the paper's cost; torch.optim solvers use it in
            place of "paper") or "autograd" (the same exact gradient, about 2x the cost); metamorphosis:
            "adjoint" (default, its exact gradient) or "autograd".
        model: "lddmm" (default) or "metamorphosis": the image path ``d/dt f + <grad f, nu> = zeta`` also
            changes intensities (eq:Metam:ODE); ``tau``: weight of the source's penalty, 1.0; ``source_sigma``:
            None (the paper's L2 source) or the width of a Gaussian RKHS for the source (smooth intensity changes);
            ``source_mask``: None, ``"template"`` (intensities change only on the template's support, dilated by
            1 unit) or an array ``(nx, ny)`` in [0, 1].
        source_step_size: metamorphosis with Algorithm 1: the source's step (default ``1 / (tau + ||T||^2)``).
        source_lr: metamorphosis with torch.optim: the source's learning rate (default ``lr``).
        source_start: metamorphosis with Algorithm 1: iterations with the source frozen (0: none).
        solver: "algorithm1" (default), "fast" (coarse-to-fine, ``indreg.solvers.MultilevelSolver``; its
            options in ``optimizer_kwargs``), "lbfgs", or any ``torch.optim`` optimizer name (case-insensitive).
        max_iter: 200. grad_tol: stop when the gradient norm is below it (0: never).
        step_size: Algorithm 1's step, 0.02. lr: the torch.optim learning rate (1.0 for L-BFGS; required
            for the others). optimizer_kwargs: passed to the torch.optim optimizer.
        step_halving: True (default): reject and halve steps that increase the objective or fold.
        max_halvings: 20: halvings tried within one iteration (2^-20: intensities up to ~1000x the paper's
            0..1 are handled in the first iteration); the halved step is kept for later iterations.
        tv_weight: weight of a TV term on the deformed template, 0.
        device, dtype: default the template's (numpy input: CPU; float64 arrays stay float64, others float32).
        callback: ``callback(state, info)`` after every iteration; returning True stops the run.
        progress: True shows a tqdm bar on a terminal, else progress lines on the "indreg" logger
            (a stderr handler is added for the call if logging is not configured). log_every: 10.
        target: optional ground truth ``(nx, ny)``: adds ``ssim`` and ``psnr`` to the result.

    Raises:
        TypeError: an unknown option (the message lists the valid ones), a wrong type.
        ValueError: a shape mismatch, non-finite values, an invalid value; the message names the argument.
    """
    from . import metrics

    s = setup(template, data, operator, **options)
    o, problem = s.options, s.problem
    state = initial_state(problem)
    handler = _console_handler(o["progress"])
    try:
        log.info("%s | %s", problem, s.solver)
        loop = _ApiLoop(problem, s.solver, state, o["max_iter"], every=o["log_every"], progress=o["progress"],
                        callback=o["callback"])
        status = loop.run()
    finally:
        if handler is not None:
            log.removeHandler(handler)
    m = state.momentum
    deformed = final_image(problem, state)
    with torch.no_grad():
        velocity = problem.velocity(m)
        phi = problem.deformation.deformation(velocity)
    result = RegistrationResult(
        deformed=deformed, momentum=m, velocity=velocity, deformation=phi, trajectory=image_trajectory(problem, state),
        history=loop.history, iterations=state.iteration, objective=evaluate(problem, state)["objective"],
        min_jacobian=problem.min_jacobian(velocity), residual=relative_residual(operator, deformed, problem.data),
        status=status, warnings=loop.warnings, seconds=loop.seconds, problem=problem)
    if is_metamorphosis(problem):
        result.source = state.source
        result.deformation_part, result.intensity_part = problem.parts(m, state.source)
    if o["target"] is not None:
        result.ssim, result.psnr = metrics.ssim(deformed, o["target"]), metrics.psnr(deformed, o["target"])
    return result
