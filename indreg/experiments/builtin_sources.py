"""The app's built-in data sources (``indreg.experiments.sources``): ``phantom`` (the paper's suites), ``files``
(your own data, ``indreg.load``) and ``dynamic`` (a breathing phantom measured over time), each with the ``data``
keys it reads and their checks.

Convention: as :mod:`indreg.experiments.sources` (images float64 on the CPU, axis 0 = x; data
``operator.range_shape``).
"""
from __future__ import annotations

import logging
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Optional

from omegaconf import DictConfig, OmegaConf

from ..io import conventions as _conventions
from .._checks import is_finite_number
from .. import phantoms
from ..io import DataFileError, check_file, read_angles
from ..alignment.tilt_axis import check_tilt_axis
from .errors import ConfigError
from .sources import Data, Source, register_source

# torch and indreg.inputs (the operators) are imported where used: the app's preflight checks a source's config
# without them.
if TYPE_CHECKING:
    import torch

__all__ = ["FileConvention", "IntegerScale", "CONFIG_KEYS", "phantom_data", "file_data", "dynamic_data",
           "geometry_options", "make_data"]

log = logging.getLogger("indreg.experiments.sources")

#: data=files: the tool whose layout, angles, units and detector centre the files follow (indreg.io.conventions).
FileConvention = Enum("FileConvention", {name: name for name in _conventions.CONVENTIONS}, type=str)
IntegerScale = Enum("IntegerScale", {name: name for name in _conventions.INTEGER_SCALES}, type=str)

#: How ``indreg.load``'s messages name its arguments in the app: the config keys.
CONFIG_KEYS = {"template": "data.template", "data": "data.sinogram", "target": "data.target",
               "half_width": "data.half_width", "geometry": "geometry.kind", "angles": "geometry.angles",
               "angle_unit": "geometry.angle_unit", "num_angles": "geometry.num_angles",
               "det_count": "geometry.det_count", "tilt_axis": "geometry.tilt_axis",
               "tilt_axis_angle": "geometry.tilt_axis_angle", "convention": "data.convention",
               "integer_scale": "data.integer_scale"}


def _angles(g) -> Optional[torch.Tensor]:
    """``geometry.angles`` (a text-file path or a list, in ``geometry.angle_unit``) in radians, or None."""
    import torch

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


def make_data(cfg: DictConfig, T, target_64: Optional[torch.Tensor], clean: Optional[torch.Tensor] = None) -> tuple:
    """Noise-free and noisy data (float64, CPU) and the realised SNR in dB (``cfg.noise.convention``); ``clean``:
    the noise-free data ``T(target_64)`` where already projected (then ``target_64`` is not read)."""
    from ..noise import add_white_noise, snr_db

    clean = T(target_64) if clean is None else clean
    n = cfg.noise
    if n.snr_db is None and n.std is None:
        return clean, clean.clone(), float("inf")
    seed = cfg.seed if n.seed is None else n.seed
    k = len(T.range_shape)  # one data set: a sinogram or a whole tilt series
    noisy, noise = add_white_noise(clean, snr_db=n.snr_db, std=n.std, convention=n.convention.value, seed=seed,
                                   event_dims=k)
    return clean, noisy, float(snr_db(clean, noise, convention=n.convention.value, event_dims=k))


