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
    validation   held-out angles (``holdout``) and early stopping (``patience``)
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

from dataclasses import make_dataclass

from .. import conventions as _conventions
from .. import options as _options
from .. import phantoms as _phantoms
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


TiltAxis = Enum("TiltAxis", {name: name for name in AXES}, type=str)   # the image axes x, y, z
#: data=files: the tool whose layout, angles, units and detector centre the files follow (indreg.conventions).
FileConvention = Enum("FileConvention", {name: name for name in _conventions.CONVENTIONS}, type=str)
IntegerScale = Enum("IntegerScale", {name: name for name in _conventions.INTEGER_SCALES}, type=str)


class FBPFilter(str, Enum):
    ram_lak = "ram-lak"
    shepp_logan = "shepp-logan"
    cosine = "cosine"
    hamming = "hamming"
    hann = "hann"


@dataclass
class PhantomConfig:
    """Template I and target f_true (``indreg.phantoms``), digitised on ``size`` cells per axis of
    ``[-half_width, half_width]^ndim`` (``ndim`` 2: images, 3: volumes). ``thickness`` (3D only; null: ``size``):
    a slab of ``size x size x thickness`` cubic cells, ``[-h, h]^2 x [-h t / n, h t / n]``; the 3D phantoms are
    defined on the box's normalised coordinates, so they flatten with it (electron tomography's thin specimen)."""
    template: Phantom = Phantom["j"]
    target: Phantom = Phantom["v"]
    size: int = 64
    half_width: float = 16.0
    ndim: int = 2
    thickness: Optional[int] = None


@dataclass
class _DataFiles:
    source: str = "phantom"
    template: Optional[str] = None
    sinogram: Optional[str] = None
    target: Optional[str] = None
    half_width: float = 16.0
    frames: int = 12                # source=dynamic: time points K (t_k = k / K)
    amplitude: float = 0.4          # source=dynamic: the breathing amplitude A (indreg.dynamic)
    template_known: bool = True     # source=dynamic: false: the template is unknown (reconstructed with the motion)
    convention: FileConvention = FileConvention.indreg   # source=files: skimage, astra, tomopy, imod, odl
    integer_scale: IntegerScale = IntegerScale.fraction  # source=files: 8/16-bit pictures as fractions, or raw


DataConfig = make_dataclass("DataConfig", _options.schema_fields("data"), bases=(_DataFiles,))
DataConfig.__doc__ = """Where template and data come from: ``source`` is a built-in source, an ``indreg.sources`` entry point or
    ``module:function`` (``indreg.experiments.sources``).

    ``phantom`` (default): the ``phantom`` group's template and target, data simulated with the ``geometry`` and
    ``noise`` groups. ``files``: ``template`` and ``sinogram`` (and optionally ``target``) read from files
    (``indreg.io``), on the domain ``[-half_width, half_width]^2`` with the template's (square) pixel grid, in
    another tool's ``convention`` (``indreg.conventions``: layout, angles, units, detector centre) and with 8- /
    16-bit pictures as fractions of their full scale (``integer_scale: fraction``, or ``raw``).
    ``dynamic``: the breathing phantom of ``indreg.dynamic`` measured at ``frames`` time points (``amplitude``;
    ``template_known: false`` hands the run no template: ``deformation=spatiotemporal`` reconstructs it).
    ``template_scale`` / ``background`` (``indreg.options``, the same as ``indreg.register``'s): the template's
    intensity factor and the data's offset, applied before the run (``indreg.run.prepare``).
    """


@dataclass
class GeometryConfig:
    """Acquisition geometry. ``kind``: ``parallel`` or ``fan_flat``. Angles: ``angles`` (a text-file path or a
    list, in ``angle_unit``) or else ``num_angles`` of ``partition``. Detector: ``det_count`` bins on
    ``[det_min, det_max]`` (at the detector; ``null`` both: fitted to the domain). ``data=files`` takes
    ``det_count`` (and ``num_angles``) from the sinogram. Fan beam: ``src_radius`` (source to origin),
    ``det_radius`` (origin to detector). Tilt series (3D): rotation about ``tilt_axis``; angles ``angles`` or else
    ``tilt_min``, ``tilt_min + tilt_step``, ..., ``tilt_max`` (in ``angle_unit``); ``det_count`` columns per
    detector row, one row per slice along the tilt axis (docs/tilt_series.md); ``tilt_axis_angle``: the angle of
    the tilt axis in a measured stack's images (degrees from Y, counterclockwise; null: the ``.mdoc``'s, else 0),
    the stack is rotated by its opposite (``indreg.tilt_axis``)."""
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
    tilt_axis_angle: Optional[float] = None


@dataclass
class NoiseConfig:
    """Additive white noise: give ``snr_db`` (in ``convention``) or ``std`` (or neither: noise-free data)."""
    snr_db: Optional[float] = 4.87
    std: Optional[float] = None
    convention: NoiseConvention = NoiseConvention.code
    seed: Optional[int] = None  # None: the run's seed


def _group(name: str, doc: str, extra=()):
    """The schema of a registration group, generated from ``indreg.options`` (one declaration for the app and
    ``indreg.register``); ``extra``: the app's own keys."""
    cls = make_dataclass(name, [*_options.schema_fields(name[:-len("Config")].lower()), *extra])
    cls.__doc__ = doc
    return cls


DeformationConfig = _group("DeformationConfig", "Deformation: the model (``indreg.models``: lddmm, metamorphosis), "
                           "time steps N, group action, backward, interpolation, and the model's own options.")
