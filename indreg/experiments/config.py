"""Typed (structured) configs of the experiment app, registered in Hydra's ConfigStore.

The dataclasses below are the *schema* of ``indreg/conf/**.yaml``: Hydra merges every yaml file into them, so an
unknown key (``solver.gama=1``), a wrong type (``solver.gamma=abc``) or a value outside an enum
(``deformation.action=affine``, ``phantom.target=cat``) fails at composition with a message that names the key.
Range checks that a type cannot express (``solver.gamma >= 0``, ``kernel.sigma > 0``, ...) are done by
:func:`validate` when the app starts, also naming the key.

Config groups (one sub-config each) and top-level keys::

    data         where template and data come from: ``phantom`` (simulated, the default) or ``files``
    phantom      template/target names (``indreg.phantoms.get``) and the grid size n (domain [-16, 16]^2)
    geometry     parallel- or fan-beam geometry: angles x detector bins (the authors' ODL partition by default)
    noise        white noise at an SNR in dB ("code" convention, docs/paper_notes.md) or with a fixed std
    deformation  LDDMM time steps N, group action, backward (gradient) scheme, interpolation scheme
    kernel       Gaussian RKHS kernel width sigma
    solver       gamma, step size, iterations; Algorithm 1 or a torch.optim parametrisation
    baseline     FBP (filter, frequency scaling) and TV (mu, iterations) reconstructions from the same data
    logging      evaluation / image / checkpoint period k, TensorBoard, progress bar, figure
    experiment   presets of the paper's test suites (package _global_), ``suite1_jv`` by default
    sweep        multirun presets (``sweep=suite3_table``: the paper's sensitivity table)
    name, seed, dtype, device, resume, stop_after

The yaml files live in the package (``indreg/conf``, :data:`CONFIG_DIR`), so an installed wheel composes exactly
the configs of the checkout.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Dict, Optional

from omegaconf import DictConfig, OmegaConf

from .. import phantoms as _phantoms
from ..deform import functional as _Fd
from ..deform import lddmm as _lddmm
from ..deform import metamorphosis as _metamorphosis
from ..domain import AXES
from . import sources
from .errors import ConfigError   # re-exported: ``from indreg.experiments.config import ConfigError``

Phantom = Enum("Phantom", {name: name for name in _phantoms.names()}, type=str)
Phantom.__doc__ = "Phantom names accepted by ``indreg.phantoms.get``."


class Dtype(str, Enum):
    float32 = "float32"
    float64 = "float64"


class AnglePartition(str, Enum):
    """``paper``: ODL's ``uniform_partition(0, pi, n, nodes_on_bdry=(True, False))``; ``uniform``: k pi / n."""
    paper = "paper"
    uniform = "uniform"


class GeometryKind(str, Enum):
    """``parallel``: ``ParallelBeamGeometry``; ``fan_flat``: ``FanBeamGeometry`` (flat detector), both 2D;
    ``tilt_series``: ``TiltSeriesGeometry`` (3D, single-axis tilt series of electron tomography)."""
    parallel = "parallel"
    fan_flat = "fan_flat"
    tilt_series = "tilt_series"


class AngleUnit(str, Enum):
    deg = "deg"
    rad = "rad"


class NoiseConvention(str, Enum):
    code = "code"
    paper = "paper"


# the deformation operator's choices, from the one place that defines them
Action = Enum("Action", {name: name for name in _Fd.ACTIONS}, type=str)
Backward = Enum("Backward", {name: name for name in (*_lddmm.BACKWARDS, *_metamorphosis.BACKWARDS)}, type=str)
Interpolation = Enum("Interpolation", {name: name for name in _Fd.INTERPOLATIONS}, type=str)
TiltAxis = Enum("TiltAxis", {name: name for name in AXES}, type=str)   # the image axes x, y, z


class Model(str, Enum):
    """``lddmm``: ``LDDMMDeformation``; ``metamorphosis``: ``MetamorphosisDeformation`` (intensities change too)."""
    lddmm = "lddmm"
    metamorphosis = "metamorphosis"


class SolverName(str, Enum):
    algorithm1 = "algorithm1"
    torch_optim = "torch_optim"
    fast = "fast"            # indreg.solvers.MultilevelSolver (optimizer_kwargs: its options)


class Optimizer(str, Enum):
    lbfgs = "lbfgs"
    adam = "adam"
    sgd = "sgd"


class FBPFilter(str, Enum):
    ram_lak = "ram-lak"
    shepp_logan = "shepp-logan"
    cosine = "cosine"
    hamming = "hamming"
    hann = "hann"


