"""Unrolled Algorithm 1: learned gradient descent on the time-dependent momentum, with learned step sizes, learned
heavy-ball coefficients and an optional small correction network.

``K`` cheap steps in Algorithm 1's space (the iterate is the momentum ``m = (m_0, ..., m_N)`` of the velocity
``nu = K m`` on the N+1 time points; ``K`` below is the kernel only where it multiplies)::

    m_{k+1} = m_k - alpha_k h_k + beta_k (m_k - m_{k-1}) + U_k(W(K m_k, I), r_k, I),
    alpha_k = alpha * softplus(a_k) / softplus(0),     beta_k = tanh(b_k)  (beta_0 = 0)

``h_k`` is the L2 gradient of Algorithm 1's objective ``E(nu) = (gamma/2) sum_i (1/N)||nu_i||_V^2 + (1/2)||T W(nu,
I) - g||^2_data`` at ``m_k`` (``IndirectRegistration.l2_gradient``: one forward and the paper's backward of the
deformation, no shooting), ``r_k = T^*(T W(K m_k, I) - g)`` the back-projected residual (a by-product of that
backward), ``alpha`` Algorithm 1's step (``a_k = 0`` reproduces it), ``beta_k`` Polyak's heavy-ball coefficient
(``heavy_ball``; the last step's direction carried on, at no extra cost) and ``U_k`` (``correction``) a
``MomentumUNet`` on three images whose output, one field ``(B, 2, nx, ny)``, is added at every time point. On the
velocity the step reads ``nu_{k+1} = nu_k - alpha_k K h_k + beta_k (nu_k - nu_{k-1}) + K U_k``. The start ``m_0``
is the one-shot network's geodesic: its prediction ``Lambda(I, FBP(g))`` shot (``GeodesicShooting``), the
transported momenta ``m_{t_i}`` taken as the N+1 fields, as the benchmark's "one-shot + k Algorithm 1 steps"
starts (or zero without ``initial``). Untrained (``a_k = b_k = 0``, zero correction heads) the ``K`` steps are
exactly ``K`` Algorithm 1 iterations from that start.

Gradient of the scheme: ``h_k`` and the correction's inputs are computed without a graph (stop-gradient), so
``m_K`` is a linear recursion in the constant ``h_k``, ``x_k`` with coefficients ``alpha_k``, ``beta_k`` plus the
``U_k(x_k)``: the training loss reaches ``a_k``, ``b_k`` and ``U_k`` directly, and the backward costs one pass
through each ``U_k`` (no double backward).

Notes
-----
template, FBP, deformed templates and residuals ``(B, nx, ny)``; momenta and gradients ``(B, N+1, 2,
nx, ny)`` (component 0 = x, 1 = y; N = the shooting layer's ``num_steps``); data ``(B, *range_shape)`` of the loss's
ray transform. The correction networks see ``W(K m_k, I)``, ``r_k / residual_scale`` and ``I`` (3 channels);
``residual_scale`` is a buffer (saved with the weights), set once from a batch by ``calibrate`` (the mean RMS of
``r_0``).
"""
from __future__ import annotations

import math

import torch
from torch import nn

from .._checks import check_bool, check_int, check_positive
from ..deform.lddmm import LDDMMDeformation
from .loss import IndirectShootingLoss, check_scheme
from .unet import MomentumUNet

__all__ = ["UnrolledDescent", "descent_gradient", "descent_terms"]


def _deformation(loss: IndirectShootingLoss) -> LDDMMDeformation:
    """Algorithm 1's deformation operator for the loss's shooting layer (same grid, N and action; paper's backward)."""
    s = loss.shooting
    return LDDMMDeformation(s.domain, s.num_steps, s.deformation.action)


def _time_weight(loss: IndirectShootingLoss) -> float:
    return loss.shooting.domain.cell_volume / loss.shooting.num_steps