KernelConfig = _group("KernelConfig", "Kernel: the Gaussian RKHS kernel width sigma (physical units).")
SolverConfig = _group("SolverConfig", "Solver: ``name`` algorithm1, fast, torch_optim (with ``optimizer``) or a "
                      "torch.optim name; objective weights, steps and iterations (``indreg.options``). "
                      "``step_size`` is Algorithm 1's, ``lr`` torch.optim's: each is used only by its solver, so an "
                      "``experiment=`` preset never changes an optimizer's learning rate.",
                      extra=[("optimizer", str, field(default="lbfgs"))])
ValidationConfig = _group("ValidationConfig", "Validation without a ground truth (``indreg.validation``): "
                          "``holdout`` angles (every k-th, or a list of indices) are left out of the fit and their "
                          "relative residual is evaluated every ``logging.every`` iterations; ``patience``: early "
                          "stopping after that many evaluations without a new minimum.")


@dataclass
class BaselineConfig:
    """Direct reconstructions from the same data: FBP (Hamming, 0.4) and TV (Chambolle-Pock); for volumes also
    SIRT (``sirt_iterations``, nonnegative). ``tv_mu`` is relative to the data's intensity unit
    (``indreg.forward.intensity_scale``: TV's weight is ``tv_mu`` times it, so the baseline does not depend on
    the data's units; suite 1's 9.096 is the paper's mu = 3.0 on its data)."""
    enabled: bool = True
    fbp_filter: FBPFilter = FBPFilter.hamming
    fbp_frequency_scaling: float = 0.4
    fbp_padding: bool = True
    tv_mu: float = 9.096
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
    validation: ValidationConfig = field(default_factory=ValidationConfig)


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
    """A finite real number (bools and strings are not numbers)."""
    from .._checks import check_number

    try:
        return v is not None and math.isfinite(check_number(v, "value"))
    except (TypeError, ValueError):
        return False


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
    _require(c.phantom.thickness is None or (c.phantom.ndim == 3 and 7 <= c.phantom.thickness <= c.phantom.size),
             "phantom.thickness", "null or, for volumes (phantom.ndim=3), an integer in [7, phantom.size] (7: the "
             "SSIM window)", c.phantom.thickness)
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
    check_registration(c)
    b = c.baseline
    _require(_finite(b.fbp_frequency_scaling) and 0 < b.fbp_frequency_scaling <= 1, "baseline.fbp_frequency_scaling",
             "a number in (0, 1]", b.fbp_frequency_scaling)
    _require(_finite(b.tv_mu) and b.tv_mu >= 0, "baseline.tv_mu", "a number >= 0", b.tv_mu)
    _require(b.tv_iterations >= 1, "baseline.tv_iterations", "an integer >= 1", b.tv_iterations)
    _require(b.sirt_iterations >= 1, "baseline.sirt_iterations", "an integer >= 1", b.sirt_iterations)
    lg = c.logging
    _require(lg.every >= 1, "logging.every", "an integer >= 1", lg.every)
    _require(lg.checkpoint_every >= 1, "logging.checkpoint_every", "an integer >= 1", lg.checkpoint_every)


def registration_values(cfg: DictConfig) -> dict:
    """The ``indreg.register`` options of the config's ``kernel``, ``deformation`` and ``solver`` groups
    (``solver.name=torch_optim`` names its optimizer in ``solver.optimizer``)."""
    plain = to_plain(cfg)
    values = {o.name: plain[o.group][o.key] for o in _options.all_options() if o.group in plain}
    if values["solver"] == "torch_optim":
        values["solver"] = plain["solver"]["optimizer"]
    return values


def check_registration(cfg: DictConfig) -> dict:
    """``indreg.options.resolve`` on the config's values (options of another solver / model are dropped);
    errors name the config key."""
    try:
        return _options.resolve(registration_values(cfg), label=lambda o: o.config_key, strict=False)
    except _options.OptionError as e:
        raise ConfigError(f"invalid config value {e.label}={e.value!r}: expected {e.expected}") from None


def _validate_data(c: DictConfig) -> None:
    """The ``data`` and ``geometry`` groups (which keys a source needs is its own business, checked here)."""
    d, g = c.data, c.geometry
    sources.resolve(d.source)
    if d.source == "files":
        for key in ("template", "sinogram"):
            _require(bool(d[key]), f"data.{key}", "a file path (data=files)", d[key])
        _require(_finite(d.half_width) and d.half_width > 0, "data.half_width", "a number > 0", d.half_width)
    elif d.source == "dynamic":
        _require(d.frames >= 1, "data.frames", "an integer >= 1", d.frames)
        _require(_finite(d.amplitude) and 0 <= d.amplitude < 1, "data.amplitude", "a number in [0, 1)", d.amplitude)
        _require(g.num_angles is not None and g.num_angles >= 1, "geometry.num_angles",
                 "an integer >= 1 (angles per time point)", g.num_angles)
        _require(g.det_count is not None and g.det_count >= 1, "geometry.det_count", "an integer >= 1", g.det_count)
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
    _require(g.tilt_axis_angle is None or _finite(g.tilt_axis_angle), "geometry.tilt_axis_angle",
             "a finite number of degrees or null", g.tilt_axis_angle)
    _require(g.tilt_axis_angle is None or (g.kind.value == "tilt_series" and d.source != "phantom"),
             "geometry.tilt_axis_angle", "null except for a measured tilt series (data=files geometry=tilt_series): "
             "simulated data are in indreg's layout", g.tilt_axis_angle)
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
