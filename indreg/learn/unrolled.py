"""Unrolled momentum updates through the indirect gradient: learned gradient descent on the initial momentum.

``K`` learned steps ``m_{k+1} = m_k + U_k(m_k, grad_k, W(m_k, I), I, FBP(g))`` from ``m_0`` (a one-shot network's
prediction ``Lambda(I, FBP(g))``, or zero), where ``grad_k`` is the exact L2 gradient at ``m_k`` of the indirect
loss ``||T W(m, I) - g||^2_data + gamma <m, K m>`` (``IndirectShootingLoss``: geodesic shooting and the
projector with their own backward passes) and ``U_k`` a small ``MomentumUNet`` (one per step, or one shared).
This is Adler & Oektem's learned gradient descent with LDDMM's physics in the gradient.

Gradient of the scheme (``gradient``):
    ``"detached"`` (the default; what ``indreg-train-momentum model=unrolled`` trains): ``grad_k`` is an input
    of step ``k`` without a graph (stop-gradient), so the training loss reaches the parameters of earlier steps
    only through ``m_k``. One shooting forward and backward per step, as at inference.
    ``"exact"``: ``grad_k`` keeps its graph (double backward through shooting and the projector), so the scheme's
    gradient is the derivative of the whole map; measured at 64^2, batch 8: a gradient 0.11 s, with its graph
    differentiated again 0.51 s (4.4x) on one CPU core.

Memory: with ``checkpoint=True`` each update network runs under ``torch.utils.checkpoint``; with detached
gradients autograd keeps only the ``K`` step inputs (``O(K n^2)``).

Notes
-----
template, FBP and deformed templates ``(B, nx, ny)``, momenta and gradients ``(B, 2, nx, ny)``
(component 0 = x, 1 = y), data ``(B, *range_shape)`` of the loss's ray transform. The update networks see
``m_k / momentum_scale``, ``grad_k / gradient_scale`` and the three images (7 channels); ``gradient_scale`` is a
buffer (saved with the weights), set once from a batch by ``calibrate`` (the mean RMS of ``grad_0``).
"""
from __future__ import annotations

import copy

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint as _checkpoint

from .._checks import check_bool, check_int, check_positive
from .loss import IndirectShootingLoss, check_scheme
from .unet import MomentumUNet

__all__ = ["UnrolledMomentum", "indirect_gradient"]

GRADIENTS = ("detached", "exact")


def _unchecked(loss: IndirectShootingLoss) -> IndirectShootingLoss:
    """``loss`` with a shooting layer that does not checkpoint its time steps (same map, half the gradient's cost)."""
    if not loss.shooting.checkpoint:
        return loss
    shooting = copy.copy(loss.shooting)
    shooting.checkpoint = False
    return IndirectShootingLoss(shooting, loss.transforms[0] if loss.shared else loss.transforms, loss.gamma)


def indirect_gradient(loss: IndirectShootingLoss, momentum: torch.Tensor, template: torch.Tensor, data,
                      create_graph: bool = False) -> tuple:
    """``(grad, deformed)``: the L2 gradient of the per-sample indirect loss at ``momentum`` ``(B, 2, nx, ny)`` and
    the deformed templates ``W(momentum, template)`` ``(B, nx, ny)``; without ``create_graph`` both carry no graph
    (the momentum is detached first). The shooting keeps its whole graph for this one gradient (no checkpointing of
    its time steps: measured 0.12 s instead of 0.25 s per sample at 64^2, N = 10, on a busy CPU core).

    Parameters
    ----------
    loss : IndirectShootingLoss
        The indirect loss.
    momentum : torch.Tensor
        ``m``, ``(B, 2, nx, ny)``.
    template : torch.Tensor
        ``I``.
    data : torch.Tensor or list of torch.Tensor
        ``g`` as the loss takes it.
    create_graph : bool
        Keep the gradient's graph (double backward).

    Returns
    -------
    grad : torch.Tensor
        ``(B, 2, nx, ny)``.
    deformed : torch.Tensor
        ``W(m, I)``, ``(B, nx, ny)``.
    """
    loss = _unchecked(loss)
    with torch.enable_grad():
        m = momentum if create_graph else momentum.detach().requires_grad_(True)
        terms = loss.terms(m, template, data)
        (grad,) = torch.autograd.grad(terms["loss"].sum(), m, create_graph=create_graph)
    deformed = terms["deformed"]
    return (grad, deformed) if create_graph else (grad.detach(), deformed.detach())