def descent_terms(loss: IndirectShootingLoss, momentum: torch.Tensor, template: torch.Tensor, data,
                  deformation: LDDMMDeformation | None = None) -> dict:
    """Per-sample terms ``(B,)`` of ``2 E`` at the time-dependent ``momentum`` ``(B, N+1, 2, nx, ny)`` in the
    loss's scale: ``data_fit = ||T f - g||^2_data``, ``regulariser = sum_i (1/N) <m_i, K m_i>``, ``loss = data_fit
    + gamma regulariser``, and ``deformed = f = W(K m, I)`` (differentiable through the paper's backward).

    Parameters
    ----------
    loss : IndirectShootingLoss
        Its shooting layer, operator(s) and ``gamma``.
    momentum : torch.Tensor
        ``m``, ``(B, N+1, 2, nx, ny)``.
    template : torch.Tensor
        ``I``, ``(B, nx, ny)`` or ``(nx, ny)``.
    data : torch.Tensor or list of torch.Tensor
        ``g`` as the loss takes it.
    deformation : LDDMMDeformation, optional
        Algorithm 1's operator (default: the loss's grid, N and action, the paper's backward).

    Returns
    -------
    dict
        ``loss``, ``data_fit``, ``regulariser`` ``(B,)`` and ``deformed`` ``(B, nx, ny)``.

    Raises
    ------
    ValueError
        A momentum of another shape.
    """
    shooting = loss.shooting
    if momentum.dim() != 5 or tuple(momentum.shape[1:]) != (shooting.num_steps + 1, 2, *shooting.domain.shape):
        raise ValueError(f"momentum must have shape (B, {shooting.num_steps + 1}, 2, "
                         f"{', '.join(map(str, shooting.domain.shape))}), got {tuple(momentum.shape)}")
    nu = shooting.kernel.apply(momentum)
    deformed = (deformation or _deformation(loss))(nu, template)
    fit = loss.data_fit(deformed, data)
    reg = _time_weight(loss) * (momentum * nu).flatten(1).sum(1)
    return {"loss": fit + loss.gamma * reg, "data_fit": fit, "regulariser": reg, "deformed": deformed}


def descent_gradient(loss: IndirectShootingLoss, momentum: torch.Tensor, template: torch.Tensor, data,
                     deformation: LDDMMDeformation | None = None) -> tuple:
    """``(h, deformed, residual)`` at ``momentum`` ``(B, N+1, 2, nx, ny)``, without a graph: Algorithm 1's L2
    gradient ``h = gamma m + (N / cell_volume) dL/dnu`` of every sample (``IndirectRegistration.l2_gradient``, batched),
    ``W(K m, I)`` and the back-projected residual ``T^*(T f - g)`` in torch's scale (``dL/df``, ``L = (1/2)||T f -
    g||^2_data``).

    Parameters
    ----------
    loss : IndirectShootingLoss
        Its shooting layer, operator(s) and ``gamma``.
    momentum : torch.Tensor
        ``m``, ``(B, N+1, 2, nx, ny)``.
    template : torch.Tensor
        ``I``.
    data : torch.Tensor or list of torch.Tensor
        ``g`` as the loss takes it.
    deformation : LDDMMDeformation, optional
        Algorithm 1's operator (default as :func:`descent_terms`).

    Returns
    -------
    h : torch.Tensor
        ``(B, N+1, 2, nx, ny)``.
    deformed : torch.Tensor
        ``W(K m, I)``, ``(B, nx, ny)``.
    residual : torch.Tensor
        ``T^*(T f - g)`` in torch's scale, ``(B, nx, ny)``.
    """
    nu = loss.shooting.kernel.apply(momentum.detach())
    with torch.enable_grad():
        leaf = nu.requires_grad_(True)
        deformed = (deformation or _deformation(loss))(leaf, template)
        fit = 0.5 * loss.data_fit(deformed, data).sum()
        d_nu, d_f = torch.autograd.grad(fit, (leaf, deformed))
    h = d_nu.div_(_time_weight(loss)).add_(momentum.detach(), alpha=loss.gamma)
    return h, deformed.detach(), d_f


