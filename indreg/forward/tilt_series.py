"""Single-axis tilt series (electron tomography): the 3D ray transform for rotations about one image axis.

Every slice of the volume orthogonal to the tilt axis is imaged by the same 2D parallel-beam geometry, so the
3D operator is the 2D Joseph matrix ``A`` (``ray_transform``) applied to all slices at once: the tilt axis is
moved into the batch and one sparse-dense product does every slice of every volume of a batch. The backward
of the forward product is the exact transpose, as in 2D. Conventions: docs/tilt_series.md.
"""
from __future__ import annotations

import numbers

import torch
from torch import nn

from .._checks import check_tensor
from ..domain import AXES, ImageDomain
from .geometry import ParallelBeamGeometry
from .algebra import WeightedDataMixin
from .ray_transform import RayTransform, _Backproject, _Project

TILT_ANGLE_UNITS = ("deg", "rad")


def _axis_index(tilt_axis) -> int:
    """``"x"``/``"y"``/``"z"`` or 0/1/2 -> the array axis 0, 1 or 2."""
    if isinstance(tilt_axis, str) and len(tilt_axis) == 1 and tilt_axis in AXES:
        return AXES.index(tilt_axis)
    if isinstance(tilt_axis, numbers.Integral) and not isinstance(tilt_axis, bool) and tilt_axis in (0, 1, 2):
        return int(tilt_axis)
    raise ValueError(f"tilt_axis must be 'x', 'y', 'z' (or 0, 1, 2), got {tilt_axis!r}")


