"""The two backward passes of the deformation without autograd: the paper's gradient (Algorithm 1, lines
8-10; ``gradient_record`` / ``paper_gradient``) and the exact derivative of the discrete map, its hand-written
discrete adjoint (``exact_record`` / ``exact_gradient``).

Notes
-----
as the recursions (``flows``): batch dims already agreed, velocities ``(..., N+1, d, *shape)``,
images ``(..., *shape)``, physical units of ``ImageDomain``; gradients w.r.t. tensor entries.
"""
from __future__ import annotations

import torch

from ..._checks import broadcast_shapes
from ...domain import ImageDomain
from .differences import (_add_divergence_adjoint, _difference_factors, _differences_into, _growth_into,
                          _padded_scratch)
from .flows import _check_action, _check_interpolation, _Steps, jacobian_trajectory, template_trajectory
from .sampling import _sample_adjoint, displaced_grid, sample


def gradient_record(template: torch.Tensor, velocity: torch.Tensor, domain: ImageDomain,
                    action: str = "geometric", interpolation: str = "reinterpolate", scheme: str = "central",
                    moving: list | None = None) -> torch.Tensor:
    """The forward pass's record for ``paper_gradient``, shaped like the velocity ``(..., N+1, d, *shape)``.

    ``record[..., i, 0, ...] = W(nu, I)(t_i)`` (the trajectory, ``deformed_trajectory``) and, for the geometric
    action, ``record[..., i, 1, ...] = 1 + div nu(t_i)/N`` (the factors of line 8); for the mass-preserving
    action the second slots hold ``|D phi_{t_i,0}|`` (3D: the third slots are scratch). No autograd.
    ``paper_gradient`` overwrites it with the
    velocity gradient, step ``i`` after reading slot ``i``: forward and backward together hold one
    velocity-sized tensor, ``O(N n^2)`` as the paper's complexity analysis.
    """
    _check_action(action)
    d = domain.ndim
    t = -d - 2
    record = velocity.new_empty(broadcast_shapes(template.shape[:-d], velocity.shape[:t]) + velocity.shape[t:])
    frames, factors = record.unbind(t + 1)[:2]
    template_trajectory(template, velocity, domain, interpolation, moving, out=frames)
    if action == "geometric":
        _growth_into(factors, velocity, domain, scheme, 1.0 / (velocity.shape[t] - 1))
    else:
        frames.mul_(jacobian_trajectory(velocity, domain, scheme, moving, out=factors))
    return record