@dataclass
class PhantomConfig:
    """Template I and target f_true (``indreg.phantoms``), digitised on ``size`` cells per axis of
    ``[-half_width, half_width]^ndim`` (``ndim`` 2: images, 3: volumes)."""
    template: Phantom = Phantom["j"]
    target: Phantom = Phantom["v"]
    size: int = 64
    half_width: float = 16.0
    ndim: int = 2


@dataclass
class DataConfig:
    """Where template and data come from: ``source`` is a built-in source, an ``indreg.sources`` entry point or
    ``module:function`` (``indreg.experiments.sources``).

    ``phantom`` (default): the ``phantom`` group's template and target, data simulated with the ``geometry`` and
    ``noise`` groups. ``files``: ``template`` and ``sinogram`` (and optionally ``target``) read from files
    (``indreg.io``), on the domain ``[-half_width, half_width]^2`` with the template's (square) pixel grid.
    """
    source: str = "phantom"
    template: Optional[str] = None
    sinogram: Optional[str] = None
    target: Optional[str] = None
    half_width: float = 16.0


@dataclass
class GeometryConfig:
    """Acquisition geometry. ``kind``: ``parallel`` or ``fan_flat``. Angles: ``angles`` (a text-file path or a
    list, in ``angle_unit``) or else ``num_angles`` of ``partition``. Detector: ``det_count`` bins on
    ``[det_min, det_max]`` (at the detector; ``null`` both: fitted to the domain). ``data=files`` takes
    ``det_count`` (and ``num_angles``) from the sinogram. Fan beam: ``src_radius`` (source to origin),
    ``det_radius`` (origin to detector). Tilt series (3D): rotation about ``tilt_axis``; angles ``angles`` or else
    ``tilt_min``, ``tilt_min + tilt_step``, ..., ``tilt_max`` (in ``angle_unit``); ``det_count`` columns per
    detector row, one row per slice along the tilt axis (docs/tilt_series.md)."""
    kind: GeometryKind = GeometryKind.parallel
    num_angles: Optional[int] = 10
    det_count: Optional[int] = 92
    det_min: Optional[float] = -24.0
    det_max: Optional[float] = 24.0
    partition: AnglePartition = AnglePartition.paper
    angles: Optional[Any] = None
    angle_unit: AngleUnit = AngleUnit.deg
    src_radius: Optional[float] = None
    det_radius: float = 0.0
    tilt_axis: TiltAxis = TiltAxis.y
    tilt_min: float = -60.0
    tilt_max: float = 60.0
    tilt_step: float = 2.0


@dataclass
class NoiseConfig:
    """Additive white noise: give ``snr_db`` (in ``convention``) or ``std`` (or neither: noise-free data)."""
    snr_db: Optional[float] = 4.87
    std: Optional[float] = None
    convention: NoiseConvention = NoiseConvention.code
    seed: Optional[int] = None  # None: the run's seed


@dataclass
class DeformationConfig:
    """LDDMM flow with N time steps (t_i = i / N), group action and derivative scheme (``LDDMMDeformation``).
    ``model=metamorphosis`` (``deformation=metamorphosis``): the image path also changes intensities
    (``MetamorphosisDeformation``, geometric action, backward ``adjoint`` or ``autograd``); ``tau`` weighs the
    source term's penalty; ``source_sigma`` (null: the paper's L2 source) the width of an RKHS for the source;
    ``source_mask=template`` confines the intensity changes to the template's support."""
    num_steps: int = 20
    action: Action = Action.geometric
    backward: Backward = Backward.paper
    interpolation: Interpolation = Interpolation.reinterpolate
    model: Model = Model.lddmm
    tau: float = 1.0
    source_sigma: Optional[float] = None
    source_mask: Optional[str] = None


@dataclass
class KernelConfig:
    """Gaussian RKHS kernel ``exp(-|x - y|^2 / (2 sigma^2))`` (physical units)."""
    sigma: float = 6.0


@dataclass
class SolverConfig:
    """Objective weights and the optimiser. ``step_size`` is Algorithm 1's epsilon (the presets set it); ``lr`` is
    the learning rate of torch.optim (``solver=lbfgs`` / ``adam`` set their own), so an ``experiment=`` preset
    never changes an optimizer's learning rate."""
    name: SolverName = SolverName.algorithm1
    gamma: float = 1e-6
    tv_weight: float = 0.0
    step_size: float = 0.02
    lr: float = 1.0
    max_iter: int = 200
    grad_tol: float = 0.0
    step_halving: bool = False
    max_halvings: int = 20
    optimizer: Optimizer = Optimizer.lbfgs
    optimizer_kwargs: Dict[str, Any] = field(default_factory=dict)
    source_step_size: Optional[float] = None  # metamorphosis, algorithm1: null = 1 / (tau + ||T||^2)
    source_lr: Optional[float] = None         # metamorphosis, torch_optim: null = lr
    source_start: int = 0                     # metamorphosis, algorithm1: iterations with the source frozen


