"""The image domain: a physical rectangle sampled at cell centres, with L2 inner products."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ._checks import check_int, check_tensor


def _corner(point, name: str) -> tuple:
    """A corner ``(x, y)`` of the rectangle as 2 finite floats (an infinite extent has no cells to sample)."""
    try:
        values = tuple(float(v) for v in point)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be 2 finite numbers (x, y), got {point!r}") from None
    if len(values) != 2:
        raise ValueError(f"{name} must have 2 entries (x, y), got {point!r}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be finite, got {point!r}")
    return values


@dataclass(frozen=True)
class ImageDomain:
    """A rectangle ``[min_pt, max_pt]`` in R^2 discretised by ``shape`` cells, sampled at cell centres.

    Convention:
        - An image is a tensor ``(..., nx, ny)``: array axis 0 is x, axis 1 is y ("ij" indexing),
          any leading batch dims.
        - Pixel ``(i, j)`` sits at the cell centre
          ``x_i = min_pt[0] + (i + 1/2) * cell_sides[0]``, ``y_j = min_pt[1] + (j + 1/2) * cell_sides[1]``.
        - ``min_pt < max_pt`` are finite corners ``(x, y)`` with a finite extent.
        - Units are physical (the paper's domain is ``[-16, 16]^2``), so the paper's kernel width sigma,
          regularisation gamma and step size mean the same at every resolution.
        - Inner products and norms are L2: ``<f, g> = cell_volume * sum_ij f_ij g_ij``, so adjoints of
          operators defined on this domain are L2 adjoints.

    Example:
        >>> dom = ImageDomain((64, 64), (-16.0, -16.0), (16.0, 16.0))
        >>> dom.cell_volume
        0.25
    """

    shape: tuple
    min_pt: tuple = (-16.0, -16.0)
    max_pt: tuple = (16.0, 16.0)

    def __post_init__(self):
        shape = tuple(self.shape) if hasattr(self.shape, "__len__") else (self.shape, self.shape)
        if len(shape) != 2:
            raise ValueError(f"shape must have 2 entries (nx, ny), got {self.shape!r}")
        shape = tuple(check_int(n, "shape entry", 1) for n in shape)
        lo, hi = _corner(self.min_pt, "min_pt"), _corner(self.max_pt, "max_pt")
        for a, b, ax in zip(lo, hi, "xy"):
            if not b > a:
                raise ValueError(f"min_pt must be < max_pt on axis {ax}, got {a} >= {b}")
            if not math.isfinite(b - a):
                raise ValueError(f"max_pt - min_pt must be finite, overflows on axis {ax}: {b} - {a}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "min_pt", lo)
        object.__setattr__(self, "max_pt", hi)

    @classmethod
    def paper(cls, n: int) -> "ImageDomain":
        """The paper's domain ``[-16, 16]^2`` with ``n x n`` pixels."""
        return cls((n, n), (-16.0, -16.0), (16.0, 16.0))

    @property
    def extent(self) -> tuple:
        """Side lengths ``(max_pt - min_pt)`` per axis."""
        return tuple(b - a for a, b in zip(self.min_pt, self.max_pt))

    @property
    def cell_sides(self) -> tuple:
        """Pixel side lengths ``(hx, hy)`` in physical units."""
        return tuple(e / n for e, n in zip(self.extent, self.shape))

    @property
    def cell_volume(self) -> float:
        """Pixel area ``hx * hy``: the weight of the L2 inner product."""
        hx, hy = self.cell_sides
        return hx * hy

    def axes(self, dtype=torch.float64, device=None) -> tuple:
        """Cell-centre coordinates ``(x, y)``, 1D tensors of lengths ``nx`` and ``ny``."""
        return tuple(
            a + (torch.arange(n, dtype=dtype, device=device) + 0.5) * h
            for a, n, h in zip(self.min_pt, self.shape, self.cell_sides))

    def points(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """Cell centres as a tensor ``(2, nx, ny)``: ``[0]`` holds x, ``[1]`` holds y."""
        x, y = self.axes(dtype, device)
        return torch.stack(torch.meshgrid(x, y, indexing="ij"))

    def zeros(self, *batch, dtype=torch.float64, device=None) -> torch.Tensor:
        """An all-zero image ``(*batch, nx, ny)``."""
        return torch.zeros(*batch, *self.shape, dtype=dtype, device=device)

    def check_image(self, f, name: str = "image") -> torch.Tensor:
        """Validate an image ``(..., nx, ny)``: floating dtype, finite values, this domain's shape."""
        return check_tensor(f, name, self.shape)

    def inner(self, f: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """L2 inner product over the last two axes, ``cell_volume * sum(f * g)``; batch dims kept."""
        return self.cell_volume * (f * g).sum(dim=(-2, -1))

    def norm(self, f: torch.Tensor) -> torch.Tensor:
        """L2 norm over the last two axes."""
        return self.inner(f, f).sqrt()

    def to_grid(self, x: torch.Tensor) -> torch.Tensor:
        """Map physical points ``(..., 2)`` (x, y) to ``grid_sample`` coordinates (``align_corners=False``).

        ``grid_sample`` on a tensor ``(..., nx, ny)`` reads ``grid[..., 0]`` along the last axis (y) and
        ``grid[..., 1]`` along axis -2 (x), both normalised so that -1 and 1 are the domain's edges.
        """
        lo = torch.tensor(self.min_pt, dtype=x.dtype, device=x.device)
        ext = torch.tensor(self.extent, dtype=x.dtype, device=x.device)
        u = 2.0 * (x - lo) / ext - 1.0
        return u.flip(-1)