def paper_gradient(grad_out: torch.Tensor, velocity: torch.Tensor, record: torch.Tensor, domain: ImageDomain,
                   action: str = "geometric", interpolation: str = "reinterpolate", scheme: str = "central",
                   need_velocity: bool = True, moving: list | None = None) -> tuple:
    """The paper's gradient (Algorithm 1, lines 8-10, kernel not applied), scaled for torch entries.

    Given ``G = dL/dW`` (``grad_out (..., nx, ny)``, torch entries), ``velocity (..., N+1, 2, nx, ny)`` and
    the forward pass's ``record`` (``gradient_record``: the trajectory ``W(nu, I)(t_i)`` and the factors
    ``1 + div nu(t_i)/N``), carries ``G`` back along the flow (eq:ODEflow2b) for ``i = N-1..0`` with the
    small steps ``s_i = Id + nu(t_i)/N``. Returns ``(grad_velocity, grad_template)``:

    - geometric:        ``dL/dnu_i = -(1/N) rho_i grad(I o phi_{t_i,0})``, ``dL/dI = rho_0``, where
                        ``rho_i = |D phi_{t_i,1}| (G o phi_{t_i,1})``;
    - mass-preserving:  ``dL/dnu_i = +(1/N) |D phi_{t_i,0}| (I o phi_{t_i,0}) grad(G o phi_{t_i,1})``,
                        ``dL/dI = G o phi_{0,1}``, with ``G o phi_{t_i,1} = (G o phi_{t_{i+1},1}) o s_i`` (line 9).

    Lines 8 and 9 carry ``|D phi_{t_i,1}| = (1 + div nu(t_i)/N) |D phi_{t_{i+1},1}| o s_i`` and
    ``G o phi_{t_i,1}`` separately; the geometric gradient only needs their product, which obeys the same
    recursion: ``rho_i = (1 + div nu(t_i)/N) rho_{i+1} o s_i``, ``rho_N = G`` (composition distributes over
    products; it is the mass-preserving action of the step on ``G``, the adjoint of the geometric action).
    It is carried as one scalar field: one interpolation per step instead of two (zero padding: ``G`` is 0
    outside the domain). The two discretisations differ only by interpolating a product instead of
    multiplying interpolants: relative difference of the velocity gradient 0.33% / 0.20% / 0.11% / 0.06% at
    16^2 N=4 / 32^2 N=8 / 64^2 N=16 / 128^2 N=32 (tests/deform/test_lddmm.py), with the same distance to
    the exact discrete derivative (autograd) to 3 digits.

    With ``G = cell_volume * grad_L2`` these are ``(1/N) * cell_volume`` times the L2 gradients before the
    kernel of eq:GradGoalFunctionalVRHKS / eq:GradGoalFunctionalVRHKS_mp (and ``cell_volume`` times the L2
    gradient w.r.t. the template). ``interpolation="compose"`` composes the displacements of
    ``phi_{t_i,1}`` (``q_i(x) = q_{i+1}(x + nu(t_i, x)/N) + nu(t_i, x)/N``) and interpolates ``G`` once per
    step (``G o (Id + q_i)``) instead of re-interpolating a transported field; the Jacobian then follows
    line 8 (border padding). ``moving``: the steps' ``step_flags``, when already known.

    ``grad_velocity`` is ``record`` itself, overwritten (step ``i`` writes slot ``i`` after reading it), or None
    unless ``need_velocity`` (``record`` is then left as it is).
    """
    _check_action(action)
    _check_interpolation(interpolation)
    d = domain.ndim
    c = -d - 1  # the component axis of the slots, the channel axis of the transported fields
    n, shape = velocity.shape[c - 1] - 1, velocity.shape[-d:]
    if record.shape[c - 1:] != velocity.shape[c - 1:]:
        raise ValueError(f"record must be shaped like the velocity (gradient_record), (..., {n + 1}, {d}, "
                         f"{', '.join(map(str, shape))}), got {tuple(record.shape)}")
    geometric, compose = action == "geometric", interpolation == "compose"
    steps = _Steps(velocity, domain, 1.0, moving)
    slots = record.unbind(c - 1)
    g_t = grad_out.unsqueeze(c)  # G o phi_{t_i,1}; for the geometric reinterpolation rho_i; (..., 1, *shape)
    jac = torch.ones_like(g_t) if geometric and compose else None  # |D phi_{t_i,1}|
    q = torch.zeros_like(grad_out.unsqueeze(c).expand(*grad_out.shape[:-d], d, *shape)) if compose else None
    if need_velocity:  # the image differentiated at step i, zero-padded, and its differences
        padded, inner = _padded_scratch(grad_out, d)
        differences = torch.empty_like(slots[0])
    factors = _difference_factors(domain, scheme)
    for i in range(n, -1, -1):
        frame, factor = slots[i].narrow(c, 0, 1), slots[i].narrow(c, 1, 1)  # W(t_i), 1 + div nu(t_i)/N
        if i < n and steps.moves(i):
            if compose:  # the transports of a step share its grid (built once)
                q = steps.move(q, i, "border") + steps.w(i)
                g_t = sample(grad_out.unsqueeze(c), displaced_grid(q, domain), "zeros")
                if geometric:  # line 8
                    jac = steps.move(jac, i, "border").mul_(factor)
            else:
                g_t = steps.move(g_t, i, "zeros")
                if geometric:  # rho_i = (1 + div nu(t_i)/N) rho_{i+1} o s_i
                    g_t.mul_(factor)
        weight = (jac * g_t if compose else g_t) if geometric else g_t
        if need_velocity:  # geometric: -(1/N) rho_i grad(W(t_i)); mass-preserving: (1/N) W(t_i) grad(G o phi_{t_i,1})
            inner.copy_(frame if geometric else g_t)
            _differences_into(differences, padded, scheme, d)
            sign = -1.0 / n if geometric else 1.0 / n
            _weigh_into(slots[i], differences, weight if geometric else frame, tuple(sign * f for f in factors))
    return (record if need_velocity else None), weight.squeeze(c)


