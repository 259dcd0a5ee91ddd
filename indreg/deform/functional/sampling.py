"""Bilinear / trilinear interpolation: ``grid_sample`` grids, ``sample``, ``warp`` and their transposes.

Convention:
    - Images ``(..., C, *shape)`` / ``(..., *shape)``, ``shape = (nx, ny)`` or ``(nx, ny, nz)``; vector fields
      ``(..., d, *shape)`` (component 0 = x, 1 = y[, 2 = z]). ``grid_sample`` grids ``(..., *shape, d)`` list
      the coordinates in reverse order (``[..., 0]`` = y, ``[..., 1]`` = x in 2D; ``[..., 0]`` = z,
      ``[..., 1]`` = y, ``[..., 2]`` = x in 3D), in grid units: ``2 / extent`` times physical lengths.
    - Interpolation is bilinear (2D) / trilinear (3D) (``grid_sample``, ``align_corners=False``: grid
      coordinates -1 and 1 are the domain's edges, so pixel centres sit exactly at the cell centres of
      ``ImageDomain``); its exact adjoint is ``grid_sampler_2d_backward`` / ``grid_sampler_3d_backward``.
      Padding: ``"zeros"`` for images and transported gradients (the image is 0 outside the domain),
      ``"border"`` for Jacobian determinants and displacement fields (continued constantly).
"""
from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

from ...domain import ImageDomain

_PADDING = {"zeros": 0, "border": 1}


def _grid_units(domain: ImageDomain, dtype, device) -> torch.Tensor:
    """Factors ``2 / extent`` (x, y[, z]) turning physical displacements into grid_sample units, ``(d, 1, .., 1)``."""
    return torch.tensor([2.0 / e for e in domain.extent], dtype=dtype, device=device).view(-1, *(1,) * domain.ndim)


