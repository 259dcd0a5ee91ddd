"""The options of a registration, declared once: ``indreg.register``'s keywords, the app's config keys
(``kernel.*``, ``deformation.*``, ``solver.*``: the Hydra schema is generated from this table), their defaults,
which solver / model each applies to, and their validation.

Each :class:`Option` names its ``register()`` keyword and its config key, its default (and the app's, where the
paper presets need another), and a check. :func:`resolve` is the one validation path: ``register()`` calls it with
the keywords (errors name the keyword), the app with the config's values (errors name the config key). An
option given with a non-default value to a solver or model it does not apply to is an error in ``register()``;
the app drops such values silently, because its presets set them for their own solver (a preset's
``solver.step_size`` is Algorithm 1's and must not become an optimizer's ``lr``).

Models add their own options (``indreg.registration.models.Model.options``), so a new model's options reach both entry
points without editing this file.

Longer than 450 lines: the option table is declared once (the schema, the docs and the checks are generated from
it); the checks themselves live in ``indreg.options.checks``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Optional

from .checks import (ALGORITHM1, FAST, TORCH, OptionError, anything, auto_or, boolean, choice,  # noqa: F401
                            holdout, mapping, number, optional)
from ..units import GAMMA_REL, STEP_REL

_NONE = object()


# ---------------------------------------------------------------------------------------------------- options
@dataclass(frozen=True)
class Option:
    """One option of the table: a keyword of ``register()`` and (unless its group is ``run``) a config key.

    Parameters
    ----------
    name : str
        The keyword of ``register()``.
    group, key : str
        Its config key ``group.key`` (group ``run``: ``register()`` only).
    default : object
        ``register()``'s default.
    check : callable
        ``check(value, label) -> value`` normalised, or an ``OptionError`` naming ``label`` (``indreg.options.checks``).
    doc : str
        The help line (``help(indreg.register)``, configs/README.md).
    type : type
        Its type in the Hydra schema.
    solvers : tuple of str, optional
        The registered solvers it applies to (``"torch"``: the family of every torch.optim optimizer; None: all).
    models : tuple of str, optional
        The models it applies to (None: all).
    app_default : object, optional
        The app schema's default if not ``default`` (the paper's: the solver classes take it too,
        :func:`default`).
    resumable : bool
        It may change between an interrupted run and its resumption (the iterates do not depend on it: the
        iteration budget, how the work is split).
    """
    name: str
    group: str
    key: str
    default: Any
    check: Callable
    doc: str
    type: Any = Any
    solvers: Optional[tuple] = None
    models: Optional[tuple] = None
    app_default: Any = _NONE
    resumable: bool = False

    @property
    def config_key(self) -> str:
        return f"{self.group}.{self.key}"

    @property
    def schema_default(self):
        return self.default if self.app_default is _NONE else self.app_default

    def applies(self, solver: str, model: str) -> bool:
        ok_solver = self.solvers is None or solver in self.solvers or getattr(_serving(solver), "name", None) in \
            self.solvers
        return ok_solver and (self.models is None or model in self.models)

    def where(self) -> str:
        """Which solver / model the option belongs to, for error messages."""
        parts = []
        if self.models is not None:
            parts.append(" or ".join(f"model={m!r}" for m in self.models))
        if self.solvers is not None:
            parts.append(" or ".join(getattr(SOLVERS.get(s), "family", "") or f"solver={s!r}" for s in self.solvers))
        return " with ".join(parts)


# ---------------------------------------------------------------------------------------------------- models
# The registry of deformation models lives here, below ``indreg.registration.models`` (which fills it), so that checking an
# option never imports the models' code.
MODELS: dict = {}


@dataclass(frozen=True)
class Model:
    """A deformation model, the entry of ``register(model=...)`` / ``deformation.model`` (``docs/extending.md``).

    Parameters
    ----------
    name : str
        The value of ``model=``.
    build : callable
        ``build(operator, template, data, kernel, options) -> (problem, solver_options)`` (``template`` None,
        unknown, only with ``template_optional``); ``solver_options``: keyword arguments of a solver's build,
        keyed by the registered solver's name (:class:`Solver`; ``steps`` / ``frozen`` for ``"algorithm1"``,
        ``lrs`` for ``"torch"``), and ``"wrap"``: a function of the solver built that returns the solver to run
        (an alternation around it).
    options : tuple of Option
        Its own options (``models=(name,)``: keywords of ``register()`` and config keys).
    doc : str
        One line for listings.
    check : callable, optional
        ``check(options, label)``: checks across options, errors via ``label(name)``.
    template_optional : bool
        ``template=None`` (unknown) is allowed: the model reconstructs it.
    defaults : callable, optional
        ``defaults(options)``: fills options left None by the model's own rules.
    """
    name: str
    build: Callable
    options: tuple = ()
    doc: str = ""
    check: Optional[Callable] = None   # check(options, label): cross-option checks, errors via label(name)
    template_optional: bool = False    # template=None (unknown) is allowed: the model reconstructs it
    defaults: Optional[Callable] = None  # defaults(options): fills options left None by the model's own rules

    def make(self, operator, template, data, kernel, o: dict) -> tuple:
        """``(problem, solver_options)`` of :attr:`build`, its return checked; a plug-in's own exception other
        than a ValueError / TypeError (which name their problem) becomes one ValueError naming the model, the
        original chained."""
        built = _build(f"model {o['model']!r}", self.build, operator, template, data, kernel, o)
        if not (isinstance(built, tuple) and len(built) == 2 and isinstance(built[1], dict)):
            raise TypeError(f"model {o['model']!r}: build must return (problem, solver_options dict), got "
                            f"{type(built).__name__}")
        return built


def _build(what: str, build: Callable, *args):
    """``build(*args)``; a plug-in's own exception other than a ValueError / TypeError (which name their problem)
    becomes one ValueError naming ``what`` (e.g. ``model 'mine'``), the original chained."""
    try:
        return build(*args)
    except (ValueError, TypeError):
        raise
    except Exception as e:
        if getattr(build, "__module__", "").startswith("indreg."):
            raise
        raise ValueError(f"{what}: build raised {type(e).__name__}: {e}") from e


# ---------------------------------------------------------------------------------------------------- solvers
# The registry of solvers lives here too, below the modules that fill it (``indreg.builtin_solvers``: algorithm1,
# fast, the torch.optim optimizers; a plug-in's own module), so that checking an option never imports a solver.
SOLVERS: dict = {}


@dataclass(frozen=True)
class Solver:
    """A solver, the entry of ``register(solver=...)`` / ``solver.name`` (``docs/extending.md``).

    Parameters
    ----------
    name : str
        The value of ``solver=`` (the app's ``solver.name``) and the key of a model's ``solver_options``.
    build : callable
        ``build(problem, options, model_kwargs) -> solver``: an iterative solver (``step(state) -> info``,
        ``status(info)``, ``state_dict`` / ``load_state_dict``, ``halves_steps``;
        ``indreg.solvers.state.IterativeSolver`` gives all but ``step``); ``model_kwargs``: the model's
        ``solver_options[name]`` (e.g. Algorithm 1's ``steps``).
    options : tuple of Option
        Its own options (``solvers=(name,)``: keywords of ``register()`` and config keys, as a model's).
    doc : str
        One line for listings.
    accepts : callable, optional
        A family's test of other names it serves (``accepts(value) -> the value normalised, or None``: the
        torch.optim optimizers by class name).
    check : callable, optional
        ``check(options, label)``: checks across options (errors via ``OptionError(label(name), ...)``).
    expected : str
        How the list of solvers names it (default ``'name'``).
    family : str
        How an option's error names its solvers (default ``solver='name'``).
    """
    name: str
    build: Callable
    options: tuple = ()
    doc: str = ""
    accepts: Optional[Callable] = None
    check: Optional[Callable] = None
    expected: str = ""
    family: str = ""

    def make(self, problem, o: dict, model_kwargs: dict):
        """The solver of :attr:`build`; a plug-in's own exception other than a ValueError / TypeError becomes one
        ValueError naming the solver, the original chained."""
        return _build(f"solver {self.name!r}", self.build, problem, o, model_kwargs)


def register_solver(entry: Solver) -> Solver:
    """Add ``entry`` to the solver registry (a name already there is replaced).

    Parameters
    ----------
    entry : Solver
        The solver to register.

    Returns
    -------
    Solver
        ``entry``.

    Raises
    ------
    TypeError
        ``entry`` is no :class:`Solver`.
    """
    return add_to_registry(SOLVERS, entry, Solver, "register_solver takes an indreg.registration.solver_registry.Solver")


def solver(name: str) -> Solver:
    """The registered solver serving ``name`` (its own name, or one a family accepts); ``"package.module:attribute"``
    imports a ``Solver`` (or a module that registers it) and registers it under that name, as :func:`model`."""
    if isinstance(name, str) and name not in SOLVERS and ":" in name:
        _import(name, SOLVERS, Solver, "solver", "indreg.registration.solver_registry.Solver")
    found = _serving(name)
    if found is None:
        raise ValueError(f"solver must be {solver_names()} or 'package.module:attribute', got {name!r}")
    return found


def _serving(name):
    if name in SOLVERS:
        return SOLVERS[name]
    for entry in SOLVERS.values():
        if entry.accepts is not None and isinstance(name, str) and entry.accepts(name) is not None:
            return entry
    return None


def solver_names() -> str:
    """The registered solvers as an error names them: ``'algorithm1', 'fast' or a torch.optim optimizer name``."""
    what = list(dict.fromkeys(e.expected or repr(e.name) for e in SOLVERS.values()))
    return " or ".join(filter(None, (", ".join(what[:-1]), what[-1] if what else "")))


def solver_kind(name: str) -> str:
    """The registry name of the solver serving ``name`` (``"torch"`` for a torch.optim optimizer): the key of a
    model's ``solver_options``."""
    return solver(name).name


# ---------------------------------------------------------------------------------------------------- corrections
# The registry of in-the-fit corrections (``indreg.registration.corrections``: the protocol; the built-in alignment,
# ``indreg.alignment.correction``, and intensity fit; a plug-in's own module), here for the same reason.
CORRECTIONS: dict = {}


@dataclass(frozen=True)
class Correction:
    """A correction of the data model re-estimated in the fit, in a chain around the solver
    (``indreg.registration.corrections`` has the protocol in full).

    Parameters
    ----------
    name : str
        Its name: ``result.corrections[name]``, metrics.json's entry, the figure ``<name>.png``.
    wrap : callable
        ``wrap(solver, fit) -> solver``: ``solver`` itself where the options leave the correction off, else an
        ``indreg.solvers.state.RefitSolver`` around it (``fit``: an ``indreg.registration.corrections.Fit``).
    options : tuple of Option
        Its own options (keywords of ``register()``, config keys).
    doc : str
        One line for listings.
    model : callable, optional
        ``model(fit)``: puts the data model it estimates in place before the problem is built (sets
        ``fit.operator``, e.g. the alignment's ``T_s``) and may keep its state in ``fit.states[name]``.
    start : callable, optional
        ``start(fit, template, data)``: once the units are measured, before the template's factor is set (may
        update ``fit.units``; the alignment fits the template's scale through it).
    check : callable, optional
        ``check(options, label)``: checks across options.
    plot : callable, optional
        ``plot(summary, path)``: the app's figure of its summary.
    fixed : callable, optional
        ``fixed(problem) -> dict``: the summary of a part of the data model that is in the problem but not
        re-estimated (an imported alignment used as it is), ``{}`` when there is none.
    """
    name: str
    wrap: Callable
    options: tuple = ()
    doc: str = ""
    model: Optional[Callable] = None
    start: Optional[Callable] = None
    check: Optional[Callable] = None
    plot: Optional[Callable] = None
    fixed: Optional[Callable] = None


def register_correction(entry: Correction) -> Correction:
    """Add ``entry`` to the chain of corrections, after those registered before it (a name already there is
    replaced in place).

    Parameters
    ----------
    entry : Correction
        The correction to register.

    Returns
    -------
    Correction
        ``entry``.

    Raises
    ------
    TypeError
        ``entry`` is no :class:`Correction`.
    """
    return add_to_registry(CORRECTIONS, entry, Correction,
                           "register_correction takes an indreg.registration.corrections.Correction")


def add_to_registry(registry: dict, entry, cls: type, expected: str):
    """``registry[entry.name] = entry`` (a name already there is replaced) for an instance of ``cls``; else a
    one-line TypeError (``expected``: e.g. "register_model takes an indreg.registration.models.Model"). Returns ``entry``."""
    if not isinstance(entry, cls):
        raise TypeError(f"{expected}, got {type(entry).__name__}")
    registry[entry.name] = entry
    return entry


def register_model(model: Model) -> Model:
    """Add ``model`` to the registry (a name already there is replaced).

    Parameters
    ----------
    model : Model
        The model to register.

    Returns
    -------
    Model
        ``model``.

    Raises
    ------
    TypeError
        ``model`` is no :class:`Model`.
    """
    return add_to_registry(MODELS, model, Model, "register_model takes an indreg.registration.models.Model")


def model(name: str) -> Model:
    """The registered model ``name``; ``"package.module:attribute"`` imports a ``Model`` (or a module that
    registers it) and registers it under that name, so the app takes ``deformation.model=my.module:MODEL``."""
    if name not in MODELS and isinstance(name, str) and ":" in name:
        _import(name)
    if name not in MODELS:
        raise ValueError(f"model must be one of {', '.join(map(repr, MODELS))} or 'package.module:attribute', "
                         f"got {name!r}")
    return MODELS[name]


def _import(path: str, registry: Optional[dict] = None, cls: type = Model, what: str = "model",
            public: str = "indreg.registration.models.Model") -> None:
    """Import ``path`` (``package.module:attribute``), an instance of ``cls``, into ``registry`` under ``path`` and its
    own name; one-line ValueError (nothing the failed import registered stays) when it cannot."""
    import importlib

    registry = MODELS if registry is None else registry
    module, _, attr = path.partition(":")
    before = dict(registry)
    try:
        entry = getattr(importlib.import_module(module), attr)
        problem = None if isinstance(entry, cls) else f"is a {type(entry).__name__}, not an {public}"
    except Exception as e:   # a syntax error or an exception at import: one line
        problem = f"cannot be imported: {type(e).__name__}: {e}"
    except SystemExit as e:   # the module called sys.exit() at import
        problem = f"cannot be imported: it called sys.exit({e.code!r}) at import"
    if problem is not None:   # nothing the failed import registered stays
        registry.clear()
        registry.update(before)
        raise ValueError(f"{what} {path!r} {problem}")
    registry[path] = entry
    registry.setdefault(entry.name, entry)   # its options name it (Option.models / solvers) by its own name


def _solver(v, label):
    expected = f"{solver_names()}; a plug-in: 'package.module:attribute'"
    if not isinstance(v, str):
        raise OptionError(label, v, expected, TypeError)
    key = v if v in SOLVERS or ":" in v else v.lower()
    try:
        entry = solver(key)
    except ValueError as e:
        msg = str(e)
        raise OptionError(label, v, expected if msg.startswith("solver must be ") else
                          f"an importable solver ({msg})") from None
    if key == entry.name and entry.accepts is not None and entry.accepts(key) is None:   # a family's own name
        raise OptionError(label, v, expected)
    if key in SOLVERS and SOLVERS[key] is entry:
        return entry.name if SOLVERS.get(entry.name) is entry else key   # a plug-in by its own name
    return entry.accepts(key)


def _model(v, label):
    if not isinstance(v, str):
        raise OptionError(label, v, "a model name (str)", TypeError)
    try:
        model(v)
    except ValueError as e:
        msg = str(e)
        expected = msg.split(", got ")[0].replace("model must be ", "") if msg.startswith("model must be ") else \
            f"an importable model ({msg})"
        raise OptionError(label, v, expected) from None
    m = model(v)
    return m.name if MODELS.get(m.name) is m else v   # a plug-in by its own name, so that its options apply


_positive = number(0.0, strict=True)
_nonneg = number(0.0)

CORE = (
    Option("sigma", "kernel", "sigma", None, auto_or(_positive, "a finite number > 0"),
           "width of the Gaussian kernel of V (physical units); None: 1/8 of the box's largest side, 'auto': "
           "chosen from held-out angles among 1/16, 1/8, 1/4 of it (3 registrations first; indreg.kernel_width)",
           Optional[Any], app_default=6.0),
    Option("num_steps", "deformation", "num_steps", 20, number(1, integer=True), "time steps N", int),
    Option("action", "deformation", "action", "geometric", choice(("geometric", "mass_preserving")),
           "group action: geometric or mass_preserving", str),
    Option("interpolation", "deformation", "interpolation", "compose", optional(choice(("reinterpolate", "compose"))),
           "compose (phi_{1,0} composed, the template sampled once: less numerical blur) or reinterpolate (the "
           "paper's); None: the model's rule (compose with solver='fast' or velocity_factor > 1, else "
           "reinterpolate; the app's default, which the paper's presets use)", Optional[str], app_default=None),
    Option("backward", "deformation", "backward", None, optional(choice(("paper", "exact", "autograd", "adjoint"))),
           "the deformation's backward; None: the model's default (LDDMM paper, metamorphosis adjoint)",
           Optional[str], app_default="paper"),
    Option("model", "deformation", "model", "lddmm", lambda v, label: _model(v, label),
           "the deformation model: a name in indreg.registration.models or 'package.module:attribute'", str),
    Option("gamma", "solver", "gamma", None, optional(_nonneg),
           "regularisation weight (absolute, the paper's); None: gamma_rel S (S = ||g||^2 / L^2, indreg.units)",
           Optional[float]),
    Option("gamma_rel", "solver", "gamma_rel", GAMMA_REL, _nonneg,
           "with gamma None: the regularisation weight relative to the data term, gamma = gamma_rel S", float),
    Option("tv_weight", "solver", "tv_weight", 0.0, _nonneg,
           "weight of a TV term on the reconstruction (absolute; 0: none, unless tv_rel is given)", float),
    Option("tv_rel", "solver", "tv_rel", None, optional(_nonneg),
           "the TV weight relative to the TV weight unit: tv_weight = tv_rel x indreg.forward.tv_weight_unit (the "
           "intensity unit x the box side squared: the TV baseline's convention; with tv_weight 0)", Optional[float]),
    Option("solver", "solver", "name", ALGORITHM1, lambda v, label: _solver(v, label),
           "'algorithm1', 'fast' (coarse to fine), a torch.optim name or a registered solver "
           "(indreg.registration.solver_registry; 'package.module:attribute')", str),
    Option("max_iter", "solver", "max_iter", 200, number(0, integer=True), "iterations", int, resumable=True),
    Option("step_size", "solver", "step_size", None, optional(_positive),
           "Algorithm 1's step (absolute, the paper's); None: step_rel / S (S = ||g||^2 / L^2, indreg.units)",
           Optional[float], solvers=(ALGORITHM1,)),
    Option("step_rel", "solver", "step_rel", STEP_REL, _positive,
           "with step_size None: Algorithm 1's step relative to the data term, step_size = step_rel / S", float,
           solvers=(ALGORITHM1,)),
    Option("lr", "solver", "lr", None, optional(_positive),
           "the torch.optim learning rate (None: 1.0 for L-BFGS, required for the others)", Optional[float],
           solvers=(TORCH,), app_default=1.0),
    Option("step_halving", "solver", "step_halving", True, boolean,
           "halve steps that increase the objective or fold", bool, solvers=(ALGORITHM1,), app_default=False),
    Option("max_halvings", "solver", "max_halvings", 20, number(0, integer=True), "halvings within one iteration",
           int, solvers=(ALGORITHM1,)),
    Option("grad_tol", "solver", "grad_tol", 0.0, _nonneg, "stop when the gradient norm is below it (0: never)",
           float),
    Option("optimizer_kwargs", "solver", "optimizer_kwargs", None, mapping,
           "keyword arguments of the torch.optim optimizer, or solver='fast''s options", Dict[str, Any],
           solvers=(FAST, TORCH), app_default={}),
    Option("holdout", "validation", "holdout", None, holdout,
           "angles left out of the fit and used for validation: every k-th (an integer k >= 2) or a list of "
           "indices; None: all are fitted", Any),
    Option("patience", "validation", "patience", None, optional(number(1, integer=True)),
           "with holdout: stop after this many evaluations without a new minimum of the held-out residual "
           "(None: never)", Optional[int]),
    Option("split", "validation", "split", "auto", choice(("auto", True, False)),
           "the result split into the part the data determine and the part the prior fills (indreg.evaluation: "
           "result.data_part, result.prior_part); 'auto': on up to 2^21 voxels, off for several time points",
           Any),
    Option("uncertainty", "validation", "uncertainty", "auto", choice(("auto", True, False)),
           "a per-voxel standard deviation by perturbed re-optimisation (indreg.evaluation.uncertainty: "
           "result.uncertainty); 'auto': on when the run has held-out angles (holdout), up to 2^21 voxels, one "
           "process, one time point; docs/evaluation.md", Any),
    Option("uncertainty_samples", "validation", "uncertainty_samples", 6, number(2, integer=True),
           "re-optimisations of the uncertainty (each about 5 iterations of the run)", int),
    Option("uncertainty_noise", "validation", "uncertainty_noise", None, optional(number(0, strict=True)),
           "the data's noise standard deviation per datum where it is known (the fitted data's units: after the "
           "background and the logarithm); None: estimated from the data (indreg.units.noise_std)",
           Optional[float]),
)

_step_size = next(o for o in CORE if o.name == "step_size")

def _callback(v, label):
    from ..callbacks import as_callback

    try:
        as_callback(v, label)
    except TypeError:
        raise OptionError(label, v, "callable(state, info), an indreg.callbacks.Callback or a list of them",
                          TypeError) from None
    return v


#: The values of ``template_scale`` that fit the template's factor (and offset) with the deformation
#: (``indreg.registration.intensity``).
TEMPLATE_FITS = ("fit", "fit+offset")
#: How the inputs are brought to one unit before the run (``indreg.units.prepare``): the app's ``data.*`` keys.
INPUTS = (
    Option("template_scale", "data", "template_scale", None,
           auto_or(_positive, "a finite number > 0", ("auto",) + TEMPLATE_FITS),
           "the template's intensity factor: None (a warning if ||T I|| / ||g|| is outside [1/3, 3]), 'auto' "
           "(the least-squares c = <T I, g> / <T I, T I>), 'fit' / 'fit+offset' (a factor, and an offset, fitted "
           "with the deformation: model lddmm with the geometric action; indreg.registration.intensity) or a number",
           Optional[Any]),
    Option("transmission", "data", "transmission", None, auto_or(_positive, "a finite number > 0 (I0)"),
           "bright-field / transmission intensities made line integrals -ln(I / I0): 'auto' or I0 (None: the data "
           "are line integrals); 'auto' takes I0 from the frames' vacuum, else the slab law -ln<I> = a / cos(theta "
           "- theta0) + b (indreg.units.transmission)", Optional[Any]),
    Option("background", "data", "background", None, auto_or(number(), "a finite number"),
           "an offset subtracted from the data: None (a warning when they look offset), 'auto' or a number; 'auto' "
           "takes the vacuum's level at the detector's border, or a slab tilt series' intercept, never the level of "
           "a border that is specimen (indreg.units.border); a number that makes most of the data negative is refused",
           Optional[Any]),
    Option("wide_box", "data", "wide_box", "auto", choice(("auto", True, False)),
           "a box wider than the detector for a specimen wider than it: 'auto' (where the border is specimen), True "
           "or False; wide enough that every ray reaching the detector crosses the specimen inside it "
           "(indreg.forward.wide_box; the data term stays on the detector's pixels)",
           Any),
    Option("slab_thickness", "data", "slab_thickness", None, optional(_positive),
           "the specimen's thickness along the beam at angle 0 for the wide box (None: the template's support "
           "along the beam, else the box's thickness)", Optional[float]),
    Option("slab_extent", "data", "slab_extent", None, optional(_positive),
           "the specimen's lateral extent for the wide box (None: unbounded, a slab; for a full-angle scan the chord "
           "law of the data's mean profile)", Optional[float]),
    Option("template_padding", "data", "template_padding", "edge", choice(("edge", "zero", "level")),
           "how a template on the given box fills the wide box: 'edge' (its outermost cells repeated outwards), "
           "'zero' or 'level' (the median of its faces)", str),
    Option("orientation", "data", "orientation", "check", choice(("check", "warn", "off")),
           "the orientation probe before the run (indreg.io.orientation): 'check' (a warning when the template's "
           "projection fits the data clearly better read another way: detector reversed, angles in the opposite "
           "sense, a stack turned; an error when by far), 'warn' (a warning only) or 'off'", str),
)

RUN = (
    Option("device", "run", "device", None, anything, "None: the template's; 'auto', 'cpu', 'cuda[:i]'"),
    Option("dtype", "run", "dtype", None, anything, "None: the template's (arrays: float32 unless float64)"),
    Option("callback", "run", "callback", None, _callback,
           "fn(state, info) after every iteration (True stops the run), an indreg.callbacks.Callback (the app's loop "
           "hooks: begin, before, after, describe, end; a & b) or a list of them"),
    Option("progress", "run", "progress", None, optional(boolean),
           "progress of the run and of sigma='auto''s trial runs: None (a bar on a terminal, silent otherwise), "
           "True (a bar on a terminal, log lines on stderr otherwise) or False"),
    Option("log_every", "run", "log_every", 10, number(1, integer=True), "log period (iterations)"),
    Option("target", "run", "target", None, anything, "ground truth for SSIM / PSNR"),
    Option("extrapolation", "run", "extrapolation", False, boolean,
           "the edge validation first (indreg.registration.extrapolation): the angles at the edges of the measured "
           "range held out, the template alone, lddmm, residual and their blends with the template where the data "
           "cannot see scored on them, the best run on all angles (result.extrapolation); about 3 runs' time"),
)


def all_options() -> tuple:
    """The core options, then every registered model's and solver's own, then the run options."""
    seen, out = set(), []
    own = (o for entry in (*MODELS.values(), *SOLVERS.values()) for o in entry.options)
    for o in (*CORE, *own, *INPUTS, *(o for c in CORRECTIONS.values() for o in c.options), *RUN):
        if o.name not in seen:
            seen.add(o.name)
            out.append(o)
    return tuple(out)


def check_value(name: str, value, label: str):
    """``value`` checked as the option ``name`` (the one check of a value that another app reads under its own key).

    Parameters
    ----------
    name : str
        The option's name in the table (``register()``'s keyword), e.g. ``"sigma"``.
    value : object
        The value to check.
    label : str
        The key as the user named it, for the message (e.g. ``"kernel.sigma"``).

    Returns
    -------
    object
        The value, normalised.

    Raises
    ------
    OptionError
        One line naming ``label``, the value and what was expected.
    """
    return next(o for o in all_options() if o.name == name).check(value, label)


def defaults() -> dict:
    return {o.name: o.default for o in all_options()}


def default(name: str, app: bool = False):
    """The table's default of the core option ``name``: ``register()``'s, or with ``app`` the app's (the paper's,
    ``Option.app_default``, where it has its own). The solver classes take their defaults from here."""
    o = next(o for o in (*CORE, *INPUTS, *RUN) if o.name == name)
    return o.schema_default if app else o.default


def relative(o: dict, scale: float, intensity: Callable[[], float]) -> dict:
    """``gamma`` and ``step_size`` left None take their relative form at the data-term scale ``S`` (``scale``,
    ``indreg.units.data_term_scale``): ``gamma = gamma_rel S``, ``step_size = step_rel / S``; ``tv_rel`` given (and
    ``tv_weight`` 0) gives ``tv_weight = tv_rel * intensity()`` (the TV weight unit,
    ``indreg.forward.tv_weight_unit``). Returns ``o``."""
    if o["gamma"] is None:
        o["gamma"] = o["gamma_rel"] * scale
    if o["step_size"] is None and _step_size.applies(o["solver"], o["model"]):
        o["step_size"] = o["step_rel"] / scale
    if o["tv_rel"] is not None and o["tv_weight"] == 0:
        o["tv_weight"] = o["tv_rel"] * intensity()
    return o


def _given(o: Option, value) -> bool:
    """Whether ``value`` differs from the option's default (arrays, numpy's or torch's, count as given)."""
    if hasattr(value, "__array__"):
        return True
    return value is not o.default and value != o.default


def resolve(values: dict, label: Callable[[Option], str] = lambda o: o.name, strict: bool = True) -> dict:
    """Validate ``values`` (option name -> value; missing: the default) and return them normalised.

    ``label(option)`` names an option in errors (``register()``: the keyword; the app: the config key).
    ``strict`` (``register()``): an unknown name is a TypeError, and an option given with a non-default value
    to a solver or model it does not apply to is a TypeError; otherwise (the app) such values are reset to the
    default. Raises ``OptionError`` (``kind`` TypeError or ValueError) naming the option.
    """
    for name, find, registry in (("model", model, MODELS), ("solver", solver, SOLVERS)):
        if isinstance(values.get(name), str) and ":" in values[name] and values[name] not in registry:
            try:   # a plug-in's options join the table before unknown names are looked for
                find(values[name])
            except ValueError:
                pass   # reported with the option's label below
    options = {o.name: o for o in all_options()}
    unknown = sorted(set(values) - set(options))
    if unknown:
        raise TypeError(f"unknown option(s) {', '.join(unknown)}; valid options: {', '.join(sorted(options))}")
    out = {name: values.get(name, o.default) for name, o in options.items()}
    for name in ("solver", "model"):
        out[name] = options[name].check(out[name], label(options[name]))
    for name, o in options.items():
        if o.applies(out["solver"], out["model"]):
            if name not in ("solver", "model"):
                out[name] = o.check(out[name], label(o))
        elif strict and _given(o, out[name]):
            raise OptionError(label(o), out[name], f"left unset: it is an option of {o.where()}", TypeError)
        else:
            out[name] = o.default
    chosen_solver = solver(out["solver"])
    if chosen_solver.check is not None:
        chosen_solver.check(out, lambda name: label(options[name]))
    if out["patience"] is not None and out["holdout"] is None:
        raise OptionError(label(options["patience"]), out["patience"],
                          f"None without {label(options['holdout'])} (early stopping watches the held-out residual)")
    if out["tv_rel"] is not None and out["tv_weight"] != 0:
        raise OptionError(label(options["tv_rel"]), out["tv_rel"], f"None when {label(options['tv_weight'])} is "
                          "given (one TV weight: absolute or relative)")
    for correction in CORRECTIONS.values():
        if correction.check is not None:
            correction.check(out, lambda name: label(options[name]))
    chosen = model(out["model"])
    if chosen.check is not None:
        chosen.check(out, lambda name: label(options[name]))
    return out


def schema_fields(group: str) -> list:
    """``(key, type, dataclasses.field(default=...))`` of a config group, for ``dataclasses.make_dataclass``."""
    out = []
    for o in all_options():
        if o.group == group:
            d = o.schema_default
            f = field(default_factory=lambda d=d: dict(d)) if isinstance(d, dict) else field(default=d)
            out.append((o.key, o.type, f))
    return out