def phantom_data(cfg: DictConfig) -> Data:
    """The ``phantom`` group's template and target on ``size^ndim`` cells; data simulated in float64 on the CPU
    (noise drawn with the run's seed), so the same config gives the same data on every device. Over the ranks of
    ``torchrun`` a tilt series is built by rows (``split_setup.simulated_rows``: each rank its share of the slices;
    the target on rank 0 only), the same values to rounding."""
    from ..inputs import box_domain, make_geometry, make_operator, square_domain
    from ..ranks import default_group
    from . import split_setup

    p, g = cfg.phantom, cfg.geometry
    domain = (square_domain(p.size, p.half_width, p.ndim) if p.thickness is None and p.rows is None
              else box_domain((p.size, p.rows or p.size, p.thickness or p.size), p.half_width))
    T = make_operator(domain, make_geometry(g.kind.value, g.det_count, angles=_angles(g), **geometry_options(g)))
    group = default_group()
    if split_setup.splits(T, group):
        template, target, clean = split_setup.simulated_rows(p.template.value, p.target.value, T, group)
    else:
        target, template, clean = phantoms.get(p.target.value, domain), phantoms.get(p.template.value, domain), None
    clean, noisy, snr = make_data(cfg, T, target, clean)
    report = {}
    if g.kind.value == "tilt_series":   # simulated in indreg's layout: the check's numbers, for comparison
        check = check_tilt_axis(noisy.numpy())
        log.info("simulated tilt series: %s", check.describe())
        report = {"tilt_axis_angle": None, **check.metrics()}
    return Data(domain=domain, geometry=T.geometry, operator=T, template_64=template, data_64=noisy,
                label=p.template.value, target_64=target, clean_64=clean, snr_db=snr, report=report,
                paper=True)


def _files_exist(cfg: DictConfig) -> None:
    """``data=files``: the files named by the config exist and have a known format (``indreg.io.check_file``;
    an angle file exists), checked before the app creates its run directory; their contents are read by the run.
    Raises ``DataFileError`` naming the key."""
    d, g = cfg.data, cfg.geometry
    for key in ("template", "sinogram", "target"):
        if d[key]:
            check_file(d[key], f"data.{key}")
    spec = _angle_spec(g)
    if isinstance(spec, str) and not Path(spec).is_file():
        raise DataFileError(f"geometry.angles file {spec}: no such file")


def file_data(cfg: DictConfig) -> Data:
    """``indreg.load`` with the ``data`` and ``geometry`` groups' values (messages name the config keys): a square
    template and a sinogram, or (``geometry=tilt_series``) a template volume and a tilt series; ``det_count`` is
    the data's width (``geometry.det_count`` / ``num_angles``, if set, must agree); ``data.convention`` and
    ``data.integer_scale`` say how to read them; ``data.alignment`` (a tilt series) another tool's alignment of the
    raw stack (``indreg.alignment.files``). No noise is added."""
    from ..inputs import load as load_inputs

    d, g = cfg.data, cfg.geometry
    try:
        inputs = load_inputs(d.template, d.sinogram, g.kind.value, angles=_angle_spec(g),
                             angle_unit=g.angle_unit.value, target=d.target or None, half_width=d.half_width,
                             det_min=g.det_min, det_max=g.det_max, det_count=g.det_count, num_angles=g.num_angles,
                             tilt_axis=g.tilt_axis.value, tilt_axis_angle=g.tilt_axis_angle,
                             src_radius=g.src_radius, det_radius=g.det_radius, convention=d.convention.value,
                             integer_scale=d.integer_scale.value, names=CONFIG_KEYS,
                             alignment=d.alignment or None)
    except DataFileError:
        raise
    except (ValueError, TypeError) as e:   # a config value (inline angles); the message names its key
        raise ConfigError(str(e)) from None
    return Data.from_inputs(inputs)


def dynamic_data(cfg: DictConfig) -> Data:
    """``indreg.dynamic.acquisition``: ``data.frames`` frames of the breathing phantom (``data.amplitude``) on
    ``phantom.size^2`` cells of [-16, 16]^2, ``geometry.num_angles`` angles per frame (all frames together uniform
    on [0, pi)), ``geometry.det_count`` bins, noise at ``noise.snr_db`` per frame (seeded). The operator is a
    ``TimeSeriesOperator``; the target is the last frame, ``targets`` the true frames and template."""
    import torch

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