def _weigh_into(out: torch.Tensor, differences: torch.Tensor, weight: torch.Tensor, factors: tuple) -> None:
    """``out (..., d, *shape) = differences * weight * factors``, ``weight (..., 1, *shape)`` (the gradient's
    quotient factors, one per axis, folded into the weight; ``weight`` may share memory with ``out``: it is
    scaled into a temporary first)."""
    if all(f == factors[0] for f in factors):
        torch.mul(differences, weight * factors[0], out=out)
        return
    c = -len(factors) - 1
    scaled = [weight.squeeze(c) * f for f in factors]
    for o, d, w in zip(out.unbind(c), differences.unbind(c), scaled):
        torch.mul(d, w, out=o)


def _step_adjoint(grad: torch.Tensor, f: torch.Tensor, steps: _Steps, i: int, padding_mode: str,
                  need_input: bool, need_grid: bool) -> tuple:
    """``_sample_adjoint`` of the step ``f o (Id + w_i)``. A skipped (zero) step is the identity in the forward
    pass: its transpose is the identity, its grid gradient still the slope at the cell centres (the discrete
    map's derivative at ``nu(t_i) = 0``)."""
    moves = steps.moves(i)
    back, slope = _sample_adjoint(grad, f, steps.grid(i), padding_mode, need_input and moves, need_grid)
    return (back if moves else grad) if need_input else None, slope


class ExactRecord:
    """What the reverse sweep of ``exact_gradient`` needs from the forward pass (``exact_record``).

    ``slots``, shaped like the velocity ``(..., N+1, d, *shape)``: for ``"reinterpolate"`` the images
    ``I o phi_{t_i,0}`` in ``slots[..., i, 0]`` and, mass-preserving, ``|D phi_{t_i,0}|`` in ``slots[..., i, 1]``;
    for ``"compose"`` the displacements ``u_i = phi_{t_i,0} - Id`` (grid units). ``exact_gradient`` overwrites
    ``slots`` with the velocity gradient. ``"compose"`` with the mass-preserving action also keeps the
    determinants ``jacobians (..., N+1, *shape)`` and the last image ``image = I o phi_{1,0} (..., *shape)``.
    """

    def __init__(self, slots, jacobians=None, image=None):
        self.slots, self.jacobians, self.image = slots, jacobians, image


def exact_record(template: torch.Tensor, velocity: torch.Tensor, domain: ImageDomain, action: str = "geometric",
                 interpolation: str = "reinterpolate", scheme: str = "central",
                 moving: list | None = None) -> tuple:
    """The forward pass for ``exact_gradient``: ``(W(nu, I), ExactRecord)``, no autograd.

    ``W(nu, I)`` is bit for bit that of ``deformed_trajectory`` and of ``gradient_record`` (the same operations on
    the same values). Memory: the record is one velocity-sized tensor (mass-preserving ``"compose"``: plus one
    ``(..., N+1, nx, ny)`` tensor of determinants), which ``exact_gradient`` turns into the velocity gradient.
    """
    _check_action(action)
    _check_interpolation(interpolation)
    d = domain.ndim
    c = -d - 1
    batch = broadcast_shapes(template.shape[:-d], velocity.shape[:c - 1])
    slots = velocity.new_empty(batch + velocity.shape[c - 1:])
    geometric = action == "geometric"
    if interpolation == "reinterpolate":
        frames, jacobians = slots.unbind(c)[:2]
        template_trajectory(template, velocity, domain, interpolation, moving, out=frames)
        if geometric:
            return frames.select(c, -1).clone(), ExactRecord(slots)
        jacobian_trajectory(velocity, domain, scheme, moving, out=jacobians)
        return frames.select(c, -1) * jacobians.select(c, -1), ExactRecord(slots)
    _displacements_into(slots, velocity, domain, moving)
    last = slots.select(c - 1, -1)
    if bool(last.ne(0).any()) or bool(slots.ne(0).any()):  # as _sample_displaced: identity iff all u_i = 0
        image = sample(template.expand(*batch, *template.shape[-d:]).unsqueeze(c), displaced_grid(last, domain),
                       "zeros").squeeze(c)
    else:
        image = template.expand(*batch, *template.shape[-d:]).clone()
    if geometric:
        return image, ExactRecord(slots)
    jacobians = jacobian_trajectory(velocity, domain, scheme, moving)
    return image * jacobians.select(c, -1), ExactRecord(slots, jacobians, image)


