"""Your data as plain Python: ``indreg.load`` reads (or takes) a template, measured data and their angles and builds
the image domain, the acquisition geometry and the forward operator, i.e. the arguments of ``indreg.register``::

    d = indreg.load("template.png", "sino.npy", "parallel", angles="angles.tlt", det_min=-24, det_max=24)
    result = indreg.register(d.template, d.data, d.operator, target=d.target)

The experiment app's ``data=files`` source is this function called with the config's values
(``indreg.experiments.sources``); its ``phantom`` source builds its geometry with :func:`make_geometry` too.

Geometries (``geometry=``)::

    parallel     2D parallel beam (ParallelBeamGeometry)
    fan_flat     2D fan beam, flat detector (FanBeamGeometry: src_radius, det_radius)
    tilt_series  3D single-axis tilt series of electron tomography (TiltSeriesGeometry: tilt_axis); the stack is
                 rotated so that its tilt axis runs along the detector rows (``tilt_axis_angle``, or the
                 ``.mdoc`` next to it) and checked for consistency (``indreg.alignment.tilt_axis``)

Notes
-----
- 2D: template ``(n, n)`` on ``[-half_width, half_width]^2`` (square, so that the cells are square), data
  ``(num_angles, det_count)``, one row per angle. 3D: template ``(nx, ny, nz)`` on cubic cells of side
  ``2 half_width / max(nx, ny, nz)``, centred (a slab keeps its aspect ratio), data
  ``(num_tilts, det_rows, det_cols)`` (docs/tilt_series.md). Axis 0 = x.
- ``template``, ``data``, ``target``: a path (any format of :mod:`indreg.io`: ``file.npz:key``,
  ``file.h5:/dataset``, ...) or an array (numpy, torch) in indreg's layout. ``angles``: a text file (one angle
  a line, IMOD ``.tlt``) or a list, in ``angle_unit``; without it, the ``.tlt`` / ``.rawtlt`` next to the
  data file (an ``.mrc``/``.st``/``.ali`` sinogram, or any tilt-series file).
- ``convention`` (2D): the tool whose layout, angles, units and detector centre the files and arrays follow
  (``indreg.io.conventions``: ``indreg`` default, ``skimage``, ``astra``, ``tomopy``, ``imod``, ``odl``); a tilt
  series takes ``indreg`` or ``imod`` (IMOD's stack layout is indreg's; ``imod`` negates the angles, IMOD's
  sense of rotation, and multiplies pixel sums by the voxel side). ``integer_scale``: 8- / 16-bit pictures as
  ``fraction`` of their full scale (default) or ``raw``. The log says how each file was read and warns when the
  template's projection fits the data better read another way (:func:`indreg.io.orientation.orientation_hint`;
  the readings no convention makes are probed before the run: ``indreg.io.orientation``).
- Detector: ``det_count`` (columns) is the data's width; ``det_count=`` and ``num_angles=``, if given, must
  agree with the data. ``det_min = det_max = None``: in 2D the operator fits the detector to the domain, a
  tilt series gets columns as wide as the voxels, centred on the tilt axis.
- The returned tensors are float64 on the CPU, in indreg's layout whatever the convention (so is what
  ``indreg.register`` returns from them); ``d.as_given(result.deformed)`` is the result in the files' layout.
- Bad input raises one line before any computation: :class:`indreg.io.DataFileError` for a file (naming it),
  a count or shape that does not fit, or a geometry that cannot be built; ``ValueError`` / ``TypeError`` for
  an argument's value (inline angles, ``angle_unit``, ``half_width``, an array).

Longer than 450 lines: ``load`` and its readers of each kind of input share one set of checks; the module docstring
is the user's guide to them.
"""
from __future__ import annotations

import logging
import math
import numbers
import os
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from . import io
from .io import conventions, orientation
from ._checks import check_positive
from .domain import AXES, ImageDomain
from .forward import FanBeamGeometry, ParallelBeamGeometry, TiltSeriesGeometry
from .io import DataFileError
from .alignment.tilt_axis import TiltAxisCheck, align_tilt_axis, check_tilt_axis

