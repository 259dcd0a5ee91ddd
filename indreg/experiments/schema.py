"""The schema of the experiment app's configs (``indreg/conf/**.yaml``): typed dataclasses that Hydra merges
every yaml file into, so an unknown key, a wrong type or a value outside an enum fails at composition with a
message naming the key (``indreg.experiments.config`` registers it and checks ranges).

The registration groups (``deformation``, ``kernel``, ``solver``, ``validation``, and ``data``'s
``template_scale`` / ``background``) are generated from the option table ``indreg.options``; :func:`build_schema`
builds the whole ``RegisterConfig`` from the table as it is, so a model registered later (a plug-in named on the
command line) brings its options.
"""
from __future__ import annotations

from dataclasses import dataclass, field, make_dataclass
from enum import Enum
from typing import Any, List, Optional

from ..registration import corrections as _corrections  # noqa: F401  (the registry of corrections, with their options)
from ..registration import models as _models  # noqa: F401  (fills the registry of models whose options the schema holds)
from .. import options as _options
from .. import phantoms as _phantoms
from ..domain import AXES
from . import builtin_sources  # noqa: F401  (registers the built-in sources: phantom, files, dynamic)
from . import sources

__all__ = ["Phantom", "Dtype", "AnglePartition", "GeometryKind", "AngleUnit", "NoiseConvention", "TiltAxis",
           "FBPFilter", "PhantomConfig", "GeometryConfig", "NoiseConfig", "BaselineConfig", "LoggingConfig",
           "build_schema"]

Phantom = Enum("Phantom", {name: name for name in _phantoms.names()}, type=str)
Phantom.__doc__ = "Phantom names accepted by ``indreg.phantoms.get``."


def _choices(name: str, values, doc: str = "") -> type:
    """A string enum whose members are named by their values (``values``)."""
    cls = Enum(name, {v: v for v in values}, type=str)
    cls.__doc__ = doc or f"One of {', '.join(values)}."
    return cls


Dtype = _choices("Dtype", ("float32", "float64"))
AnglePartition = _choices("AnglePartition", ("paper", "uniform"), "``paper``: ODL's ``uniform_partition(0, pi, n, "
                          "nodes_on_bdry=(True, False))``; ``uniform``: k pi / n.")
GeometryKind = _choices("GeometryKind", ("parallel", "fan_flat", "tilt_series"), "``parallel``: "
                        "``ParallelBeamGeometry``; ``fan_flat``: ``FanBeamGeometry`` (flat detector), both 2D; "
                        "``tilt_series``: ``TiltSeriesGeometry`` (3D, single-axis tilt series of electron tomography).")
AngleUnit = _choices("AngleUnit", ("deg", "rad"))
NoiseConvention = _choices("NoiseConvention", ("code", "paper"))


