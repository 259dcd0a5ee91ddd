"""Bilinear / trilinear interpolation: ``grid_sample`` grids, ``sample``, ``warp`` and their transposes.

Notes
-----
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

from ..._checks import broadcast_shapes
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
    interpolation weights. In 3D on a CPU with one thread and the output on the input's grid, points displaced
    by at most a cell along x are sampled plane by plane (``_planewise_sample``; else ``grid_sample``).
    ``grid_sample`` parallelises over the batch only; a single image on a CPU with ``k``
    threads is sampled as ``k`` bands of output rows (along x; the image expanded, not copied): the same
    values, ``k`` threads at work (at 256^2 with 2 threads: 2x faster forward, 1.7x backward).
    """
    d = grid.shape[-1]
    batch, (c, *shape), out_shape = f.shape[:-d - 1], f.shape[-d - 1:], grid.shape[-d - 1:-1]
    f, grid = f.reshape(-1, c, *shape), grid.reshape(-1, *out_shape, d)
    if _planewise_applies(f, grid):
        return _PlanewiseSample.apply(f, grid, padding_mode).reshape(*batch, c, *out_shape)
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
    batch = broadcast_shapes(f.shape[:-d], points.shape[:-d - 1])
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
    slope of ``f`` across the cell each point falls in). Either is None when not needed. ``f (..., C, *in_shape)``
    may be on another grid than ``grad`` (e.g. the whole template for a slab's points).
    ``grid_sampler_2d_backward`` / ``grid_sampler_3d_backward`` parallelise over the batch only: a single
    image on a CPU with ``k`` threads is done as ``k`` bands of rows (as ``sample``), whose ``k`` scatters are
    summed (the same values up to the order of the sums)."""
    d = grid.shape[-1]
    batch, (c, *shape) = grad.shape[:-d - 1], grad.shape[-d - 1:]
    if not (need_input or need_grid):
        return None, None
    f_shape = f.shape[-d:]
    grad, f = grad.reshape(-1, c, *shape), f.expand(*batch, c, *f_shape).reshape(-1, c, *f_shape)
    grid, bands = grid.expand(*batch, *shape, d).reshape(-1, *shape, d), _bands(grad, *shape)
    if bands > 1:
        grad, f, grid = grad.reshape(bands, c, shape[0] // bands, *shape[1:]), f.expand(bands, c, *f_shape), \
            grid.reshape(bands, shape[0] // bands, *shape[1:], d)
    backward = torch.ops.aten.grid_sampler_2d_backward if d == 2 else torch.ops.aten.grid_sampler_3d_backward
    gi, gg = backward(grad, f, grid, 0, _PADDING[padding_mode], False, [need_input, need_grid])
    if need_input and bands > 1:
        gi = gi.sum(0)
    return (gi.reshape(*batch, c, *f_shape) if need_input else None), \
        (gg.reshape(*batch, *shape, d) if need_grid else None)



# ----------------------------------------------------------------------------------------------------------
# trilinear interpolation plane by plane: linear along x of bilinear interpolations in the (y, z) planes
def _planewise_applies(f: torch.Tensor, grid: torch.Tensor) -> bool:
    """Whether ``sample`` tries ``_planewise_sample``: 3D on a CPU with one thread, the output's planes along x
    those of the input (``grid (B, nx, *out, 3)`` for ``f (B, C, nx, ny, nz)``: the whole grid, or a slab across
    y or z, ``indreg.problems.slabs``).

    Measured (``scripts/bench_sampler.py``, median CPU ms, float32, one channel, points up to 0.75 cells away):
    1 thread, 64^3 8.3 (3D ``grid_sample``, a scalar loop) vs 6.0 (plane-wise: its 2D kernel is vectorised),
    128^3 66.8 vs 40.1 (1.7x). With 2 threads ``sample``'s row bands of the 3D kernel won (128^3: 64-69 vs
    124-128 CPU ms, 190 vs 355 ms wall), hence one thread only. In 2D ``grid_sample`` is already vectorised;
    on a GPU its kernels are parallel (not measured here): both keep ``grid_sample``. Where a point moves more
    than a cell along x (large velocity steps: the 3D tilt-series benchmark reaches 3 cells per step at
    N = 10) the check costs one pass (``aminmax``) and ``grid_sample`` runs."""
    return grid.shape[-1] == 3 and f.device.type == "cpu" and f.shape[-3] == grid.shape[-4] \
        and torch.get_num_threads() == 1


def _planewise_sample(f: torch.Tensor, grid: torch.Tensor, padding_mode: str,
                      padded: torch.Tensor | None = None) -> torch.Tensor | None:
    """``grid_sample(f, grid, "bilinear", padding_mode, align_corners=False)`` for ``f (B, C, nx, ny, nz)`` and
    ``grid (B, nx, my, mz, 3)``, or None when some point lies more than a cell along x from its own plane.

    The point of output node ``(i, j, k)`` has the pixel coordinate ``x = ((g_x + 1) nx - 1) / 2`` along x
    (``"border"``: clamped to ``[0, nx-1]``, ``grid_sample``'s clipping). If ``s = x - i`` lies in ``[-1, 1]``,
    linear interpolation along x is the 3-point stencil ``relu(-s) f[i-1] + (1 - |s|) f[i] + relu(s) f[i+1]``
    (the hat functions: the two weights of the cell ``x`` falls in and a 0), so the trilinear value is that
    stencil applied to the bilinear interpolations, at the point's ``(y, z)``, of the planes ``i-1, i, i+1``
    (zero planes beyond the domain; ``"border"`` never weights them). Those are one batched 2D
    ``grid_sample`` (vectorised on a CPU): batch ``i``, channels the three planes (a strided view, no copy
    but the x padding). The same values as the 3D ``grid_sample`` up to rounding. ``padded``: ``f`` with a zero
    plane before and after along x, ``(B, C, nx+2, ny, nz)``, where the caller keeps one (no copy per call: the
    slabs of ``indreg.problems.slabs`` sample one template many times).
    """
    _, c, nx, ny, nz = f.shape
    g = grid[..., 2]
    node = torch.arange(nx, dtype=g.dtype, device=g.device).view(-1, 1, 1)
    if padding_mode == "zeros":
        s = torch.add((nx - 1) / 2 - node, g, alpha=nx / 2)
    else:
        s = torch.mul(g, nx / 2).add_((nx - 1) / 2).clamp_(0, nx - 1).sub_(node)
    low, high = torch.aminmax(s)
    if not (low >= -1 and high <= 1):
        return None
    behind, ahead = s.clamp(max=0).neg_().unsqueeze(-3), s.clamp(min=0).unsqueeze(-3)
    weights = (behind, torch.rsub(behind, 1).sub_(ahead), ahead)  # (B, nx, 1, ny, nz)
    out = f.new_empty((*f.shape[:-2], *grid.shape[-3:-1]))
    for b in range(f.shape[0]):
        fb = F.pad(f[b], (0, 0, 0, 0, 1, 1)) if padded is None else padded[b]
        fb = fb.movedim(0, 1).contiguous()  # (nx+2, C, ny, nz): no copy for C = 1
        planes = fb.as_strided((nx, 3 * c, ny, nz), (c * ny * nz, ny * nz, nz, 1))
        bilinear = F.grid_sample(planes, grid[b, ..., :2], mode="bilinear", padding_mode=padding_mode,
                                 align_corners=False).unflatten(1, (3, c))  # (nx, 3, C, ny, nz)
        target = out[b].movedim(0, 1)
        torch.mul(bilinear[:, 0], weights[0][b], out=target)
        target.addcmul_(bilinear[:, 1], weights[1][b]).addcmul_(bilinear[:, 2], weights[2][b])
    return out


class _PlanewiseSample(torch.autograd.Function):
    """``sample`` of ``f (B, C, nx, ny, nz)`` at ``grid (B, nx, ny, nz, 3)`` by ``_planewise_sample``
    (``grid_sample`` where it does not apply), with ``_sample_adjoint`` as backward. A backward that records a
    graph (double backward) differentiates ``grid_sample`` instead: the same derivative, differentiable again."""

    @staticmethod
    def forward(ctx, f, grid, padding_mode):
        ctx.save_for_backward(f, grid)
        ctx.padding_mode = padding_mode
        out = _planewise_sample(f, grid, padding_mode)
        if out is None:
            out = F.grid_sample(f, grid, mode="bilinear", padding_mode=padding_mode, align_corners=False)
        return out

    @staticmethod
    def backward(ctx, grad):
        f, grid = ctx.saved_tensors
        need = ctx.needs_input_grad[:2]
        if torch.is_grad_enabled():
            inputs = [t for t, n in zip((f, grid), need) if n]
            out = F.grid_sample(f, grid, mode="bilinear", padding_mode=ctx.padding_mode, align_corners=False)
            grads = iter(torch.autograd.grad(out, inputs, grad, create_graph=True))
            return (*(next(grads) if n else None for n in need), None)
        return (*_sample_adjoint(grad, f, grid, ctx.padding_mode, *need), None)
