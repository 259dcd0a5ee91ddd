"""A simulated tilt series built over the ranks of a process group: each rank evaluates its share of the phantoms'
slices along the tilt axis and projects them; the shares are then gathered.

Every rank needs the whole template (a displacement may carry a slab's points anywhere in it) and the whole data
(the units and the relative weights are computed from it, and rank 0 writes it), so both are assembled by an
``all_gather``; the target only rank 0 uses (the figures of merit), so it is gathered there. The noise is then drawn
on every rank from the whole noise-free data, as one process draws it: the same data, the same noise.

Convention: volumes ``(nx, ny, nz)`` and data ``(num_tilts, det_rows, det_cols)`` float64 on the CPU; a rank's
share is the contiguous range ``[start, stop)`` of the tilt axis' slices (``slabs._share``: the first ``n % world``
ranks one more), and data row ``j`` is slice ``j``. The gathers run on the group's device (CPU for gloo, the rank's
GPU for NCCL) and return CPU tensors.
"""
from __future__ import annotations

import torch
import torch.distributed as dist

from .. import phantoms
from ..forward.tilt_series import TiltSeriesTransform
from ..problems.slabs import _share

__all__ = ["row_range", "all_gather_rows", "gather_rows", "simulated_rows", "splits"]


def row_range(n: int, group) -> tuple:
    """``(start, stop)``: this rank's contiguous share of ``n`` slices."""
    share = _share(n, dist.get_rank(group), dist.get_world_size(group))
    return share.start, share.stop


def splits(T, group) -> bool:
    """Whether a simulated tilt series of ``T`` is built by rows over ``group``: a ``TiltSeriesTransform`` with at
    least one slice a rank (else every rank builds it whole)."""
    return (group is not None and type(T) is TiltSeriesTransform
            and T.domain.shape[T.geometry.axis] >= dist.get_world_size(group))


def _device(group) -> torch.device:
    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend(group) == "nccl" \
        else torch.device("cpu")


def _padded(part: torch.Tensor, axis: int, n: int, group) -> torch.Tensor:
    """``part`` on the group's device, zero-padded along ``axis`` to the largest share (gathers need one size)."""
    size = -(-n // dist.get_world_size(group))
    pad = part.new_zeros(part.shape[:axis] + (size - part.shape[axis],) + part.shape[axis + 1:])
    return torch.cat([part, pad], axis).to(_device(group))


def _joined(pieces: list, axis: int, n: int, group) -> torch.Tensor:
    """The ranks' padded ``pieces`` cut to their shares and joined along ``axis``, on the CPU."""
    world = dist.get_world_size(group)
    cut = [p.narrow(axis, 0, len(_share(n, r, world))) for r, p in enumerate(pieces)]
    return torch.cat(cut, axis).cpu()


def all_gather_rows(part: torch.Tensor, axis: int, n: int, group) -> torch.Tensor:
    """Every rank's ``part`` (its share of ``n`` rows along ``axis``, ``row_range``) joined into the whole, on every
    rank."""
    mine = _padded(part, axis, n, group)
    pieces = [torch.empty_like(mine) for _ in range(dist.get_world_size(group))]
    dist.all_gather(pieces, mine, group=group)
    return _joined(pieces, axis, n, group)


def gather_rows(part: torch.Tensor, axis: int, n: int, group, dst: int = 0) -> torch.Tensor | None:
    """As ``all_gather_rows``, joined on rank ``dst`` only (None on the others)."""
    mine = _padded(part, axis, n, group)
    here = dist.get_rank(group) == dst
    pieces = [torch.empty_like(mine) for _ in range(dist.get_world_size(group))] if here else None
    dist.gather(mine, pieces, dst=dst, group=group)
    return _joined(pieces, axis, n, group) if here else None


def simulated_rows(template: str, target: str, T: TiltSeriesTransform, group) -> tuple:
    """``(template, target, clean)``: the phantoms ``template`` and ``target`` (``indreg.phantoms`` names) on
    ``T.domain`` and the noise-free data ``T(target)``, each rank evaluating and projecting only its share of the
    slices along the tilt axis (``row_range``); template and data whole on every rank, the target on rank 0 (None
    on the others). One process's ``phantoms.get`` and ``T`` to rounding (a cell's mean may sum in another order)."""
    axis, n = T.geometry.axis, T.domain.shape[T.geometry.axis]
    rows = (axis, *row_range(n, group))
    mine = phantoms.get(target, T.domain, rows=rows)
    clean = all_gather_rows(T.project_rows(mine), 1, n, group)
    whole_target = gather_rows(mine, axis, n, group)
    del mine
    whole_template = all_gather_rows(phantoms.get(template, T.domain, rows=rows), axis, n, group)
    return whole_template, whole_target, clean