TiltAxis = Enum("TiltAxis", {name: name for name in AXES}, type=str)   # the image axes x, y, z


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
    defined on the box's normalised coordinates, so they flatten with it (electron tomography's thin specimen).
    ``rows`` (3D only; null: ``size``): cells along y (the tilt axis of ``geometry=tilt_series``), a slab of
    ``size x rows x thickness`` cells, the phantoms squeezed along y with the box."""
    template: Phantom = Phantom["j"]
    target: Phantom = Phantom["v"]
    size: int = 64
    half_width: float = 16.0
    ndim: int = 2
    thickness: Optional[int] = None
    rows: Optional[int] = None


_DATA_DOC = """Where template and data come from: ``source`` is a built-in source, an ``indreg.sources`` entry point or
    ``module:attribute`` (``indreg.experiments.sources``); each source declares the keys it reads.

    ``phantom`` (default): the ``phantom`` group's template and target, data simulated with the ``geometry`` and
    ``noise`` groups. ``files``: ``template`` and ``sinogram`` (and optionally ``target``) read from files
    (``indreg.io``), on the domain ``[-half_width, half_width]^2`` with the template's (square) pixel grid, in
    another tool's ``convention`` (``indreg.io.conventions``: layout, angles, units, detector centre) and with 8- /
    16-bit pictures as fractions of their full scale (``integer_scale: fraction``, or ``raw``).
    ``dynamic``: the breathing phantom of ``indreg.dynamic`` measured at ``frames`` time points (``amplitude``;
    ``template_known: false`` hands the run no template: ``deformation=spatiotemporal`` reconstructs it).
    ``template_scale`` / ``background`` (``indreg.options``, the same as ``indreg.register``'s): the template's
    intensity factor and the data's offset, applied before the run (``indreg.units.prepare``); ``transmission``:
    bright-field intensities made line integrals; ``wide_box`` / ``slab_thickness`` / ``slab_extent`` /
    ``template_padding``: a box wider than the detector for a specimen wider than it (docs/slab.md).
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
    the stack is rotated by its opposite (``indreg.alignment.tilt_axis``)."""
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


@dataclass
class BaselineConfig:
    """Direct reconstructions from the same data: FBP (Hamming, 0.4) and TV (Chambolle-Pock); for volumes also
    SIRT (``sirt_iterations``, nonnegative). ``tv_mu`` is relative to the TV weight unit
    (``indreg.forward.tv_weight_unit``, the data's intensity unit times the box's largest side squared: TV's weight
    is ``tv_mu`` times it, so the baseline does not depend on the intensity or length units; suite 1's 0.0088828125
    is the paper's mu = 3.0 on its data)."""
    enabled: bool = True
    fbp_filter: FBPFilter = FBPFilter.hamming
    fbp_frequency_scaling: float = 0.4
    fbp_padding: bool = True
    tv_mu: float = 0.0088828125
    tv_iterations: int = 1000
    sirt_iterations: int = 100


@dataclass
class LoggingConfig:
    """Every ``every`` iterations: SSIM/PSNR and image to TensorBoard; checkpoint every ``checkpoint_every``.
    ``length_unit``: the name of the domain's length unit (e.g. ``nm``) on the figures' axes and scale bars
    (null: "a.u.", arbitrary units)."""
    every: int = 10
    checkpoint_every: int = 10
    tensorboard: bool = True
    progress: bool = True
    figure: bool = True
    length_unit: Optional[str] = None


_GROUP_DOCS = {
    "deformation": "Deformation: the model (``indreg.registration.models``: lddmm, metamorphosis, spatiotemporal or a plug-in "
                   "``module:attribute``), time steps N, group action, backward, interpolation, and the model's own "
                   "options.",
    "kernel": "Kernel: the Gaussian RKHS kernel width sigma (physical units).",
    "solver": "Solver: ``name`` algorithm1, fast, torch_optim (with ``optimizer``) or a torch.optim name; objective "
              "weights, steps and iterations (``indreg.options``). ``step_size`` is Algorithm 1's, ``lr`` "
              "torch.optim's: each is used only by its solver, so an ``experiment=`` preset never changes an "
              "optimizer's learning rate.",
    "validation": "Validation without a ground truth (``indreg.evaluation.validation``): ``holdout`` angles (every k-th, or a "
                  "list of indices) are left out of the fit and their relative residual is evaluated every "
                  "``logging.every`` iterations; ``patience``: early stopping after that many evaluations without a "
                  "new minimum.",
}
_GROUP_EXTRA = {"solver": [("optimizer", str, field(default="lbfgs"))]}


def _group(name: str):
    """The schema of config group ``name`` generated from ``indreg.options`` (one declaration for the app and
    ``indreg.register``; the registered models' options included) and, for ``data``, from the registered data
    sources' own keys (``indreg.experiments.sources.Source.options``)."""
    own = [("source", str, field(default="phantom")), *sources.data_fields()] if name == "data" else []
    cls = make_dataclass(f"{name.capitalize()}Config",
                         [*own, *_options.schema_fields(name), *_GROUP_EXTRA.get(name, ())])
    cls.__doc__ = _DATA_DOC if name == "data" else _GROUP_DOCS[name]
    return cls


def build_schema() -> type:
    """``RegisterConfig``, the whole run's schema, from the option table as it is now: a model registered after
    the import of this module (a plug-in named on the command line) brings its options (``register_schema``)."""
    groups = {name: _group(name) for name in ("data", *_GROUP_DOCS)}
    cls = make_dataclass("RegisterConfig", [
        ("name", str, field(default="suite1_jv")), ("seed", int, field(default=0)),
        ("dtype", Dtype, field(default=Dtype.float32)), ("device", str, field(default="auto")),
        ("resume", bool, field(default=False)), ("stop_after", Optional[int], field(default=None)),
        ("plugins", List[str], field(default_factory=list)),
        ("data", groups["data"], field(default_factory=groups["data"])),
        ("phantom", PhantomConfig, field(default_factory=PhantomConfig)),
        ("geometry", GeometryConfig, field(default_factory=GeometryConfig)),
        ("noise", NoiseConfig, field(default_factory=NoiseConfig)),
        *((g, groups[g], field(default_factory=groups[g])) for g in ("deformation", "kernel", "solver")),
        ("baseline", BaselineConfig, field(default_factory=BaselineConfig)),
        ("logging", LoggingConfig, field(default_factory=LoggingConfig)),
        ("validation", groups["validation"], field(default_factory=groups["validation"]))])
    cls.__doc__ = "The whole run. ``stop_after``: stop (checkpoint, as if interrupted) once this many iterations " \
                  "are done. ``plugins``: modules imported before the config is composed (from the working " \
                  "directory or PYTHONPATH), whose registrations (a correction, a solver, a model, a source, a file " \
                  "format) and their options then take part."
    return cls
