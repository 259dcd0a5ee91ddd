"""The data term of a tilt-series registration evaluated slab by slab along the tilt axis, within a memory bound,
and split over the processes of a ``torch.distributed`` group.

With a band-limited velocity (``CoarseVelocityDeformation``) and a tilt series (``TiltSeriesTransform``: detector
row ``j`` sees slice ``j`` only), the data term splits over slabs ``s`` of consecutive fine slices:

    E(m) = reg(m) + sum_s D_s(m),   D_s = (1/2) ||A (I o (Id + P_s u_N)) - g_s||^2_data

``u_N = phi_{1,0} - Id`` on the coarse grid is composed once (replicated, cheap); per slab ``P_s u_N`` (``P``'s
rows at the slab's cell centres, ``upsample_rows``) places the slab's points, the fixed template is sampled there,
the slab's slices are projected and compared with its detector rows ``g_s``, and the residual goes back through
``A^T``, the warp's adjoint and ``P_s^T`` into ``dL/du_N`` (and ``dL/dJ_N``, mass-preserving) on the coarse grid.
One coarse reverse sweep (``functional.backward._displacement_sweep``) then gives ``dL/dnu``: the gradient of
``IndirectRegistration.l2_gradient`` to rounding, with no full-size displacement or intermediate held. In a
process group each rank owns a contiguous share of the slabs; their ``dL/du_N`` (and ``dL/dJ_N``) and data fit
are summed by one ``all_reduce`` per gradient, so every rank runs the same coarse sweep and solver step: the
iterates are identical on all ranks. Each rank keeps the whole template and data (a 256^3 float32 template is
64 MiB, against ~3 GiB of a whole-volume gradient): no halo to bound, whatever the displacement.

Notes
-----
volumes ``(nx, ny, nz)`` on ``image_domain`` (tilt axis ``t`` = ``ray_transform.geometry.axis``),
data ``(num_tilts, det_rows, det_cols)`` with row ``j`` the slice ``j`` along ``t``; a slab is the half-open range
``[start, stop)`` of fine slice indices; coarse fields ``(C, *velocity_domain.shape)``; displacements in grid units
(``2 / extent`` times physical lengths, the same on both grids); ``slab_size`` counts fine slices, ``max_memory``
bytes. 3D only (a tilt series); float32 / float64, any device.

Longer than 450 lines: one algorithm: the slab-wise data term, its memory bound and its all-reduce over ranks.
"""
from __future__ import annotations

import logging
import math

import torch

from ..deform.coarse import CoarseVelocityDeformation
from ..deform.functional.backward import ExactRecord, _displacement_sweep, _displacements_into
from ..deform.functional.coarse import upsample, upsample_adjoint
from ..deform.functional.flows import _Steps, jacobian_trajectory
from ..deform.functional.sampling import _planewise_applies, _planewise_sample, _sample_adjoint, sample
from ..forward.ray_transform import _matmul, matmul_columns
from ..forward.tilt_series import TiltSeriesTransform
from .lddmm import IndirectRegistration
from ..ranks import default_group, gather_rows, process_group, rank_rows, rank_world  # noqa: F401  (re-exported)

log = logging.getLogger("indreg")

__all__ = ["SlabwiseRegistration", "slab_refusal", "slab_ranges", "choose_slab_size", "available_memory",
           "process_group", "default_group", "upsample_rows", "upsample_rows_adjoint", "SLAB_BYTES_PER_VOXEL",
           "WHOLE_BYTES_PER_VOXEL", "SLABS_PER_RANK", "projector_bytes",
           "COLUMN_BLOCK_BYTES"]

#: Working set of a slab per fine voxel, in scalars of the run's dtype (displacement, grid, warped image, its
#: gradient, the grid's slope and its planar copy: ``docs/3d.md``, "Slab-wise").
SLAB_BYTES_PER_VOXEL = 20
#: Slabs a rank gets at least when the slab size is automatic (smaller slabs cost no time: 8 slabs of 32 slices at
#: 256^3 ran as fast as the whole volume, ``scripts/bench_slabs.py``).
SLABS_PER_RANK = 4
#: A slab's slices as the projector's dense operand, per block of ``A``'s columns, in bytes (on a CPU): the slices of
#: a 1024 x 256 slab of 16 slices (16 MiB) read per nonzero missed the cache, 26 ms a slice in float32; in blocks of
#: 2 MiB 7.2 ms (``matmul_columns``). Smaller slabs (256^3 in slabs of 32 slices: 8 MiB) gain less.
COLUMN_BLOCK_BYTES = 2 * 2 ** 20
#: Peak of a whole-volume gradient per fine voxel, in scalars (190 bytes per voxel measured in float32 at 256^3).
WHOLE_BYTES_PER_VOXEL = 48