class TiltSeriesGeometry:
    """Rotation of the specimen about one image axis (the tilt axis), parallel beam, flat 2D detector.

    Parameters
    ----------
    angles : array_like
        Tilt angles (1D, finite, any order, non-uniform allowed), in ``angle_unit``.
    det_count : int
        Detector columns (bins along ``s``, >= 1).
    det_min, det_max : float, optional
        Detector extent along ``s`` (physical units); both None: fitted to the slice.
    tilt_axis : {"y", "x", "z"} or {0, 1, 2}
        The image axis the specimen turns about.
    angle_unit : {"deg", "rad"}
        The unit of ``angles`` (keyword, required: no guessing).
    angle_weights : array_like, optional
        FBP quadrature cells (radians, positive), default the midpoint cells.

    Raises
    ------
    ValueError
        A missing or unknown ``angle_unit``, an unknown ``tilt_axis``, and the angle and detector errors of
        ``ParallelBeamGeometry``.
    TypeError
        As ``ParallelBeamGeometry``.

    Notes
    -----
    Tilt axis ``t``; the two other axes ``(u, v)`` in increasing order: ``(x, z)`` for the default ``t = y``,
    ``(y, z)`` for ``t = x``, ``(x, y)`` for ``t = z``.

    - Slice ``j`` (the cells at ``t = t_j``) is a 2D image ``(n_u, n_v)`` imaged by
      ``ParallelBeamGeometry(angles, det_count, det_min, det_max)``: datum ``p(theta_k, t_j, s_d)`` is the
      integral over ``{s_d w + r w_perp}`` in the ``(u, v)`` plane with ``w = (cos theta, sin theta)``,
      ``w_perp = (-sin theta, cos theta)``. At tilt 0 the beam runs along +v (+z for ``t = y``) and the
      detector columns along u (x).
    - Data ``(..., num_tilts, det_rows, det_cols)``: ``det_rows = n_t`` rows at the slices' ``t_j`` (row
      spacing = the cell side along ``t``), ``det_cols = det_count`` cell-centred bins on
      ``[det_min, det_max]`` along ``s``. For ``t = y`` this is an MRC/IMOD stack ``(tilt, Y, X)`` as stored.
    - Angles: ``angle_unit`` is required (``"deg"`` or ``"rad"``; no guessing), any order, non-uniform.
    - Data inner product ``angle_cell * det_cell * row_cell * sum`` with ``angle_cell = pi / num_tilts``
      (the 2D weight times the row spacing), so the L2 adjoint is ``(data_weight / cell_volume) A^T``
      slice by slice. FBP weighs tilt ``k`` by ``angle_weights[k]`` (midpoint cells: the step of a
      regular tilt series).
    - ``det_min = det_max = None``: the detector is fitted to the slice (its half-diagonal), see
      ``ParallelBeamGeometry``; for data measured on a detector as wide as the volume pass
      ``det_min, det_max = domain.min_pt[u], domain.max_pt[u]``.

    Examples
    --------
    >>> g = TiltSeriesGeometry.uniform(-60, 60, 2, det_count=64, det_min=-16.0, det_max=16.0)
    >>> g.num_tilts, g.tilt_axis
    (61, 'y')
    """

    def __init__(self, angles, det_count: int, det_min: float | None = None, det_max: float | None = None,
                 tilt_axis="y", *, angle_unit: str, angle_weights=None):
        if angle_unit not in TILT_ANGLE_UNITS:
            raise ValueError(f"angle_unit must be 'deg' or 'rad' (required for a tilt series), got {angle_unit!r}")
        self.axis = _axis_index(tilt_axis)
        self.slice_geometry = ParallelBeamGeometry(det_count=det_count, det_min=det_min, det_max=det_max,
                                                   angles=angles, angle_unit=angle_unit,
                                                   angle_weights=angle_weights)
        self.det_rows = None   # set by resolve(domain)
        self.row_cell = None

    @classmethod
    def uniform(cls, min_deg: float, max_deg: float, step_deg: float, det_count: int, det_min: float | None = None,
                det_max: float | None = None, tilt_axis="y"):
        """Tilts ``min_deg, min_deg + step_deg, ..., max_deg`` degrees (``ParallelBeamGeometry.tilt_series``)."""
        g = ParallelBeamGeometry.tilt_series(min_deg, max_deg, step_deg, det_count, det_min, det_max)
        return cls(g.angles, det_count, det_min, det_max, tilt_axis, angle_unit="rad")

    @property
    def tilt_axis(self) -> str:
        """``"x"``, ``"y"`` or ``"z"``."""
        return AXES[self.axis]

    @property
    def slice_axes(self) -> tuple:
        """The array axes ``(u, v)`` of a slice: the two non-tilt axes in increasing order."""
        return tuple(a for a in range(3) if a != self.axis)

    angles = property(lambda self: self.slice_geometry.angles, doc="Tilt angles in radians (float64, 1D).")
    num_tilts = property(lambda self: self.slice_geometry.num_angles, doc="Number of tilts.")
    det_count = property(lambda self: self.slice_geometry.det_count, doc="Detector columns (bins along s).")
    det_min = property(lambda self: self.slice_geometry.det_min, doc="Detector start along s.")
    det_max = property(lambda self: self.slice_geometry.det_max, doc="Detector end along s.")
    det_cell = property(lambda self: self.slice_geometry.det_cell, doc="Column width.")
    det_points = property(lambda self: self.slice_geometry.det_points, doc="Column centres along s.")
    angle_cell = property(lambda self: self.slice_geometry.angle_cell, doc="``pi / num_tilts``.")
    angle_weights = property(lambda self: self.slice_geometry.angle_weights, doc="FBP quadrature cells.")

    @property
    def is_resolved(self) -> bool:
        """Whether the detector (extent and rows) is set for a domain."""
        return self.det_rows is not None and self.slice_geometry.is_resolved

    def _require_resolved(self):
        if not self.is_resolved:
            raise ValueError("TiltSeriesGeometry is not resolved for a domain: call geometry.resolve(domain) "
                             "(TiltSeriesTransform does this)")

    @property
    def shape(self) -> tuple:
        """Data shape ``(num_tilts, det_rows, det_cols)``."""
        self._require_resolved()
        return (self.num_tilts, self.det_rows, self.det_count)

    @property
    def data_weight(self) -> float:
        """Weight of the data inner product, ``angle_cell * det_cell * row_cell``."""
        self._require_resolved()
        return self.angle_cell * self.det_cell * self.row_cell

    def slice_domain(self, domain: ImageDomain) -> ImageDomain:
        """The 2D domain ``(n_u, n_v)`` of one slice of ``domain``."""
        u, v = self.slice_axes
        return ImageDomain((domain.shape[u], domain.shape[v]), (domain.min_pt[u], domain.min_pt[v]),
                           (domain.max_pt[u], domain.max_pt[v]))

    def resolve(self, domain: ImageDomain) -> "TiltSeriesGeometry":
        """A copy with the detector rows of ``domain`` and, if unset, the detector extent fitted to a slice."""
        if not isinstance(domain, ImageDomain) or domain.ndim != 3:
            raise ValueError(f"a tilt series needs a 3D ImageDomain, got {domain!r}")
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.slice_geometry = self.slice_geometry.resolve(self.slice_domain(domain))
        new.det_rows, new.row_cell = domain.shape[self.axis], domain.cell_sides[self.axis]
        return new

    def __repr__(self) -> str:
        return (f"TiltSeriesGeometry(num_tilts={self.num_tilts}, det_count={self.det_count}, "
                f"det_min={self.det_min}, det_max={self.det_max}, tilt_axis={self.tilt_axis!r})")


