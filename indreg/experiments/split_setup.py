"""A simulated tilt series built over the ranks of a process group: each rank evaluates its share of the phantoms'
slices along the tilt axis and projects them; the shares are then gathered.

Every rank needs the whole template (a displacement may carry a slab's points anywhere in it) and the whole data
(the units and the relative weights are computed from it, and rank 0 writes it), so both are assembled by an
``all_gather``; the target only rank 0 uses (the figures of merit), so it is gathered there. The noise is then drawn
on every rank from the whole noise-free data, as one process draws it: the same data, the same noise.

Convention: volumes ``(nx, ny, nz)`` and data ``(num_tilts, det_rows, det_cols)`` float64 on the CPU; a rank's
share is the contiguous range ``[start, stop)`` of the tilt axis' slices (``indreg.ranks.rank_rows``: the first
``n % world`` ranks one more), and data row ``j`` is slice ``j``; the shares are joined by ``indreg.ranks``.
"""
from __future__ import annotations

import torch.distributed as dist

from .. import phantoms
from ..ranks import all_gather_rows, gather_rows, rank_rows
from ..forward.tilt_series import TiltSeriesTransform

__all__ = ["row_range", "counts", "simulated_rows", "splits"]


def row_range(n: int, group) -> tuple:
    """``(start, stop)``: this rank's contiguous share of ``n`` slices."""
    return rank_rows(n, dist.get_rank(group), dist.get_world_size(group))


def splits(T, group) -> bool:
    """Whether a simulated tilt series of ``T`` is built by rows over ``group``: a ``TiltSeriesTransform`` with at
    least one slice a rank (else every rank builds it whole)."""
    return (group is not None and type(T) is TiltSeriesTransform
            and T.domain.shape[T.geometry.axis] >= dist.get_world_size(group))


def counts(n: int, group) -> list:
    """Every rank's number of slices (``rank_rows`` of ``n``), rank 0's first."""
    world = dist.get_world_size(group)
    return [b - a for a, b in (rank_rows(n, r, world) for r in range(world))]


def simulated_rows(template: str, target: str, T: TiltSeriesTransform, group) -> tuple:
    """``(template, target, clean)``: the phantoms ``template`` and ``target`` (``indreg.phantoms`` names) on
    ``T.domain`` and the noise-free data ``T(target)``, each rank evaluating and projecting only its share of the
    slices along the tilt axis (``row_range``); template and data whole on every rank, the target on rank 0 (None
    on the others). One process's ``phantoms.get`` and ``T`` to rounding (a cell's mean may sum in another order)."""
    axis, n = T.geometry.axis, T.domain.shape[T.geometry.axis]
    rows, shares = (axis, *row_range(n, group)), counts(n, group)
    mine = phantoms.get(target, T.domain, rows=rows)
    clean = all_gather_rows(T.project_rows(mine), 1, shares, group)
    whole_target = gather_rows(mine, axis, shares, group)
    del mine
    whole_template = all_gather_rows(phantoms.get(template, T.domain, rows=rows), axis, shares, group)
    return whole_template, whole_target, clean