def _check_phantom(c: DictConfig, require) -> None:
    g = c.geometry
    require(g.num_angles is not None and g.num_angles >= 1 or g.angles is not None or g.kind.value == "tilt_series",
            "geometry.num_angles", "an integer >= 1 (or geometry.angles)", g.num_angles)
    require(g.det_count is not None and g.det_count >= 1, "geometry.det_count", "an integer >= 1", g.det_count)
    require(g.tilt_axis_angle is None, "geometry.tilt_axis_angle", "null except for a measured tilt series "
            "(data=files geometry=tilt_series): simulated data are in indreg's layout", g.tilt_axis_angle)
    ndim = 3 if g.kind.value == "tilt_series" else 2
    require(c.phantom.ndim == ndim, "phantom.ndim", f"{ndim} for geometry.kind={g.kind.value}", c.phantom.ndim)


def _check_files(c: DictConfig, require) -> None:
    d = c.data
    for key in ("template", "sinogram"):
        require(bool(d[key]), f"data.{key}", "a file path (data=files)", d[key])
    require(is_finite_number(d.half_width) and d.half_width > 0, "data.half_width", "a number > 0", d.half_width)


def _check_dynamic(c: DictConfig, require) -> None:
    d, g = c.data, c.geometry
    require(d.frames >= 1, "data.frames", "an integer >= 1", d.frames)
    require(is_finite_number(d.amplitude) and 0 <= d.amplitude < 1, "data.amplitude", "a number in [0, 1)", d.amplitude)
    require(g.num_angles is not None and g.num_angles >= 1, "geometry.num_angles",
            "an integer >= 1 (angles per time point)", g.num_angles)
    require(g.det_count is not None and g.det_count >= 1, "geometry.det_count", "an integer >= 1", g.det_count)
    require(g.kind.value == "parallel", "geometry", "parallel (the dynamic source simulates 2D parallel-beam "
            "frames)", g.kind.value)


def _cells(p) -> str:
    """The grid of the ``phantom`` group: ``64^2`` or ``nx x ny x nz``."""
    shape = (p.size,) * p.ndim if p.thickness is None and p.rows is None else \
        (p.size, p.rows or p.size, p.thickness or p.size)
    return f"{p.size}^{p.ndim}" if len(set(shape)) == 1 else " x ".join(map(str, shape))


def _describe_phantom(c: DictConfig) -> str:
    return f"{c.phantom.template.value} -> {c.phantom.target.value} ({_cells(c.phantom)} cells, " \
           f"{c.geometry.kind.value} geometry)"


def _describe_files(c: DictConfig) -> str:
    return f"{c.data.template} and {c.data.sinogram} ({c.geometry.kind.value} geometry)"


def _describe_dynamic(c: DictConfig) -> str:
    return f"{c.data.frames} frames of a breathing phantom ({c.phantom.size}^2 cells)"


register_source(Source("phantom", phantom_data, check=_check_phantom, doc="the paper's phantoms, simulated data",
                       describe=_describe_phantom))
register_source(Source("files", file_data, check=_check_files, preflight=_files_exist, measured=True,
                       describe=_describe_files, doc="your own files (indreg.load)", options=(
    ("template", Optional[str], None), ("sinogram", Optional[str], None), ("target", Optional[str], None),
    ("half_width", float, 16.0),
    ("convention", FileConvention, FileConvention.indreg),      # skimage, astra, tomopy, imod, odl
    ("integer_scale", IntegerScale, IntegerScale.fraction),    # 8/16-bit pictures as fractions, or raw
    ("alignment", Optional[str], None))))   # a tilt series' IMOD .xf / AreTomo .aln, applied in the operator
register_source(Source("dynamic", dynamic_data, check=_check_dynamic, doc="a breathing phantom measured over time",
                       describe=_describe_dynamic, options=(
    ("frames", int, 12),              # time points K (t_k = k / K)
    ("amplitude", float, 0.4),        # the breathing amplitude A (indreg.dynamic)
    ("template_known", bool, True))))  # false: the template is unknown (reconstructed with the motion)