log = logging.getLogger("indreg")

GEOMETRIES = ("parallel", "fan_flat", "tilt_series")
#: How error messages call :func:`load`'s arguments; the app passes its config keys instead.
NAMES = {key: key for key in ("template", "data", "target", "geometry", "angles", "angle_unit", "half_width",
                              "num_angles", "det_count", "tilt_axis", "tilt_axis_angle", "convention",
                              "integer_scale")}
#: Conventions with a meaning beyond the 2D parallel beam: a tilt series (IMOD's layout is indreg's, its angles
#: the opposite sense), a fan beam.
_CONVENTIONS_3D = ("indreg", "imod")
_CONVENTIONS_FAN = ("indreg", "odl")


@dataclass
class RegistrationInputs:
    """What :func:`load` returns: ``indreg.register(d.template, d.data, d.operator, target=d.target)``.

    Attributes
    ----------
    template : torch.Tensor
        ``operator.domain.shape``, float64 on the CPU.
    data : torch.Tensor
        ``operator.range_shape``, float64 on the CPU.
    operator : LinearOperator
        The forward operator (an ``AlignedOperator`` with an alignment file).
    domain : ImageDomain
        The template's domain.
    geometry : object
        The operator's geometry (detector extent resolved).
    target : torch.Tensor or None
        The ground truth (the template's shape), None without one.
    label : str
        Names the template: its file name, ``"array"`` for an array.
    tilt_axis_angle : float or None
        Tilt series: the rotation applied (degrees); None: none.
    tilt_axis : TiltAxisCheck or None
        Tilt series: the consistency check of the data as returned (``indreg.alignment.tilt_axis``).
    convention : str
        How the files were read (``indreg.io.conventions``). The tensors here are in indreg's layout (axis 0 = x),
        and so is what ``indreg.register`` returns from them (it must fit the operator and these tensors):
        :meth:`as_given` turns an image of the run back into the files' layout.
    """
    template: torch.Tensor
    data: torch.Tensor
    operator: object
    domain: ImageDomain
    geometry: object
    target: Optional[torch.Tensor] = None
    label: str = "array"
    tilt_axis_angle: Optional[float] = None
    tilt_axis: Optional[TiltAxisCheck] = None
    convention: str = "indreg"

    def as_given(self, images) -> np.ndarray:
        """Images of the run ``(..., nx, ny)`` (``result.deformed``, ``result.trajectory``, a baseline) as float64
        numpy in the layout of the files given to :func:`load` (``convention``); a volume as it is.

        Parameters
        ----------
        images : torch.Tensor or numpy.ndarray
            In indreg's layout (axis 0 = x), as ``indreg.register`` returns them.

        Returns
        -------
        numpy.ndarray
            The last two axes in the convention's layout (``indreg.io.conventions.images_from_indreg``).

        Raises
        ------
        ValueError
            The last axes are not the domain's shape.
        """
        a = images.detach().cpu().double().numpy() if isinstance(images, torch.Tensor) else np.asarray(images, float)
        if a.shape[a.ndim - self.domain.ndim:] != tuple(self.domain.shape):
            raise ValueError(f"images of shape {a.shape}: the last axes must be the domain's {tuple(self.domain.shape)}")
        return a if self.domain.ndim == 3 else conventions.images_from_indreg(a, self.convention)

    def report(self) -> dict:
        """The tilt series' numbers for a run's metrics: the angle applied and the check's (empty in 2D)."""
        if self.tilt_axis is None:
            return {}
        return {"tilt_axis_angle": self.tilt_axis_angle, **self.tilt_axis.metrics()}