def _displacements_into(slots: torch.Tensor, velocity: torch.Tensor, domain: ImageDomain, moving: list | None) -> None:
    """``displacements_t0`` written into ``slots (..., N+1, d, *shape)`` (the same operations, no stack)."""
    steps, u = _Steps(velocity, domain, -1.0, moving), slots.unbind(-domain.ndim - 2)
    u[0].zero_()
    for i in range(1, len(u)):
        if steps.moves(i):
            torch.add(steps.move(u[i - 1], i, "border"), steps.w(i), out=u[i])
        else:
            u[i].copy_(u[i - 1])


def exact_gradient(grad_out: torch.Tensor, template: torch.Tensor, velocity: torch.Tensor, record: ExactRecord,
                   domain: ImageDomain, action: str = "geometric", interpolation: str = "reinterpolate",
                   scheme: str = "central", need_velocity: bool = True, need_template: bool = True,
                   moving: list | None = None) -> tuple:
    """The exact derivative of the discrete map ``(nu, I) -> W(nu, I)``, transposed: ``(dL/dnu, dL/dI)``.

    Given ``G = dL/dW`` (``grad_out (..., nx, ny)``, torch entries), the inputs (broadcast to one batch) and the
    forward pass's ``exact_record``, a reverse sweep over the time steps (the discrete adjoint; no autograd
    graph). Equal to autograd through the forward recursions up to rounding. Returns
    ``(grad_velocity, grad_template)``, each None unless ``need_velocity`` / ``need_template``;
    ``grad_velocity`` is ``record.slots`` overwritten (step ``i`` writes slot ``i`` after reading slot ``i-1``).

    Derivation. Write ``w_i = -nu(t_i)/N`` (grid units: times ``2 / extent``) and ``S_i f = f o (Id + w_i)``
    (bilinear, ``sample``). One step ``(f, w_i) -> S_i f`` has the derivative
    ``d(S_i f) = S_i df + (grad_b f)(Id + w_i) . dw_i``, where ``grad_b f`` is the gradient of the piecewise
    bilinear interpolant of ``f``: at a point, the one-sided slopes across the cell it falls in (the upwind
    difference, not the central one of the paper). Its adjoint maps ``lam`` to
    ``(S_i^T lam, lam (grad_b f)(Id + w_i))``: ``S_i^T`` scatters ``lam`` with the bilinear weights (the transpose
    of ``grid_sample``); the second part is pointwise. Both come from one ``grid_sampler_2d_backward`` call.
    A step skipped because ``nu(t_i) = 0`` is the identity, whose transpose is the identity; its second part
    is still evaluated (the derivative at ``nu(t_i) = 0`` exists).

    - ``"reinterpolate"``, geometric (eq:ODEflow1b, Algorithm 1 line 7): ``f_0 = I``, ``f_i = S_i f_{i-1}``,
      ``W = f_N``. With ``lam_N = G``, for ``i = N..1``:
      ``dL/dw_i = lam_i (grad_b f_{i-1})(Id + w_i)``, ``lam_{i-1} = S_i^T lam_i``; then ``dL/dI = lam_0``.
    - mass-preserving (eq:DeforOpMP): also ``J_0 = 1``, ``J_i = c_i B_i`` with ``B_i = S_i J_{i-1}`` (border
      padding) and ``c_i = 1 - div nu(t_i)/N``; ``W = J_N f_N``. Hence ``lam_N = G J_N`` and the determinant's
      adjoint ``mu_N = G f_N``; per step ``dL/dc_i = mu_i B_i``, ``mu_{i-1} = S_i^T (c_i mu_i)`` and
      ``dL/dw_i`` gains ``c_i mu_i (grad_b J_{i-1})(Id + w_i)``; ``c_i`` adds
      ``dL/dnu(t_i) += -(1/N) div^T(mu_i B_i)`` (``divergence_adjoint``). ``B_i`` is recomputed (one
      interpolation per step), ``c_i`` too.
    - ``"compose"``: ``u_0 = 0``, ``u_i = S_i u_{i-1} + w_i`` (border padding, ``displacements_t0``),
      ``f = I o (Id + u_N)``, ``W = f`` (mass-preserving: ``J_N f``, ``J`` as above). With ``lam = G`` (``G J_N``):
      ``dL/dI = T^T lam`` (the scatter at ``Id + u_N``), ``k_N = lam (grad_b I)(Id + u_N)`` (a vector field);
      for ``i = N..1``: ``dL/dw_i = k_i + sum_c k_{i,c} (grad_b u_{i-1,c})(Id + w_i)``,
      ``k_{i-1} = S_i^T k_i`` (two channels; ``u_0 = 0`` contributes nothing).

    Finally ``dL/dnu(t_i) = -(1/N) (2 / extent) dL/dw_i`` (plus the ``c_i`` term) for ``i >= 1`` and
    ``dL/dnu(t_0) = 0`` (the discrete map does not use ``nu(t_0)``).

    Memory: the reverse sweep reads the record (images / determinants, or the displacements) and holds a few
    image-sized fields (``lam``, ``mu``, ``k``); cost per step: one ``grid_sampler_2d_backward`` per transported
    field (the scatter dominates, about three interpolations), plus one interpolation for ``B_i``.

    Notes
    -----
    ``grad_out (..., nx, ny)``, ``template (..., nx, ny)`` and ``velocity (..., N+1, 2, nx, ny)`` with the
    same batch dims (broadcast first), physical units of ``domain``; derivatives w.r.t. tensor entries
    (the scale of ``LDDMMDeformation``'s "Gradient scale"); float32 / float64, any device (the inputs').
    """
    _check_action(action)
    _check_interpolation(interpolation)
    t = -domain.ndim - 2
    if record.slots.shape[t:] != velocity.shape[t:]:
        raise ValueError(f"record.slots must be shaped like the velocity (exact_record), got "
                         f"{tuple(record.slots.shape)}")
    steps = _Steps(velocity, domain, -1.0, moving)
    if interpolation == "reinterpolate":
        grad_i = _reinterpolate_adjoint(grad_out, velocity, record, domain, action, scheme, steps, need_velocity,
                                        need_template)
    else:
        grad_i = _compose_adjoint(grad_out, template, velocity, record, domain, action, scheme, steps, need_velocity,
                                  need_template)
    if not need_velocity:
        return None, grad_i
    record.slots.select(t, 0).zero_()
    return record.slots, grad_i


