"""Data sources of the experiment app: where the template, the data and the forward operator come from.

``data.source`` picks a function ``fn(cfg) -> Data`` (:func:`resolve`):

    phantom   the paper's suites: ``indreg.phantoms`` template and target, data ``T(target)`` plus white noise
    dynamic   a breathing Shepp-Logan phantom measured a few angles at a time (``indreg.dynamic``): data of
              ``data.frames`` time points for ``deformation=spatiotemporal`` (docs/spatiotemporal.md)
    files     your own data: ``indreg.load`` (:mod:`indreg.inputs`) with the config's ``data`` and ``geometry``
              values: template, sinogram (and optionally a target) read by ``indreg.io``; with
              ``geometry=tilt_series`` a template volume and an MRC tilt series with its .tlt angles
    NAME      an entry point ``NAME = "my_package.my_module:my_source"`` of the group ``indreg.sources`` (in the
              ``[project.entry-points."indreg.sources"]`` table of your package's pyproject.toml)
    my_package.my_module:my_source
              any importable ``module:function``, no installation needed (the module on ``sys.path`` /
              ``PYTHONPATH``): ``indreg-register data=files data.source=my_package.my_module:my_source
              data.sinogram=...`` (``data=files`` first: the settings for measured data, docs/own_data.md)

The contract of a source: ``fn(cfg)`` gets the composed, validated config (a ``DictConfig`` of
``indreg.experiments.config.RegisterConfig``: ``cfg.data.template``, ``cfg.data.sinogram``, ``cfg.data.target``,
``cfg.data.half_width``, the ``geometry`` group, ``cfg.seed``, ...) and returns a :class:`Data` record, or what
``indreg.load`` returns (a ``RegistrationInputs``, e.g. ``return indreg.load(my_template, my_data, ...)``).
Invalid input raises one line before any computation: ``indreg.io.DataFileError`` (a file),
:class:`~indreg.experiments.errors.ConfigError` (a config value) or ``ValueError`` (shown as an invalid
configuration). The run loop only sees :class:`Data`, so a new source is one function (built in: one here with
:func:`source` and a ``conf/data/<name>.yaml``).

Convention: images ``(n, n)`` (or volumes ``(nx, ny, nz)``) float64 on the CPU, axis 0 = x, on
``[-half_width, half_width]^d`` (square / cubic cells); data ``operator.range_shape``: ``(num_angles, det_count)``
(a tilt series: ``(num_tilts, det_rows, det_cols)``) float64 on the CPU.
"""
from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import torch
from omegaconf import DictConfig, OmegaConf

from .. import phantoms
from ..domain import ImageDomain
from ..inputs import RegistrationInputs, box_domain, make_geometry, make_operator, square_domain
from ..inputs import load as load_inputs
from ..io import DataFileError, check_file, read_angles
from ..tilt_axis import check_tilt_axis
from .errors import ConfigError

log = logging.getLogger(__name__)

#: The entry-point group of installed sources (``data.source=<entry point name>``).
ENTRY_POINTS = "indreg.sources"
#: The built-in sources by name (:func:`source`).
SOURCES: dict = {}
#: How ``indreg.load``'s messages name its arguments in the app: the config keys.
CONFIG_KEYS = {"template": "data.template", "data": "data.sinogram", "target": "data.target",
               "half_width": "data.half_width", "geometry": "geometry.kind", "angles": "geometry.angles",
               "angle_unit": "geometry.angle_unit", "num_angles": "geometry.num_angles",
               "det_count": "geometry.det_count", "tilt_axis": "geometry.tilt_axis",
               "tilt_axis_angle": "geometry.tilt_axis_angle", "convention": "data.convention",
               "integer_scale": "data.integer_scale"}


@dataclass
class Data:
    """What a source provides (float64, CPU). ``target_64`` / ``clean_64`` / ``snr_db`` are ``None`` when
    unknown (measured data). ``label``: a short name of the template for hparams and titles. ``report``: numbers
    of the data for metrics.json (a tilt series: ``tilt_axis_angle`` and the tilt-axis check's, ``indreg.tilt_axis``).
    ``paper``: the paper's simulated phantoms, scored also in the paper's conventions (``ssim_paper``,
    ``psnr_paper``). ``template_known`` False: the run gets no template (a model that reconstructs it, e.g.
    ``spatiotemporal``; ``template_64`` is then only shown). ``targets``: ground truths of the model's outputs by
    name (``frames`` ``(K, *shape)``, ``template``), scored as ``<name>_ssim`` (mean over a leading frame axis)."""
    domain: ImageDomain
    geometry: object
    operator: object
    template_64: torch.Tensor
    data_64: torch.Tensor
    label: str
    target_64: Optional[torch.Tensor] = None
    clean_64: Optional[torch.Tensor] = None
    snr_db: Optional[float] = None
    report: dict = field(default_factory=dict)
    paper: bool = False
    template_known: bool = True
    targets: dict = field(default_factory=dict)

    @classmethod
    def from_inputs(cls, d: RegistrationInputs) -> "Data":
        """The record of measured data loaded by ``indreg.load``."""
        return cls(domain=d.domain, geometry=d.geometry, operator=d.operator, template_64=d.template,
                   data_64=d.data, label=d.label, target_64=d.target, report=d.report())


