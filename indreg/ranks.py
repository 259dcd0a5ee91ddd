"""Ranks as a capability: the ``torch.distributed`` process group a run is split over (``process_group``,
``default_group``, ``rank_world``) and rows of a volume (or of its data) shared over its ranks: each rank holds a
contiguous share along one axis (``rank_rows``), and the shares are joined into the whole on every rank
(``all_gather_rows``) or on one (``gather_rows``). Below ``indreg.forward`` and ``indreg.problems``: used by the
slab-wise registration (``indreg.problems.slabs``), the baselines over ranks (``indreg.forward.split``), the data
built by rows (``indreg.experiments.split_setup``) and the app's runner. A problem says whether it splits over the
ranks by ``splits_over_ranks`` (``indreg.problems.problem.RegistrationProblem``).

Notes
-----
``counts[r]`` is rank ``r``'s number of rows along ``axis`` (rank 0's rows first, then rank 1's, ...);
every rank passes the same ``counts``. The exchange runs on the group's device (the CPU for gloo, this rank's GPU
for NCCL) and the whole comes back on the device of ``part``.
"""
from __future__ import annotations

import torch
import torch.distributed as dist

__all__ = ["process_group", "default_group", "rank_world", "rank_rows", "all_gather_rows", "gather_rows"]


def process_group(distributed: bool | None, device) -> object | None:
    """The process group a registration is split over: ``torch.distributed``'s default group, started (gloo on a
    CPU, NCCL on CUDA) when this process was launched by ``torchrun`` with ``WORLD_SIZE > 1``; None for one
    process. ``distributed`` None: whether ``WORLD_SIZE > 1``; False: None."""
    import os

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if distributed is False or (distributed is None and world < 2) or world < 2 and not dist.is_initialized():
        return None
    if not dist.is_initialized():
        dist.init_process_group("nccl" if torch.device(device).type == "cuda" else "gloo")
    return dist.group.WORLD if dist.get_world_size() > 1 else None


def default_group():
    """The default process group when ``torch.distributed`` is initialised with more than one rank, else None."""
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        return dist.group.WORLD
    return None


def rank_world(group) -> tuple:
    """``(rank, world size)`` in ``group``; ``(0, 1)`` for None (one process)."""
    return (0, 1) if group is None else (dist.get_rank(group), dist.get_world_size(group))


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