def load(template, data, geometry: str = "parallel", *, angles=None, angle_unit: str = "deg", target=None,
         half_width: float = 16.0, det_min: Optional[float] = None, det_max: Optional[float] = None,
         det_count: Optional[int] = None, num_angles: Optional[int] = None, tilt_axis: str = "y",
         tilt_axis_angle: Optional[float] = None, src_radius: Optional[float] = None, det_radius: float = 0.0,
         convention: str = "indreg", integer_scale: str = "fraction", names: Optional[dict] = None,
         alignment=None) -> RegistrationInputs:
    """Template, data, operator (and optionally the ground truth ``target``) of a registration from files or
    arrays (layouts and units: the module's Notes).

    Parameters
    ----------
    template : str or os.PathLike or array_like
        The template: a path (any format of :mod:`indreg.io`: ``file.npz:key``, ``file.h5:/dataset``, ...) or an
        array (numpy, torch) in indreg's layout; 2D square ``(n, n)``, or 3D ``(nx, ny, nz)`` for a tilt series.
    data : str or os.PathLike or array_like
        The measured data, a path or an array: ``(num_angles, det_count)``, or ``(num_tilts, det_rows,
        det_cols)`` for a tilt series.
    geometry : {"parallel", "fan_flat", "tilt_series"}
        The acquisition geometry (``fan_flat`` needs ``src_radius``).
    angles : str or os.PathLike or sequence of float, optional
        A text file (one angle a line, IMOD ``.tlt``) or a list, in ``angle_unit``; None: the ``.tlt`` /
        ``.rawtlt`` next to the data file.
    angle_unit : {"deg", "rad"}
        The unit of ``angles``.
    target : str or os.PathLike or array_like, optional
        The ground truth, the template's shape (for SSIM / PSNR).
    half_width : float
        The domain's half side (the longest axis of a volume), > 0.
    det_min, det_max : float, optional
        The detector's extent (at the detector, in the domain's length unit); None: in 2D fitted to the
        domain, a tilt series gets columns as wide as the voxels, centred on the tilt axis.
    det_count, num_angles : int, optional
        If given, they must agree with the data (``det_count``: its width).
    tilt_axis : {"y", "x", "z"}
        Tilt series: the volume's axis the specimen turns about.
    tilt_axis_angle : float, optional
        Tilt series: the angle of the tilt axis in the detector image, degrees from the image's Y towards -X
        (counterclockwise; IMOD / SerialEM's); the stack is rotated by its opposite before anything else
        (``indreg.alignment.tilt_axis.align_tilt_axis``: exact for multiples of 90, interpolated otherwise).
        None: the ``.mdoc`` next to a stack file (``name.mrc.mdoc`` or ``name.mdoc``, its ``TiltAxisAngle`` /
        ``Tilt axis angle``), else no rotation. The rotated stack is then checked
        (``indreg.alignment.tilt_axis.check_tilt_axis``): a stack whose axis still runs along X is an error when
        an angle was given (by the argument or the ``.mdoc``) and a warning otherwise.
    src_radius : float, optional
        ``fan_flat``: source-to-origin distance.
    det_radius : float
        ``fan_flat``: origin-to-detector distance.
    convention : str
        The tool whose layout, angles, units and detector centre the files and arrays follow
        (``indreg.io.conventions``: ``indreg`` default, ``skimage``, ``astra``, ``tomopy``, ``imod``, ``odl``); a
        tilt series takes ``indreg`` or ``imod``.
    integer_scale : {"fraction", "raw"}
        8- / 16-bit pictures as a fraction of their full scale (default) or raw.
    names : dict, optional
        How messages call the arguments (:data:`NAMES` by default; the app passes ``{"data": "data.sinogram",
        ...}``).
    alignment : str or os.PathLike, optional
        Tilt series: an IMOD ``.xf`` or AreTomo ``.aln`` file of the raw stack (``indreg.alignment.files``): its
        shifts and per-tilt maps become the operator's own (an ``AlignedOperator``; ``register(..., align=...)``
        refines them), its tilt angles (the ``.aln``'s, or the ``.xf``'s ``.tlt`` unless ``angles`` is given)
        the geometry's, its dark frames are left out, and the stack is not rotated (the file's maps hold the
        tilt axis' angle).

    Returns
    -------
    RegistrationInputs
        The template, data, operator, domain, geometry and target (float64 on the CPU).

    Raises
    ------
    DataFileError
        A problem with a file (naming it), a count or shape that does not fit, a geometry that cannot be built.
    ValueError, TypeError
        A bad argument value (inline angles, ``angle_unit``, ``half_width``, an array).
    """
    key = {**NAMES, **(names or {})}
    _check_arguments(geometry, angle_unit, half_width, tilt_axis, tilt_axis_angle, key)
    conv = _convention(convention, integer_scale, geometry, key)
    ndim = 3 if geometry == "tilt_series" else 2
    read = dict(convention=conv, integer_scale=integer_scale)
    f = _image(template, key["template"], ndim, **read)
    if min(f.shape) < 2:
        raise DataFileError(f"{_where(key['template'], template)}: shape {' x '.join(map(str, f.shape))} has a single "
                            "pixel along an axis; a registration needs an image of at least 2 pixels per axis")
    if ndim == 2 and f.shape[0] != f.shape[1]:
        raise DataFileError(f"{_where(key['template'], template)}: shape {f.shape[0]} x {f.shape[1]} is not square; "
                            f"the domain [-{half_width:g}, {half_width:g}]^2 needs n x n pixels (square cells): pad "
                            "or resample the image")
    g = _measurements(data, key["data"], ndim, **read)
    axis = None
    if alignment is not None:   # another tool's alignment of the raw stack, applied in the operator
        g, radians, alignment = _aligned_stack(g, alignment, angles, angle_unit, ndim, tilt_axis_angle, key)
    elif ndim == 3:
        g, tilt_axis_angle, axis = _align(g, data, tilt_axis_angle, key)
    if alignment is None:
        radians = _angles(angles, angle_unit, data, g.shape, ndim, key)
    _check_counts(g.shape, data, num_angles, det_count, ndim, key)
    truth = _target(target, f, ndim, key, read)
    domain = conventions.domain_for(conv, f.shape[0], half_width) if ndim == 2 else box_domain(f.shape, half_width)
    given_detector = det_min, det_max
    if ndim == 2:   # the convention's units, angles and detector
        h = domain.cell_sides[0]
        g, radians = conventions.sinogram_units(g, conv, h), conventions.angles_to_indreg(radians, conv)
        det_min, det_max = conventions.detector_for(conv, g.shape[-1], h, det_min, det_max)
    if ndim == 3:   # imod: IMOD's sense of rotation and pixel sums (docs/file_formats.md)
        h = domain.cell_sides[1 if tilt_axis == "x" else 0]
        g, radians = conventions.sinogram_units(g, conv, h), conventions.angles_to_indreg(radians, conv)
        if conv.name != "indreg":
            log.info("%s: %s", _where(key["data"], data), conventions.describe_sinogram(conv).replace(
                "rows = angles, columns = bins", "(tilts, rows, columns) as stored"))
    if ndim == 3 and det_min is None and det_max is None:   # measured data: columns as wide as the voxels
        det_max = g.shape[2] * h / 2
        det_min = -det_max
    try:
        T = make_operator(domain, make_geometry(geometry, g.shape[-1], angles=torch.as_tensor(radians), det_min=det_min,
                                                det_max=det_max, src_radius=src_radius, det_radius=det_radius,
                                                tilt_axis=tilt_axis))
    except ValueError as e:
        raise DataFileError(f"geometry: {e}") from None
    if tuple(g.shape) != tuple(T.range_shape):
        raise DataFileError(f"{_where(key['data'], data)}: shape {tuple(g.shape)} but the template {tuple(f.shape)} "
                            f"with tilt axis {tilt_axis} needs {tuple(T.range_shape)} (tilts, rows along the tilt "
                            "axis, columns)")
    if ndim == 2 and geometry == "parallel":
        _check_orientation(f, g, radians, conv, template, half_width, *given_detector, key)
        if truth is not None and (hint := orientation.target_hint(truth, torch.from_numpy(g), T)):   # its layout
            log.warning("%s: %s; check %s", _where(key["target"], target), hint, key["convention"])
    operator = T
    if alignment is not None:
        from .alignment.files import to_operator
        operator = to_operator(T, alignment)
    label = io.split_path(template)[0].name if _is_path(template) else "array"
    return RegistrationInputs(template=torch.from_numpy(f), data=torch.from_numpy(g), operator=operator,
                              domain=domain,
                              geometry=T.geometry, target=truth, label=label, tilt_axis_angle=tilt_axis_angle,
                              tilt_axis=axis, convention=conv.name)


