"""Rows of a volume (or of its data) shared over the ranks of a ``torch.distributed`` process group: each rank holds a
contiguous share along one axis (``rank_rows``), and the shares are joined into the whole on every rank
(``all_gather_rows``) or on one (``gather_rows``). Used by the slab-wise registration (``indreg.problems.slabs``),
the baselines over ranks (``indreg.forward.split``) and the data built by rows (``indreg.experiments.split_setup``).

Convention: ``counts[r]`` is rank ``r``'s number of rows along ``axis`` (rank 0's rows first, then rank 1's, ...);
every rank passes the same ``counts``. The exchange runs on the group's device (the CPU for gloo, this rank's GPU
for NCCL) and the whole comes back on the device of ``part``.
"""
from __future__ import annotations

import torch
import torch.distributed as dist

__all__ = ["rank_rows", "all_gather_rows", "gather_rows"]


def rank_rows(n: int, rank: int, world: int) -> tuple:
    """Rank ``rank``'s rows ``(start, stop)`` of ``n``: contiguous shares, the first ``n % world`` ranks one more."""
    base, extra = divmod(n, world)
    start = rank * base + min(rank, extra)
    return start, start + base + (rank < extra)


def _device(group) -> torch.device:
    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend(group) == "nccl" \
        else torch.device("cpu")


def _padded(part: torch.Tensor, axis: int, counts: list, group) -> torch.Tensor:
    """``part`` on the group's device, zero-padded along ``axis`` to the largest share (a gather needs one size)."""
    if part.shape[axis] != counts[dist.get_rank(group)]:
        raise ValueError(f"rank {dist.get_rank(group)}'s part has {part.shape[axis]} rows along axis {axis}, "
                         f"expected {counts[dist.get_rank(group)]} (counts {list(counts)})")
    pad = part.new_zeros(part.shape[:axis] + (max(counts) - part.shape[axis],) + part.shape[axis + 1:])
    return torch.cat([part, pad], axis).to(_device(group))


def _joined(pieces: list, axis: int, counts: list, device) -> torch.Tensor:
    """The ranks' padded ``pieces`` cut to their ``counts`` and joined along ``axis``, on ``device``."""
    return torch.cat([p.narrow(axis, 0, c) for p, c in zip(pieces, counts)], axis).to(device)


def all_gather_rows(part: torch.Tensor, axis: int, counts: list, group) -> torch.Tensor:
    """Every rank's ``part`` (its ``counts[rank]`` rows along ``axis``) joined into the whole, on every rank."""
    mine = _padded(part, axis, counts, group)
    pieces = [torch.empty_like(mine) for _ in counts]
    dist.all_gather(pieces, mine, group=group)
    return _joined(pieces, axis, counts, part.device)


def gather_rows(part: torch.Tensor, axis: int, counts: list, group, dst: int = 0) -> torch.Tensor | None:
    """As ``all_gather_rows``, joined on rank ``dst`` of ``group`` only (None on the others)."""
    mine = _padded(part, axis, counts, group)
    here = dist.get_rank(group) == dst
    pieces = [torch.empty_like(mine) for _ in counts] if here else None
    dist.gather(mine, pieces, dst=dist.get_global_rank(group, dst), group=group)
    return _joined(pieces, axis, counts, part.device) if here else None