#: A volume whose slices are not rows of its memory (tilt axis y or z) is projected in chunks of slices of at most
#: this many bytes, each copied to rows: not a copy of the whole volume (1 GiB at 1024 x 1024 x 256 in float32).
COPY_CHUNK_BYTES = 64 * 2 ** 20


def _viewable(slices: torch.Tensor, width: int) -> bool:
    """Whether ``slices (n_t, n_u, n_v)`` reads as rows ``(n_t, width)`` without a copy."""
    try:
        slices.view(-1, width)
    except RuntimeError:
        return False
    return True


class TiltSeriesTransform(WeightedDataMixin, nn.Module):
    """Single-axis tilt-series ray transform ``T: L2(domain) -> L2(tilts x rows x columns)`` (a ``LinearOperator``).

    ``(T f)(theta_k, t_j, s_d)`` is the 2D parallel-beam ray transform of the slice ``f(., t_j, .)``
    (``TiltSeriesGeometry``), discretised by the 2D Joseph matrix ``A`` of that slice geometry, the same for
    every slice: ``T f = A`` applied slice by slice, in one batched sparse product.

    Parameters
    ----------
    domain : ImageDomain
        The 3D volume domain ``(nx, ny, nz)``.
    geometry : TiltSeriesGeometry
        The tilts and the detector (resolved for ``domain`` here).

    Raises
    ------
    ValueError
        A domain that is not 3D.
    TypeError
        A geometry that is no ``TiltSeriesGeometry``.

    Notes
    -----
    - Input volumes ``(..., nx, ny, nz)`` on a 3D ``domain`` (axis 0 = x), float32 or float64, any leading
      batch dims, any device. Output data ``(..., num_tilts, det_rows, det_cols)``, line integrals in
      physical length units (a unit ball of radius r gives ``2 r`` through its centre).
    - ``transpose`` is the exact matrix transpose ``A^T`` per slice; ``adjoint`` is the L2 adjoint for
      ``domain.inner`` and ``inner_data``: ``T^* = (data_weight / cell_volume) A^T`` (the cell side along
      the tilt axis cancels, so the factor is the 2D one).
    - Derivative: ``T`` is linear, ``T'(f) = T``; its autograd backward is ``A^T`` (and the backward of
      ``transpose`` is ``A``), exact and twice differentiable.
    - ``self.geometry`` is the resolved geometry; ``self.slice_transform`` the 2D ``RayTransform`` of one
      slice (used by ``fbp``).

    Examples
    --------
    >>> dom = ImageDomain((32, 24, 16))
    >>> T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 3, det_count=40))
    >>> T(dom.zeros(2)).shape
    torch.Size([2, 41, 24, 40])
    """

    def __init__(self, domain: ImageDomain, geometry: TiltSeriesGeometry):
        super().__init__()
        if not isinstance(domain, ImageDomain) or domain.ndim != 3:
            raise ValueError(f"domain must be a 3D ImageDomain (nx, ny, nz), got {domain!r}")
        if not isinstance(geometry, TiltSeriesGeometry):
            raise TypeError(f"geometry must be a TiltSeriesGeometry, got {type(geometry).__name__}")
        self.domain = domain
        self.slice_transform = RayTransform(geometry.slice_domain(domain), geometry.slice_geometry)
        self.geometry = geometry.resolve(domain)

    def on_rows(self, domain: ImageDomain) -> "TiltSeriesTransform":
        """The same transform on ``domain``, a volume of the same slices (the same cells across the tilt axis) and any
        number of them along it: its slice transform, and so its system matrix, shared (not built again)."""
        u, v = self.geometry.slice_axes
        if not isinstance(domain, ImageDomain) or domain.ndim != 3 or \
                self.geometry.slice_domain(domain) != self.geometry.slice_domain(self.domain):
            raise ValueError(f"on_rows needs a 3D domain with the slices of {self.domain} (axes "
                             f"{AXES[u]}, {AXES[v]}), got {domain!r}")
        new = type(self).__new__(type(self))
        nn.Module.__init__(new)
        new.domain, new.slice_transform, new.geometry = domain, self.slice_transform, self.geometry.resolve(domain)
        return new

    def on_domain(self, domain: ImageDomain) -> "TiltSeriesTransform":
        """The same tilts and detector columns (extent included) on another grid of the volume, e.g. a coarser one
        for coarse-to-fine solvers; the detector rows follow the grid along the tilt axis (one row per slice)."""
        return TiltSeriesTransform(domain, self.geometry)

    @property
    def system(self):
        """The 2D system matrix shared by all slices."""
        return self.slice_transform.system

    def _check_dtype(self, x, name):
        self.slice_transform._check_dtype(x, name)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        """``T f``: volumes ``(..., nx, ny, nz)`` -> data ``(..., num_tilts, det_rows, det_cols)``."""
        return self._slices(self.domain.check_image(f, "volume"))

    def project_rows(self, f: torch.Tensor) -> torch.Tensor:
        """``T`` of consecutive slices: ``f`` ``(..., nx, ny, nz)`` with the tilt axis cut to any ``k`` slices ->
        their detector rows ``(..., num_tilts, k, det_cols)``: the same values as those rows of ``T`` of the whole
        volume (e.g. one process's share of a simulated tilt series)."""
        u, v = self.geometry.slice_axes
        shape = self.domain.shape
        if not (isinstance(f, torch.Tensor) and f.dim() >= 3 and f.shape[f.dim() - 3 + u] == shape[u]
                and f.shape[f.dim() - 3 + v] == shape[v] and f.shape[f.dim() - 3 + self.geometry.axis] >= 1):
            raise ValueError(f"volume rows must be a tensor (..., nx, ny, nz) of {shape} with any number of slices "
                             f"along the tilt axis {AXES[self.geometry.axis]}, got "
                             f"{tuple(f.shape) if isinstance(f, torch.Tensor) else type(f).__name__}")
        return self._slices(f)

    def _slices(self, f: torch.Tensor) -> torch.Tensor:
        self._check_dtype(f, "volume")
        slices = f.movedim(f.dim() - 3 + self.geometry.axis, -3)           # (..., n_t, n_u, n_v)
        batch = slices.shape[:-2]
        width = slices.shape[-2] * slices.shape[-1]
        chunk = max(1, COPY_CHUNK_BYTES // (width * f.element_size()))
        if f.dim() == 3 and slices.shape[0] > chunk and not _viewable(slices, width):
            # the slices are not rows of f's memory (a tilt axis other than x): copied a chunk at a time, not whole
            out = torch.cat([_Project.apply(slices[i:i + chunk].reshape(-1, width), self.system)
                             for i in range(0, slices.shape[0], chunk)])
        else:
            out = _Project.apply(slices.reshape(-1, width), self.system)
        return out.reshape(*batch, self.geometry.num_tilts, self.geometry.det_count).movedim(-3, -2)

    def A(self, f: torch.Tensor) -> torch.Tensor:
        """The forward operator ``T f`` (same as calling the module)."""
        return self(f)

    def transpose(self, y: torch.Tensor) -> torch.Tensor:
        """Exact matrix transpose ``A^T y`` slice by slice: data -> volumes ``(..., nx, ny, nz)``."""
        y = check_tensor(y, "data", self.range_shape)
        self._check_dtype(y, "data")
        rows = y.movedim(-2, -3)                                          # (..., n_t, tilts, cols)
        batch = rows.shape[:-2]
        out = _Backproject.apply(rows.reshape(-1, rows.shape[-2] * rows.shape[-1]), self.system)
        u, v = self.geometry.slice_axes
        out = out.reshape(*batch, self.domain.shape[u], self.domain.shape[v])
        return out.movedim(-3, out.dim() - 3 + self.geometry.axis)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """L2 adjoint ``T^* y = (data_weight / cell_volume) A^T y`` (backprojection)."""
        return self.adjoint_scale * self.transpose(y)

    def A_adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """deepinv's ``A_adjoint``: the adjoint for plain sums, i.e. ``transpose``."""
        return self.transpose(y)

    def extra_repr(self) -> str:
        return f"domain={self.domain}, geometry={self.geometry}, nnz per slice={self.system.nnz}"
