"""Grids of one box at other resolutions, in space and in time: cell averages to a coarser grid (``restrict``),
piecewise-constant values on a finer one (``prolong``), a time-dependent field on another time grid
(``resample_time``). Used by the coarse levels of a problem (``IndirectRegistration.coarsened``) and by the
coarse-to-fine solver (``indreg.solvers.MultilevelSolver``).

Notes
-----
images ``(..., *shape)`` with the last ``len(shape)`` axes the grid (2D or 3D); time-dependent fields
``(N+1, ...)`` at ``t_i = i / N``.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["resample_time", "restrict", "prolong"]


def resample_time(m: torch.Tensor, num_steps: int) -> torch.Tensor:
    """``m (N+1, ...)`` at ``t_i = i/N`` linearly interpolated to ``t_j = j/num_steps``, ``(num_steps+1, ...)``."""
    n_old = m.shape[0] - 1
    if n_old == num_steps:
        return m
    t = torch.arange(num_steps + 1, dtype=torch.float64) * (n_old / num_steps)
    i0 = t.floor().long().clamp(max=n_old - 1)
    w = (t - i0).to(m.dtype).to(m.device).view(-1, *([1] * (m.dim() - 1)))
    i0 = i0.to(m.device)
    return torch.lerp(m[i0], m[i0 + 1], w)


def restrict(f: torch.Tensor, shape: tuple) -> torch.Tensor:
    """Cell averages of ``f (..., *fine)`` over the cells of a coarser grid ``shape`` of the same box (2D or 3D:
    the last ``len(shape)`` axes)."""
    d = len(shape)
    if tuple(f.shape[-d:]) == tuple(shape):
        return f
    lead = f.shape[:-d]
    pool = F.adaptive_avg_pool2d if d == 2 else F.adaptive_avg_pool3d
    return pool(f.reshape(-1, 1, *f.shape[-d:]), shape).reshape(*lead, *shape)


def prolong(f: torch.Tensor, shape: tuple) -> torch.Tensor:
    """``f (..., *coarse)`` as a piecewise-constant density on the finer grid ``shape`` (each coarse cell's value
    on the fine cells it covers): ``K`` of the result is ``K`` of ``f`` up to the quadrature error of the
    finer Riemann sum, and ``restrict`` inverts it for integer factors."""
    d = len(shape)
    if tuple(f.shape[-d:]) == tuple(shape):
        return f
    lead = f.shape[:-d]
    out = F.interpolate(f.reshape(-1, 1, *f.shape[-d:]), size=tuple(shape), mode="nearest-exact")
    return out.reshape(*lead, *shape)