def _reinterpolate_adjoint(grad_out, velocity, record, domain, action, scheme, steps, need_velocity, need_template):
    """The reverse sweep of ``exact_gradient`` for ``"reinterpolate"``; returns ``dL/dI`` (or None)."""
    c = -domain.ndim - 1
    slots, n = record.slots.unbind(c - 1), velocity.shape[c - 1] - 1
    images, jacobians = [s.select(c, 0) for s in slots], [s.select(c, 1) for s in slots]
    mass = action == "mass_preserving"
    lam = (grad_out * jacobians[n] if mass else grad_out).unsqueeze(c)  # dL/df_i
    mu = grad_out * images[n] if mass and need_velocity else None  # dL/dJ_i
    for i in range(n, 0, -1):
        lam, slope = _step_adjoint(lam, images[i - 1].unsqueeze(c), steps, i, "zeros", need_template or i > 1,
                                   need_velocity)
        if need_velocity:
            if mass:
                mu, slope_j, dc = _jacobian_step_adjoint(mu, jacobians[i - 1], velocity, steps, i, domain, scheme)
                slope.add_(slope_j)
            _write_velocity_gradient(slots[i], slope, steps.scale)
            if mass:  # c_i = 1 - div nu(t_i)/N
                _add_divergence_adjoint(slots[i], dc, domain, scheme, -1.0 / n)
    return lam.squeeze(c) if need_template else None


def _compose_adjoint(grad_out, template, velocity, record, domain, action, scheme, steps, need_velocity,
                     need_template):
    """The reverse sweep of ``exact_gradient`` for ``"compose"``; returns ``dL/dI`` (or None)."""
    c = -domain.ndim - 1
    slots, n = record.slots.unbind(c - 1), velocity.shape[c - 1] - 1
    mass = action == "mass_preserving"
    lam = grad_out * record.jacobians.select(c, n) if mass else grad_out
    moved = bool(slots[n].ne(0).any()) or bool(record.slots.ne(0).any())  # exact_record's identity test
    grad_i, kappa = _warp_adjoint(lam, template, slots[n], domain, moved, need_template, need_velocity)
    if need_velocity:
        _displacement_sweep(kappa, grad_out * record.image if mass else None, record, velocity, domain, scheme,
                            steps)
    return grad_i