def source(name: str) -> Callable:
    """Register ``fn(cfg) -> Data`` as the built-in data source ``name``."""
    def register(fn):
        SOURCES[name] = fn
        return fn
    return register


def load(cfg: DictConfig) -> Data:
    """The data of ``cfg.data.source`` (:func:`resolve`)."""
    data = resolve(cfg.data.source)(cfg)
    if isinstance(data, RegistrationInputs):
        return Data.from_inputs(data)
    if not isinstance(data, Data):
        raise ConfigError(f"data.source={cfg.data.source} returned a {type(data).__name__}: expected an "
                          "indreg.experiments.sources.Data or what indreg.load returns")
    return data


def resolve(name: str) -> Callable:
    """The source function of ``data.source=name``: a built-in source, else an entry point ``name`` of the group
    ``indreg.sources``, else ``module:function`` imported. Raises :class:`ConfigError` (one line) when it is none
    of these or cannot be imported."""
    if name in SOURCES:
        return SOURCES[name]
    try:
        fn, problem = (_import(name) if ":" in name else _entry_point(name)), None
    except Exception as e:   # the user's module: a missing module or attribute, a syntax error, ... as one line
        fn, problem = None, f"{type(e).__name__}: {' '.join(str(e).split())}"
    if problem is not None:   # raised outside the except: no chained context in the one-line message
        raise ConfigError(f"invalid config value data.source={name!r}: cannot import it ({problem})")
    if fn is None:
        known = sorted(SOURCES) + sorted(ep.name for ep in _entry_points())
        raise ConfigError(f"invalid config value data.source={name!r}: expected one of {', '.join(known)} or an "
                          "importable module:function (e.g. my_package.my_module:my_source)")
    if not callable(fn):
        raise ConfigError(f"invalid config value data.source={name!r}: {type(fn).__name__} is not callable; "
                          "expected a function cfg -> Data")
    return fn


def _import(path: str):
    """The object ``module:attribute`` (attribute may be dotted, as in entry points)."""
    module, _, attribute = path.partition(":")
    obj = importlib.import_module(module)
    for part in attribute.split("."):
        obj = getattr(obj, part)
    return obj


def _entry_points() -> tuple:
    from importlib.metadata import entry_points

    return tuple(entry_points(group=ENTRY_POINTS))


def _entry_point(name: str):
    """The loaded entry point ``name`` of the group ``indreg.sources``, or None."""
    for ep in _entry_points():
        if ep.name == name:
            return ep.load()
    return None


def _angles(g) -> Optional[torch.Tensor]:
    """``geometry.angles`` (a text-file path or a list, in ``geometry.angle_unit``) in radians, or None."""
    spec = _angle_spec(g)
    if spec is None:
        return None
    try:
        angles = read_angles(spec, g.angle_unit.value, name="geometry.angles")
    except DataFileError:
        raise
    except ValueError as e:  # inline values
        raise ConfigError(f"geometry.angles: {e}") from None
    return torch.as_tensor(angles, dtype=torch.float64)


def _angle_spec(g):
    """``geometry.angles`` as plain Python: a path (str), a list, or None."""
    if g.angles is None:
        return None
    return OmegaConf.to_container(g.angles) if OmegaConf.is_list(g.angles) else str(g.angles)


def geometry_options(g) -> dict:
    """The ``geometry`` group as keywords of ``indreg.inputs.make_geometry`` (all but ``det_count``, ``angles``)."""
    return {"num_angles": g.num_angles, "partition": g.partition.value, "det_min": g.det_min, "det_max": g.det_max,
            "src_radius": g.src_radius, "det_radius": g.det_radius, "tilt_axis": g.tilt_axis.value,
            "tilt_min": g.tilt_min, "tilt_max": g.tilt_max, "tilt_step": g.tilt_step,
            "angle_unit": g.angle_unit.value}


def make_data(cfg: DictConfig, T, target_64: torch.Tensor) -> tuple:
    """Noise-free and noisy data (float64, CPU) and the realised SNR in dB (``cfg.noise.convention``)."""
    from ..noise import add_white_noise, snr_db

    clean = T(target_64)
    n = cfg.noise
    if n.snr_db is None and n.std is None:
        return clean, clean.clone(), float("inf")
    seed = cfg.seed if n.seed is None else n.seed
    k = len(T.range_shape)  # one data set: a sinogram or a whole tilt series
    noisy, noise = add_white_noise(clean, snr_db=n.snr_db, std=n.std, convention=n.convention.value, seed=seed,
                                   event_dims=k)
    return clean, noisy, float(snr_db(clean, noise, convention=n.convention.value, event_dims=k))