def to_grid_units(v: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """A displacement / velocity field ``(..., d, *shape)`` in physical units expressed in grid units."""
    return v * _grid_units(domain, v.dtype, v.device)


def identity_grid(domain: ImageDomain, dtype=torch.float64, device=None) -> torch.Tensor:
    """The cell centres in ``grid_sample`` coordinates, ``(*shape, d)`` in reversed order: ``[..., 0]`` = y,
    ``[..., 1]`` = x (2D); ``[..., 0]`` = z, ``[..., 1]`` = y, ``[..., 2]`` = x (3D)."""
    device = torch.device("cpu") if device is None else torch.device(device)
    return _identity_grid(domain, dtype, device)


@functools.lru_cache(maxsize=32)
def _identity_grid(domain, dtype, device):
    return domain.to_grid(domain.points(dtype, device).movedim(0, -1))


def displaced_grid(w: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """``grid_sample`` grid ``(..., *shape, d)`` of the points ``x + w(x)``, ``w (..., d, *shape)`` in grid units."""
    return identity_grid(domain, w.dtype, w.device) + w.movedim(-domain.ndim - 1, -1).flip(-1)


def sample(f: torch.Tensor, grid: torch.Tensor, padding_mode: str = "zeros") -> torch.Tensor:
    """Bilinear (2D) / trilinear (3D) interpolation of ``f (..., C, *shape)`` at ``grid (..., *out_shape, d)``
    (same batch dims; d = ``grid.shape[-1]``, 2 or 3).

    Returns ``(..., C, *out_shape)``. Adjoint (what autograd uses): a scatter of the incoming values with the
    interpolation weights. ``grid_sample`` parallelises over the batch only; a single image on a CPU with ``k``
    threads is sampled as ``k`` bands of output rows (along x; the image expanded, not copied): the same
    values, ``k`` threads at work (at 256^2 with 2 threads: 2x faster forward, 1.7x backward).
    """
    d = grid.shape[-1]
    batch, (c, *shape), out_shape = f.shape[:-d - 1], f.shape[-d - 1:], grid.shape[-d - 1:-1]
    f, grid = f.reshape(-1, c, *shape), grid.reshape(-1, *out_shape, d)
    bands = _bands(f, *out_shape)
    if bands > 1:
        f, grid = f.expand(bands, c, *shape), grid.reshape(bands, out_shape[0] // bands, *out_shape[1:], d)
    out = F.grid_sample(f, grid, mode="bilinear", padding_mode=padding_mode, align_corners=False)
    return out.reshape(*batch, c, *out_shape)


def _bands(f: torch.Tensor, *out_shape: int) -> int:
    """Number of row bands (along x) for ``sample``: the CPU thread count for one single-channel image whose
    row count it divides, with at least 8192 output pixels per band (measured: smaller bands lose to the
    thread overhead, 96^2 with 2 threads 28 vs 25 us; 128^2 wins, 28 vs 44 us), else 1 (banding a batch or
    several channels would copy the grid or the output)."""
    threads = torch.get_num_threads()
    if f.device.type != "cpu" or f.shape[0] != 1 or f.shape[1] != 1 or threads < 2 or out_shape[0] % threads \
            or math.prod(out_shape) < 8192 * threads:
        return 1
    return threads


def warp(f: torch.Tensor, points: torch.Tensor, domain: ImageDomain, padding_mode: str = "zeros") -> torch.Tensor:
    """``f o points``: interpolation of the image ``f (..., *shape)`` at ``points (..., d, *out_shape)``.

    ``points`` are physical coordinates (component 0 = x, 1 = y[, 2 = z]); batch dims of ``f`` and ``points``
    broadcast. Outside the domain ``f`` is 0 (``padding_mode="zeros"``) or continued from its border
    (``"border"``). Returns ``(..., *out_shape)``.
    """
    d = domain.ndim
    batch = torch.broadcast_shapes(f.shape[:-d], points.shape[:-d - 1])
    f = f.expand(*batch, *f.shape[-d:])
    grid = domain.to_grid(points.expand(*batch, *points.shape[-d - 1:]).movedim(-d - 1, -1))
    return sample(f.unsqueeze(-d - 1), grid, padding_mode).squeeze(-d - 1)


@functools.lru_cache(maxsize=32)
def _planar_identity_grid(domain, dtype, device):
    return _identity_grid(domain, dtype, device).movedim(-1, 0).contiguous()


def _sample_displaced(f: torch.Tensor, u: torch.Tensor, domain: ImageDomain, padding_mode: str) -> torch.Tensor:
    """``f o (Id + u)``, skipping the interpolation when ``u`` is exactly zero and no graph is recorded."""
    k = domain.ndim + 1
    if not (torch.is_grad_enabled() and u.requires_grad) and not bool(u.ne(0).any()):
        return f.expand(*u.shape[:-k], *f.shape[-k:])
    return sample(f.expand(*u.shape[:-k], *f.shape[-k:]), displaced_grid(u, domain), padding_mode)


def _sample_adjoint(grad: torch.Tensor, f: torch.Tensor, grid: torch.Tensor, padding_mode: str,
                    need_input: bool, need_grid: bool) -> tuple:
    """The two transposes of ``sample(f, grid, padding_mode)`` applied to ``grad (..., C, *shape)``, in one pass:
    ``(S^T grad, d<grad, S(f)>/d grid)``, i.e. the scatter of ``grad`` with the interpolation weights
    ``(..., C, *shape)`` and the grid gradient ``(..., *shape, d)`` (reversed order: ``[..., 0]`` = y,
    ``[..., 1]`` = x in 2D, ``[..., 0]`` = z, ``[..., 1]`` = y, ``[..., 2]`` = x in 3D; grid units: the one-sided
    slope of ``f`` across the cell each point falls in). Either is None when not needed.
    ``grid_sampler_2d_backward`` / ``grid_sampler_3d_backward`` parallelise over the batch only: a single
    image on a CPU with ``k`` threads is done as ``k`` bands of rows (as ``sample``), whose ``k`` scatters are
    summed (the same values up to the order of the sums)."""
    d = grid.shape[-1]
    batch, (c, *shape) = grad.shape[:-d - 1], grad.shape[-d - 1:]
    if not (need_input or need_grid):
        return None, None
    grad, f = grad.reshape(-1, c, *shape), f.expand(*batch, c, *shape).reshape(-1, c, *shape)
    grid, bands = grid.expand(*batch, *shape, d).reshape(-1, *shape, d), _bands(grad, *shape)
    if bands > 1:
        grad, f, grid = grad.reshape(bands, c, shape[0] // bands, *shape[1:]), f.expand(bands, c, *shape), \
            grid.reshape(bands, shape[0] // bands, *shape[1:], d)
    backward = torch.ops.aten.grid_sampler_2d_backward if d == 2 else torch.ops.aten.grid_sampler_3d_backward
    gi, gg = backward(grad, f, grid, 0, _PADDING[padding_mode], False, [need_input, need_grid])
    if need_input and bands > 1:
        gi = gi.sum(0)
    return (gi.reshape(*batch, c, *shape) if need_input else None), \
        (gg.reshape(*batch, *shape, d) if need_grid else None)