class UnrolledDescent(nn.Module):
    """``K`` learned Algorithm 1 steps on the time-dependent momentum (see the module docstring).

    ``initial`` maps ``(B, 2, nx, ny)`` (template, FBP) to the initial momentum whose geodesic starts the descent;
    ``None`` starts from zero. ``forward(template, fbp, data)`` returns ``m_K`` ``(B, N+1, 2, nx, ny)``, whose
    deformed template is ``deformation(K m_K, I)`` (``deformation``: Algorithm 1's ``LDDMMDeformation``);
    ``num_updates=j`` stops after ``j`` steps, ``trajectory`` returns ``[m_0, ..., m_K]``, ``oneshot`` the initial
    network's ``(B, 2, nx, ny)`` prediction. ``step_size`` is Algorithm 1's step ``alpha`` (``step_sizes``: the learned
    ``alpha_k``); ``heavy_ball`` adds the learned ``beta_k`` (``inertias``); ``correction`` adds the network ``U``
    (``shared``: one ``U`` for all steps). The initial network gets no gradient (it is trained on its own first).

    Parameters
    ----------
    loss : IndirectShootingLoss
        The training loss (its shooting layer sets the grid, N and the kernel; its operator the data).
    num_updates : int
        ``K`` (>= 1).
    step_size : float
        Algorithm 1's step ``alpha`` (> 0).
    width, levels : int
        The correction networks' (``MomentumUNet``).
    shared : bool
        One correction network for all steps.
    correction : bool
        Add the correction networks ``U_k``.
    initial : torch.nn.Module, optional
        ``(B, 2, nx, ny)`` (template, FBP) -> the one-shot momentum; None: start from zero.
    momentum_scale : float
        The correction networks' output scale (``MomentumUNet``).
    heavy_ball : bool
        Learn the heavy-ball coefficients ``beta_k``.

    Raises
    ------
    TypeError
        A loss that is no ``IndirectShootingLoss``, an ``initial`` that is no module.
    ValueError
        A count or scale out of range.

    Examples
    --------
    >>> import indreg
    >>> dom = indreg.ImageDomain.paper(16)
    >>> shooting = indreg.GeodesicShooting(dom, indreg.GaussianKernel(dom, 5.0), num_steps=3)
    >>> loss = IndirectShootingLoss(shooting, indreg.RayTransform(dom, indreg.ParallelBeamGeometry.paper(4, 24)),
    ...                             gamma=1e-3)
    >>> scheme = UnrolledDescent(loss, num_updates=4, width=4, levels=2).double()
    >>> images = torch.rand(2, 16, 16, dtype=torch.float64)      # templates, and FBPs here too
    >>> m = scheme(images, images, loss.transforms[0](images))  # Algorithm 1's momentum: (B, N+1, 2, nx, ny)
    >>> m.shape
    torch.Size([2, 4, 2, 16, 16])
    """

    def __init__(self, loss: IndirectShootingLoss, num_updates: int = 10, step_size: float = 0.02, width: int = 8,
                 levels: int = 2, shared: bool = True, correction: bool = True, initial: nn.Module | None = None,
                 momentum_scale: float = 1.0, heavy_ball: bool = True):
        super().__init__()
        check_scheme(loss, initial)
        self.loss = loss
        self.initial = initial
        self.num_updates = check_int(num_updates, "num_updates", 1)
        self.step_size = check_positive(step_size, "step_size")
        self.shared = check_bool(shared, "shared")
        self.correction = check_bool(correction, "correction")
        self.momentum_scale = check_positive(momentum_scale, "momentum_scale")
        self.heavy_ball = check_bool(heavy_ball, "heavy_ball")
        self.step_logits = nn.Parameter(torch.zeros(self.num_updates))
        if self.heavy_ball:                   # b_1 .. b_{K-1} (step 0 has no previous iterate)
            self.inertia_logits = nn.Parameter(torch.zeros(self.num_updates - 1))
        count = (1 if self.shared else self.num_updates) if self.correction else 0
        self.updates = nn.ModuleList(MomentumUNet(3, width, levels, momentum_scale=self.momentum_scale)
                                     for _ in range(count))
        self.register_buffer("residual_scale", torch.ones(()))
        self.deformation = _deformation(loss)

    def extra_repr(self) -> str:
        return f"num_updates={self.num_updates}, step_size={self.step_size}, shared={self.shared}, " \
               f"correction={self.correction}, heavy_ball={self.heavy_ball}"

    @property
    def step_sizes(self) -> torch.Tensor:
        """``alpha_k = alpha softplus(a_k) / softplus(0)`` ``(K,)``, positive (``a_k = 0``: Algorithm 1's step)."""
        return self.step_size * nn.functional.softplus(self.step_logits) / math.log(2.0)

    @property
    def inertias(self) -> torch.Tensor:
        """The heavy-ball coefficients ``beta_k = tanh(b_k)`` of steps ``k = 1..K-1``, ``(K-1,)``, in ``(-1, 1)``
        (``b_k = 0``: none)."""
        return torch.tanh(self.inertia_logits)

    def oneshot(self, template: torch.Tensor, fbp: torch.Tensor) -> torch.Tensor:
        """The initial network's momentum ``(B, 2, nx, ny)`` (zero without one)."""
        if self.initial is None:
            return template.new_zeros(template.shape[0], 2, *template.shape[1:])
        return self.initial(torch.stack([template, fbp], dim=1))

    @torch.no_grad()
    def start(self, template: torch.Tensor, fbp: torch.Tensor) -> torch.Tensor:
        """``m_0`` ``(B, N+1, 2, nx, ny)``: the transported momenta of the one-shot geodesic (zero without one)."""
        m = self.oneshot(template, fbp)
        if self.initial is None:
            return m.unsqueeze(1).expand(-1, self.loss.shooting.num_steps + 1, -1, -1, -1).clone()
        return self.loss.shooting(m, template, return_all=True).momentum

    @torch.no_grad()
    def calibrate(self, template: torch.Tensor, fbp: torch.Tensor, data) -> float:
        """Set ``residual_scale`` to the mean over the batch of the RMS of ``r_0``; returns it."""
        _, _, residual = descent_gradient(self.loss, self.start(template, fbp), template, data)
        scale = residual.square().mean(dim=(1, 2)).sqrt().mean()
        if not torch.isfinite(scale) or scale <= 0:
            raise ValueError(f"cannot calibrate the residual scale: the mean RMS of r_0 is {float(scale)}")
        self.residual_scale.fill_(scale)
        return float(scale)

    def update(self, k: int, momentum, h, deformed, residual, template, previous=None) -> torch.Tensor:
        """``m_{k+1} = m_k - alpha_k h_k + beta_k (m_k - m_{k-1}) + U_k(W(K m_k, I), r_k / residual_scale, I)``
        (``k`` counts from 0; the heavy-ball term with ``heavy_ball`` and a ``previous`` iterate ``m_{k-1}``)."""
        step = momentum - self.step_sizes[k] * h
        if self.heavy_ball and previous is not None:
            step = step + self.inertias[k - 1] * (momentum - previous)
        if not self.correction:
            return step
        x = torch.stack([deformed, residual / self.residual_scale, template], dim=1)
        return step + self.updates[0 if self.shared else k](x).unsqueeze(1)

    def trajectory(self, template: torch.Tensor, fbp: torch.Tensor, data, num_updates: int | None = None) -> list:
        """``[m_0, m_1, ..., m_j]`` for ``j = num_updates`` (default ``K``)."""
        steps = self.num_updates if num_updates is None else num_updates
        if not isinstance(steps, int) or not 0 <= steps <= self.num_updates:
            raise ValueError(f"num_updates must be an integer in [0, {self.num_updates}], got {steps!r}")
        momenta = [self.start(template, fbp)]
        for k in range(steps):
            h, deformed, residual = descent_gradient(self.loss, momenta[-1], template, data, self.deformation)
            previous = momenta[-2] if k else None
            momenta.append(self.update(k, momenta[-1], h, deformed, residual, template, previous))
        return momenta

    def forward(self, template: torch.Tensor, fbp: torch.Tensor, data, num_updates: int | None = None,
                oneshot: bool = False) -> torch.Tensor:
        """``m_j`` for ``j = num_updates`` (default ``K``); with ``oneshot`` the initial network's prediction with its
        graph (its own training phase, through a DDP wrapper)."""
        if oneshot:
            return self.oneshot(template, fbp)
        return self.trajectory(template, fbp, data, num_updates)[-1]