def square_domain(n: int, half_width: float, ndim: int = 2) -> ImageDomain:
    """``n`` cells per axis on ``[-half_width, half_width]^ndim``."""
    return ImageDomain((n,) * ndim, (-half_width,) * ndim, (half_width,) * ndim)


def box_domain(shape: tuple, half_width: float) -> ImageDomain:
    """Cubic cells of side ``2 half_width / max(shape)``, centred: the longest axis spans
    ``[-half_width, half_width]`` (a slab of electron tomography keeps its aspect ratio)."""
    h = 2.0 * half_width / max(shape)
    return ImageDomain(tuple(shape), tuple(-h * n / 2 for n in shape), tuple(h * n / 2 for n in shape))


def make_geometry(kind: str, det_count: int, *, angles: Optional[torch.Tensor] = None,
                  num_angles: Optional[int] = None, partition: str = "uniform", det_min: Optional[float] = None,
                  det_max: Optional[float] = None, src_radius: Optional[float] = None, det_radius: float = 0.0,
                  tilt_axis: str = "y", tilt_min: float = -60.0, tilt_max: float = 60.0, tilt_step: float = 2.0,
                  angle_unit: str = "deg"):
    """The geometry ``kind`` (:data:`GEOMETRIES`) with ``det_count`` detector bins (columns) on
    ``[det_min, det_max]`` (``None`` both: the operator fits the detector to the domain).

    Angles: ``angles`` (radians, 1D), else ``num_angles`` of ``partition`` (``paper``: ODL's
    ``uniform_partition(0, pi, n, nodes_on_bdry=(True, False))``, ``k pi / (n - 1/2)``; ``uniform``: the
    geometry's own equispaced angles), else for a tilt series ``tilt_min, tilt_min + tilt_step, ..., tilt_max``
    (in ``angle_unit``).
    """
    if kind == "tilt_series":
        if angles is None:
            deg = 1.0 if angle_unit == "deg" else 180 / math.pi
            return TiltSeriesGeometry.uniform(tilt_min * deg, tilt_max * deg, tilt_step * deg, det_count, det_min,
                                              det_max, tilt_axis)
        return TiltSeriesGeometry(angles, det_count, det_min, det_max, tilt_axis, angle_unit="rad")
    paper = angles is None and partition == "paper"
    if paper and kind == "parallel":
        return ParallelBeamGeometry.paper(num_angles, det_count, det_min=det_min, det_max=det_max)
    if paper:
        angles = torch.arange(num_angles, dtype=torch.float64) * (math.pi / (num_angles - 0.5))
    count = None if angles is not None else num_angles
    if kind == "fan_flat":
        return FanBeamGeometry(num_angles=count, det_count=det_count, src_radius=src_radius, det_radius=det_radius,
                               det_min=det_min, det_max=det_max, angles=angles)
    return ParallelBeamGeometry(num_angles=count, det_count=det_count, det_min=det_min, det_max=det_max,
                                angles=angles)