@source("phantom")
def phantom_data(cfg: DictConfig) -> Data:
    """The ``phantom`` group's template and target on ``size^ndim`` cells; data simulated in float64 on the CPU
    (noise drawn with the run's seed), so the same config gives the same data on every device."""
    p, g = cfg.phantom, cfg.geometry
    domain = (square_domain(p.size, p.half_width, p.ndim) if p.thickness is None
              else box_domain((p.size, p.size, p.thickness), p.half_width))
    T = make_operator(domain, make_geometry(g.kind.value, g.det_count, angles=_angles(g), **geometry_options(g)))
    target = phantoms.get(p.target.value, domain)
    template = phantoms.get(p.template.value, domain)
    clean, noisy, snr = make_data(cfg, T, target)
    report = {}
    if g.kind.value == "tilt_series":   # simulated in indreg's layout: the check's numbers, for comparison
        check = check_tilt_axis(noisy.numpy())
        log.info("simulated tilt series: %s", check.describe())
        report = {"tilt_axis_angle": None, **check.metrics()}
    return Data(domain=domain, geometry=T.geometry, operator=T, template_64=template, data_64=noisy,
                label=p.template.value, target_64=target, clean_64=clean, snr_db=snr, report=report,
                paper=True)


def check_files(cfg: DictConfig) -> None:
    """``data=files``: the files named by the config exist and have a known format (``indreg.io.check_file``;
    an angle file exists), checked before the app creates its run directory; their contents are read by the run.
    Raises ``DataFileError`` naming the key."""
    d, g = cfg.data, cfg.geometry
    if d.source != "files":
        return
    for key in ("template", "sinogram", "target"):
        if d[key]:
            check_file(d[key], f"data.{key}")
    spec = _angle_spec(g)
    if isinstance(spec, str) and not Path(spec).is_file():
        raise DataFileError(f"geometry.angles file {spec}: no such file")


@source("files")
def file_data(cfg: DictConfig) -> Data:
    """``indreg.load`` with the ``data`` and ``geometry`` groups' values (messages name the config keys): a square
    template and a sinogram, or (``geometry=tilt_series``) a template volume and a tilt series; ``det_count`` is
    the data's width (``geometry.det_count`` / ``num_angles``, if set, must agree); ``data.convention`` and
    ``data.integer_scale`` say how to read them. No noise is added."""
    d, g = cfg.data, cfg.geometry
    try:
        inputs = load_inputs(d.template, d.sinogram, g.kind.value, angles=_angle_spec(g),
                             angle_unit=g.angle_unit.value, target=d.target or None, half_width=d.half_width,
                             det_min=g.det_min, det_max=g.det_max, det_count=g.det_count, num_angles=g.num_angles,
                             tilt_axis=g.tilt_axis.value, tilt_axis_angle=g.tilt_axis_angle,
                             src_radius=g.src_radius, det_radius=g.det_radius, convention=d.convention.value,
                             integer_scale=d.integer_scale.value, names=CONFIG_KEYS)
    except DataFileError:
        raise
    except (ValueError, TypeError) as e:   # a config value (inline angles); the message names its key
        raise ConfigError(str(e)) from None
    return Data.from_inputs(inputs)


@source("dynamic")
def dynamic_data(cfg: DictConfig) -> Data:
    """``indreg.dynamic.acquisition``: ``data.frames`` frames of the breathing phantom (``data.amplitude``) on
    ``phantom.size^2`` cells of [-16, 16]^2, ``geometry.num_angles`` angles per frame (all frames together uniform
    on [0, pi)), ``geometry.det_count`` bins, noise at ``noise.snr_db`` per frame (seeded). The operator is a
    ``TimeSeriesOperator``; the target is the last frame, ``targets`` the true frames and template."""
    from ..dynamic import acquisition
    from ..forward import TimeSeriesOperator

    d, g, n = cfg.data, cfg.geometry, cfg.noise
    if n.std is not None:
        raise ConfigError("data.source=dynamic takes noise.snr_db (per frame), not noise.std")
    seed = cfg.seed if n.seed is None else n.seed
    a = acquisition(cfg.phantom.size, d.frames, g.num_angles, g.det_count, d.amplitude,
                    300.0 if n.snr_db is None else n.snr_db, seed)
    template = a.template if d.template_known else torch.zeros_like(a.template)
    targets = {"frames": a.frames} if d.template_known else {"frames": a.frames, "template": a.template}
    return Data(domain=a.domain, geometry=a.operators[0].geometry, operator=TimeSeriesOperator(a.operators),
                template_64=template, data_64=a.data, label="breathing_shepp_logan", target_64=a.frames[-1],
                clean_64=a.clean, snr_db=a.snr_db, template_known=d.template_known, targets=targets)
