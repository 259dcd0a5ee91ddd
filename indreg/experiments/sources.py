"""Data sources of the experiment app: where the template, the data and the forward operator come from.

A source is a function ``cfg -> Data`` registered under a name with :func:`source`; ``data.source=<name>`` picks
it (config group ``data``: ``conf/data/<name>.yaml``). The run loop only sees :class:`Data`, so adding a source
means one function here and one yaml file, nothing else.

    phantom   the paper's suites: ``indreg.phantoms`` template and target, data ``T(target)`` plus white noise
    files     your own data: template, sinogram (and optionally a target) read by ``indreg.io``; with
              ``geometry=tilt_series`` a template volume and an MRC tilt series with its .tlt angles

Convention: images ``(n, n)`` (or volumes ``(n, n, n)``) float64 on the CPU, axis 0 = x, on
``[-half_width, half_width]^d`` (square / cubic cells); data ``(num_angles, det_count)`` (a tilt series:
``(num_tilts, det_rows, det_cols)``) float64 on the CPU. Every input problem of the ``files`` source raises
``indreg.io.DataFileError`` naming the file (or config key) before any computation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from omegaconf import DictConfig, OmegaConf

from .. import phantoms
from ..domain import ImageDomain
from ..forward import FanBeamGeometry, ParallelBeamGeometry, RayTransform, TiltSeriesGeometry, TiltSeriesTransform
from .config import ConfigError

SOURCES: dict = {}


@dataclass
class Data:
    """What a source provides (float64, CPU). ``target_64`` / ``clean_64`` / ``snr_db`` are ``None`` when
    unknown (measured data). ``label``: a short name of the template for hparams and titles."""
    domain: ImageDomain
    geometry: object
    operator: object
    template_64: torch.Tensor
    data_64: torch.Tensor
    label: str
    target_64: Optional[torch.Tensor] = None
    clean_64: Optional[torch.Tensor] = None
    snr_db: Optional[float] = None


def source(name: str) -> Callable:
    """Register ``fn(cfg) -> Data`` as the data source ``name``."""
    def register(fn):
        SOURCES[name] = fn
        return fn
    return register


def load(cfg: DictConfig) -> Data:
    """The data of ``cfg.data.source``."""
    return SOURCES[cfg.data.source](cfg)


def square_domain(n: int, half_width: float, ndim: int = 2) -> ImageDomain:
    """``n`` cells per axis on ``[-half_width, half_width]^ndim``."""
    return ImageDomain((n,) * ndim, (-half_width,) * ndim, (half_width,) * ndim)


def _angles(g) -> Optional[torch.Tensor]:
    """``geometry.angles`` (a text-file path or a list, in ``geometry.angle_unit``) in radians, or None."""
    from ..io import DataFileError, read_angles

    if g.angles is None:
        return None
    spec = OmegaConf.to_container(g.angles) if OmegaConf.is_list(g.angles) else str(g.angles)
    try:
        angles = read_angles(spec, g.angle_unit.value, name="geometry.angles")
    except DataFileError:
        raise
    except ValueError as e:  # inline values
        raise ConfigError(f"geometry.angles: {e}") from None
    return torch.as_tensor(angles, dtype=torch.float64)


def make_geometry(g, domain: ImageDomain, det_count: int, angles: Optional[torch.Tensor] = None):
    """The geometry of ``g`` (the ``geometry`` group): explicit ``angles`` (radians) or ``num_angles`` of
    ``partition`` (a tilt series: ``tilt_min:tilt_step:tilt_max``); ``det_min = det_max = null``: the operator
    fits the detector to the domain."""
    if g.kind.value == "tilt_series":
        if angles is None:
            deg = 1.0 if g.angle_unit.value == "deg" else 180 / math.pi
            return TiltSeriesGeometry.uniform(g.tilt_min * deg, g.tilt_max * deg, g.tilt_step * deg, det_count,
                                              g.det_min, g.det_max, g.tilt_axis.value)
        return TiltSeriesGeometry(angles, det_count, g.det_min, g.det_max, g.tilt_axis.value, angle_unit="rad")
    paper = angles is None and g.partition.value == "paper"
    if paper and g.kind.value == "parallel":
        return ParallelBeamGeometry.paper(g.num_angles, det_count, det_min=g.det_min, det_max=g.det_max)
    if paper:
        angles = torch.arange(g.num_angles, dtype=torch.float64) * (math.pi / (g.num_angles - 0.5))
    if g.kind.value == "fan_flat":
        return FanBeamGeometry(num_angles=None if angles is not None else g.num_angles,
                                       det_count=det_count, src_radius=g.src_radius, det_radius=g.det_radius,
                                       det_min=g.det_min, det_max=g.det_max, angles=angles)
    return ParallelBeamGeometry(num_angles=None if angles is not None else g.num_angles, det_count=det_count,
                                det_min=g.det_min, det_max=g.det_max, angles=angles)


def make_operator(domain: ImageDomain, geometry):
    """The forward operator of ``geometry`` on ``domain``: a ``TiltSeriesTransform`` or a ``RayTransform``."""
    if isinstance(geometry, TiltSeriesGeometry):
        return TiltSeriesTransform(domain, geometry)
    return RayTransform(domain, geometry)


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
    p = cfg.phantom
    domain = square_domain(p.size, p.half_width, p.ndim)
    geometry = make_geometry(cfg.geometry, domain, cfg.geometry.det_count, _angles(cfg.geometry))
    T = make_operator(domain, geometry)
    geometry = T.geometry                      # with the detector extent resolved
    target = phantoms.get(p.target.value, domain)
    template = phantoms.get(p.template.value, domain)
    clean, noisy, snr = make_data(cfg, T, target)
    return Data(domain=domain, geometry=geometry, operator=T, template_64=template, data_64=noisy,
                label=p.template.value, target_64=target, clean_64=clean, snr_db=snr)


TILT_SERIES = (".mrc", ".st", ".ali")


def _file_angles(cfg: DictConfig, num_rows: int) -> torch.Tensor:
    """Angles of a measured sinogram: ``geometry.angles``, else a .tlt / .rawtlt next to an MRC tilt series."""
    from ..io import DataFileError, read_angles, split_path, tilt_angles_for

    g, sinogram = cfg.geometry, cfg.data.sinogram
    angles, origin = _angles(g), "geometry.angles"
    if angles is None:
        tilt = tilt_angles_for(sinogram) if split_path(sinogram)[0].suffix.lower() in TILT_SERIES else None
        if tilt is None:
            raise DataFileError("geometry.angles is required with data=files: a text file (one angle a line) or a "
                                "list, in geometry.angle_unit (an .mrc/.st/.ali sinogram may instead have a "
                                "sibling .tlt/.rawtlt file)")
        origin = str(tilt)
        angles = torch.as_tensor(read_angles(str(tilt), g.angle_unit.value, name=origin), dtype=torch.float64)
    if angles.numel() != num_rows:
        raise DataFileError(f"data.sinogram {sinogram}: {num_rows} rows (one per angle) but {origin} gives "
                            f"{angles.numel()} angles")
    if g.num_angles is not None and g.num_angles != num_rows:
        raise DataFileError(f"data.sinogram {sinogram}: {num_rows} rows but geometry.num_angles={g.num_angles}")
    return angles


def _target(path, template, read) -> Optional[torch.Tensor]:
    """The optional ground truth ``data.target`` (``read``: ``read_image`` or ``read_volume``), shaped as the
    template."""
    from ..io import DataFileError

    if not path:
        return None
    target = read(path, name="data.target")
    if target.shape != template.shape:
        raise DataFileError(f"data.target {path}: shape {target.shape} differs from the template's {template.shape}")
    return torch.from_numpy(target)


def box_domain(shape: tuple, half_width: float) -> ImageDomain:
    """Cubic cells of side ``2 half_width / max(shape)``, centred: the longest axis spans
    ``[-half_width, half_width]`` (a slab of electron tomography keeps its aspect ratio)."""
    h = 2.0 * half_width / max(shape)
    return ImageDomain(tuple(shape), tuple(-h * n / 2 for n in shape), tuple(h * n / 2 for n in shape))


def _tilt_series_files(cfg: DictConfig) -> Data:
    """``data=files`` with ``geometry=tilt_series``: a template volume and a tilt series (with its angles).
    ``geometry.det_min = det_max = null``: the detector columns have the voxels' width, centred on the axis."""
    from ..io import DataFileError, read_tilt_series, read_volume, split_path

    d, g = cfg.data, cfg.geometry
    template = read_volume(d.template, name="data.template")
    domain = box_domain(template.shape, d.half_width)
    spec = None if g.angles is None else (OmegaConf.to_container(g.angles) if OmegaConf.is_list(g.angles)
                                          else str(g.angles))
    try:
        data, angles = read_tilt_series(d.sinogram, spec, g.angle_unit.value, name="data.sinogram")
    except ValueError as e:
        if isinstance(e, DataFileError):
            raise
        raise ConfigError(f"geometry.angles: {e}") from None
    target = _target(d.target, template, read_volume)
    det_min, det_max = g.det_min, g.det_max
    if det_min is None:  # measured data: detector columns as wide as the volume's voxels, centred
        u = 0 if g.tilt_axis.value != "x" else 1
        det_max = data.shape[2] * domain.cell_sides[u] / 2
        det_min = -det_max
    try:
        geometry = TiltSeriesGeometry(torch.as_tensor(angles, dtype=torch.float64), data.shape[2], det_min, det_max,
                                      g.tilt_axis.value, angle_unit="rad")
        T = make_operator(domain, geometry)
    except ValueError as e:
        raise DataFileError(f"geometry: {e}") from None
    if tuple(data.shape) != tuple(T.range_shape):
        raise DataFileError(f"data.sinogram {d.sinogram}: shape {tuple(data.shape)} but the template "
                            f"{tuple(template.shape)} with tilt axis {g.tilt_axis.value} needs "
                            f"{tuple(T.range_shape)} (tilts, rows along the tilt axis, columns)")
    return Data(domain=domain, geometry=T.geometry, operator=T, template_64=torch.from_numpy(template),
                data_64=torch.from_numpy(data), label=split_path(d.template)[0].name, target_64=target)


