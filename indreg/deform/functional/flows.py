"""The time-stepping recursions of the flow: eq:ODEflow1b forward in time (trajectories of the template
and of the Jacobian determinant, displacements, the deformation ``phi_{1,0}``).

Differentiable by autograd; without a graph to record they run in place (reused buffers, ``out=``).

Notes
-----
- Images ``(..., nx, ny)``, vector fields ``(..., 2, nx, ny)``, velocity fields ``(..., N+1, 2, nx, ny)``
  at ``t_i = i / N`` (3D: ``(..., 3, nx, ny, nz)``, module ``functional``); physical units of
  ``ImageDomain``.
- In the recursions the batch dims of images and velocities must already agree (broadcast first).
- Interpolation and padding as in ``sampling``; differences as in ``differences``.
"""
from __future__ import annotations

import torch

from ...domain import ImageDomain
from .differences import _growth_into, divergence
from .sampling import _planar_identity_grid, _sample_displaced, identity_grid, sample, to_grid_units

ACTIONS = ("geometric", "mass_preserving")
INTERPOLATIONS = ("reinterpolate", "compose")


def _check_action(action: str) -> None:
    if action not in ACTIONS:
        raise ValueError(f"action must be one of {ACTIONS}, got {action!r}")


def _check_interpolation(interpolation: str) -> None:
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")


def step_flags(velocity: torch.Tensor, ndim: int = 2) -> tuple:
    """``(moving, finite)`` of a velocity ``(..., N+1, d, *shape)`` (``d = ndim`` image axes) in one pass without
    temporaries.

    ``moving[i]``: ``nu(t_i)`` is numerically nonzero (its L2 norm over all batch entries is > 0; a step whose
    squares all underflow moves every point by less than a rounding error and is skipped, which is exact);
    ``finite``: the norms are finite (nan and inf propagate; a finite field whose squares overflow reports
    False, and ``LDDMMDeformation`` then runs the full element check). Used to skip the zero steps
    (``_Steps``) and, by ``LDDMMDeformation``, as the finiteness check of the input.
    """
    norms = torch.linalg.vector_norm(velocity.detach().flatten(-ndim - 1), dim=-1)
    norms = norms.reshape(-1, norms.shape[-1]).amax(0)
    return (norms > 0).tolist(), bool(torch.isfinite(norms).all())


class _Steps:
    """The small deformations ``Id + sign * nu(t_i)/N`` of the time steps, as ``grid_sample`` grids.

    ``grid(i)`` is the grid of ``x + w_i(x)``, ``w_i = sign * nu(t_i)/N`` in grid units (``w(i)``), built per
    step, so no ``O(N n^d)`` temporaries are made. Without autograd it is built planar, ``(..., d, *shape)``
    (d contiguous fused adds into a reused buffer) and handed to ``grid_sample`` as the strided view
    ``(..., *shape, d)`` (``grid_sample`` reads any strides; the same values, half the cost of writing the
    interleaved layout); the last one is kept for a second transport of the same step. ``moves(i)`` is False
    for a step whose velocity is exactly zero everywhere (all batch entries) while no graph is recorded: the
    step is skipped, so ``nu = 0`` maps every image to itself bit for bit (``(2j + 1) / n - 1`` is not exact
    in floating point and ``grid_sample`` scales its rounding error by ``n / 2``: an identity step would
    change a 438^2 float32 image by ~3e-5). ``moving`` (``step_flags``) can be given when already known.
    While autograd records (``backward="autograd"``) every step is interpolated, so derivatives w.r.t. ``nu``
    exist at ``nu = 0``; the identity then holds up to that rounding.
    """

    def __init__(self, velocity: torch.Tensor, domain: ImageDomain, sign: float, moving: list | None = None):
        d = self.ndim = domain.ndim
        n = velocity.shape[-d - 2] - 1
        self.velocity, self.domain = velocity, domain
        self.step = sign / n
        self.scale = tuple(self.step * 2.0 / e for e in domain.extent)  # physical -> grid units, times sign / N
        self.recording = torch.is_grad_enabled() and velocity.requires_grad
        self._moving, self._buffer, self._buffer_step, self._velocities = moving, None, None, None
        if self.recording:  # one graph node for all steps (per-step slicing would zero-fill a full-size
            # gradient for every slice in backward)
            w = to_grid_units(velocity, domain) * self.step
            self._w = w.unbind(-d - 2)
            base = identity_grid(domain, velocity.dtype, velocity.device)
            self._grids = (base + w.movedim(-d - 1, -1).flip(-1)).unbind(-d - 2)
        else:  # planar identity grid in grid_sample's order ([z,] y, x) in grid units, each (*shape)
            self.base = _planar_identity_grid(domain, velocity.dtype, velocity.device).unbind(0)

    def moves(self, i: int) -> bool:
        if self.recording:
            return True
        if self._moving is None:
            self._moving = step_flags(self.velocity, self.ndim)[0]
        return self._moving[i]

    def w(self, i: int) -> torch.Tensor:
        """``sign * nu(t_i)/N`` in grid units, ``(..., d, *shape)``."""
        if self.recording:
            return self._w[i]
        return to_grid_units(self.velocity.select(-self.ndim - 2, i), self.domain) * self.step

    def grid(self, i: int) -> torch.Tensor:
        if self.recording:
            return self._grids[i]
        if self._buffer_step != i:
            d = self.ndim
            if self._velocities is None:
                self._velocities = self.velocity.unbind(-d - 2)
            v = self._velocities[i]
            # an image may require grad: grid_sample then keeps the grid for backward (no reuse)
            if self._buffer is None or torch.is_grad_enabled():
                self._buffer = torch.empty_like(v)
                self._planes, self._grid = self._buffer.unbind(-d - 1), self._buffer.movedim(-d - 1, -1)
            for k, vk in enumerate(v.unbind(-d - 1)):  # grid plane d-1-k holds component k (x, y[, z])
                torch.add(self.base[d - 1 - k], vk, alpha=self.scale[k], out=self._planes[d - 1 - k])
            self._buffer_step = i
        return self._grid

    def move(self, f: torch.Tensor, i: int, padding_mode: str) -> torch.Tensor:
        """``f o (Id + w_i)`` for ``f (..., C, *shape)``."""
        return sample(f, self.grid(i), padding_mode) if self.moves(i) else f