def slab_refusal(ray_transform, deformation, tv_weight: float = 0.0) -> str | None:
    """Why the data term cannot be split into slabs (one line), or None when it can."""
    if type(ray_transform) is not TiltSeriesTransform:
        return (f"the operator {type(ray_transform).__name__} is not a single-axis tilt series (TiltSeriesTransform: "
                f"one detector row per slice), so its data rows do not split into slabs")
    if not isinstance(deformation, CoarseVelocityDeformation):
        return (f"the deformation {type(deformation).__name__} has no coarse velocity grid (velocity_factor > 1: "
                f"CoarseVelocityDeformation)")
    if deformation.backward != "exact":
        return f"the deformation's backward is {deformation.backward!r}: slab-wise needs 'exact'"
    if tv_weight > 0:
        return "tv_weight > 0: the TV term couples neighbouring slices"
    return None


def slab_ranges(n: int, slab_size: int) -> list:
    """The slabs ``[(0, s), (s, 2 s), ...]`` of ``n`` slices, ``s = slab_size`` (the last one shorter)."""
    return [(a, min(a + slab_size, n)) for a in range(0, n, slab_size)]


def available_memory(device) -> int:
    """Bytes free for this process: ``torch.cuda.mem_get_info`` on a GPU, ``MemAvailable`` of ``/proc/meminfo``
    on a CPU (the physical memory where that file is missing)."""
    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import os
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def choose_slab_size(shape: tuple, axis: int, itemsize: int, max_memory: int | None = None, device="cpu",
                     velocity_numel: int = 0, projector_bytes: int = 0, warn: bool = False) -> int:
    """Fine slices per slab: all of them (the whole-volume path) when a whole gradient
    (``WHOLE_BYTES_PER_VOXEL``) fits in ``max_memory``, else as many as a slab's working set
    (``SLAB_BYTES_PER_VOXEL``) allows in what the template (twice: the plane-wise sampler's padded copy), the run's
    volume, 8 velocity-sized coarse arrays (``velocity_numel`` values each: momentum, velocity, record, gradient,
    the solver's trial and the kernel's buffers) and the projector (``projector_bytes``:
    ``_SystemMatrix.working_bytes``) leave (at least 1: then, with ``warn``, a warning, one line, says how much the
    run needs).
    ``max_memory`` None: half of ``available_memory(device)``."""
    budget = available_memory(device) // 2 if max_memory is None else int(max_memory)
    voxels = math.prod(shape)
    fixed = (3 * voxels + 8 * velocity_numel) * itemsize + projector_bytes
    if WHOLE_BYTES_PER_VOXEL * itemsize * voxels + fixed <= budget:
        return shape[axis]
    per_slice = SLAB_BYTES_PER_VOXEL * itemsize * voxels // shape[axis]
    if warn and fixed + per_slice > budget:
        log.warning("max_memory=%.4g GiB cannot hold the slab-wise registration: it needs %.4g GiB besides its slabs "
                    "(the template and its padded copy, the deformed volume, the coarse arrays, the projector) and "
                    "%.4g GiB a slice: it runs with slabs of one slice, about %.4g GiB", budget / 2 ** 30,
                    fixed / 2 ** 30, per_slice / 2 ** 30, (fixed + per_slice) / 2 ** 30)
    return max(1, min(shape[axis], (budget - fixed) // per_slice))


def projector_bytes(ray_transform, template: torch.Tensor) -> int:
    """What the tilt series' projector holds in a run of ``template``'s dtype and device (its slice's system matrix:
    ``_SystemMatrix.working_bytes``); 0 for an operator without one."""
    system = getattr(ray_transform, "system", None)
    working = getattr(system, "working_bytes", None)
    return int(working(template.dtype, template.device)) if working is not None else 0


# ------------------------------------------------------------------------------------------ P restricted to a slab
def _row_weights(coarse: int, fine: int, start: int, stop: int, dtype, device) -> tuple:
    """The linear interpolation (``align_corners=False``, clamped at the outer coarse centres, as
    ``F.interpolate``) from ``coarse`` to ``fine`` cell centres along one axis, for fine indices ``[start, stop)``:
    ``(i0, i1, w)`` with value ``(1 - w) f[i0] + w f[i1]``."""
    src = (torch.arange(start, stop, dtype=torch.float64, device=device) + 0.5) * (coarse / fine) - 0.5
    src = src.clamp_(0, coarse - 1)
    i0 = src.floor().long()
    i1 = torch.clamp(i0 + 1, max=coarse - 1)
    return i0, i1, (src - i0).to(dtype)


def upsample_rows(f: torch.Tensor, fine: tuple, axis: int, start: int, stop: int) -> torch.Tensor:
    """``P f`` at the fine cell centres whose index along ``axis`` is in ``[start, stop)``: ``f (C, *coarse)`` ->
    ``(C, *fine)`` with ``axis`` cut to ``stop - start`` (``upsample``'s trilinear map, done as its linear factor
    along ``axis`` then the bilinear one in the planes across it)."""
    a = axis + 1
    i0, i1, w = _row_weights(f.shape[a], fine[axis], start, stop, f.dtype, f.device)
    shape = [1] * f.dim()
    shape[a] = -1
    w = w.view(shape)
    rows = f.index_select(a, i0).mul_(1 - w).add_(f.index_select(a, i1).mul_(w))     # (C, .., n, ..) coarse planes
    plane = tuple(n for k, n in enumerate(fine) if k != axis)
    rows = rows.movedim(a, 0)   # each plane of each channel a batch entry: F.interpolate's faster case
    out = upsample(rows.reshape(-1, 1, *rows.shape[2:]), plane)  # 16 x 3 planes to 1024 x 256: 142 vs 330 ms
    return out.view(*rows.shape[:2], *plane).movedim(0, a)


def upsample_rows_adjoint(g: torch.Tensor, coarse: tuple, fine: tuple, axis: int, start: int,
                          stop: int) -> torch.Tensor:
    """The transpose of ``upsample_rows(., fine, axis, start, stop)``: ``g (C, *slab)`` -> ``(C, *coarse)``."""
    a = axis + 1
    plane = tuple(n for k, n in enumerate(coarse) if k != axis)
    rows = upsample_adjoint(g.movedim(a, 0), plane).movedim(0, a)                    # (C, .., n, ..) coarse planes
    i0, i1, w = _row_weights(coarse[axis], fine[axis], start, stop, g.dtype, g.device)
    shape = [1] * g.dim()
    shape[a] = -1
    w = w.view(shape)
    out = rows.new_zeros(rows.shape[:a] + (coarse[axis],) + rows.shape[a + 1:])
    out.index_add_(a, i0, rows * (1 - w))
    return out.index_add_(a, i1, rows.mul_(w))


# ----------------------------------------------------------------------------------------------------- the problem
class SlabwiseRegistration(IndirectRegistration):
    """``IndirectRegistration`` whose data term, gradient and deformed template are computed slab by slab along
    the tilt axis (module docstring), on this process's slabs of ``group`` (a ``torch.distributed`` process group:
    the default group when it is initialised with more than one rank, else None; ``False``: none).

    Parameters
    ----------
    ray_transform, deformation, kernel, template, data, gamma, tv_weight, tv_smoothing
        As ``IndirectRegistration``; ``ray_transform`` a ``TiltSeriesTransform``, ``deformation`` a
        ``CoarseVelocityDeformation`` with ``backward="exact"``, ``tv_weight`` 0.
    slab_size : int, optional
        Fine slices per slab (None: ``choose_slab_size`` from ``max_memory``, and at least ``SLABS_PER_RANK``
        slabs a rank; in a group of ``k`` ranks at most ``ceil(n / k)``, so that every rank has slabs).
    max_memory : int, optional
        Bytes for a gradient's working set (None: half the free memory of the template's device).
    group : torch.distributed.ProcessGroup or False, optional
        The ranks that share the slabs (None: the default group when initialised with more than one rank;
        ``False``: none).

    Raises
    ------
    ValueError
        A problem that cannot be split (``slab_refusal``'s reason), a ``slab_size`` that is no integer >= 1,
        fewer slices along the tilt axis than ranks; and the errors of ``IndirectRegistration``.
    TypeError
        As ``IndirectRegistration``.

    ``slab_ranges`` / ``own``: all slabs and the indices of this rank's (contiguous, balanced); ``allreduce_bytes``:
    what one gradient's ``all_reduce`` sends (the coarse ``dL/du_N``, ``dL/dJ_N`` when mass-preserving, the fit).
    """

    splits_over_ranks = True

    def __init__(self, ray_transform, deformation, kernel, template, data, gamma, tv_weight=0.0, tv_smoothing=1e-3,
                 slab_size: int | None = None, max_memory: int | None = None, group=None):
        super().__init__(ray_transform, deformation, kernel, template, data, gamma, tv_weight, tv_smoothing)
        reason = slab_refusal(ray_transform, deformation, self.tv_weight)
        if reason is not None:
            raise ValueError(f"the data term cannot be evaluated slab-wise: {reason}")
        self.axis = ray_transform.geometry.axis
        self.group = default_group() if group is None else (None if group is False else group)
        self.rank, self.world = rank_world(self.group)
        n = self.image_domain.shape[self.axis]
        #: the bytes this run may take beyond its inputs (``max_memory``, else half the free memory): the result's
        #: pieces are kept within it (``indreg.registration.run.build_result``)
        self.max_memory = available_memory(template.device) // 2 if max_memory is None else int(max_memory)
        if slab_size is None:   # automatic: at least SLABS_PER_RANK slabs a rank
            slab_size = min(choose_slab_size(self.image_domain.shape, self.axis, template.element_size(),
                                             max_memory, template.device, math.prod(self.momentum_shape),
                                             projector_bytes(ray_transform, template), warn=True),
                            -(-n // (SLABS_PER_RANK * self.world)))
        if isinstance(slab_size, bool) or not isinstance(slab_size, int) or slab_size < 1:
            raise ValueError(f"slab_size must be an integer >= 1 (fine slices per slab), got {slab_size!r}")
        self.slab_size = min(slab_size, -(-n // self.world))
        self.slab_ranges = slab_ranges(n, self.slab_size)
        if len(self.slab_ranges) < self.world:
            raise ValueError(f"{self.world} ranks need at least as many slabs: the tilt axis has {n} slices")
        self.own = _share(len(self.slab_ranges), self.rank, self.world)
        mass = deformation.action == "mass_preserving"
        self.allreduce_bytes = ((self.image_domain.ndim + mass) * math.prod(self.domain.shape) + 1) \
            * template.element_size()
        self._coords = [(2.0 * (x - a) / e - 1.0) for x, a, e in zip(self.image_domain.axes(template.dtype,
                        template.device), self.image_domain.min_pt, self.image_domain.extent)]
        self._padded = None   # the template with a zero plane either side along x, for the plane-wise sampler

    def __repr__(self):
        return (super().__repr__()[:-1] + f", slab_size={self.slab_size}, slabs={len(self.slab_ranges)}, "
                f"rank={self.rank}/{self.world})")

    def with_deformation(self, deformation) -> IndirectRegistration:
        """The same problem with another deformation (whole-volume where it cannot be split)."""
        if slab_refusal(self.ray_transform, deformation, self.tv_weight) is not None:
            return IndirectRegistration(self.ray_transform, deformation, self.kernel, self.template, self.data,
                                        self.gamma, self.tv_weight, self.tv_smoothing)
        return SlabwiseRegistration(self.ray_transform, deformation, self.kernel, self.template, self.data,
                                    self.gamma, self.tv_weight, self.tv_smoothing, self.slab_size,
                                    group=self.group if self.group is not None else False)

    # ---------------------------------------------------------------------------------------- per slab
    def _grid(self, w: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        """The ``grid_sample`` grid ``(*slab, d)`` of the slab's points ``x + w(x)``, ``w (d, *slab)`` grid units."""
        d = self.image_domain.ndim
        grid = w.new_empty(*w.shape[1:], d)
        for k, coord in enumerate(self._coords):
            if k == self.axis:
                coord = coord[start:stop]
            torch.add(w[k], coord.view([-1 if j == k else 1 for j in range(d)]), out=grid[..., d - 1 - k])
        return grid

    def _sample(self, grid: torch.Tensor) -> torch.Tensor:
        """``I`` at the slab's points ``grid (*slab, d)``: plane by plane where ``sample`` would be (one CPU
        thread, a slab across y or z), from one padded copy of the template kept for all slabs, else ``sample``."""
        f = self.template[None, None]
        if _planewise_applies(f, grid[None]):
            if self._padded is None:
                self._padded = torch.nn.functional.pad(f, (0, 0, 0, 0, 1, 1))
            out = _planewise_sample(f, grid[None], "zeros", self._padded)
            if out is not None:
                return out[0, 0]
        return sample(self.template.unsqueeze(0), grid, "zeros").squeeze(0)

    def _project(self, f: torch.Tensor) -> torch.Tensor:
        """``A`` slice by slice: ``f (*slab)`` -> ``(n, num_tilts, det_cols)``; on a CPU, when a slab's slices
        outgrow ``COLUMN_BLOCK_BYTES``, by blocks of ``A``'s columns (``matmul_columns``)."""
        slices = f.movedim(self.axis, 0)
        x = slices.reshape(slices.shape[0], -1)
        system = self.ray_transform.system
        width = max(1, COLUMN_BLOCK_BYTES // (self.slab_size * f.element_size()))
        if f.device.type == "cpu" and width < x.shape[1]:
            rows = matmul_columns(system.column_blocks(f.dtype, f.device, width), x)
        else:
            rows = _matmul(system.get(f.dtype, f.device)[0], x)
        return rows.reshape(slices.shape[0], self.ray_transform.geometry.num_tilts, -1)

    def _backproject(self, r: torch.Tensor) -> torch.Tensor:
        """``A^T`` slice by slice: ``(n, num_tilts, det_cols)`` -> ``(*slab)``."""
        u, v = self.ray_transform.geometry.slice_axes
        out = _matmul(self.ray_transform.system.get(r.dtype, r.device)[1], r.reshape(r.shape[0], -1))
        return out.reshape(r.shape[0], self.image_domain.shape[u], self.image_domain.shape[v]).movedim(0, self.axis)

    def _warped(self, u_n: torch.Tensor, jac_n, start: int, stop: int) -> tuple:
        """``(grid, image, pj, f)`` of the slab ``[start, stop)``: its points, ``I`` there, ``P J`` (or None) and the
        deformed template ``f = I o (Id + P u)`` (times ``P J``)."""
        fine = self.image_domain.shape
        grid = self._grid(upsample_rows(u_n, fine, self.axis, start, stop), start, stop)
        image = self._sample(grid)
        pj = None if jac_n is None else upsample_rows(jac_n.unsqueeze(0), fine, self.axis, start, stop).squeeze(0)
        return grid, image, pj, image if pj is None else pj * image

    def _slab(self, u_n: torch.Tensor, jac_n, start: int, stop: int, grads: tuple | None):
        """The slab ``[start, stop)``'s data fit; with ``grads = (kappa, mu)`` (coarse ``dL/du_N``, ``dL/dJ_N`` or
        None) its share of the gradient added into them."""
        fine, coarse = self.image_domain.shape, self.domain.shape
        grid, image, pj, f = self._warped(u_n, jac_n, start, stop)
        residual = self._project(f).sub_(self.data.narrow(1, start, stop - start).movedim(1, 0))
        weight = self.ray_transform.geometry.data_weight
        fit = 0.5 * (weight * residual.square().sum())
        if grads is None:
            return fit
        g = self._backproject(residual.mul_(weight))           # dL/df on the slab
        lam = g if pj is None else g * pj
        _, slope = _sample_adjoint(lam.unsqueeze(0), self.template.unsqueeze(0), grid, "zeros", False, True)
        del grid, lam
        d = self.image_domain.ndim
        kappa = torch.stack([slope[..., d - 1 - k] for k in range(d)])
        del slope
        grads[0].add_(upsample_rows_adjoint(kappa, coarse, fine, self.axis, start, stop))
        if grads[1] is not None:
            grads[1].add_(upsample_rows_adjoint((g * image).unsqueeze(0), coarse, fine, self.axis, start,
                                                stop).squeeze(0))
        return fit

    # ------------------------------------------------------------------------------- the objective
    def _flow(self, nu: torch.Tensor) -> tuple:
        """``(slots, jacobians, moving)``: the coarse ``u_i`` (grid units) and, mass-preserving, ``J_i``."""
        moving = self.deformation._check_velocity(nu)
        slots = torch.empty_like(nu)
        _displacements_into(slots, nu, self.domain, moving)
        mass = self.deformation.action == "mass_preserving"
        jac = jacobian_trajectory(nu, self.domain, self.deformation.scheme, moving) if mass else None
        return slots, jac, moving

    def _fit(self, nu: torch.Tensor) -> float:
        """The data fit ``sum_s D_s`` over all ranks."""
        slots, jac, _ = self._flow(nu)
        jac_n = None if jac is None else jac[-1]
        fit = sum(self._slab(slots[-1], jac_n, *self.slab_ranges[s], None) for s in self.own)
        return float(self._all_reduce(fit.reshape(1))[0])

    def terms(self, m: torch.Tensor, nu: torch.Tensor | None = None) -> dict:
        """``objective, data_fit, regulariser, tv`` (0-dim tensors, no graph: slab-wise has no autograd path)."""
        with torch.no_grad():
            nu = self.velocity(m) if nu is None else nu
            zero = torch.zeros((), dtype=m.dtype, device=m.device)
            out = {"data_fit": zero + self._fit(nu), "tv": zero, "regulariser": self.regulariser(m, nu)}
        out["objective"] = out["data_fit"] + out["regulariser"]
        return out

    def _assemble(self, out: torch.Tensor, u: torch.Tensor, jac) -> torch.Tensor:
        """``out`` filled slab by slab with ``I o (Id + P u)`` (times ``P J``): every slab, no communication."""
        for start, stop in self.slab_ranges:
            out.narrow(self.axis, start, stop - start).copy_(self._warped(u, jac, start, stop)[3])
        return out

    def deformed(self, m: torch.Tensor) -> torch.Tensor:
        """``W(K m, I)``, assembled slab by slab."""
        with torch.no_grad():
            slots, jac, _ = self._flow(self.velocity(m))
            return self._assemble(torch.empty_like(self.template), slots[-1], None if jac is None else jac[-1])

    def trajectory(self, m: torch.Tensor) -> torch.Tensor:
        """``W(K m, I)(t_i)`` for i = 0..N, ``(N+1, *shape)``, each assembled slab by slab."""
        with torch.no_grad():
            slots, jac, _ = self._flow(self.velocity(m))
            out = self.template.new_empty(slots.shape[0], *self.template.shape)
            for i in range(slots.shape[0]):
                self._assemble(out[i], slots[i], None if jac is None else jac[i])
            return out

    def image_frames(self, x: tuple):
        """``W(K m, I)(t_i)`` for i = 0..N one at a time, each assembled slab by slab (one fine volume held). In a
        group each rank assembles its own slabs and rank 0 gets the frames gathered: whole there, None on the other
        ranks (every rank iterates them to the end)."""
        with torch.no_grad():   # not held across a yield: the caller's grad mode stays its own
            slots, jac, _ = self._flow(self.velocity(x[0]))
        for i in range(slots.shape[0]):
            with torch.no_grad():
                frame = self._assemble(torch.empty_like(self.template), slots[i], None if jac is None else jac[i]) \
                    if self.group is None else self._gathered(slots[i], None if jac is None else jac[i])
            yield frame

    def _gathered(self, u: torch.Tensor, jac) -> torch.Tensor | None:
        """``I o (Id + P u)`` (times ``P J``) on this rank's slabs, joined on rank 0 (``indreg.ranks.gather_rows``)."""
        start, stop = self.slab_ranges[self.own[0]][0], self.slab_ranges[self.own[-1]][1]
        shape = list(self.template.shape)
        shape[self.axis] = stop - start
        mine = self.template.new_empty(shape)
        for a, b in (self.slab_ranges[s] for s in self.own):
            mine.narrow(self.axis, a - start, b - a).copy_(self._warped(u, jac, a, b)[3])
        counts = [sum(b - a for a, b in (self.slab_ranges[s] for s in _share(len(self.slab_ranges), r, self.world)))
                  for r in range(self.world)]
        return gather_rows(mine, self.axis, counts, self.group)

    def deformation_field(self, nu: torch.Tensor) -> torch.Tensor:
        """``phi_{1,0}`` ``(d, *shape)`` in physical points (``CoarseVelocityDeformation.deformation``), filled slab by
        slab from the coarse ``phi_{1,0} - Id``: the output and one slab's interpolation held, not a second field."""
        from ..deform.functional import displacement_10

        with torch.no_grad():
            u = displacement_10(nu, self.domain, self.deformation._check_velocity(nu))   # coarse, physical units
            fine, d = self.image_domain.shape, self.image_domain.ndim
            out = nu.new_empty(d, *fine)
            axes = self.image_domain.axes(nu.dtype, nu.device)
            for start, stop in self.slab_ranges:
                part = out.narrow(self.axis + 1, start, stop - start)
                part.copy_(upsample_rows(u, fine, self.axis, start, stop))
                for k, x in enumerate(axes):
                    x = x[start:stop] if k == self.axis else x
                    part[k].add_(x.view([-1 if j == k else 1 for j in range(d)]))
            return out

    def relative_residual(self, x: tuple) -> float:
        """``||T f - g|| / ||g||`` from the slabs' data fit (``2 D / ||g||^2``): no whole deformed volume projected."""
        with torch.no_grad():
            fit = self._fit(self.velocity(x[0]))
            gg = float(self.ray_transform.inner_data(self.data, self.data).sum())
        return math.sqrt(2.0 * fit / gg) if gg > 0 else float("nan")

    def volume_bytes(self) -> int:
        """Bytes of one fine volume of the run's dtype."""
        return math.prod(self.image_domain.shape) * self.template.element_size()

    def l2_gradient(self, m: torch.Tensor) -> tuple:
        """``IndirectRegistration.l2_gradient`` slab-wise: this rank's slabs, one ``all_reduce`` of the coarse
        ``dL/du_N`` (``dL/dJ_N``) and the fit, then the coarse reverse sweep on every rank."""
        with torch.no_grad():
            nu = self.velocity(m)
            slots, jac, moving = self._flow(nu)
            c = -self.domain.ndim - 1
            size = math.prod(self.domain.shape)
            buffer = nu.new_zeros((self.domain.ndim + (jac is not None)) * size + 1)
            kappa = buffer[:self.domain.ndim * size].view(self.domain.ndim, *self.domain.shape)
            mu = None if jac is None else buffer[self.domain.ndim * size:-1].view(self.domain.shape)
            for s in self.own:
                fit = self._slab(slots[-1], None if jac is None else jac[-1], *self.slab_ranges[s], (kappa, mu))
                buffer[-1] += fit
            self._all_reduce(buffer)
            _displacement_sweep(kappa, mu, ExactRecord(slots, jac), nu, self.domain, self.deformation.scheme,
                                _Steps(nu, self.domain, -1.0, moving))
            slots.select(c - 1, 0).zero_()
            h = slots.div_(self.time_weight).add_(m, alpha=self.gamma)
            terms = {"data_fit": float(buffer[-1]), "tv": 0.0, "regulariser": float(self.regulariser(m, nu))}
        terms["objective"] = terms["data_fit"] + terms["tv"] + terms["regulariser"]
        return terms, h, nu

    def differentiable(self, x: tuple) -> tuple:
        raise TypeError("SlabwiseRegistration has no autograd path (solver 'algorithm1'; torch.optim solvers and "
                        "'fast' run the whole volume: slab_size=None with enough max_memory)")

    def _all_reduce(self, t: torch.Tensor) -> torch.Tensor:
        """The sum of ``t`` over the group's ranks, in place (``t`` itself without a group)."""
        if self.group is not None:
            import torch.distributed as dist
            dist.all_reduce(t, group=self.group)
        return t


def _share(count: int, rank: int, world: int) -> range:
    """Rank ``rank``'s contiguous share of ``count`` items (``indreg.ranks.rank_rows``) as a range."""
    return range(*rank_rows(count, rank, world))


