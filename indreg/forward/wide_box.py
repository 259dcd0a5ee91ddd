"""The wide box of a slab specimen: a reconstruction box wider than the detector where the specimen is.

A specimen wider than the field of view (a cryo-ET slab of ice, a lamella, region-of-interest CT of tissue) puts
material outside the detector-wide box on the rays that reach the detector: at tilt ``theta`` the rays through a
slab of thickness ``t`` reach ``|u| = (W / 2 + (t / 2) |sin theta|) / |cos theta|`` across a detector of width
``W``. A box ending at the detector's edge cannot explain that material, whatever the model (docs/slab.md). The
wide box adds whole cells along the slice plane's axes (never along a tilt axis) until every point of the specimen
that a ray reaching the detector crosses lies inside; the detector, and with it the data, stay as measured: the
wide box's rays that miss the detector are not data (the operator's range is the detector's pixels only).

Not to be confused with ``indreg.problems.slabs`` / ``indreg.forward.split``: those split a volume into memory
slabs along the tilt axis.

Convention (the slice plane ``(u, v)``: ``(x, y)`` in 2D, ``TiltSeriesGeometry.slice_axes`` in 3D, ``(x, z)``
for the default tilt axis y):
    - At angle 0 the beam runs along +v and the detector along u: v is the specimen's thickness direction, u its
      lateral one.
    - The specimen is the rectangle ``|u - u_c| <= extent / 2``, ``|v - v_c| <= thickness / 2`` about the given
      box's centre ``(u_c, v_c)`` (physical units); ``thickness`` None: the given box's extent along v;
      ``extent`` None: unbounded (a slab), each axis of the wide box then capped at ``max_width`` times the given
      box's extent (a full-angle scan of an unbounded slab would need an infinite box).
    - Parallel beam: the rays of angle ``theta`` reaching the detector ``[det_min, det_max]`` fill the strip
      ``det_min <= u cos theta + v sin theta <= det_max``; fan beam: the wedge from the source through the
      detector's ends. The wide box is the smallest box of whole cells (the given box's cell sides) that holds the
      given box and the bounding box of the specimen's part in every angle's strip / wedge (its extreme points are
      the edge rays' crossings of the specimen's border and the specimen's corners inside the bundle).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .._checks import check_positive
from ..domain import ImageDomain
from .geometry import FanBeamGeometry, ParallelBeamGeometry

__all__ = ["MAX_WIDTH", "PADDINGS", "WideBox", "wide_box", "specimen_box", "slab_thickness", "slice_axes"]

#: Without ``extent`` each axis of the wide box is at most this many times the given box's extent: a +-70 degree
#: tilt series of a slab as thick as the box needs 3.7x (``(1 + |sin 70|) / cos 70`` halves), a full-angle scan of
#: an unbounded slab would need an infinite box.
MAX_WIDTH = 4.0
#: How a template on the given box is padded to the wide box (``WideBox.pad_image``).
PADDINGS = ("edge", "zero", "level")


def _slice_frame(operator) -> tuple:
    """``(geometry_2d, slice_domain, (u, v) array axes)`` of a 2D ray transform or a tilt series; TypeError else."""
    geometry = getattr(operator, "geometry", None)
    if hasattr(geometry, "slice_geometry"):   # a tilt series: every slice the same 2D geometry
        return geometry.slice_geometry, geometry.slice_domain(operator.domain), geometry.slice_axes
    if isinstance(geometry, (ParallelBeamGeometry, FanBeamGeometry)):
        return geometry, operator.domain, (0, 1)
    raise TypeError(f"a wide box needs a RayTransform (parallel or fan beam) or a TiltSeriesTransform, got "
                    f"{type(operator).__name__}")


def slice_axes(operator) -> tuple:
    """The array axes ``(u, v)`` of ``operator``'s slice plane.

    Parameters
    ----------
    operator : RayTransform, TiltSeriesTransform or an aligned one around them
        The operator.

    Returns
    -------
    tuple
        ``(0, 1)`` in 2D, the tilt series' ``slice_axes`` in 3D.

    Raises
    ------
    TypeError
        Another operator.
    """
    inner = operator.operator if hasattr(operator, "shifts") and hasattr(operator, "operator") else operator
    return _slice_frame(inner)[2]


def _edge_rays(geometry) -> tuple:
    """Per angle, the two rays through the detector's ends: points ``(K, 2, 2)``, directions ``(K, 2, 2)`` in the
    slice plane, and ``t_min`` (``-inf`` for lines, 0 for rays from a fan's source)."""
    angles = geometry.angles.numpy()
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    ends = np.array([geometry.det_min, geometry.det_max])[None, :]
    if isinstance(geometry, FanBeamGeometry):
        src = np.stack([geometry.src_radius * s, -geometry.src_radius * c], -1) * np.ones((1, 2, 1))
        det = np.stack([-geometry.det_radius * s + ends * c, geometry.det_radius * c + ends * s], -1)
        return src, det - src, 0.0
    points = np.stack([ends * c, ends * s], -1)
    directions = np.stack([-s, c], -1) * np.ones((1, 2, 1))
    return points, directions, -math.inf


def _in_bundle(geometry, points: np.ndarray) -> np.ndarray:
    """``(K, P)``: whether each point ``(P, 2)`` lies on a ray of angle k that reaches the detector."""
    angles = geometry.angles.numpy()[:, None]
    e = np.stack([np.cos(angles), np.sin(angles)], -1)            # detector direction (K, 1, 2)
    along = (points[None] * e).sum(-1)
    if isinstance(geometry, FanBeamGeometry):
        n = np.stack([-np.sin(angles), np.cos(angles)], -1)
        depth = (points[None] * n).sum(-1) + geometry.src_radius   # distance from the source along the axis
        with np.errstate(divide="ignore", invalid="ignore"):
            along = np.where(depth > 0, (geometry.src_radius + geometry.det_radius) * along / depth, np.nan)
    return (along >= geometry.det_min) & (along <= geometry.det_max)


def _clip(points, directions, t_min, lo, hi) -> np.ndarray:
    """Liang-Barsky: the end points ``(M, 2, 2)`` of the lines ``p + t d`` (``t >= t_min``) inside the rectangle
    ``[lo, hi]`` (NaN for a line that misses it)."""
    p, d = points.reshape(-1, 2), directions.reshape(-1, 2)
    t0 = np.full(len(p), t_min, dtype=np.float64)
    t1 = np.full(len(p), math.inf)
    for a in range(2):
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo[a] - p[:, a]) / d[:, a], (hi[a] - p[:, a]) / d[:, a]
        flat = d[:, a] == 0
        outside = flat & ((p[:, a] < lo[a]) | (p[:, a] > hi[a]))
        t0 = np.where(flat, t0, np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(flat, t1, np.minimum(t1, np.maximum(ta, tb)))
        t1 = np.where(outside, -math.inf, t1)
    hit = (t0 <= t1) & np.isfinite(t0) & np.isfinite(t1)
    with np.errstate(invalid="ignore"):
        ends = p[:, None, :] + np.stack([t0, t1], -1)[:, :, None] * d[:, None, :]
    return np.where(hit[:, None, None], ends, np.nan)


def specimen_box(geometry, domain: ImageDomain, thickness: float | None = None, extent: float | None = None,
                 max_width: float = MAX_WIDTH) -> tuple:
    """The bounds of the specimen's part that rays reaching the detector cross (module docstring).

    Parameters
    ----------
    geometry : ParallelBeamGeometry or FanBeamGeometry
        A resolved 2D geometry (detector extent set).
    domain : ImageDomain
        The given box's slice plane (2D).
    thickness, extent : float, optional
        The specimen's extent along v and u (physical units); None: the box's thickness, and unbounded.
    max_width : float
        The cap, times ``domain``'s extent per axis, about its centre.

    Returns
    -------
    tuple
        ``((u_lo, u_hi), (v_lo, v_hi), capped)``: physical bounds joined with ``domain``'s, and whether the cap bound
        them.
    """
    lo0, hi0 = np.array(domain.min_pt), np.array(domain.max_pt)
    centre, size = (lo0 + hi0) / 2, hi0 - lo0
    wanted = np.array([math.inf if extent is None else extent, size[1] if thickness is None else thickness]) / 2
    cap = max_width * size / 2
    half = np.minimum(wanted, cap)
    lo, hi = centre - half, centre + half
    points, directions, t_min = _edge_rays(geometry)
    ends = _clip(points, directions, t_min, lo, hi).reshape(-1, 2)
    corners = np.array([[lo[0], lo[1]], [lo[0], hi[1]], [hi[0], lo[1]], [hi[0], hi[1]]])
    inside = corners[_in_bundle(geometry, corners).any(0)]
    found = np.concatenate([ends[~np.isnan(ends).any(1)], inside, lo0[None], hi0[None]])
    b_lo, b_hi = found.min(0), found.max(0)
    tol = 1e-9 * size
    capped = bool(((wanted > cap) & ((b_lo <= lo + tol) | (b_hi >= hi - tol))).any())
    return (float(b_lo[0]), float(b_hi[0])), (float(b_lo[1]), float(b_hi[1])), capped


def slab_thickness(template: torch.Tensor, domain: ImageDomain, axis: int, fraction: float = 0.05) -> float | None:
    """The specimen's thickness that a template shows.

    Parameters
    ----------
    template : torch.Tensor
        ``domain.shape``.
    domain : ImageDomain
        The template's box.
    axis : int
        The array axis of the beam at angle 0 (v).
    fraction : float
        A plane belongs to the specimen where its mean differs from the emptier face's by more than this fraction
        of the template's range.

    Returns
    -------
    float or None
        Twice the largest distance from the box's centre along ``axis`` of the specimen's planes (their cells
        whole); None when the template fills the box along ``axis`` (or is constant).
    """
    f = template.detach().double().movedim(axis - domain.ndim, -1)
    profile = f.reshape(-1, f.shape[-1]).mean(0)
    faces = float(torch.stack([profile[0], profile[-1]]).min())
    spread = float(f.max() - f.min())
    if not spread > 0:
        return None
    full = (profile - faces).abs() > fraction * spread
    if bool(full[0]) and bool(full[-1]) or not bool(full.any()):
        return None
    coords = domain.axes()[axis]
    centre = (domain.min_pt[axis] + domain.max_pt[axis]) / 2
    h = domain.cell_sides[axis]
    return float(2 * ((coords[full] - centre).abs().max() + h / 2))


@dataclass(frozen=True)
class WideBox:
    """A wide box around the box as given (:func:`wide_box` makes it).

    Attributes
    ----------
    field : ImageDomain
        The box as given, as wide as the detector: the field of view.
    domain : ImageDomain
        The wide box: the same cell sides, more cells along the slice plane's axes.
    pad : tuple
        ``(before, after)`` cells added per array axis.
    thickness : float
        The specimen's thickness it was made for (physical units).
    extent : float or None
        The specimen's lateral extent (None: a slab, unbounded).
    capped : bool
        Whether ``max_width`` bound it.
    """
    field: ImageDomain
    domain: ImageDomain
    pad: tuple
    thickness: float
    extent: float | None = None
    capped: bool = False

    @property
    def widened(self) -> bool:
        """Whether any cell was added."""
        return any(a or b for a, b in self.pad)

    @property
    def width_factor(self) -> float:
        """The wide box's largest extent over the given box's, per axis (1.0: not widened)."""
        return max(w / f for w, f in zip(self.domain.extent, self.field.extent))

    def crop(self, image: torch.Tensor) -> torch.Tensor:
        """The field of view of an image of the wide box.

        Parameters
        ----------
        image : torch.Tensor
            ``(..., *domain.shape)``.

        Returns
        -------
        torch.Tensor
            ``(..., *field.shape)``, a view.
        """
        out = image
        for axis, (a, b) in zip(self.domain.dims, self.pad):
            out = out.narrow(axis, a, out.shape[axis] - a - b)
        return out

    def field_mask(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """The field of view as a mask on the wide box.

        Parameters
        ----------
        dtype : torch.dtype
            Its dtype.
        device : torch.device, optional
            Its device.

        Returns
        -------
        torch.Tensor
            ``domain.shape``: 1 on the field's cells, 0 on the added ones.
        """
        mask = self.domain.zeros(dtype=dtype, device=device)
        self.crop(mask).fill_(1.0)
        return mask

    def pad_image(self, image: torch.Tensor, mode: str = "edge") -> torch.Tensor:
        """An image of the given box on the wide box.

        Parameters
        ----------
        image : torch.Tensor
            ``(..., *field.shape)``.
        mode : {'edge', 'zero', 'level'}
            ``edge`` repeats the outermost cells outwards (a slab's profile across its thickness continues),
            ``zero`` pads with 0 (vacuum), ``level`` with the median of the image's faces along each widened axis (a
            constant background).

        Returns
        -------
        torch.Tensor
            ``(..., *domain.shape)``.

        Raises
        ------
        ValueError
            Another mode.
        """
        if mode not in PADDINGS:
            raise ValueError(f"template padding must be one of {', '.join(PADDINGS)}, got {mode!r}")
        out = image
        for axis, (a, b), n in zip(self.field.dims, self.pad, self.field.shape):
            if not (a or b):
                continue
            index = torch.arange(-a, n + b, device=image.device).clamp(0, n - 1)
            grown = out.index_select(axis, index)
            if mode != "edge":
                level = 0.0 if mode == "zero" else float(torch.cat([out.narrow(axis, 0, 1).reshape(-1),
                                                                    out.narrow(axis, n - 1, 1).reshape(-1)]).median())
                inner = (index == torch.arange(-a, n + b, device=image.device))
                shape = [1] * grown.dim()
                shape[axis] = -1
                grown = torch.where(inner.reshape(shape), grown, torch.full_like(grown, level))
            out = grown
        return out

    def widen(self, operator):
        """An operator of the given box on the wide box: the same geometry and detector.

        Parameters
        ----------
        operator : LinearOperator
            On ``field``, with ``on_domain`` (a ray transform, a tilt series), or an aligned operator around one
            (``shifts`` and ``angle`` around an ``operator``: it keeps its alignment).

        Returns
        -------
        LinearOperator
            ``operator.on_domain(domain)``; ``operator`` itself when nothing was added.

        Raises
        ------
        ValueError
            An operator of another box. TypeError: one without ``on_domain``.
        """
        if tuple(operator.domain.shape) != tuple(self.field.shape):
            raise ValueError(f"the operator's domain {tuple(operator.domain.shape)} is not the box this wide box was "
                             f"made for, {tuple(self.field.shape)}")
        if not self.widened:
            return operator
        if hasattr(operator, "shifts") and hasattr(operator, "operator"):   # an AlignedOperator
            inner = self.widen(operator.operator)
            return type(operator)(inner, operator.shifts, float(operator.angle), operator.interpolation,
                                  operator.edge, operator.matrices)
        if not callable(getattr(operator, "on_domain", None)):
            raise TypeError(f"{type(operator).__name__} has no on_domain(domain): it cannot be put on a wide box")
        return operator.on_domain(self.domain)


def wide_box(operator, thickness: float | None = None, extent: float | None = None,
             max_width: float = MAX_WIDTH) -> WideBox:
    """The wide box of an operator for a specimen of ``thickness`` and lateral ``extent`` (module docstring).

    Whole cells are added along the slice plane's axes until every specimen point on a ray reaching the detector is
    inside, at most ``max_width`` times the given extent per axis.

    Parameters
    ----------
    operator : RayTransform, TiltSeriesTransform or an aligned one around them
        On the detector-wide box.
    thickness : float, optional
        The specimen's thickness along the beam at angle 0 (physical units); None: the box's.
    extent : float, optional
        Its lateral extent (physical units); None: unbounded (a slab).
    max_width : float
        The cap, times the given box's extent per axis (>= 1).

    Returns
    -------
    WideBox
        The wide box (``widened`` False where nothing was needed).

    Raises
    ------
    TypeError
        Another operator.
    ValueError
        A thickness, extent or max_width that is not a positive number (max_width below 1).
    """
    geometry, plane, (u, v) = _slice_frame(getattr(operator, "operator", operator) if hasattr(operator, "shifts")
                                           else operator)
    thickness = None if thickness is None else check_positive(thickness, "slab thickness")
    extent = None if extent is None else check_positive(extent, "slab extent")
    max_width = check_positive(max_width, "max_width")
    if max_width < 1:
        raise ValueError(f"max_width must be >= 1 (the wide box holds the given one), got {max_width}")
    (u_lo, u_hi), (v_lo, v_hi), capped = specimen_box(geometry, plane, thickness, extent, max_width)
    domain = operator.domain
    pad = [(0, 0)] * domain.ndim
    for axis, lo, hi in ((u, u_lo, u_hi), (v, v_lo, v_hi)):
        h = domain.cell_sides[axis]
        pad[axis] = tuple(max(0, math.ceil(x / h - 1e-6)) for x in (domain.min_pt[axis] - lo,
                                                                      hi - domain.max_pt[axis]))
    h = domain.cell_sides
    wide = ImageDomain(tuple(n + a + b for n, (a, b) in zip(domain.shape, pad)),
                       tuple(m - a * s for m, (a, _), s in zip(domain.min_pt, pad, h)),
                       tuple(m + b * s for m, (_, b), s in zip(domain.max_pt, pad, h)))
    return WideBox(domain, wide, tuple(pad), domain.extent[v] if thickness is None else thickness, extent, capped)