def _warp_adjoint(lam, template, u, domain, moved, need_template, need_velocity) -> tuple:
    """The transposes of ``f = I o (Id + u)`` (``u (..., d, *shape)`` in grid units; the identity unless ``moved``)
    applied to ``lam = dL/df``: ``(dL/dI, dL/du)``, ``dL/du`` planar (x, y[, z]) ``(..., d, *shape)``, each None
    unless needed."""
    d = domain.ndim
    c = -d - 1
    grad_i, slope = _sample_adjoint(lam.unsqueeze(c), template.unsqueeze(c), displaced_grid(u, domain), "zeros",
                                    need_template and moved, need_velocity)
    if need_template and not moved:
        grad_i = lam.unsqueeze(c)
    kappa = torch.stack([slope[..., d - 1 - k] for k in range(d)], dim=c) if need_velocity else None
    return (grad_i.squeeze(c) if need_template else None), kappa


def _displacement_sweep(kappa, mu, record, velocity, domain, scheme, steps) -> None:
    """The reverse sweep over the steps ``u_i = S_i u_{i-1} + w_i`` (``record.slots`` holds the ``u_i``) and, when
    ``mu = dL/dJ_N`` is given, over the determinants ``J_i = c_i S_i J_{i-1}`` (``record.jacobians``), from
    ``kappa = dL/du_N`` (planar, grid units): writes ``dL/dnu(t_i)`` into ``record.slots[..., i, :, ...]`` for
    ``i = N..1`` (slot ``i`` after reading slot ``i - 1``)."""
    c = -domain.ndim - 1
    slots, n = record.slots.unbind(c - 1), velocity.shape[c - 1] - 1
    mass = mu is not None
    for i in range(n, 0, -1):
        # u_i = S_i u_{i-1} + w_i; u_0 = 0 has no slope
        back, slope = _step_adjoint(kappa, slots[i - 1], steps, i, "border", i > 1, i > 1)
        if mass:
            mu, slope_j, dc = _jacobian_step_adjoint(mu, record.jacobians.select(c, i - 1), velocity, steps, i,
                                                     domain, scheme)
            slope = slope_j if slope is None else slope.add_(slope_j)
        _write_velocity_gradient(slots[i], slope, steps.scale, kappa)
        if mass:
            _add_divergence_adjoint(slots[i], dc, domain, scheme, -1.0 / n)
        kappa = back


def _jacobian_step_adjoint(mu, jacobian, velocity, steps, i, domain, scheme) -> tuple:
    """The determinant's part of step ``i`` in reverse (``J_i = c_i B_i``, ``B_i = S_i J_{i-1}``): from
    ``mu_i = dL/dJ_i`` and ``J_{i-1}`` (``jacobian``), ``(mu_{i-1}, grid gradient, dL/dc_i = mu_i B_i)``."""
    c = -domain.ndim - 1
    growth = _growth_into(torch.empty_like(mu), velocity.select(c - 1, i), domain, scheme,
                          -1.0 / (velocity.shape[c - 1] - 1))  # c_i, recomputed
    dc = steps.move(jacobian.unsqueeze(c), i, "border").squeeze(c) * mu  # B_i recomputed
    back, slope = _step_adjoint(growth.mul_(mu).unsqueeze(c), jacobian.unsqueeze(c), steps, i, "border", i > 1,
                                True)
    return (back.squeeze(c) if i > 1 else None), slope, dc


def _write_velocity_gradient(slot: torch.Tensor, slope, scale: tuple, planar: torch.Tensor | None = None) -> None:
    """``slot (..., d, *shape) = dL/dnu(t_i)`` from ``dL/dw_i``: the grid gradient ``slope (..., *shape, d)``
    (reversed order, or None) plus ``planar (..., d, *shape)`` (x, y[, z]; or None), grid units, times
    ``-(1/N) 2 / extent`` per component (``_Steps.scale``)."""
    d = len(scale)
    for k in range(d):
        out = slot.select(-d - 1, k)
        if slope is None:
            torch.mul(planar.select(-d - 1, k), scale[k], out=out)
        elif planar is None:
            torch.mul(slope[..., d - 1 - k], scale[k], out=out)
        else:
            torch.add(planar.select(-d - 1, k), slope[..., d - 1 - k], out=out).mul_(scale[k])
