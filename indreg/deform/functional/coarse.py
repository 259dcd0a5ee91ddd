"""A velocity on a coarser grid of the same box as the image (a band-limited velocity): the flow on the coarse
grid, its displacement interpolated to the image's cell centres, the template sampled once.

With ``u_i = phi_{t_i,0} - Id`` composed on the coarse grid by eq:ODEflow1b (``displacements_t0``: border
padding, grid units) and ``P`` the interpolation from the coarse cell centres to the fine ones (``upsample``), the
deformation is ``W(nu, I) = I o (Id + P u_N)`` (geometric) or ``(P J_N) I o (Id + P u_N)`` (mass-preserving,
``J_N`` the first-order product ``jacobian_trajectory`` on the coarse grid): the ``"compose"`` interpolation with
``phi_{1,0}`` interpolated. ``coarse_record`` / ``coarse_gradient`` are its forward pass and the exact derivative
of this discrete map (``P^T`` after the fine warp's adjoint, then ``exact_gradient``'s reverse sweep on the coarse
grid).

Notes
-----
as the recursions (``flows``): batch dims already agreed; velocities ``(..., N+1, d, *coarse)`` on
``coarse``, images ``(..., *fine)`` on ``fine`` (two ``ImageDomain`` of the same box); displacements in the record
in grid units (``2 / extent`` times physical lengths: the same on both grids); gradients w.r.t. tensor entries.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ..._checks import broadcast_shapes
from ...domain import ImageDomain
from .backward import ExactRecord, _displacement_sweep, _displacements_into, _warp_adjoint
from .flows import _check_action, _Steps, displacements_t0, jacobian_trajectory
from .sampling import displaced_grid, sample

_MODES = {2: "bilinear", 3: "trilinear"}
_UPSAMPLE_BACKWARD = {2: torch.ops.aten.upsample_bilinear2d_backward,
                      3: torch.ops.aten.upsample_trilinear3d_backward}


def upsample(f: torch.Tensor, shape: tuple) -> torch.Tensor:
    """``P f``: the field ``f (..., C, *coarse)`` interpolated at the cell centres of the grid ``shape`` of the same
    box, ``(..., C, *shape)``.

    Bilinear (2D) / trilinear (3D) between the coarse cell centres (``align_corners=False``: both grids sample the
    box at their cell centres, so ``P`` is ``sample(f, identity_grid(fine), "border")``, tests), continued
    constantly beyond the outer coarse centres (the ``"border"`` padding of displacements and determinants).
    ``F.interpolate`` (parallel over the output on a CPU). ``f`` itself when it is on ``shape`` already.
    Differentiable by autograd; its transpose is ``upsample_adjoint``.
    """
    d = len(shape)
    coarse = tuple(f.shape[-d:])
    if coarse == tuple(shape):
        return f
    lead, c = f.shape[:-d - 1], f.shape[-d - 1]
    out = F.interpolate(f.reshape(-1, c, *coarse), size=tuple(shape), mode=_MODES[d], align_corners=False)
    return out.reshape(*lead, c, *shape)


def upsample_adjoint(g: torch.Tensor, shape: tuple) -> torch.Tensor:
    """``P^T g``: the transpose of ``upsample`` onto the coarser grid ``shape``, ``g (..., C, *fine)`` ->
    ``(..., C, *shape)`` (each fine value scattered to the coarse centres with its interpolation weights)."""
    d = len(shape)
    fine = tuple(g.shape[-d:])
    if fine == tuple(shape):
        return g
    lead, c = g.shape[:-d - 1], g.shape[-d - 1]
    flat = g.reshape(-1, c, *fine)
    out = _UPSAMPLE_BACKWARD[d](flat, list(fine), [flat.shape[0], c, *shape], False)
    return out.reshape(*lead, c, *shape)


def _upsample_scalar(f: torch.Tensor, shape: tuple) -> torch.Tensor:
    """``upsample`` of a scalar field ``(..., *coarse)``."""
    c = -len(shape) - 1
    return upsample(f.unsqueeze(c), shape).squeeze(c)


def _warped(template: torch.Tensor, u: torch.Tensor, fine: ImageDomain, moved: bool) -> torch.Tensor:
    """``I o (Id + P u)`` on ``fine`` for a coarse displacement ``u (..., d, *coarse)`` (grid units), a fresh
    tensor; a copy of the template when not ``moved``."""
    c = -fine.ndim - 1
    template = template.expand(*u.shape[:c], *template.shape[c + 1:])
    if not moved:
        return template.clone()
    return sample(template.unsqueeze(c), displaced_grid(upsample(u, fine.shape), fine), "zeros").squeeze(c)


def _displacements(velocity: torch.Tensor, coarse: ImageDomain, moving: list | None) -> torch.Tensor:
    """``u_i`` for ``i = 0..N`` (grid units): ``displacements_t0`` while autograd records, else written in place
    (``exact_record``'s values)."""
    if torch.is_grad_enabled() and velocity.requires_grad:
        return displacements_t0(velocity, coarse)
    u = torch.empty_like(velocity)
    _displacements_into(u, velocity, coarse, moving)
    return u


def _moved(u: torch.Tensor) -> bool:
    """Whether the template is sampled: always while autograd records ``u`` (derivatives at ``nu = 0``), else
    unless every ``u_i`` is exactly 0 (``nu = 0`` returns the template bit for bit)."""
    return (torch.is_grad_enabled() and u.requires_grad) or bool(u.ne(0).any())


def coarse_trajectory(template: torch.Tensor, velocity: torch.Tensor, coarse: ImageDomain, fine: ImageDomain,
                      action: str = "geometric", scheme: str = "central", moving: list | None = None,
                      last: bool = False) -> torch.Tensor:
    """``W(nu, I)(t_i)`` for ``i = 0..N``, ``(..., N+1, *fine)`` (or ``t_N`` alone, ``(..., *fine)``, if
    ``last``): ``I o (Id + P u_i)``, times ``P J_i`` for the mass-preserving action. Differentiable by
    autograd; without a graph the values of ``coarse_record``. ``moving``: the steps' ``step_flags``."""
    _check_action(action)
    d = coarse.ndim
    c = -d - 1
    u = _displacements(velocity, coarse, moving)
    moved = _moved(u)
    times = [u.shape[c - 1] - 1] if last else range(u.shape[c - 1])
    images = [_warped(template, u.select(c - 1, i), fine, moved) for i in times]
    if action == "mass_preserving":
        jac = jacobian_trajectory(velocity, coarse, scheme, moving)
        images = [_upsample_scalar(jac.select(c, i), fine.shape) * f for i, f in zip(times, images)]
    return images[0] if last else torch.stack(images, dim=c)


def coarse_record(template: torch.Tensor, velocity: torch.Tensor, coarse: ImageDomain, fine: ImageDomain,
                  action: str = "geometric", scheme: str = "central", moving: list | None = None) -> tuple:
    """The forward pass for ``coarse_gradient``: ``(W(nu, I), ExactRecord)``, no autograd.

    The record holds the coarse displacements ``u_i`` (``slots``, shaped like the velocity) and, mass-preserving,
    the coarse determinants ``J_i`` and the fine image ``I o (Id + P u_N)``; ``W`` is that of
    ``coarse_trajectory(..., last=True)`` bit for bit.
    """
    _check_action(action)
    d = coarse.ndim
    c = -d - 1
    batch = broadcast_shapes(template.shape[:-d], velocity.shape[:c - 1])
    slots = velocity.new_empty(batch + velocity.shape[c - 1:])
    _displacements_into(slots, velocity, coarse, moving)
    moved = bool(slots.ne(0).any())
    image = _warped(template, slots.select(c - 1, -1), fine, moved)
    if action == "geometric":
        return image, ExactRecord(slots)
    jacobians = jacobian_trajectory(velocity, coarse, scheme, moving)
    return _upsample_scalar(jacobians.select(c, -1), fine.shape) * image, ExactRecord(slots, jacobians, image)


def coarse_gradient(grad_out: torch.Tensor, template: torch.Tensor, velocity: torch.Tensor, record: ExactRecord,
                    coarse: ImageDomain, fine: ImageDomain, action: str = "geometric", scheme: str = "central",
                    need_velocity: bool = True, need_template: bool = True, moving: list | None = None) -> tuple:
    """The exact derivative of ``(nu, I) -> W(nu, I)`` (``coarse_record``), transposed: ``(dL/dnu, dL/dI)``.

    With ``lam = G`` (mass-preserving ``G P J_N``), ``G = dL/dW`` (``grad_out (..., *fine)``): the fine warp's
    adjoint gives ``dL/dI`` (the scatter at ``Id + P u_N``) and ``dL/d(P u_N) = lam (grad_b I)(Id + P u_N)``,
    whose ``P^T`` (``upsample_adjoint``) is ``dL/du_N``; mass-preserving, ``dL/dJ_N = P^T(G I o (Id + P u_N))``.
    From there the reverse sweep of ``exact_gradient``'s ``"compose"`` case on the coarse grid. Each result None
    unless ``need_velocity`` / ``need_template``; ``dL/dnu`` is ``record.slots`` overwritten, 0 at ``t_0``.
    """
    _check_action(action)
    c = -coarse.ndim - 1
    slots, n = record.slots, velocity.shape[c - 1] - 1
    if slots.shape[c - 1:] != velocity.shape[c - 1:]:
        raise ValueError(f"record.slots must be shaped like the velocity (coarse_record), got {tuple(slots.shape)}")
    mass = action == "mass_preserving"
    lam = grad_out * _upsample_scalar(record.jacobians.select(c, n), fine.shape) if mass else grad_out
    last = slots.select(c - 1, n)
    moved = bool(last.ne(0).any()) or bool(slots.ne(0).any())
    grad_i, kappa = _warp_adjoint(lam, template, upsample(last, fine.shape), fine, moved, need_template,
                                  need_velocity)
    if not need_velocity:
        return None, grad_i
    mu = upsample_adjoint((grad_out * record.image).unsqueeze(c), coarse.shape).squeeze(c) if mass else None
    _displacement_sweep(upsample_adjoint(kappa, coarse.shape), mu, record, velocity, coarse, scheme,
                        _Steps(velocity, coarse, -1.0, moving))
    slots.select(c - 1, 0).zero_()
    return slots, grad_i