class UnrolledMomentum(nn.Module):
    """``K`` learned updates of the initial momentum through the indirect gradient (see the module docstring).

    ``initial`` maps ``(B, 2, nx, ny)`` (template, FBP) to ``m_0``; ``None`` starts from zero. ``forward(template,
    fbp, data)`` returns ``m_K``; ``forward(..., num_updates=j)`` stops after ``j`` updates (``j = 0``: the
    initial network alone), ``trajectory`` returns ``[m_0, ..., m_K]``. The update networks' last layers start at
    zero, so an untrained scheme returns ``m_0``. The initial network gets a gradient only from ``num_updates=0``
    (it is trained on its own first and fixed inside the scheme) unless ``train_initial``.

    Parameters
    ----------
    loss : IndirectShootingLoss
        The indirect loss whose gradient the updates see.
    num_updates : int
        ``K`` (>= 1).
    width, levels : int
        The update networks' (``MomentumUNet``).
    shared : bool
        One update network for all steps.
    initial : torch.nn.Module, optional
        ``(B, 2, nx, ny)`` (template, FBP) -> ``m_0``; None: zero.
    momentum_scale : float
        The update networks' output scale.
    gradient : {"detached", "exact"}
        The scheme's gradient (module docstring).
    checkpoint : bool
        Run each update network under ``torch.utils.checkpoint``.
    train_initial : bool
        Let the training loss reach the initial network too.

    Raises
    ------
    TypeError
        A loss that is no ``IndirectShootingLoss``, an ``initial`` that is no module.
    ValueError
        An unknown ``gradient``, a count or scale out of range.

    Examples
    --------
    >>> from indreg import GaussianKernel, GeodesicShooting, ImageDomain, ParallelBeamGeometry, RayTransform
    >>> dom = ImageDomain.paper(16)
    >>> T = RayTransform(dom, ParallelBeamGeometry.paper(4, 24))
    >>> loss = IndirectShootingLoss(GeodesicShooting(dom, GaussianKernel(dom, 5.0), 3), T, gamma=1e-3)
    >>> scheme = UnrolledMomentum(loss, num_updates=2, width=4, levels=2).double()
    >>> template = torch.rand(3, 16, 16, dtype=torch.float64)
    >>> data = T(template)
    >>> scheme(template, template, data).shape
    torch.Size([3, 2, 16, 16])
    """

    def __init__(self, loss: IndirectShootingLoss, num_updates: int = 3, width: int = 16, levels: int = 2,
                 shared: bool = False, initial: nn.Module | None = None, momentum_scale: float = 1.0,
                 gradient: str = "detached", checkpoint: bool = True, train_initial: bool = False):
        super().__init__()
        check_scheme(loss, initial)
        if gradient not in GRADIENTS:
            raise ValueError(f"gradient must be one of {', '.join(GRADIENTS)}, got {gradient!r}")
        self.loss = loss
        self.initial = initial
        self.num_updates = check_int(num_updates, "num_updates", 1)
        self.shared = check_bool(shared, "shared")
        self.momentum_scale = check_positive(momentum_scale, "momentum_scale")
        self.gradient = gradient
        self.checkpoint = check_bool(checkpoint, "checkpoint")
        self.train_initial = check_bool(train_initial, "train_initial")
        self.updates = nn.ModuleList(MomentumUNet(7, width, levels, momentum_scale=self.momentum_scale)
                                     for _ in range(1 if self.shared else self.num_updates))
        self.register_buffer("gradient_scale", torch.ones(()))

    def extra_repr(self) -> str:
        return f"num_updates={self.num_updates}, shared={self.shared}, gradient={self.gradient!r}"

    def start(self, template: torch.Tensor, fbp: torch.Tensor) -> torch.Tensor:
        """``m_0``: the initial network's prediction, or zero."""
        if self.initial is None:
            return template.new_zeros(template.shape[0], 2, *template.shape[1:])
        return self.initial(torch.stack([template, fbp], dim=1))

    @torch.no_grad()
    def calibrate(self, template: torch.Tensor, fbp: torch.Tensor, data) -> float:
        """Set ``gradient_scale`` to the mean over the batch of the RMS of ``grad_0``; returns it."""
        grad, _ = indirect_gradient(self.loss, self.start(template, fbp), template, data)
        scale = grad.square().mean(dim=(1, 2, 3)).sqrt().mean()
        if not torch.isfinite(scale) or scale <= 0:
            raise ValueError(f"cannot calibrate the gradient scale: the mean RMS of grad_0 is {float(scale)}")
        self.gradient_scale.fill_(scale)
        return float(scale)

    def update(self, k: int, momentum, grad, deformed, template, fbp) -> torch.Tensor:
        """``m_{k+1} = m_k + U_k(m_k, grad_k, W(m_k, I), I, FBP)`` (``k`` counts from 0)."""
        x = torch.cat([momentum / self.momentum_scale, grad / self.gradient_scale,
                       torch.stack([deformed, template, fbp], dim=1)], dim=1)
        net = self.updates[0 if self.shared else k]
        if self.checkpoint and torch.is_grad_enabled():
            return momentum + _checkpoint(net, x, use_reentrant=False)
        return momentum + net(x)

    def trajectory(self, template: torch.Tensor, fbp: torch.Tensor, data, num_updates: int | None = None) -> list:
        """``[m_0, m_1, ..., m_j]`` for ``j = num_updates`` (default ``K``)."""
        steps = self.num_updates if num_updates is None else num_updates
        if not isinstance(steps, int) or not 0 <= steps <= self.num_updates:
            raise ValueError(f"num_updates must be an integer in [0, {self.num_updates}], got {steps!r}")
        with torch.set_grad_enabled(torch.is_grad_enabled() and (self.train_initial or steps == 0)):
            momenta = [self.start(template, fbp)]
        for k in range(steps):
            exact = self.gradient == "exact" and torch.is_grad_enabled() and momenta[-1].requires_grad
            grad, deformed = indirect_gradient(self.loss, momenta[-1], template, data, create_graph=exact)
            momenta.append(self.update(k, momenta[-1], grad, deformed, template, fbp))
        return momenta

    def forward(self, template: torch.Tensor, fbp: torch.Tensor, data, num_updates: int | None = None) -> torch.Tensor:
        return self.trajectory(template, fbp, data, num_updates)[-1]