@dataclass
class BaselineConfig:
    """Direct reconstructions from the same data: FBP (Hamming, 0.4) and TV (Chambolle-Pock); for volumes also
    SIRT (``sirt_iterations``, nonnegative)."""
    enabled: bool = True
    fbp_filter: FBPFilter = FBPFilter.hamming
    fbp_frequency_scaling: float = 0.4
    fbp_padding: bool = True
    tv_mu: float = 3.0
    tv_iterations: int = 1000
    sirt_iterations: int = 100


@dataclass
class LoggingConfig:
    """Every ``every`` iterations: SSIM/PSNR and image to TensorBoard; checkpoint every ``checkpoint_every``."""
    every: int = 10
    checkpoint_every: int = 10
    tensorboard: bool = True
    progress: bool = True
    figure: bool = True


@dataclass
class RegisterConfig:
    """The whole run. ``stop_after``: stop (checkpoint, as if interrupted) once this many iterations are done."""
    name: str = "suite1_jv"
    seed: int = 0
    dtype: Dtype = Dtype.float32
    device: str = "auto"
    resume: bool = False
    stop_after: Optional[int] = None
    data: DataConfig = field(default_factory=DataConfig)
    phantom: PhantomConfig = field(default_factory=PhantomConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    kernel: KernelConfig = field(default_factory=KernelConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)


SCHEMA_NAME = "indreg_schema"

#: The app's yaml configs, shipped inside the package (``indreg/conf``; the checkout's top-level ``configs`` is a
#: link to it): one source of truth for the checkout and the installed wheel. Users add their own config groups
#: or presets with Hydra's search path, e.g. ``indreg-register 'hydra.searchpath=[file:///my/configs]' ...``.
CONFIG_DIR = Path(__file__).resolve().parents[1] / "conf"


#: Example data shipped with the package, named in configs as ``${indreg_data:<file name>}``.
DATA_DIR = Path(__file__).resolve().parents[1] / "data"


def register_schema() -> None:
    """Store the schema ``indreg_schema`` (``RegisterConfig``) that ``conf/config.yaml`` starts from, and the
    resolver ``${indreg_data:name}`` (the path of a file shipped in ``indreg/data``)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=SCHEMA_NAME, node=RegisterConfig)
    register_resolvers()


_DEVICE = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")
_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")  # a single path component (it names the run dir)


def _require(ok: bool, key: str, expected: str, value) -> None:
    if not ok:
        raise ConfigError(f"invalid config value {key}={value!r}: expected {expected}")


def _finite(v) -> bool:
    return v is not None and math.isfinite(float(v))


def _unknown_keys(node, schema, prefix: str = "") -> list:
    """Dotted keys of ``node`` absent from ``schema`` (e.g. added with Hydra's ``+key=value``)."""
    out = []
    for key in node:
        if key not in schema:
            out.append(prefix + str(key))
        elif OmegaConf.is_dict(schema[key]) and key != "optimizer_kwargs":
            out += _unknown_keys(node[key], schema[key], f"{prefix}{key}.")
    return out


def validate(cfg: DictConfig) -> None:
    """Range checks the schema's types cannot express; raises :class:`ConfigError` naming the key."""
    c = cfg
    unknown = _unknown_keys(cfg, OmegaConf.structured(RegisterConfig))
    if unknown:
        raise ConfigError(f"unknown config key(s) {', '.join(unknown)}: not in the schema "
                          "indreg.experiments.config.RegisterConfig")
    _require(bool(_NAME.fullmatch(c.name)), "name", "letters, digits, '.', '_' and '-', not starting with '.'",
             c.name)
    _require(0 <= c.seed < 2 ** 32, "seed", "an integer in [0, 2**32) (numpy's seed range)", c.seed)
    _require(bool(_DEVICE.match(c.device)), "device", "'auto', 'cpu', 'cuda' or 'cuda:<index>'", c.device)
    _check_cuda(c.device)
    _require(c.stop_after is None or c.stop_after >= 0, "stop_after", "null or an integer >= 0", c.stop_after)
    _require(c.phantom.size >= 4, "phantom.size", "an integer >= 4", c.phantom.size)
    _require(c.phantom.ndim in (2, 3), "phantom.ndim", "2 (images) or 3 (volumes)", c.phantom.ndim)
    _require(_finite(c.phantom.half_width) and c.phantom.half_width > 0, "phantom.half_width", "a number > 0",
             c.phantom.half_width)
    _validate_data(c)
    n = c.noise
    _require(n.snr_db is None or n.std is None, "noise.snr_db", "at most one of noise.snr_db and noise.std",
             (n.snr_db, n.std))
    _require(n.snr_db is None or (_finite(n.snr_db) and abs(n.snr_db) <= 300), "noise.snr_db",
             "a number in [-300, 300] (dB) or null", n.snr_db)
    _require(n.std is None or (_finite(n.std) and n.std >= 0), "noise.std", "a number >= 0 or null", n.std)
    _require(n.seed is None or 0 <= n.seed < 2 ** 32, "noise.seed", "null or an integer in [0, 2**32)", n.seed)
    _require(c.deformation.num_steps >= 1, "deformation.num_steps", "an integer >= 1", c.deformation.num_steps)
    _validate_model(c)
    _require(_finite(c.kernel.sigma) and c.kernel.sigma > 0, "kernel.sigma", "a number > 0", c.kernel.sigma)
    s = c.solver
    _require(_finite(s.gamma) and s.gamma >= 0, "solver.gamma", "a number >= 0", s.gamma)
    _require(_finite(s.tv_weight) and s.tv_weight >= 0, "solver.tv_weight", "a number >= 0", s.tv_weight)
    _require(_finite(s.step_size) and s.step_size > 0, "solver.step_size", "a number > 0", s.step_size)
    _require(_finite(s.lr) and s.lr > 0, "solver.lr", "a number > 0", s.lr)
    _require(s.max_iter >= 0, "solver.max_iter", "an integer >= 0", s.max_iter)
    _require(_finite(s.grad_tol) and s.grad_tol >= 0, "solver.grad_tol", "a number >= 0", s.grad_tol)
    _require(s.max_halvings >= 0, "solver.max_halvings", "an integer >= 0", s.max_halvings)
    if s.name.value == "torch_optim":
        _check_optimizer_kwargs(s.optimizer.value, s.optimizer_kwargs)
    if s.name.value == "fast":
        _check_fast_kwargs(s.optimizer_kwargs)
    b = c.baseline
    _require(_finite(b.fbp_frequency_scaling) and 0 < b.fbp_frequency_scaling <= 1, "baseline.fbp_frequency_scaling",
             "a number in (0, 1]", b.fbp_frequency_scaling)
    _require(_finite(b.tv_mu) and b.tv_mu >= 0, "baseline.tv_mu", "a number >= 0", b.tv_mu)
    _require(b.tv_iterations >= 1, "baseline.tv_iterations", "an integer >= 1", b.tv_iterations)
    _require(b.sirt_iterations >= 1, "baseline.sirt_iterations", "an integer >= 1", b.sirt_iterations)
    lg = c.logging
    _require(lg.every >= 1, "logging.every", "an integer >= 1", lg.every)
    _require(lg.checkpoint_every >= 1, "logging.checkpoint_every", "an integer >= 1", lg.checkpoint_every)


def _validate_model(c: DictConfig) -> None:
    """``deformation.model`` and the keys whose valid values depend on it."""
    d, s = c.deformation, c.solver
    backwards = _metamorphosis.BACKWARDS if d.model.value == "metamorphosis" else _lddmm.BACKWARDS
    _require(d.backward.value in backwards, "deformation.backward",
             f"one of {', '.join(backwards)} for deformation.model={d.model.value}", d.backward.value)
    if d.model.value == "metamorphosis":
        _require(d.action.value == "geometric", "deformation.action", "geometric for deformation.model=metamorphosis",
                 d.action.value)
    _require(_finite(d.tau) and d.tau >= 0, "deformation.tau", "a number >= 0", d.tau)
    _require(d.source_mask in (None, "template"), "deformation.source_mask", "null or template", d.source_mask)
    _require(d.source_sigma is None or (_finite(d.source_sigma) and d.source_sigma > 0), "deformation.source_sigma",
             "null or a number > 0", d.source_sigma)
    for key in ("source_step_size", "source_lr"):
        v = s[key]
        _require(v is None or (_finite(v) and v > 0), f"solver.{key}", "null or a number > 0", v)
    _require(s.source_start >= 0, "solver.source_start", "an integer >= 0", s.source_start)


def _validate_data(c: DictConfig) -> None:
    """The ``data`` and ``geometry`` groups (which keys a source needs is its own business, checked here)."""
    d, g = c.data, c.geometry
    sources.resolve(d.source)
    if d.source == "files":
        for key in ("template", "sinogram"):
            _require(bool(d[key]), f"data.{key}", "a file path (data=files)", d[key])
        _require(_finite(d.half_width) and d.half_width > 0, "data.half_width", "a number > 0", d.half_width)
    elif d.source == "phantom":
        _require(g.num_angles is not None and g.num_angles >= 1 or g.angles is not None
                 or g.kind.value == "tilt_series", "geometry.num_angles", "an integer >= 1 (or geometry.angles)",
                 g.num_angles)
        _require(g.det_count is not None and g.det_count >= 1, "geometry.det_count", "an integer >= 1",
                 g.det_count)
    _require((g.det_min is None) == (g.det_max is None), "geometry.det_min",
             "both det_min and det_max, or neither (fitted to the domain)", (g.det_min, g.det_max))
    if g.det_min is not None:
        _require(_finite(g.det_min) and _finite(g.det_max) and g.det_min < g.det_max, "geometry.det_min",
                 "finite det_min < det_max", (g.det_min, g.det_max))
    if g.kind.value == "tilt_series":
        _require(_finite(g.tilt_step) and g.tilt_step > 0, "geometry.tilt_step", "a number > 0", g.tilt_step)
        _require(_finite(g.tilt_min) and _finite(g.tilt_max) and g.tilt_min <= g.tilt_max, "geometry.tilt_min",
                 "finite tilt_min <= tilt_max", (g.tilt_min, g.tilt_max))
    if d.source == "phantom":
        ndim = 3 if g.kind.value == "tilt_series" else 2
        _require(c.phantom.ndim == ndim, "phantom.ndim", f"{ndim} for geometry.kind={g.kind.value}", c.phantom.ndim)
    if g.kind.value == "fan_flat":
        _require(_finite(g.src_radius) and g.src_radius > 0, "geometry.src_radius",
                 "a number > 0 (source to origin) for geometry.kind=fan_flat", g.src_radius)
    _require(_finite(g.det_radius) and g.det_radius >= 0, "geometry.det_radius", "a number >= 0", g.det_radius)


def _check_cuda(device: str) -> None:
    """``device=cuda[:i]`` needs a CUDA device (with that index)."""
    if not device.startswith("cuda"):
        return
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    index = int(device.split(":")[1]) if ":" in device else 0
    _require(index < count, "device", f"'auto', 'cpu' or a CUDA device of this machine ({count} CUDA device(s) "
             "available)", device)


def _check_optimizer_kwargs(optimizer: str, kwargs) -> None:
    """Every ``solver.optimizer_kwargs`` key must be a keyword of the torch.optim optimizer's constructor."""
    import inspect

    from ..solvers.torch_optim import _optimizer_class

    allowed = set(inspect.signature(_optimizer_class(optimizer).__init__).parameters) - {"self", "params", "lr"}
    for key in kwargs:
        _require(key in allowed, f"solver.optimizer_kwargs.{key}",
                 f"a keyword of torch.optim {_optimizer_class(optimizer).__name__} ({', '.join(sorted(allowed))})",
                 kwargs[key])


def _check_fast_kwargs(kwargs) -> None:
    """``solver=fast``: every ``solver.optimizer_kwargs`` key must be an option of ``MultilevelSolver``."""
    from ..solvers.multilevel import options

    for key in kwargs:
        _require(key in options(), f"solver.optimizer_kwargs.{key}",
                 f"an option of solver=fast (indreg.solvers.MultilevelSolver: {', '.join(options())})", kwargs[key])


def path_component(name) -> str:
    """``name`` as one safe path component (resolver ``indreg_path``, used in the run-dir templates): anything
    but letters, digits, ``._-`` becomes ``_`` and a leading ``.`` is dropped, so ``name=../../x`` cannot place
    Hydra's run dir outside ``outputs/``; ``validate`` then refuses the name itself."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", str(name)).lstrip(".")
    return safe or "_"


def register_resolvers() -> None:
    OmegaConf.register_new_resolver("indreg_path", path_component, replace=True)
    OmegaConf.register_new_resolver("indreg_data", lambda name: str(DATA_DIR / name), replace=True)


def to_plain(cfg: DictConfig) -> dict:
    """The config as plain python (enums as strings), e.g. for metrics.json and checkpoints."""
    return OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