def make_operator(domain: ImageDomain, geometry):
    """The forward operator of ``geometry`` on ``domain`` (``indreg.forward.operator_for``)."""
    from .forward import operator_for

    return operator_for(domain, geometry)


# --- the checks of load -------------------------------------------------------------------------------------

def _is_path(value) -> bool:
    return isinstance(value, (str, os.PathLike))


def _where(name: str, value) -> str:
    """How a message names an argument: ``"data.template t.png"`` for a file, the name alone for an array."""
    return f"{name} {value}" if _is_path(value) else name


def _check_arguments(geometry, angle_unit, half_width, tilt_axis, tilt_axis_angle, key: dict) -> None:
    if geometry not in GEOMETRIES:
        raise ValueError(f"{key['geometry']} must be one of {', '.join(GEOMETRIES)}, got {geometry!r}")
    if angle_unit not in io.ANGLE_UNITS:
        raise ValueError(f"{key['angle_unit']} must be 'deg' or 'rad', got {angle_unit!r}")
    check_positive(half_width, key["half_width"])
    if tilt_axis not in tuple(AXES):
        raise ValueError(f"{key['tilt_axis']} must be 'x', 'y' or 'z', got {tilt_axis!r}")
    if tilt_axis_angle is not None:
        if isinstance(tilt_axis_angle, bool) or not isinstance(tilt_axis_angle, numbers.Real) \
                or not abs(tilt_axis_angle) <= 180:
            raise ValueError(f"{key['tilt_axis_angle']} must be a finite number of degrees in [-180, 180] or None, "
                             f"got {tilt_axis_angle!r}")
        if geometry != "tilt_series":
            raise ValueError(f"{key['tilt_axis_angle']} applies to a tilt series ({key['geometry']}=tilt_series), "
                             f"got {key['geometry']}={geometry}")