@source("files")
def file_data(cfg: DictConfig) -> Data:
    """Template, sinogram and optional target from files (``indreg.io``).

    Requires a square template (``n x n``: the domain ``[-half_width, half_width]^2`` then has square cells) and
    a target of the template's shape; ``det_count`` is the sinogram's width (``geometry.det_count``, if set,
    must agree). No noise is added.
    """
    from ..io import DataFileError, read_image, read_sinogram, split_path

    d, g = cfg.data, cfg.geometry
    if g.kind.value == "tilt_series":
        return _tilt_series_files(cfg)
    template = read_image(d.template, name="data.template")
    nx, ny = template.shape
    if nx != ny:
        raise DataFileError(f"data.template {d.template}: shape {nx} x {ny} is not square; the domain "
                            f"[-{d.half_width:g}, {d.half_width:g}]^2 needs n x n pixels (square cells): pad "
                            "or resample the image")
    sinogram = read_sinogram(d.sinogram, name="data.sinogram")
    angles = _file_angles(cfg, sinogram.shape[0])
    if g.det_count is not None and g.det_count != sinogram.shape[1]:
        raise DataFileError(f"data.sinogram {d.sinogram}: {sinogram.shape[1]} detector bins but "
                            f"geometry.det_count={g.det_count}")
    target = _target(d.target, template, read_image)
    domain = square_domain(nx, d.half_width)
    try:
        geometry = make_geometry(g, domain, sinogram.shape[1], angles)
        T = RayTransform(domain, geometry)
    except ValueError as e:
        raise DataFileError(f"geometry: {e}") from None
    return Data(domain=domain, geometry=T.geometry, operator=T, template_64=torch.from_numpy(template),
                data_64=torch.from_numpy(sinogram), label=split_path(d.template)[0].name, target_64=target)