def displacements_t0(velocity: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """Displacements ``u_i = phi_{t_i,0} - Id`` in grid units, ``(..., N+1, d, *shape)``, by eq:ODEflow1b.

    ``phi_{t_i,0} = phi_{t_{i-1},0} o (Id - nu(t_i)/N)``, i.e.
    ``u_i(x) = u_{i-1}(x - nu(t_i, x)/N) - nu(t_i, x)/N`` with ``u_0 = 0`` (border padding for ``u``).
    """
    steps, t = _Steps(velocity, domain, -1.0), -domain.ndim - 2
    u = [torch.zeros_like(velocity.select(t, 0))]
    for i in range(1, velocity.shape[t]):
        u.append(steps.move(u[-1], i, "border") + steps.w(i) if steps.moves(i) else u[-1])
    return torch.stack(u, dim=t)


def displacement_10(velocity: torch.Tensor, domain: ImageDomain, moving: list | None = None) -> torch.Tensor:
    """``phi_{1,0} - Id`` in physical units, ``(..., d, *shape)``: the last displacement of ``displacements_t0``.

    The same recursion (eq:ODEflow1b, border padding) keeping only the current displacement (no
    ``O(N n^2)`` stack); without autograd the step's ``-nu(t_i)/N`` is added in place.
    ``moving``: the steps' ``step_flags``, when already known.
    """
    steps, t = _Steps(velocity, domain, -1.0, moving), -domain.ndim - 2
    u = torch.zeros_like(velocity.select(t, 0))  # physical units (interpolation is unit-free)
    for i in range(1, velocity.shape[t]):
        if not steps.moves(i):
            continue
        if steps.recording:
            u = steps.move(u, i, "border") + velocity.select(t, i) * steps.step
        else:  # grid_sample's output is a fresh tensor
            u = steps.move(u, i, "border").add_(velocity.select(t, i), alpha=steps.step)
    return u


def deformation(velocity: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """``phi_{1,0}`` as physical points ``(..., d, *shape)``, composing the small deformations of eq:ODEflow1b."""
    return domain.points(velocity.dtype, velocity.device) + displacement_10(velocity, domain)


def template_trajectory(template: torch.Tensor, velocity: torch.Tensor, domain: ImageDomain,
                        interpolation: str = "reinterpolate", moving: list | None = None,
                        out: torch.Tensor | None = None) -> torch.Tensor:
    """``I o phi_{t_i,0}`` for ``i = 0..N``, ``(..., N+1, *shape)`` (Algorithm 1, line 7, eq:ODEflow1b).

    ``"reinterpolate"`` (the paper): ``I o phi_{t_i,0} = (I o phi_{t_{i-1},0}) o (Id - nu(t_i)/N)``, one
    bilinear interpolation of the current image per step (the blur accumulates over N steps).
    ``"compose"``: compose the displacements first (``displacements_t0``) and interpolate the template
    once per output time, ``I o (Id + u_i)``. ``moving``: the steps' ``step_flags``, when already known.
    ``out``: a tensor (any strides) to write the trajectory into, without autograd.
    """
    _check_interpolation(interpolation)
    recording = torch.is_grad_enabled() and (velocity.requires_grad or template.requires_grad)
    if out is not None and recording:
        raise RuntimeError("template_trajectory(out=...) does not record autograd graphs")
    d = domain.ndim
    c = -d - 1  # the channel (component) axis of (..., C, *shape), the time axis of (..., N+1, *shape)
    if interpolation == "compose":
        u = displacements_t0(velocity, domain)
        images = _sample_displaced(template.unsqueeze(c).unsqueeze(c), u, domain, "zeros").squeeze(c)
        return images if out is None else out.copy_(images)
    steps = _Steps(velocity, domain, -1.0, moving)
    if recording:
        images = [template]
        for i in range(1, velocity.shape[c - 1]):
            images.append(steps.move(images[-1].unsqueeze(c), i, "zeros").squeeze(c))
        return torch.stack(images, dim=c)
    if out is None:
        out = template.new_empty(*template.shape[:-d], velocity.shape[c - 1], *template.shape[-d:])
    frames = out.unbind(c)  # written in place: no second copy of the trajectory
    frames[0].copy_(template)
    for i in range(1, len(frames)):
        frames[i].copy_(steps.move(frames[i - 1].unsqueeze(c), i, "zeros").squeeze(c))
    return out


def jacobian_trajectory(velocity: torch.Tensor, domain: ImageDomain, scheme: str = "central",
                        moving: list | None = None, out: torch.Tensor | None = None) -> torch.Tensor:
    """``|D phi_{t_i,0}|`` for ``i = 0..N``, ``(..., N+1, *shape)`` (the mass-preserving replacement of step 8).

    ``|D phi_{t_i,0}| = (1 - div nu(t_i)/N) * |D phi_{t_{i-1},0}| o (Id - nu(t_i)/N)``, ``|D phi_{0,0}| = 1``
    (border padding). ``out``: a tensor (any strides) to write it into, without autograd.
    """
    d = domain.ndim
    c, n = -d - 1, velocity.shape[-d - 2] - 1
    steps = _Steps(velocity, domain, -1.0, moving)
    if not steps.recording:
        if out is None:
            out = velocity.new_empty(velocity.shape[:c] + velocity.shape[-d:])
        return _jacobian_trajectory_into(out, velocity, domain, scheme, steps)
    if out is not None:
        raise RuntimeError("jacobian_trajectory(out=...) does not record autograd graphs")
    nu = velocity.unbind(c - 1)  # one graph node (per-step slicing would zero-fill full-size gradients)
    jac = [torch.ones_like(nu[0].select(c, 0))]
    for i in range(1, n + 1):
        if steps.moves(i):
            moved = steps.move(jac[-1].unsqueeze(c), i, "border").squeeze(c)
            jac.append((1 - divergence(nu[i], domain, scheme) / n) * moved)
        else:
            jac.append(jac[-1])
    return torch.stack(jac, dim=c)


def _jacobian_trajectory_into(jac: torch.Tensor, velocity: torch.Tensor, domain: ImageDomain, scheme: str,
                              steps: _Steps) -> torch.Tensor:
    """``jacobian_trajectory`` without autograd, into ``jac``: the factors ``1 - div nu(t_i)/N`` of all steps at
    once, then multiplied in place by the transported previous determinant."""
    c = -domain.ndim - 1
    n = velocity.shape[c - 1] - 1
    frames = _growth_into(jac, velocity, domain, scheme, -1.0 / n).unbind(c)
    frames[0].fill_(1.0)
    for i in range(1, n + 1):
        if steps.moves(i):
            frames[i].mul_(steps.move(frames[i - 1].unsqueeze(c), i, "border").squeeze(c))
        else:
            frames[i].copy_(frames[i - 1])
    return jac


def deformed_trajectory(template: torch.Tensor, velocity: torch.Tensor, domain: ImageDomain,
                        action: str = "geometric", interpolation: str = "reinterpolate",
                        scheme: str = "central", moving: list | None = None) -> torch.Tensor:
    """``W(nu, I)(t_i)``, ``(..., N+1, *shape)``: ``I o phi_{t_i,0}`` (geometric, eq:DeforOpGeom) or
    ``|D phi_{t_i,0}| I o phi_{t_i,0}`` (mass-preserving, eq:DeforOpMP)."""
    _check_action(action)
    images = template_trajectory(template, velocity, domain, interpolation, moving)
    if action == "geometric":
        return images
    jac = jacobian_trajectory(velocity, domain, scheme, moving)
    if torch.is_grad_enabled() and (velocity.requires_grad or template.requires_grad):
        return jac * images
    return jac.mul_(images)  # jac is a fresh tensor; images may be an expanded view