def _align(g: np.ndarray, data, angle, key: dict) -> tuple:
    """The stack with its tilt axis along the rows (``tilt_axis_angle`` or the ``.mdoc``'s), the angle applied
    and the consistency check; an error if a given angle leaves the axis along X (module docstring)."""
    mdoc = io.mdoc_for(data) if _is_path(data) else None
    recorded = None if mdoc is None else io.read_tilt_axis_angle(mdoc, name=f"{key['data']} metadata")
    origin = f"{key['tilt_axis_angle']}={angle:g}" if angle is not None else None
    if angle is None and recorded is not None:
        angle, origin = recorded, f"the tilt axis angle {recorded:g} of {mdoc}"
        log.info("%s: rotating the stack by %g degrees (tilt axis angle of %s)", _where(key["data"], data), -angle,
                 mdoc.name)
    elif recorded is not None and abs(recorded - angle) > 0.5:
        log.warning("%s=%g overrides the tilt axis angle %g of %s", key["tilt_axis_angle"], angle, recorded, mdoc)
    if angle is not None:
        g = align_tilt_axis(g, angle)
    check = check_tilt_axis(g)
    where = _where(key["data"], data)
    if check.direction == "columns" and angle is not None:
        turned = "as stored" if angle % 360 == 0 else f"turned by {-angle:g} degrees"
        raise DataFileError(f"{where}: {origin} contradicts the data: {turned}, {check.describe()}; the angle is off "
                            f"by about 90 degrees (e.g. {angle + 90:g} or {angle - 90:g})")
    if check.direction == "columns":
        log.warning("%s: %s; give %s (90 or -90, IMOD's rotation angle) to rotate the stack", where,
                    check.describe(), key["tilt_axis_angle"])
    else:
        log.info("%s: %s", where, check.describe())
    return g, angle, check


def _aligned_stack(g: np.ndarray, alignment, angles, unit: str, ndim: int, tilt_axis_angle, key: dict) -> tuple:
    """The raw stack's frames that ``alignment`` (a file) covers, their angles (radians) and the alignment."""
    from .alignment.files import check_shifts, read_alignment

    if ndim != 3:
        raise ValueError(f"alignment applies to a tilt series ({key['geometry']}=tilt_series)")
    if tilt_axis_angle is not None:
        raise ValueError(f"give {key['tilt_axis_angle']} or alignment, not both: the alignment file holds the tilt "
                         "axis' angle")
    if angles is not None and not _is_path(angles):
        angles = list(np.degrees(io.read_angles(angles, unit, name=key["angles"])))
    a = read_alignment(alignment, angles, name="alignment")
    if a.raw_size and (a.raw_size[0], a.raw_size[1]) != (g.shape[2], g.shape[1]):
        raise DataFileError(f"alignment file {alignment}: RawSize {a.raw_size[0]} x {a.raw_size[1]} but the stack's "
                            f"images are {g.shape[2]} x {g.shape[1]}")
    if a.frames.max() >= g.shape[0] or (a.raw_size is None and len(a.frames) != g.shape[0]):
        raise DataFileError(f"alignment file {alignment}: {len(a.frames)} tilts (sections up to {a.frames.max()}) "
                            f"but the stack has {g.shape[0]} sections")
    check_shifts(a, g.shape[2], g.shape[1], alignment)
    log.info("alignment %s (%s): %d tilts, in-plane rotation %.2f degrees, shifts up to %.2f px, applied in the "
             "operator", alignment, a.source, len(a.frames), a.axis_angle_deg, float(np.abs(a.shifts).max()))
    return np.ascontiguousarray(g[a.frames]), np.radians(a.tilt_angles_deg), a


