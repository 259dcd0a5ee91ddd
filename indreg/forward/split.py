"""A tilt series split into slabs of rows along the tilt axis: one slab a rank of a ``torch.distributed`` group, or
one slab at a time in one process. The thin layer that runs the baselines (FBP, SIRT, TV) over ranks.

A ``TiltSeriesTransform`` is block diagonal over the slices across the tilt axis (detector row ``j`` sees slice ``j``
only), so ``T`` restricted to the rows ``[start, stop)`` is the same 2D projector on fewer slices
(``SlabTransform``), and FBP and SIRT (row and column sums per slice) are exact slab by slab. What couples the rows
is carried by the slab's domain (``SlabDomain``), so that the solvers' bodies stay those of one process:

- ``domain.inner`` / ``domain.norm`` and ``T.inner_data`` are summed over the ranks (``all_reduce``);
- ``beyond(f, domain, dim, side)``, the slice past the edge that the finite differences of
  ``indreg.forward.tv.gradient`` / ``divergence`` read, is the next rank's first slice (``side = 1``) or the previous
  rank's last (``side = -1``) along the tilt axis (zero at the volume's ends, and on the other axes): a one-slice
  halo exchange (``isend`` / ``irecv``);
- ``total`` / ``maximum`` reduce a rank's sum or maximum, ``own_rows`` cuts a whole-volume tensor to the rank's rows
  (a random start drawn whole, so that it does not depend on the number of ranks), ``gather_rows`` assembles the
  ranks' rows on one rank.

Notes
-----
volumes ``(..., nx, ny, nz)``, data ``(..., num_tilts, det_rows, det_cols)``; the tilt axis ``t`` =
``T.geometry.axis``; a slab is the half-open range ``[start, stop)`` of slices along ``t`` (the same rows of the
data); rank ``r`` of ``k`` owns the ``r``-th of ``k`` contiguous, balanced shares (``rank_rows``). Without a group
the slab is all there is (sums are local, the halo is zero). CPU tensors with gloo, CUDA with NCCL.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .. import ranks
from ..ranks import rank_rows
from ..domain import ImageDomain
from .tilt_series import TiltSeriesTransform

__all__ = ["SlabSplit", "SlabDomain", "SlabTransform", "rank_rows", "split_rows", "slab_transforms", "by_slabs",
           "beyond", "total", "maximum", "own_rows", "whole_domain", "gather_rows"]


class SlabSplit:
    """The communicator of one slab: rows ``[start, stop)`` of ``n`` along the array axis ``axis`` of a volume,
    held by this rank of ``group`` (``torch.distributed``; None: one process, no communication)."""

    def __init__(self, n: int, axis: int, start: int, stop: int, group=None):
        self.n, self.axis, self.start, self.stop, self.group = n, axis, start, stop, group
        if group is None:
            self.rank, self.world = 0, 1
        else:
            import torch.distributed as dist
            self.rank, self.world = dist.get_rank(group), dist.get_world_size(group)

    def __repr__(self) -> str:
        return f"SlabSplit(rows {self.start}:{self.stop} of {self.n}, axis {self.axis}, rank {self.rank}/{self.world})"

    def _peer(self, rank: int) -> int:
        import torch.distributed as dist
        return dist.get_global_rank(self.group, rank)

    def all_reduce(self, t: torch.Tensor, op: str = "sum") -> torch.Tensor:
        """``t`` summed (``op="max"``: maximised) over the ranks, in place; ``t`` itself without a group."""
        if self.group is not None:
            import torch.distributed as dist
            dist.all_reduce(t, op=dist.ReduceOp.SUM if op == "sum" else dist.ReduceOp.MAX, group=self.group)
        return t

    def halo(self, f: torch.Tensor, dim: int, side: int) -> torch.Tensor:
        """The neighbour's boundary slice along ``dim`` (the split axis of ``f``): the next rank's first slice
        (``side = 1``) or the previous rank's last (``side = -1``); zero past the volume's ends."""
        out = torch.zeros_like(f.narrow(dim, 0, 1), memory_format=torch.contiguous_format)   # irecv's buffer
        if self.group is None:
            return out
        import torch.distributed as dist
        sender, receiver = (self.rank > 0, self.rank < self.world - 1) if side > 0 else \
            (self.rank < self.world - 1, self.rank > 0)
        edge = f.narrow(dim, 0 if side > 0 else f.shape[dim] - 1, 1).contiguous()
        works = []
        if sender:
            works.append(dist.isend(edge, self._peer(self.rank - side), group=self.group))
        if receiver:
            works.append(dist.irecv(out, self._peer(self.rank + side), group=self.group))
        for w in works:
            w.wait()
        return out


@dataclass(frozen=True, eq=False)
class SlabDomain(ImageDomain):
    """A slab ``[start, stop)`` of ``whole`` along ``split.axis`` (an ``ImageDomain`` of the slab's cells, the cell
    sides exactly the whole domain's) whose inner products are summed over the ranks of ``split``."""

    whole: ImageDomain | None = None
    split: SlabSplit | None = None

    @classmethod
    def of(cls, whole: ImageDomain, split: SlabSplit) -> "SlabDomain":
        """The slab of ``whole`` that ``split`` holds."""
        a, h = split.axis, whole.cell_sides[split.axis]
        shape, lo, hi = list(whole.shape), list(whole.min_pt), list(whole.max_pt)
        shape[a], lo[a], hi[a] = split.stop - split.start, whole.min_pt[a] + split.start * h, \
            whole.min_pt[a] + split.stop * h
        return cls(tuple(shape), tuple(lo), tuple(hi), whole=whole, split=split)

    @property
    def cell_sides(self) -> tuple:
        """The whole domain's cell sides (not recomputed from the slab's extent: the same weights to the bit)."""
        return self.whole.cell_sides

    def inner(self, f: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """The whole domain's L2 inner product: this slab's part summed over the ranks."""
        return self.split.all_reduce(super().inner(f, g))


def beyond(f: torch.Tensor, domain: ImageDomain, dim: int, side: int) -> torch.Tensor:
    """The slice past ``f``'s edge along the image axis ``dim`` (negative, as ``domain.dims``): after the last
    (``side = 1``) or before the first (``side = -1``). Zero, except across a ``SlabDomain``'s split: the
    neighbouring rank's slice (module docstring)."""
    if isinstance(domain, SlabDomain) and dim == domain.dims[domain.split.axis]:
        return domain.split.halo(f, dim, side)
    return torch.zeros_like(f.narrow(dim, 0, 1))


def total(t: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """A sum over the image (or data) axes of a slab, summed over the ranks of a ``SlabDomain``'s split."""
    return domain.split.all_reduce(t) if isinstance(domain, SlabDomain) else t


def maximum(t: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """A maximum over a slab, maximised over the ranks of a ``SlabDomain``'s split."""
    return domain.split.all_reduce(t, "max") if isinstance(domain, SlabDomain) else t


def whole_domain(domain: ImageDomain) -> ImageDomain:
    """The domain a slab was cut from (``domain`` itself when it is no slab)."""
    return domain.whole if isinstance(domain, SlabDomain) else domain


def own_rows(f: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """A tensor ``(..., *whole.shape)`` cut to the slab's rows (``f`` itself when ``domain`` is no slab)."""
    if not isinstance(domain, SlabDomain):
        return f
    s = domain.split
    return f.narrow(domain.dims[s.axis], s.start, s.stop - s.start)


class SlabTransform(TiltSeriesTransform):
    """``T`` restricted to the slices ``[start, stop)`` along its tilt axis: the same 2D projector (shared, not
    rebuilt) on the slab's domain (``SlabDomain``), data rows ``[start, stop)``; ``inner_data`` summed over the
    ranks of the split. ``data_rows(y)`` cuts whole data to these rows."""

    def __init__(self, T: TiltSeriesTransform, split: SlabSplit):
        nn.Module.__init__(self)
        if split.axis != T.geometry.axis or split.n != T.domain.shape[split.axis]:
            raise ValueError(f"the split {split} does not cut the tilt axis of {T.geometry} on {T.domain}")
        self.domain = SlabDomain.of(T.domain, split)
        self.slice_transform = T.slice_transform
        self.geometry = T.geometry.resolve(self.domain)

    @property
    def split(self) -> SlabSplit:
        return self.domain.split

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """The whole data's weighted inner product: this slab's rows summed over the ranks."""
        return self.split.all_reduce(super().inner_data(y1, y2))

    def data_rows(self, y: torch.Tensor) -> torch.Tensor:
        """Whole data ``(..., num_tilts, det_rows, det_cols)`` cut to this slab's rows (a contiguous copy: the
        solvers read them every iteration)."""
        return y.narrow(-2, self.split.start, self.split.stop - self.split.start).contiguous()


def _check_tilt_series(T) -> None:
    if type(T) is not TiltSeriesTransform:
        raise TypeError(f"a split into slabs needs a TiltSeriesTransform (one detector row per slice), "
                        f"got {type(T).__name__}")


def split_rows(T: TiltSeriesTransform, group) -> SlabTransform:
    """This rank's ``SlabTransform`` of ``T`` in ``group`` (``rank_rows``); one line if a rank would have no rows."""
    import torch.distributed as dist

    _check_tilt_series(T)
    axis, world = T.geometry.axis, dist.get_world_size(group)
    n = T.domain.shape[axis]
    if n < world:
        raise ValueError(f"{world} ranks need at least as many slices along the tilt axis, got {n}")
    return SlabTransform(T, SlabSplit(n, axis, *rank_rows(n, dist.get_rank(group), world), group))


def slab_transforms(T: TiltSeriesTransform, slab_size: int) -> list:
    """``T`` cut into slabs of ``slab_size`` slices along its tilt axis (the last one shorter), one process."""
    _check_tilt_series(T)
    if isinstance(slab_size, bool) or not isinstance(slab_size, int) or slab_size < 1:
        raise ValueError(f"slab_size must be an integer >= 1 (slices per slab), got {slab_size!r}")
    axis = T.geometry.axis
    n = T.domain.shape[axis]
    return [SlabTransform(T, SlabSplit(n, axis, a, min(a + slab_size, n))) for a in range(0, n, slab_size)]


def by_slabs(reconstruct, T: TiltSeriesTransform, y: torch.Tensor, slab_size: int) -> torch.Tensor:
    """``reconstruct(T_s, y_s)`` (a reconstruction that is exact slab by slab: FBP, SIRT) slab after slab in one
    process, assembled into one volume ``(..., *T.domain.shape)``: one slab's working set held at a time."""
    out = None
    for Ts in slab_transforms(T, slab_size):
        part = reconstruct(Ts, Ts.data_rows(y))
        if out is None:
            out = part.new_empty(*part.shape[:part.dim() - 3], *T.domain.shape)
        out.narrow(Ts.domain.dims[Ts.split.axis], Ts.split.start, Ts.split.stop - Ts.split.start).copy_(part)
    return out


def gather_rows(x: torch.Tensor, T: SlabTransform, dst: int = 0) -> torch.Tensor | None:
    """The ranks' rows of ``x (..., *T.domain.shape)`` assembled into ``(..., *whole.shape)`` on rank ``dst``
    (None on the others): ``indreg.ranks.gather_rows`` along the split axis."""
    s = T.split
    counts = [b - a for a, b in (rank_rows(s.n, r, s.world) for r in range(s.world))]
    return ranks.gather_rows(x, x.dim() - 3 + s.axis, counts, s.group, dst)
