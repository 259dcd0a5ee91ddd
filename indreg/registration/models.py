"""The deformation models a registration can use, by name: the registry behind ``register(model=...)`` and the
app's ``deformation.model``.

A model is a :class:`Model`: its name, its own options (``indreg.options.Option``; they join ``register()``'s
keywords and the app's config schema) and ``build(operator, template, data, kernel, options) -> problem``, which
returns a registration problem (``indreg.solvers.RegistrationProblem``) and the keyword arguments its solvers need
beyond the common ones. Everything above (``indreg.register``, the app, the run loop, the result builder) is
model-agnostic, so a new model is a new problem class and one :func:`register_model` call (``docs/extending.md``).

Built in:

    lddmm          ``IndirectRegistration`` with ``LDDMMDeformation`` (the paper's method)
    metamorphosis  ``MetamorphosisRegistration`` with ``MetamorphosisDeformation`` (intensities change too)
    spatiotemporal ``SpatiotemporalRegistration``: data at several time points, one flow, template known or
                   unknown (``template=None``; docs/spatiotemporal.md)
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, Optional, Union

from . import solver_registry  # noqa: F401  (the solvers a model's solver_options name)
from .._checks import as_tensor
from ..options import (ALGORITHM1, MODELS, TORCH, Model, Option, OptionError, anything, auto_or, boolean,  # noqa: F401
                      choice, model, number, optional, register_model, solver_kind)

if TYPE_CHECKING:   # imported where used: the app's preflight loads this module without torch
    import torch


def get(name: str) -> Model:
    """The registered model ``name`` (``indreg.options.model``: ``"package.module:attribute"`` imports one).

    Parameters
    ----------
    name : str
        A registered model's name or ``"package.module:attribute"``.

    Returns
    -------
    Model
        The registry entry.

    Raises
    ------
    ValueError
        An unknown name.
    """
    return model(name)


def _interpolation(o: dict) -> None:
    """``interpolation`` None: ``"compose"`` with ``solver="fast"`` or ``velocity_factor > 1``, else the paper's
    ``"reinterpolate"``."""
    if o["interpolation"] is None:
        fast = o["solver"] == "fast" or o["velocity_factor"] > 1
        o["interpolation"] = "compose" if fast else "reinterpolate"


def _lddmm(operator, template, data, kernel, o: dict) -> tuple:
    from ..deform import LDDMMDeformation
    from ..solvers import IndirectRegistration

    if o["velocity_factor"] > 1:
        W, kernel = _coarse_velocity(kernel, o)
    else:
        W = LDDMMDeformation(kernel.domain, num_steps=o["num_steps"], action=o["action"],
                             backward=o["backward"] or "paper", interpolation=o["interpolation"])
    return _slabwise(IndirectRegistration(operator, W, kernel, template, data, o["gamma"], tv_weight=o["tv_weight"]),
                     o), {}


def _slabwise(problem, o: dict):
    """The problem slab-wise (``SlabwiseRegistration``) when it is split over processes (``distributed``), or when
    ``slab_size`` / ``max_memory`` (automatic: half the free memory) leave a whole-volume gradient no room; else
    ``problem`` itself. A split that cannot be made is an ``OptionError`` naming why (whole-volume where the
    memory bound alone asked for it)."""
    from ..problems.slabs import SlabwiseRegistration, choose_slab_size, projector_bytes, slab_refusal
    from ..ranks import process_group

    T, W, template = problem.ray_transform, problem.deformation, problem.template
    group = process_group(o["distributed"], template.device)
    reason = slab_refusal(T, W, problem.tv_weight)
    if reason is None and o["solver"] != ALGORITHM1:
        reason = f"solver {o['solver']!r} differentiates by autograd (slab-wise: solver 'algorithm1')"
    name = "distributed" if group is not None else "slab_size" if o["slab_size"] is not None else None
    if reason is not None:
        if name is not None:
            unset = "None" if name == "slab_size" else "False (one process)"
            raise OptionError(name, o[name] if name == "slab_size" else True, f"{unset} here: the registration does "
                              f"not split into slabs along the tilt axis ({reason})")
        return problem
    axis = T.geometry.axis
    slab_size = o["slab_size"] or choose_slab_size(problem.image_domain.shape, axis, template.element_size(),
                                                   o["max_memory"], template.device, math.prod(problem.momentum_shape),
                                                   projector_bytes(T, template))
    if group is None and slab_size >= problem.image_domain.shape[axis]:
        return problem
    return SlabwiseRegistration(T, W, problem.kernel, template, problem.data, problem.gamma, problem.tv_weight,
                                problem.tv_smoothing, o["slab_size"], o["max_memory"],
                                group=group if group is not None else False)


def _coarse_velocity(kernel, o: dict) -> tuple:
    """``velocity_factor > 1``: ``CoarseVelocityDeformation`` and the kernel on the coarse grid (``backward``
    "paper", the app's default, runs the exact gradient: the paper's formula has no coarse-grid form)."""
    from ..deform import CoarseVelocityDeformation, GaussianKernel, coarse_domain

    domain, f = kernel.domain, o["velocity_factor"]
    try:
        velocity_domain = coarse_domain(domain, f)   # checks that f divides every axis
    except ValueError:
        raise OptionError("velocity_factor", f, f"an integer >= 1 dividing every axis of the grid {domain.shape}") \
            from None
    backward = "exact" if o["backward"] in (None, "paper") else o["backward"]
    W = CoarseVelocityDeformation(domain, velocity_domain, o["num_steps"], o["action"], backward, o["interpolation"])
    return W, GaussianKernel(velocity_domain, kernel.sigma, kernel.method)


def _source_masks(mask, template: torch.Tensor, data: torch.Tensor, operator, domain, width: float, label: str):
    """``(source_mask, uniform_region)``: ``source_mask`` None, ``"template"`` (the template's support,
    ``template_support``), ``"data"`` (that and where the data show mass the template lacks, ``_data_only_support``:
    the ``uniform_region`` when not empty, else None) or an array."""
    import torch

    from ..problems.metamorphosis import template_support

    if mask is None:
        return None, None
    if isinstance(mask, str):
        if mask not in SOURCE_MASKS:
            raise OptionError(label, mask, f"None, {' or '.join(map(repr, SOURCE_MASKS))} or an array "
                              f"{tuple(domain.shape)}")
        support = template_support(template, domain)
        if mask == "template":
            return support, None
        extra = _data_only_support(template, data.to(template.dtype), operator, domain, width)
        region = extra * (1 - support)
        return torch.maximum(support, extra), region if bool(region.any()) else None
    return as_tensor(mask, label, domain.shape, template.dtype, template.device), None


def _data_only_support(template: torch.Tensor, data: torch.Tensor, operator, domain, width: float) -> torch.Tensor:
    """Where the data's visual hull shows mass that the template's own hull (of its noise-free projection, at the
    data's noise level) does not (``data_support``), without the parts thinner than about 4 ``width`` (the source's
    width; ``opened`` at 2 ``width``): the strips along the rays of a limited angular range, and an outline the
    deformation can reach (docs/metamorphosis.md, "The source's mask")."""
    from ..problems.metamorphosis import data_support, noise_std, opened

    noise = noise_std(data)
    own = data_support(operator(template), operator, domain, noise=noise)
    return opened(data_support(data, operator, domain, noise=noise) * (1 - own), domain, 2 * width)


#: The named source masks: the template's support, or that and where the data show mass the template lacks.
SOURCE_MASKS = ("template", "data")


def _metamorphosis(operator, template, data, kernel, o: dict) -> tuple:
    from ..deform import GaussianKernel, MetamorphosisDeformation
    from ..solvers import MetamorphosisRegistration

    domain = kernel.domain
    M = MetamorphosisDeformation(domain, num_steps=o["num_steps"], backward=o["backward"] or "adjoint",
                                 interpolation=o["interpolation"])
    source_sigma = kernel.sigma if o["source_sigma"] == "kernel" else o["source_sigma"]
    source_kernel = None if source_sigma is None else GaussianKernel(domain, source_sigma)
    mask, uniform = _source_masks(o["source_mask"], template, data, operator, domain, source_sigma or kernel.sigma,
                                  "source_mask")
    start = _source_start(o)
    staged = uniform is not None and solver_kind(o["solver"]) == ALGORITHM1   # the problem stages the source
    problem = MetamorphosisRegistration(operator, M, kernel, template, data, o["gamma"], o["tau"],
                                        tv_weight=o["tv_weight"], source_kernel=source_kernel, source_mask=mask,
                                        tau_rel=o["tau_rel"] if o["tau"] is None else None, uniform_region=uniform,
                                        source_start=start if staged else 0)
    solver_options = {ALGORITHM1: {"steps": {"source": o["source_step_size"]}, "frozen": {"source": 0 if staged else
                                                                                           start}},
                      TORCH: {"lrs": {"source": o["source_lr"]}}}
    return problem, solver_options


def _source_start(o: dict) -> int:
    """Iterations with the source frozen: ``source_start``, or ``round(source_start_fraction * max_iter)``."""
    if o["source_start"] is not None:
        return o["source_start"]
    return int(round(o["source_start_fraction"] * o["max_iter"]))


def _backward_in(allowed: tuple) -> Callable:
    def check(o: dict, label) -> None:
        if o["backward"] is not None and o["backward"] not in allowed:
            raise OptionError(label("backward"), o["backward"], f"one of {', '.join(map(repr, allowed))} "
                              f"for model={o['model']!r}")
    return check


def _check_lddmm(o: dict, label) -> None:
    _backward_in(("paper", "exact", "autograd"))(o, label)
    if o["velocity_factor"] > 1 and o["interpolation"] == "reinterpolate":
        raise OptionError(label("interpolation"), o["interpolation"], "'compose' (or None) with velocity_factor > 1: "
                          "the template is sampled once at the interpolated phi_{1,0}")


def _check_metamorphosis(o: dict, label) -> None:
    _backward_in(("adjoint", "autograd"))(o, label)
    if o["action"] != "geometric":
        raise OptionError(label("action"), o["action"], "'geometric' for model='metamorphosis'")
    mask = o["source_mask"]
    if isinstance(mask, str) and mask not in SOURCE_MASKS:
        raise OptionError(label("source_mask"), mask, f"None, {' or '.join(map(repr, SOURCE_MASKS))} or an array")
    for absolute, relative in (("tau", "tau_rel"), ("source_start", "source_start_fraction")):
        if o[absolute] is not None and o[relative] != RELATIVE_DEFAULTS[relative]:
            raise OptionError(label(relative), o[relative], f"left at its default {RELATIVE_DEFAULTS[relative]} when "
                              f"{label(absolute)} is given (it applies only with {label(absolute)} None)")


_META = ("metamorphosis",)
register_model(Model("lddmm", _lddmm, doc="the paper's LDDMM (eq:RegOptim)", check=_check_lddmm,
                     defaults=_interpolation, options=(
    Option("velocity_factor", "deformation", "velocity_factor", 1, number(1, integer=True),
           "the momentum, velocity, kernel and flow on the grid coarsened this many times per axis (it must divide "
           "every axis), phi_{1,0} interpolated to the image's grid (CoarseVelocityDeformation: interpolation "
           "compose, the exact gradient); 1: the image's grid", int, models=("lddmm",)),
    Option("slab_size", "deformation", "slab_size", None, optional(number(1, integer=True)),
           "a tilt series with velocity_factor > 1: the data term and its gradient slab by slab, this many slices "
           "along the tilt axis each (docs/3d.md); None: from max_memory (whole-volume where it fits)",
           Optional[int], models=("lddmm",), resumable=True),
    Option("max_memory", "deformation", "max_memory", None, optional(number(1.0)),
           "bytes a gradient may take, which sets slab_size when that is None; None: half the free memory",
           Optional[float], models=("lddmm",), resumable=True),
    Option("distributed", "deformation", "distributed", None, optional(boolean),
           "one registration over the processes of torchrun (torch.distributed: gloo on CPUs, NCCL on GPUs), each "
           "with its slabs; None: when launched so (WORLD_SIZE > 1); docs/distributed.md", Optional[bool],
           models=("lddmm",), resumable=True),
)))
#: The defaults of the relative metamorphosis options (docs/metamorphosis.md "Defaults relative to the data term":
#: measured on the suite-4 missing / extra, suite-3 contrast and limited-angle cases).
RELATIVE_DEFAULTS = {"tau_rel": 0.01, "source_start_fraction": 0.6}


def _fraction(v, label):
    v = number(0.0)(v, label)
    if v > 1:
        raise OptionError(label, v, "a number in [0, 1]")
    return v


def _source_sigma(v, label):
    if v is None or v == "kernel":
        return v
    if isinstance(v, str):
        raise OptionError(label, v, "None, 'kernel' or a finite number > 0")
    return number(0.0, strict=True)(v, label)


register_model(Model("metamorphosis", _metamorphosis, defaults=_interpolation,
                     doc="metamorphosis (eq:Metam:ODE): intensities change too",
                     check=_check_metamorphosis, options=(
    Option("tau", "deformation", "tau", None, optional(number(0.0)),
           "weight of the source's penalty (absolute); None: tau_rel times the data term's scale", Optional[float],
           models=_META),
    Option("tau_rel", "deformation", "tau_rel", RELATIVE_DEFAULTS["tau_rel"], number(0.0),
           "with tau None: tau = tau_rel ||T||^2 ||K_s|| (the source penalty relative to the data term's curvature "
           "on the smoothest source; docs/metamorphosis.md)", float, models=_META),
    Option("source_sigma", "deformation", "source_sigma", "kernel", _source_sigma,
           "'kernel' (a Gaussian RKHS source of the velocity kernel's width), a width, or None (the paper's L2 "
           "source)", Optional[Any], models=_META),
    Option("source_mask", "deformation", "source_mask", "data", anything,
           "'data' (the template's support dilated by 1 unit, and where the data show mass the template lacks, "
           "data_support: there a uniform source from the first iteration), 'template' (the template's support "
           "only), None or an array in [0, 1]", Optional[str], models=_META),
    Option("source_step_size", "solver", "source_step_size", None, optional(number(0.0, strict=True)),
           "Algorithm 1's source step (None: 1 / (tau + ||T||^2))", Optional[float], solvers=(ALGORITHM1,),
           models=_META),
    Option("source_lr", "solver", "source_lr", None, optional(number(0.0, strict=True)),
           "the source's torch.optim learning rate (None: lr)", Optional[float], solvers=(TORCH,), models=_META),
    Option("source_start", "solver", "source_start", None, optional(number(0, integer=True)),
           "Algorithm 1: iterations with the source frozen (its uniform part excepted); None: "
           "source_start_fraction of max_iter",
           Optional[int], solvers=(ALGORITHM1,), models=_META),
    Option("source_start_fraction", "solver", "source_start_fraction", RELATIVE_DEFAULTS["source_start_fraction"],
           _fraction, "Algorithm 1, with source_start None: the fraction of max_iter with the source frozen", float,
           solvers=(ALGORITHM1,), models=_META),
)))


def _spatiotemporal(operator, template, data, kernel, o: dict) -> tuple:
    from ..deform import LDDMMDeformation
    from ..problems.spatiotemporal import SpatiotemporalRegistration
    from ..solvers.spatiotemporal import IntertwinedSolver

    W = LDDMMDeformation(kernel.domain, num_steps=o["num_steps"], action=o["action"],
                         backward=o["backward"] or "autograd", interpolation=o["interpolation"])
    problem = SpatiotemporalRegistration(operator, W, kernel, template, data, o["times"], o["gamma"],
                                         tv_weight=o["tv_weight"], template_tv_weight=o["template_tv_weight"])
    if problem.known:
        return problem, {}
    options = {ALGORITHM1: {"steps": {"template": o["template_step_size"]}}}
    if o["template_update"] == "intertwined":
        if solver_kind(o["solver"]) != ALGORITHM1:
            raise OptionError("template_update", "intertwined", f"'joint' with solver={o['solver']!r} (the "
                              "intertwined scheme alternates with Algorithm 1's steps)")
        options[ALGORITHM1]["cycle"] = ((("momentum",), 1),)   # Algorithm 1 moves the momentum only
        options["wrap"] = lambda solver: IntertwinedSolver(solver, o["template_steps"], o["registration_steps"],
                                                           o["template_tv_weight"])
    return problem, options


def _check_spatiotemporal(o: dict, label) -> None:
    _backward_in(("autograd", "exact"))(o, label)
    if isinstance(o["times"], (list, tuple)):   # their number is checked against the data's frames at setup
        from ..problems.spatiotemporal import time_indices   # (it imports torch: only when times are given)

        try:
            time_indices(o["times"], o["num_steps"], len(o["times"]))
        except ValueError as e:
            raise OptionError(label("times"), o["times"], f"None or valid times ({str(e).split(', got ')[0]})") \
                from None
    if o["solver"] == "fast":
        raise OptionError(label("solver"), o["solver"], "'algorithm1' or a torch.optim name for "
                          "model='spatiotemporal' (no coarse-to-fine form)")
    if o["holdout"] is not None:
        raise OptionError(label("holdout"), o["holdout"], "None for model='spatiotemporal'")


_ST = ("spatiotemporal",)
register_model(Model("spatiotemporal", _spatiotemporal, check=_check_spatiotemporal, template_optional=True,
                     defaults=_interpolation,
                     doc="data at several time points, one flow (eq:SpatioTemporal); the template known or not",
                     options=(
    Option("times", "deformation", "times", None, anything,
           "the data's time points t_1 < ... < t_K in [0, 1], each on the grid j / num_steps (None: k / K)",
           Optional[Any], models=_ST),
    Option("template_update", "solver", "template_update", "joint", choice(("joint", "intertwined")),
           "template unknown: 'joint' (Algorithm 1 or torch.optim on (m, I) together) or 'intertwined' (every outer "
           "iteration a TV reconstruction of I from all frames pulled back through the current motion, then "
           "registration steps; IntertwinedSolver): a little better per iteration, 7x the cost per iteration "
           "(docs/spatiotemporal.md)",
           str, models=_ST),
    Option("template_steps", "solver", "template_steps", 50, number(1, integer=True),
           "intertwined: Chambolle-Pock iterations of the template's reconstruction per outer iteration", int,
           solvers=(ALGORITHM1,), models=_ST),
    Option("registration_steps", "solver", "registration_steps", 10, number(1, integer=True),
           "intertwined: Algorithm 1 steps on the momentum per outer iteration", int, solvers=(ALGORITHM1,),
           models=_ST),
    Option("template_step_size", "solver", "template_step_size", None, optional(number(0.0, strict=True)),
           "joint, Algorithm 1: the template's step (None: 1 / ||T||^2, T all frames' operators)", Optional[float],
           solvers=(ALGORITHM1,), models=_ST),
    Option("template_tv_weight", "solver", "template_tv_weight", 0.0, number(0.0),
           "template unknown: weight of TV(I) (its objective's; the intertwined TV step's mu is twice it)", float,
           models=_ST),
)))


def _residual(operator, template, data, kernel, o: dict) -> tuple:
    from ..deform import LDDMMDeformation
    from ..forward.tv import intensity_scale, tv_weight_unit
    from ..problems.residual import ResidualRegistration

    W = LDDMMDeformation(kernel.domain, num_steps=o["num_steps"], action=o["action"],
                         backward=o["backward"] or "paper", interpolation=o["interpolation"])
    h = min(kernel.domain.cell_sides)
    smoothing = RESIDUAL_SMOOTHING * intensity_scale(operator, data) / h
    unit = 0.5 * tv_weight_unit(operator, data)   # E's (1/2)||.||^2: half the TV baseline's mu
    auto = o["residual_tv"] in (None, "auto")
    mu = unit * (RESIDUAL_TV_FALLBACK if auto else o["residual_tv"])
    candidates = tuple(unit * c for c in RESIDUAL_TV_GRID) if auto else ()
    problem = ResidualRegistration(operator, W, kernel, template, data, o["gamma"], mu, smoothing,
                                   tv_weight=o["tv_weight"], finish_iter=o["residual_finish_iter"],
                                   mu_candidates=candidates, mu_unit=unit)
    start = int(round(o["residual_start_fraction"] * o["max_iter"]))
    return problem, {ALGORITHM1: {"steps": {"residual": o["residual_step_size"]}, "frozen": {"residual": start}},
                     "torch": {}}


def _check_residual(o: dict, label) -> None:
    _backward_in(("paper", "exact", "autograd"))(o, label)
    if o["solver"] == "fast":
        raise OptionError(label("solver"), o["solver"], "'algorithm1' or a torch.optim name for model='residual' "
                          "(no coarse-to-fine form)")


#: The residual's TV smoothing eps, relative to the data's intensity unit per cell side.
RESIDUAL_SMOOTHING = 0.01
#: ``residual_tv="auto"``: the finish's weights (in the TV weight unit), the held-out angles choose; the joint
#: iterations, and a run without held-out angles, use the fallback (docs/real_data.md, section 9).
RESIDUAL_TV_GRID = (1e-6, 1e-5, 1e-4, 1e-3)
RESIDUAL_TV_FALLBACK = 1e-4
_RES = ("residual",)
register_model(Model("residual", _residual, defaults=_interpolation, check=_check_residual,
                     doc="LDDMM plus an intensity residual regularised by TV (indreg.problems.residual): the template's "
                         "shape deformed, the intensities it cannot fit added",
                     options=(
    Option("residual_tv", "deformation", "residual_tv", "auto", auto_or(number(0.0), "a number >= 0"),
           "the residual's TV weight relative to the TV weight unit (indreg.forward.tv_weight_unit: the TV "
           "baseline's tv_mu); 'auto': the finish's weight chosen among 1e-6, 1e-5, 1e-4, 1e-3 by the held-out "
           "angles (1e-4 without them, and in the joint iterations); docs/real_data.md", Union[str, float],
           models=_RES),
    Option("residual_finish_iter", "solver", "residual_finish_iter", 200, number(0, integer=True),
           "Chambolle-Pock iterations of the finish: f = W + r solved with W fixed (TV anchored at W, f >= 0); "
           "0: none", int, models=_RES),
    Option("residual_start_fraction", "solver", "residual_start_fraction", 0.5, _fraction,
           "Algorithm 1: the fraction of max_iter with the residual frozen at 0 (the deformation first)", float,
           solvers=(ALGORITHM1,), models=_RES),
    Option("residual_step_size", "solver", "residual_step_size", None, optional(number(0.0, strict=True)),
           "Algorithm 1's residual step (None: 1 / (||T||^2 + the smoothed TV's curvature bound))",
           Optional[float], solvers=(ALGORITHM1,), models=_RES),
)))
