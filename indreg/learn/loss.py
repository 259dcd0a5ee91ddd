"""The indirect shooting loss: data misfit of the shot template in data space plus the geodesic energy."""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from .._checks import check_nonnegative, check_same, check_tensor
from ..deform.shooting import GeodesicShooting
from ..forward.operator import LinearOperator, check_operator


def _integer_index(index) -> torch.Tensor:
    """``index`` (a tensor, array or list of transform numbers) as a flat long CPU tensor; floats, booleans and
    complex numbers are refused (casting 0.7 to 0 would silently pick the wrong transform)."""
    try:
        t = torch.as_tensor(index)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"index must be a (B,) integer tensor or list, got {type(index).__name__}") from None
    if t.dtype == torch.bool or t.is_floating_point() or t.is_complex():
        raise TypeError(f"index must hold integers (transform numbers), got dtype {t.dtype}")
    return t.detach().to("cpu", torch.long).reshape(-1)


class IndirectShootingLoss(nn.Module):
    """``L(m0) = ||T(W(m0, I)) - g||^2_data + gamma <m0, K m0>_L2`` per sample (rem:AltLDDMM, indirect case).

    ``W(m0, I)`` is the template deformed along the geodesic shot from ``m0`` (``GeodesicShooting``), ``T``
    the forward operator (a ``RayTransform`` or any ``indreg.forward.LinearOperator``) and ``||.||_data`` its
    weighted data norm (``inner_data``); on a geodesic
    ``<m0, K m0> = ||nu||^2_{L2([0,1], V)}``, so this is the paper's objective eq:OptimV restricted to
    geodesics, with the paper's ``gamma`` (twice the solvers' ``(gamma/2)||nu||^2 + (1/2)||T f - g||^2``:
    same minimiser, same gamma).

    Geometry: ``ray_transform`` is one operator shared by the batch, or a sequence of them
    (per-sample geometry): then sample ``b`` uses ``ray_transform[index[b]]`` (``index`` a ``(B,)`` integer
    tensor/list), or ``ray_transform[b]`` when ``index`` is omitted (one transform per sample). Samples sharing
    a transform are projected in one batched call.

    Parameters
    ----------
    shooting : GeodesicShooting
        ``W(m0, I)``.
    ray_transform : LinearOperator or sequence of LinearOperator
        ``T``, one for the batch or one per geometry (above), on the shooting's domain.
    gamma : float
        The regularisation weight (>= 0).
    reduction : {"mean", "sum", "none"}
        How the per-sample losses are combined.

    Raises
    ------
    TypeError
        No ``GeodesicShooting``, no operator or an empty sequence of them.
    ValueError
        An operator on another domain, an unknown ``reduction``, ``gamma < 0``.

    Notes
    -----
    ``momentum (B, 2, nx, ny)``, ``template (B, nx, ny)`` or ``(nx, ny)``, ``data`` a tensor
    ``(B, *range_shape)`` or (per-sample geometries of different sizes) a list of ``B`` tensors
    ``range_shape_b``: each sinogram in the range of its sample's transform, finite, with the
    momentum's dtype (float32 / float64) and device (checked before shooting). ``reduction``: ``"mean"``
    (default), ``"sum"`` or ``"none"`` (``(B,)``).

    Examples
    --------
    >>> from indreg import GaussianKernel, ImageDomain, ParallelBeamGeometry, RayTransform, phantoms
    >>> dom = ImageDomain.paper(32)
    >>> T = RayTransform(dom, ParallelBeamGeometry.paper(6, 46))
    >>> loss_fn = IndirectShootingLoss(GeodesicShooting(dom, GaussianKernel(dom, 6.0), 5), T, gamma=1e-3)
    >>> template = phantoms.get("j", dom)
    >>> sinograms = T(phantoms.get("v", dom)).expand(2, 6, 46)   # a batch of 2
    >>> m0 = torch.zeros(2, 2, 32, 32, dtype=torch.float64, requires_grad=True)   # a network's output
    >>> loss = loss_fn(m0, template, sinograms)
    >>> loss.backward()
    >>> m0.grad.shape
    torch.Size([2, 2, 32, 32])
    """

    def __init__(self, shooting: GeodesicShooting, ray_transform, gamma: float, reduction: str = "mean"):
        super().__init__()
        if not isinstance(shooting, GeodesicShooting):
            raise TypeError(f"shooting must be a GeodesicShooting, got {type(shooting).__name__}")
        shared = isinstance(ray_transform, LinearOperator)
        transforms = [ray_transform] if shared else ray_transform
        if not isinstance(transforms, Sequence) or not transforms:
            raise TypeError("ray_transform must be a linear operator (domain, range_shape, __call__, adjoint, "
                            f"inner_data) or a non-empty sequence of them, got {type(ray_transform).__name__}")
        for k, t in enumerate(transforms):
            check_operator(t, "ray_transform" if shared else f"ray_transform[{k}]")
            if t.domain != shooting.domain:
                raise ValueError(f"ray transform domain {t.domain!r} differs from the shooting domain "
                                 f"{shooting.domain!r}")
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}")
        self.shooting = shooting
        self.transforms = list(transforms)  # operators, not necessarily nn.Modules
        self.shared = shared
        self.gamma = check_nonnegative(gamma, "gamma")
        self.reduction = reduction

    def _assignment(self, batch: int, index) -> torch.Tensor:
        """Which transform each sample uses: ``(B,)`` long tensor (on CPU)."""
        if index is None:
            if self.shared:
                return torch.zeros(batch, dtype=torch.long)
            if len(self.transforms) != batch:
                raise ValueError(f"{len(self.transforms)} ray transforms for a batch of {batch}: give one per "
                                 "sample or an index (B,) into the list")
            return torch.arange(batch)
        index = _integer_index(index)
        if index.numel() != batch:
            raise ValueError(f"index must have one entry per sample ({batch}), got {index.numel()}")
        if int(index.min()) < 0 or int(index.max()) >= len(self.transforms):
            raise ValueError(f"index entries must lie in [0, {len(self.transforms) - 1}], got {index.tolist()}")
        return index

    def _check_data(self, data, assignment: torch.Tensor, like: torch.Tensor, like_name: str) -> None:
        """``data`` against the ranges of the samples' transforms: a tensor ``(B, *range_shape)`` or a list of
        ``B`` tensors of shape ``range_shape_b``, finite, with the dtype and device of ``like``."""
        batch = assignment.numel()
        if isinstance(data, torch.Tensor):
            check_tensor(data, "data")
            for k in assignment.unique().tolist():
                shape = tuple(self.transforms[k].range_shape)
                if data.dim() != 1 + len(shape) or len(data) != batch or tuple(data.shape[1:]) != shape:
                    raise ValueError(f"data must have shape (B={batch}, {', '.join(map(str, shape))}), "
                                     f"got {tuple(data.shape)}")
            check_same(data, like, "data", like_name)
            return
        if not isinstance(data, (list, tuple)):
            raise TypeError(f"data must be a tensor (B, *range_shape) or a list of B tensors, "
                            f"got {type(data).__name__}")
        if len(data) != batch:
            raise ValueError(f"data must hold one sinogram per sample ({batch}), got {len(data)}")
        for b, (g, k) in enumerate(zip(data, assignment.tolist())):
            shape = tuple(self.transforms[k].range_shape)
            check_tensor(g, f"data[{b}]", shape)
            if g.dim() != len(shape):
                raise ValueError(f"data[{b}] must have shape {shape}, got {tuple(g.shape)}")
            check_same(g, like, f"data[{b}]", like_name)

    def data_fit(self, deformed: torch.Tensor, data, index=None) -> torch.Tensor:
        """``||T_b(deformed_b) - g_b||^2_data`` per sample, ``(B,)``, for ``deformed (B, nx, ny)``."""
        assignment = self._assignment(deformed.shape[0], index)
        self._check_data(data, assignment, deformed, "deformed")
        return self._data_fit(deformed, data, assignment)

    def _data_fit(self, deformed: torch.Tensor, data, assignment: torch.Tensor) -> torch.Tensor:
        out = deformed.new_zeros(deformed.shape[0])
        for k in assignment.unique().tolist():
            rows = (assignment == k).nonzero().flatten()
            T = self.transforms[k]
            g = torch.stack([data[b] for b in rows.tolist()]) if isinstance(data, (list, tuple)) else data[rows]
            residual = T(deformed[rows.to(deformed.device)]) - g
            out = out.index_put((rows.to(out.device),), T.inner_data(residual, residual))
        return out

    def terms(self, momentum: torch.Tensor, template: torch.Tensor, data, index=None) -> dict:
        """Per-sample ``loss``, ``data_fit``, ``regulariser`` (``(B,)`` tensors) and the ``deformed`` templates."""
        check_tensor(momentum, "momentum", (2, *self.shooting.domain.shape))
        if momentum.dim() != 4:
            raise ValueError(f"momentum must have shape (B, 2, nx, ny), got {tuple(momentum.shape)}")
        assignment = self._assignment(momentum.shape[0], index)
        self._check_data(data, assignment, momentum, "momentum")
        deformed = self.shooting(momentum, template)
        fit = self._data_fit(deformed, data, assignment)
        reg = self.shooting.energy(momentum)
        return {"loss": fit + self.gamma * reg, "data_fit": fit, "regulariser": reg, "deformed": deformed}

    def forward(self, momentum: torch.Tensor, template: torch.Tensor, data, index=None) -> torch.Tensor:
        """The loss, reduced over the batch as ``reduction`` says."""
        loss = self.terms(momentum, template, data, index)["loss"]
        return {"mean": loss.mean, "sum": loss.sum, "none": lambda: loss}[self.reduction]()


def check_scheme(loss, initial) -> None:
    """The arguments every unrolled scheme takes (``UnrolledMomentum``, ``UnrolledDescent``): an
    ``IndirectShootingLoss`` and an initial network (an ``nn.Module`` (template, FBP) -> m0) or None."""
    if not isinstance(loss, IndirectShootingLoss):
        raise TypeError(f"loss must be an IndirectShootingLoss, got {type(loss).__name__}")
    if initial is not None and not isinstance(initial, torch.nn.Module):
        raise TypeError(f"initial must be an nn.Module (template, FBP) -> m0 or None, got {type(initial).__name__}")