def _array(value, name: str, ndim: int) -> np.ndarray:
    """A float64 copy of an array argument after the checks ``indreg.io`` makes on a file's array."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
        value = value.numpy() if value.is_complex() else value.double().numpy()
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):   # ragged nested lists
        raise TypeError(f"{name} must be a path or a numeric array, got {type(value).__name__}") from None
    if a.dtype.kind == "c":
        raise TypeError(f"{name} has complex values (dtype {a.dtype}); give the real data")
    if a.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be a path or a real numeric array, got {type(value).__name__} of {a.dtype}")
    if a.ndim != ndim or a.size == 0:
        raise ValueError(f"{name} must be a non-empty {ndim}D array, got shape {a.shape}")
    out = np.array(a, dtype=np.float64, order="C")
    bad = int(np.count_nonzero(~np.isfinite(out)))
    if bad:
        raise ValueError(f"{name} has {bad} non-finite values (NaN or Inf) of {out.size}")
    return out


def _convention(name, integer_scale, geometry: str, key: dict) -> conventions.Convention:
    """The :class:`~indreg.io.conventions.Convention` ``name``, checked against the geometry; ``integer_scale`` checked."""
    conv = conventions.get_convention(name, key["convention"])
    if integer_scale not in conventions.INTEGER_SCALES:
        raise ValueError(f"{key['integer_scale']} must be one of {', '.join(conventions.INTEGER_SCALES)}, got "
                         f"{integer_scale!r}")
    allowed = {"tilt_series": _CONVENTIONS_3D, "fan_flat": _CONVENTIONS_FAN}.get(geometry,
                                                                                 tuple(conventions.CONVENTIONS))
    if conv.name not in allowed:
        raise ValueError(f"{key['convention']}={conv.name} is for 2D parallel-beam data; with {key['geometry']}="
                         f"{geometry} use {' or '.join(allowed)}")
    return conv


def _image(value, name: str, ndim: int, convention=conventions.CONVENTIONS["indreg"],
           integer_scale: str = "fraction") -> np.ndarray:
    """A template / target ``(nx, ny[, nz])``: read from a file (``io.read_image`` / ``read_volume``) or given (in
    the convention's layout)."""
    if _is_path(value):
        return io.read_image(value, name=name, ndim=ndim, convention=convention, integer_scale=integer_scale)
    a = _array(value, name, ndim)
    return conventions.image_to_indreg(a, convention) if ndim == 2 else a


def _measurements(value, name: str, ndim: int, convention=conventions.CONVENTIONS["indreg"],
                  integer_scale: str = "fraction") -> np.ndarray:
    """The data: a sinogram (``io.read_sinogram``) or a stack of projections (``io.read_stack``), or given."""
    if not _is_path(value):
        a = _array(value, name, ndim)
        return conventions.sinogram_layout(a, convention) if ndim == 2 else a
    if ndim == 3:
        return io.read_stack(value, name=name)
    return io.read_sinogram(value, name=name, convention=convention, integer_scale=integer_scale)


def _check_orientation(f: np.ndarray, g: np.ndarray, radians: np.ndarray, conv, template, half_width: float,
                       det_min, det_max, key: dict) -> None:
    """Warn when the files read in another convention fit the data clearly better (``orientation_hint``)."""
    picture = _is_path(template) and io.split_path(template)[0].suffix.lower() in io.formats.suffixes("picture")
    stored_f = np.rot90(f) if picture else conventions.image_from_indreg(f, conv)
    stored_g = g.T if conv.sinogram == "bin_angle" else g
    scores = orientation.orientation_scores(stored_f, stored_g, conventions.angles_from_indreg(radians, conv),
                                           half_width, det_min, det_max, picture)
    hint = orientation.orientation_hint(scores, conv)
    if hint is not None:
        log.warning("%s: %s; set %s accordingly", _where(key["template"], template), hint, key["convention"])
        return
    hint = orientation.flip_hint(f, g, conventions.angles_from_indreg(radians, conv), conv, half_width, det_min,
                                det_max)
    if hint is not None:
        log.warning("%s: %s", _where(key["template"], template), hint)


def _may_have_sibling(data, ndim: int) -> bool:
    """Whether the data file's angles may come from the ``.tlt`` / ``.rawtlt`` next to it (2D: a stack of sections,
    MRC)."""
    return _is_path(data) and (ndim == 3 or io.split_path(data)[0].suffix.lower() in io.formats.suffixes("sections"))


def _angles(angles, unit: str, data, shape: tuple, ndim: int, key: dict) -> np.ndarray:
    """The data's angles in radians, one per row (2D) or tilt (3D): ``angles``, else the sibling angle file."""
    if angles is None:
        angles = io.tilt_angles_for(data) if _may_have_sibling(data, ndim) else None
        if angles is None:
            raise DataFileError(f"{key['angles']} is required: a text file (one angle a line) or a list, in "
                                f"{key['angle_unit']}{_sibling_hint(data, ndim, key)}")
    origin = str(angles) if _is_path(angles) else key["angles"]
    radians = io.read_angles(angles, unit, name=key["angles"])
    if radians.size != shape[0]:
        what = "rows (one per angle)" if ndim == 2 else "tilts (sections)"
        swapped = (f"; its columns are as many: the sinogram is (bins, angles), give {key['convention']}=skimage "
                   "or transpose it") if ndim == 2 and shape[1] == radians.size else ""
        raise DataFileError(f"{_where(key['data'], data)}: {shape[0]} {what} but {origin} gives {radians.size} "
                            f"angles{swapped}")
    return radians


def _sibling_hint(data, ndim: int, key: dict) -> str:
    if _may_have_sibling(data, ndim):
        return f", or a file {io.split_path(data)[0].with_suffix('.tlt').name} (or .rawtlt) next to {data}"
    if _is_path(data):
        return " (an .mrc/.st/.ali sinogram may instead have a sibling .tlt/.rawtlt file)"
    return ""


def _check_counts(shape: tuple, data, num_angles, det_count, ndim: int, key: dict) -> None:
    """``num_angles`` / ``det_count``, when given, must be the data's."""
    rows, bins = ("rows", "detector bins") if ndim == 2 else ("tilts", "detector columns")
    if num_angles is not None and num_angles != shape[0]:
        raise DataFileError(f"{_where(key['data'], data)}: {shape[0]} {rows} but {key['num_angles']}={num_angles}")
    if det_count is not None and det_count != shape[-1]:
        raise DataFileError(f"{_where(key['data'], data)}: {shape[-1]} {bins} but {key['det_count']}={det_count}")


def _target(target, template: np.ndarray, ndim: int, key: dict, read: dict) -> Optional[torch.Tensor]:
    """The optional ground truth, shaped as the template, read as it (``read``: convention, integer_scale)."""
    if target is None:
        return None
    truth = _image(target, key["target"], ndim, **read)
    if truth.shape != template.shape:
        raise DataFileError(f"{_where(key['target'], target)}: shape {truth.shape} differs from the template's "
                            f"{template.shape}")
    return torch.from_numpy(truth)
