"""The image domain: a physical rectangle (2D) or box (3D) sampled at cell centres, with L2 inner products."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ._checks import check_int, check_number, check_tensor

if TYPE_CHECKING:   # imported where used: the app's preflight reads a domain without loading torch
    import torch


AXES = "xyz"


def _corner(point, name: str, ndim: int) -> tuple:
    """A corner of the box as ``ndim`` finite floats (an infinite extent has no cells to sample)."""
    try:
        if isinstance(point, (str, bytes)):
            raise TypeError
        values = tuple(check_number(v, name) for v in point)
    except TypeError:
        raise TypeError(f"{name} must be {ndim} finite numbers ({', '.join(AXES[:ndim])}), got {point!r}") from None
    if len(values) != ndim:
        raise ValueError(f"{name} must have {ndim} entries ({', '.join(AXES[:ndim])}) like shape, got {point!r}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be finite, got {point!r}")
    return values


@dataclass(frozen=True)
class ImageDomain:
    """A box ``[min_pt, max_pt]`` in R^d (d = 2 or 3) discretised by ``shape`` cells, sampled at cell centres.

    Parameters
    ----------
    shape : int or tuple of int
        Cells per axis, ``(nx, ny)`` or ``(nx, ny, nz)`` (each >= 1); one integer ``n`` means ``(n, n)``.
    min_pt, max_pt : tuple of float, optional
        The box's corners, d finite entries each, ``min_pt < max_pt`` on every axis; default
        ``(-16, ..., -16)`` and ``(16, ..., 16)``.

    Raises
    ------
    TypeError
        A shape or corner that is not numbers (a string, None entries).
    ValueError
        Not 2 or 3 axes, a count < 1, corners of another length, non-finite, or ``min_pt >= max_pt``.

    Notes
    -----
    - d = ``len(shape)``. An image is a tensor ``(..., nx, ny)`` (2D) or ``(..., nx, ny, nz)`` (3D): array
      axis 0 is x, axis 1 is y, axis 2 is z ("ij" indexing), any leading batch dims.
    - Cell ``(i, j[, k])`` sits at the cell centre
      ``x_i = min_pt[0] + (i + 1/2) * cell_sides[0]``, ``y_j = min_pt[1] + (j + 1/2) * cell_sides[1]``, ...
    - ``min_pt < max_pt`` are finite corners with d entries and a finite extent; default ``(-16, ..., -16)``
      and ``(16, ..., 16)``.
    - Units are physical (the paper's domain is ``[-16, 16]^2``), so the paper's kernel width sigma,
      regularisation gamma and step size mean the same at every resolution.
    - Inner products and norms are L2: ``<f, g> = cell_volume * sum f g`` over the last d axes, so adjoints
      of operators defined on this domain are L2 adjoints.

    Examples
    --------
    >>> dom = ImageDomain((64, 64), (-16.0, -16.0), (16.0, 16.0))
    >>> dom.cell_volume
    0.25
    >>> ImageDomain((32, 32, 32)).cell_volume
    1.0
    """

    shape: tuple
    min_pt: tuple | None = None
    max_pt: tuple | None = None

    def __post_init__(self):
        if isinstance(self.shape, (str, bytes)):
            raise TypeError(f"shape must be 2 or 3 integers (nx, ny[, nz]), got {self.shape!r}")
        shape = tuple(self.shape) if hasattr(self.shape, "__len__") else (self.shape, self.shape)
        if len(shape) not in (2, 3):
            raise ValueError(f"shape must have 2 entries (nx, ny) or 3 (nx, ny, nz), got {self.shape!r}")
        shape = tuple(check_int(n, "shape entry", 1) for n in shape)
        d = len(shape)
        lo = _corner((-16.0,) * d if self.min_pt is None else self.min_pt, "min_pt", d)
        hi = _corner((16.0,) * d if self.max_pt is None else self.max_pt, "max_pt", d)
        for a, b, ax in zip(lo, hi, AXES):
            if not b > a:
                raise ValueError(f"min_pt must be < max_pt on axis {ax}, got {a} >= {b}")
            if not math.isfinite(b - a):
                raise ValueError(f"max_pt - min_pt must be finite, overflows on axis {ax}: {b} - {a}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "min_pt", lo)
        object.__setattr__(self, "max_pt", hi)

    @classmethod
    def paper(cls, n: int, ndim: int = 2) -> "ImageDomain":
        """The paper's domain ``[-16, 16]^d`` with ``n`` cells per axis."""
        return cls((n,) * ndim, (-16.0,) * ndim, (16.0,) * ndim)

    @property
    def ndim(self) -> int:
        """The dimension d (2 or 3)."""
        return len(self.shape)

    @property
    def dims(self) -> tuple:
        """The image axes of a tensor ``(..., *shape)``: ``(-2, -1)`` or ``(-3, -2, -1)``."""
        return tuple(range(-self.ndim, 0))

    @property
    def extent(self) -> tuple:
        """Side lengths ``(max_pt - min_pt)`` per axis."""
        return tuple(b - a for a, b in zip(self.min_pt, self.max_pt))

    @property
    def cell_sides(self) -> tuple:
        """Cell side lengths ``(hx, hy[, hz])`` in physical units."""
        return tuple(e / n for e, n in zip(self.extent, self.shape))

    @property
    def cell_volume(self) -> float:
        """Cell area ``hx * hy`` (2D) or volume ``hx * hy * hz`` (3D): the weight of the L2 inner product."""
        return math.prod(self.cell_sides)

    def axes(self, dtype=None, device=None) -> tuple:
        """Cell-centre coordinates ``(x, y[, z])``, 1D tensors of lengths ``nx``, ``ny``[, ``nz``] (``dtype`` None:
        float64)."""
        import torch

        dtype = torch.float64 if dtype is None else dtype
        return tuple(
            a + (torch.arange(n, dtype=dtype, device=device) + 0.5) * h
            for a, n, h in zip(self.min_pt, self.shape, self.cell_sides))

    def points(self, dtype=None, device=None) -> torch.Tensor:
        """Cell centres as a tensor ``(d, *shape)``: ``[0]`` holds x, ``[1]`` holds y, ``[2]`` holds z (``dtype``
        None: float64)."""
        import torch

        return torch.stack(torch.meshgrid(*self.axes(dtype, device), indexing="ij"))

    def zeros(self, *batch, dtype=None, device=None) -> torch.Tensor:
        """An all-zero image ``(*batch, *shape)`` (``dtype`` None: float64)."""
        import torch

        return torch.zeros(*batch, *self.shape, dtype=torch.float64 if dtype is None else dtype, device=device)

    def check_image(self, f, name: str = "image") -> torch.Tensor:
        """Validate an image ``(..., *shape)``: floating dtype, finite values, this domain's shape."""
        return check_tensor(f, name, self.shape)

    def inner(self, f: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """L2 inner product over the last d axes, ``cell_volume * sum(f * g)``; batch dims kept."""
        return self.cell_volume * (f * g).sum(dim=self.dims)

    def norm(self, f: torch.Tensor) -> torch.Tensor:
        """L2 norm over the last d axes."""
        return self.inner(f, f).sqrt()

    def to_grid(self, x: torch.Tensor) -> torch.Tensor:
        """Map physical points ``(..., d)`` (x, y[, z]) to ``grid_sample`` coordinates (``align_corners=False``).

        ``grid_sample`` on a tensor ``(..., *shape)`` reads ``grid[..., 0]`` along the last axis, ``grid[..., 1]``
        along the one before, ... (the reverse of (x, y, z)), all normalised so that -1 and 1 are the edges.
        """
        import torch

        lo = torch.tensor(self.min_pt, dtype=x.dtype, device=x.device)
        ext = torch.tensor(self.extent, dtype=x.dtype, device=x.device)
        u = 2.0 * (x - lo) / ext - 1.0
        return u.flip(-1)
