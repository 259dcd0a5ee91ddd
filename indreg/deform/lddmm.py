"""The LDDMM deformation operator W(nu, I) (eq:DeforOpGeom, eq:DeforOpMP) with the paper's gradient."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.autograd.function import once_differentiable

from .._checks import FLOAT_DTYPES, broadcast_shapes, check_int, check_nonempty, check_same, check_tensor
from ..domain import ImageDomain
from . import functional as Fd

ACTIONS = Fd.ACTIONS
BACKWARDS = ("paper", "exact", "autograd")


def _check_fast(x, name: str, trailing_shape: tuple) -> None:
    """``check_tensor`` with one cheap finiteness test (the sum of finite values is finite, barring overflow;
    any nan / inf makes it non-finite), falling back to the full check for the error message."""
    if not isinstance(x, torch.Tensor) or x.dtype not in FLOAT_DTYPES or x.shape[x.dim() - len(trailing_shape):] \
            != trailing_shape or not bool(torch.isfinite(x.sum())):
        check_tensor(x, name, trailing_shape)


@dataclass(frozen=True)
class _Config:
    domain: ImageDomain
    action: str
    interpolation: str
    scheme: str
    velocity_domain: ImageDomain | None = None  # a coarser grid of the velocity (CoarseVelocityDeformation)


class _PaperDeformation(torch.autograd.Function):
    """``W(nu, I)`` with the paper's gradient as backward (Algorithm 1, lines 7-10, without the kernel).

    The forward runs the time loop without an autograd graph and keeps only ``functional.gradient_record``:
    the trajectory ``W(nu, I)(t_i)`` and the factors ``1 + div nu(t_i)/N`` in one velocity-sized tensor,
    which the backward overwrites with the velocity gradient and returns: forward and backward together hold
    one ``(B, N+1, 2, nx, ny)`` tensor (memory ``O(N n^2)``). The record is kept on ``ctx`` (not through
    ``save_for_backward``, so saved-tensor hooks do not see it) and dropped once consumed; a second backward
    through a retained graph recomputes it. ``moving``: the per-step flags of ``functional.step_flags``
    (computed once by the input check, shared by both passes). Double backward is not supported
    (``once_differentiable``): use ``backward="autograd"`` for it.
    """

    @staticmethod
    def forward(velocity, template, config, moving):
        record = _record(velocity, template, config, moving)
        d = config.domain.ndim
        return record.select(-d - 2, -1).select(-d - 1, 0).clone(), record

    @staticmethod
    def setup_context(ctx, inputs, output):
        velocity, template, config, moving = inputs
        ctx.mark_non_differentiable(output[1])
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(velocity, template)
        ctx.config, ctx.moving, ctx.record = config, moving, output[1]

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out, _grad_record):
        if grad_out is None:
            return None, None, None, None
        velocity, template = ctx.saved_tensors
        c, need_velocity = ctx.config, ctx.needs_input_grad[0]
        record = ctx.record if ctx.record is not None else _record(velocity, template, c, ctx.moving)
        if need_velocity:  # paper_gradient overwrites it
            ctx.record = None
        d = c.domain.ndim
        grad_v, grad_i = Fd.paper_gradient(
            grad_out, velocity.expand(*grad_out.shape[:-d], *velocity.shape[-d - 2:]), record, c.domain,
            c.action, c.interpolation, c.scheme, need_velocity=need_velocity, moving=ctx.moving)
        grad_v = grad_v.sum_to_size(velocity.shape) if need_velocity else None
        grad_i = grad_i.sum_to_size(template.shape) if ctx.needs_input_grad[1] else None
        return grad_v, grad_i, None, None


class _ExactDeformation(torch.autograd.Function):
    """``W(nu, I)`` with the exact derivative of the discrete map as backward (``functional.exact_gradient``).

    The forward runs the time loop without an autograd graph (bit for bit the values of the other modes) and
    keeps ``functional.exact_record`` (the image trajectory and determinants, or the composed displacements:
    one velocity-sized tensor), which the backward's reverse sweep (the hand-written discrete adjoint)
    overwrites with the velocity gradient. As ``_PaperDeformation``: the record lives on ``ctx`` and is dropped
    once consumed (a second backward through a retained graph recomputes it); once differentiable.
    """

    @staticmethod
    def forward(ctx, velocity, template, config, moving):
        deformed, record = _exact_record(velocity, template, config, moving)
        ctx.save_for_backward(velocity, template)
        ctx.config, ctx.moving, ctx.record = config, moving, record
        ctx.set_materialize_grads(False)
        return deformed

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        if grad_out is None:
            return None, None, None, None
        velocity, template = ctx.saved_tensors
        c, (need_velocity, need_template) = ctx.config, ctx.needs_input_grad[:2]
        record = ctx.record if ctx.record is not None else _exact_record(velocity, template, c, ctx.moving)[1]
        if need_velocity:  # exact_gradient overwrites it
            ctx.record = None
        d = c.domain.ndim
        batch = grad_out.shape[:-d]
        inputs = (grad_out, template.expand(*batch, *template.shape[-d:]),
                  velocity.expand(*batch, *velocity.shape[-d - 2:]), record)
        if c.velocity_domain is None:
            grad_v, grad_i = Fd.exact_gradient(*inputs, c.domain, c.action, c.interpolation, c.scheme,
                                               need_velocity=need_velocity, need_template=need_template,
                                               moving=ctx.moving)
        else:
            grad_v, grad_i = Fd.coarse_gradient(*inputs, c.velocity_domain, c.domain, c.action, c.scheme,
                                                need_velocity=need_velocity, need_template=need_template,
                                                moving=ctx.moving)
        grad_v = grad_v.sum_to_size(velocity.shape) if need_velocity else None
        grad_i = grad_i.sum_to_size(template.shape) if need_template else None
        return grad_v, grad_i, None, None


def _exact_record(velocity, template, config, moving) -> tuple:
    """``functional.exact_record`` (``coarse_record`` for a coarser velocity grid) of the broadcast inputs."""
    template, velocity = _broadcast(velocity, template, config.domain.ndim)
    if config.velocity_domain is not None:
        return Fd.coarse_record(template, velocity, config.velocity_domain, config.domain, config.action,
                                config.scheme, moving)
    return Fd.exact_record(template, velocity, config.domain, config.action, config.interpolation, config.scheme,
                           moving)


def _record(velocity, template, config, moving) -> torch.Tensor:
    """``functional.gradient_record`` of the broadcast inputs."""
    template, velocity = _broadcast(velocity, template, config.domain.ndim)
    return Fd.gradient_record(template, velocity, config.domain, config.action, config.interpolation, config.scheme,
                              moving)


def _broadcast(velocity, template, d: int) -> tuple:
    """``(template, velocity)`` expanded to their common batch dims (``d`` image axes)."""
    batch = broadcast_shapes(velocity.shape[:-d - 2], template.shape[:-d])
    return template.expand(*batch, *template.shape[-d:]), velocity.expand(*batch, *velocity.shape[-d - 2:])


class LDDMMDeformation(torch.nn.Module):
    """The deformation operator ``W(nu, I)`` of LDDMM on the time grid ``t_i = i / N`` (section "Gradient descent").

    - ``action="geometric"``: ``W(nu, I) = I o phi_{1,0}`` (eq:DeforOpGeom);
      ``action="mass_preserving"``: ``W(nu, I) = |D phi_{1,0}| I o phi_{1,0}`` (eq:DeforOpMP).
    - ``I o phi_{t_i,0}`` by the recursion of eq:ODEflow1b (Algorithm 1, line 7), ``|D phi_{t_i,0}|`` by the
      mass-preserving replacement of step 8. The discrete map uses ``nu(t_1) .. nu(t_N)``; ``nu(t_0)`` only
      enters the paper's gradient transports (eq:ODEflow2b, Remark re:inverse_linear_deformation).
    - ``backward="paper"``: a custom autograd Function whose backward is the paper's gradient
      (``functional.paper_gradient``; lines 8-9 carried as the one field ``|D phi_{t_i,1}| G o phi_{t_i,1}``):
      no graph of the time loop is kept; the forward's record (trajectory and Jacobian factors, one
      velocity-sized tensor) becomes the velocity gradient, so forward and backward together hold
      ``O(N n^2)``, about one velocity field. Without a graph to record (``torch.no_grad()``, no input
      requiring grad) the plain forward runs. ``backward="autograd"``: plain autograd through the discrete
      forward (the exact derivative of the discrete map; keeps the graph of the time loop).
      ``backward="exact"``: the same exact derivative from a hand-written discrete adjoint of the forward
      recursions (``functional.exact_gradient``: the transposed bilinear interpolations, i.e. scatters, and
      the one-sided cell slopes, step by step in reverse), with the paper mode's memory: no graph, the
      forward's record (image trajectory and determinants, or the composed displacements) becomes the
      velocity gradient. Equal to autograd up to rounding (1e-10 relative in float64, tests); use it for line
      searches (L-BFGS, nonlinear CG), which need the derivative of the function they evaluate. Measured
      (``scripts/bench_deform.py --threads 1``, float32, N=20, the three modes interleaved in one process; a
      shared 2-core machine at load 6-9, so noisy), fwd+bwd exact / paper: geometric reinterpolate 0.99-1.03 /
      1.00-1.30 / 0.99-1.35 at 64^2 / 128^2 / 256^2 over 3 runs (exact / autograd 1.0 / 0.64-0.68 /
      0.46-0.64), live memory 1.02-1.04x the paper mode's; geometric compose 0.5-0.7 with a third of the paper
      mode's live memory (the record is the displacements; the paper mode keeps the composed trajectories).
      The mass-preserving action costs about 2x the paper mode (reinterpolate 1.8-2.6, compose 1.4-2.1; 0.5-1.2x
      autograd, one run each): its adjoint
      also scatters the determinant's adjoint every step, where the paper's gradient transports one field,
      and a scatter (``grid_sampler_2d_backward``) costs about 3.5 interpolations.
    - ``interpolation="reinterpolate"`` (the paper: re-interpolate the image every step) or ``"compose"``
      (compose the displacements, interpolate the template once per time: less numerical blur; the
      paper's gradient then transports ``G`` by composed displacements too). Measured
      (``scripts/bench_deform.py --blur``, smooth velocity constant in time, max |nu| = 3, float64):
      deform-there-and-back relative L2 error / fraction of gradient energy kept / error against a
      compose N=320 reference: J 64^2 N=20: reinterpolate 0.21 / 0.73 / 0.11, compose 0.036 / 0.95 / 0.003;
      Shepp-Logan 256^2 N=20: reinterpolate 0.36 / 0.40 / 0.25, compose 0.10 / 0.85 / 0.023. Re-interpolation
      blurs more as N grows (Shepp-Logan N=80: 0.44 / 0.32 / 0.33); compose converges (0.097 / 0.85 / 0.005).
      Cost: compose adds one 2-channel interpolation of the displacement per step.
    - ``nu = 0`` returns the template bit for bit (steps with an all-zero velocity are skipped when no
      autograd graph of the velocity is recorded; see ``functional._Steps``).
    - ``scheme``: finite differences, ``"central"`` (default) or ``"forward"`` (the authors' code).
    - ``velocity_domain``: the grid of the velocity, ``domain`` here; ``CoarseVelocityDeformation`` (the subclass
      behind ``register(velocity_factor=f)``) puts the velocity and the flow on a coarser grid of the same box.
      ``replace(**changes)`` is the same kind of operator with some constructor arguments changed.

    Gradient scale (``backward="paper"``; torch's convention, derivatives w.r.t. tensor entries; the exact
    modes have the same scale):
    with ``G = dL/dW`` (entries, so the L2 gradient is ``G / cell_volume``),
    ``dL/dnu[..., i, :, :, :] = (1/N) * cell_volume * (L2 gradient at t_i before the kernel)``, i.e.
    geometric ``-(1/N) |D phi_{t_i,1}| (G o phi_{t_i,1}) grad(I o phi_{t_i,0})``, mass-preserving
    ``+(1/N) |D phi_{t_i,0}| (I o phi_{t_i,0}) grad(G o phi_{t_i,1})`` (eq:GradGoalFunctionalVRHKS(_mp)),
    and the template gets ``|D phi_{0,1}| (G o phi_{0,1})`` (geometric) or ``G o phi_{0,1}`` (mass-preserving).
    The paper's V-gradient of the data term at ``t_i`` is ``K((N / cell_volume) * dL/dnu_i)``.
    ``(1/N) * cell_volume`` is the weight of the discretised ``L2([0,1], L2)`` inner product
    (tests/deform/test_lddmm.py::test_gradient_scale_relation).

    Accuracy of the paper's gradient against the exact derivative of the discrete map (autograd), smooth
    random problems (max |nu| = 1 on [-16, 16]^2), slices ``t_1 .. t_N`` (the discrete map does not depend on
    ``nu(t_0)``: autograd gives 0 there, the paper's formula does not), central differences, float64
    (tests/deform/test_lddmm.py::test_paper_vs_autograd_rates, ``pytest -s`` prints them):

    ============  ===========================  ===========================  =========================
    grid, N       geometric: cos / rel. diff   mass-preserving: cos / rel.  template grad (geometric)
    ============  ===========================  ===========================  =========================
    16^2, N=4     0.937 / 0.35                 0.959 / 0.30                 0.054
    32^2, N=8     0.984 / 0.18                 0.992 / 0.13                 0.029
    64^2, N=16    0.996 / 0.089                0.998 / 0.069                0.016
    128^2, N=32   0.999 / 0.046                0.999 / 0.043                0.008
    ============  ===========================  ===========================  =========================

    The velocity-gradient difference is first order in the pixel size and nearly independent of N (64^2:
    0.075 / 0.079 / 0.083 / 0.084 for N = 4 / 8 / 16 / 32): the exact derivative of bilinear interpolation is
    the one-sided slope of the cell the point falls in (an O(h) derivative), where the paper uses the
    central difference of ``I o phi_{t_i,0}``. The template-gradient difference is first order in 1/N
    (64^2: 0.037 / 0.019 / 0.011 / 0.009): the transports use ``nu(t_i .. t_{N-1})`` (eq:ODEflow2b) where
    the discrete map uses ``nu(t_{i+1} .. t_N)`` (Remark re:inverse_linear_deformation). Both gradients
    converge to the same continuous L2 gradient (test_gradient_scale_relation).

    Parameters
    ----------
    domain : ImageDomain
        The images' grid (2D or 3D), also the velocity's.
    num_steps : int
        Time steps N (>= 1).
    action : {"geometric", "mass_preserving"}
        The group action.
    backward : {"paper", "autograd", "exact"}
        The backward (above).
    interpolation : {"reinterpolate", "compose"}
        Re-interpolate the image every step (the paper's) or compose the displacements (above).
    scheme : {"central", "forward"}
        The finite differences.

    Raises
    ------
    TypeError
        ``domain`` is no ``ImageDomain``.
    ValueError
        An unknown ``action``, ``backward``, ``interpolation`` or ``scheme``, ``num_steps < 1``.

    Notes
    -----
    ``velocity (..., N+1, 2, nx, ny)`` (component 0 = x, 1 = y; physical units per unit time),
    ``template (..., nx, ny)`` or ``(nx, ny)`` (shared across the batch; batch dims broadcast and the
    gradients are summed back to each input's shape); output ``(..., nx, ny)``. float32 / float64, any
    device (the inputs'). Images are 0 outside the domain (zero padding), Jacobians and displacements are
    continued from the border.

    3D (a ``domain`` with ``shape (nx, ny, nz)``): the same operator, code and options, with
    ``velocity (..., N+1, 3, nx, ny, nz)`` (component 2 = z), ``template (..., nx, ny, nz)``, output
    ``(..., nx, ny, nz)``; trilinear interpolation (``grid_sample`` on 5D tensors), the 3x3 Jacobian
    determinant, and divergences / gradients over three axes. Everything above holds per axis. Measured
    times and memory: docs/3d.md.

    Examples
    --------
    >>> from indreg import phantoms
    >>> dom = ImageDomain.paper(32)
    >>> W = LDDMMDeformation(dom, num_steps=10)
    >>> template = phantoms.get("j", dom)                   # (32, 32), float64
    >>> v = torch.zeros(11, 2, 32, 32, dtype=torch.float64, requires_grad=True)
    >>> deformed = W(v, template)                           # the zero velocity: the identity map
    >>> torch.allclose(deformed, template)
    True
    >>> deformed.square().sum().backward()                  # the paper's gradient as the backward pass
    >>> v.grad.shape
    torch.Size([11, 2, 32, 32])
    """

    def __init__(self, domain: ImageDomain, num_steps: int = 20, action: str = "geometric",
                 backward: str = "paper", interpolation: str = "reinterpolate", scheme: str = "central"):
        super().__init__()
        if not isinstance(domain, ImageDomain):
            raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
        for name, value, allowed in (("action", action, ACTIONS), ("backward", backward, BACKWARDS),
                                     ("interpolation", interpolation, Fd.INTERPOLATIONS),
                                     ("scheme", scheme, Fd.SCHEMES)):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
        self.domain = self.velocity_domain = domain
        self.num_steps = check_int(num_steps, "num_steps", 1)
        self.action, self.backward, self.interpolation, self.scheme = action, backward, interpolation, scheme
        self._config = _Config(domain, action, interpolation, scheme)

    def extra_repr(self) -> str:
        return (f"shape={self.domain.shape}, num_steps={self.num_steps}, action={self.action!r}, "
                f"backward={self.backward!r}, interpolation={self.interpolation!r}, scheme={self.scheme!r}")

    def arguments(self) -> dict:
        """The constructor's arguments by name (``replace``)."""
        return {"domain": self.domain, "num_steps": self.num_steps, "action": self.action,
                "backward": self.backward, "interpolation": self.interpolation, "scheme": self.scheme}

    def replace(self, **changes) -> "LDDMMDeformation":
        """The same kind of operator with some constructor arguments changed (e.g. ``backward="exact"``)."""
        return type(self)(**{**self.arguments(), **changes})

    def velocity_shape(self, *batch) -> tuple:
        """Shape ``(*batch, N+1, d, *shape)`` of a velocity field for this operator (``velocity_domain.shape``)."""
        return (*batch, self.num_steps + 1, self.domain.ndim, *self.velocity_domain.shape)

    def zero_velocity(self, *batch, dtype=torch.float64, device=None) -> torch.Tensor:
        """The zero velocity field ``(*batch, N+1, d, *shape)``."""
        return torch.zeros(self.velocity_shape(*batch), dtype=dtype, device=device)

    def _check_velocity(self, velocity) -> list:
        """Validates the velocity; returns its ``functional.step_flags`` (one pass: finiteness and zero steps)."""
        d = self.domain.ndim
        t = d + 2  # the time axis is -t
        if isinstance(velocity, torch.Tensor) and velocity.dim() >= t and velocity.shape[-t] != self.num_steps + 1:
            layout = "(..., N+1, 2, nx, ny)" if d == 2 else "(..., N+1, 3, nx, ny, nz)"
            raise ValueError(f"velocity must have num_steps + 1 = {self.num_steps + 1} time points on axis -{t} "
                             f"(shape {layout}), got shape {tuple(velocity.shape)}")
        shape = self.velocity_shape()
        if not isinstance(velocity, torch.Tensor) or velocity.dtype not in FLOAT_DTYPES \
                or velocity.shape[velocity.dim() - t:] != shape:
            check_tensor(velocity, "velocity", shape)
        check_nonempty(velocity, "velocity", t)
        moving, finite = Fd.step_flags(velocity, d)
        if not finite:
            check_tensor(velocity, "velocity", shape)
        return moving

    def _check(self, velocity, template) -> list:
        moving = self._check_velocity(velocity)
        _check_fast(template, "template", self.domain.shape)
        check_nonempty(template, "template", self.domain.ndim)
        check_same(velocity, template, "velocity", "template")
        d = self.domain.ndim
        try:
            broadcast_shapes(velocity.shape[:-d - 2], template.shape[:-d])
        except RuntimeError:
            raise ValueError(f"batch dims of velocity {tuple(velocity.shape[:-d - 2])} and template "
                             f"{tuple(template.shape[:-d])} do not broadcast") from None
        return moving

    def forward(self, velocity: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
        """The deformed template ``W(nu, I)``, ``(..., *shape)``."""
        moving = self._check(velocity, template)
        if self.backward != "autograd" and torch.is_grad_enabled() and (velocity.requires_grad
                                                                        or template.requires_grad):
            if self.backward == "exact":
                return _ExactDeformation.apply(velocity, template, self._config, moving)
            return _PaperDeformation.apply(velocity, template, self._config, moving)[0]
        deformed = self._trajectory(velocity, template, moving).select(-self.domain.ndim - 1, -1)
        return deformed if self.backward == "autograd" else deformed.clone()  # not a view of the trajectory

    def trajectory(self, velocity: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
        """``W(nu, I)(t_i)`` for ``i = 0..N``, ``(..., N+1, *shape)`` (differentiable by plain autograd)."""
        return self._trajectory(velocity, template, self._check(velocity, template))

    def _trajectory(self, velocity: torch.Tensor, template: torch.Tensor, moving: list) -> torch.Tensor:
        c = self._config
        template, velocity = _broadcast(velocity, template, c.domain.ndim)
        return Fd.deformed_trajectory(template, velocity, c.domain, c.action, c.interpolation, c.scheme, moving)

    def jacobian(self, velocity: torch.Tensor) -> torch.Tensor:
        """The mass-preserving action's ``|D phi_{1,0}|``, ``(..., *shape)``: the first-order product of step 8.

        ``J_i = (1 - div nu(t_i)/N) * J_{i-1} o (Id - nu(t_i)/N)`` (``functional.jacobian_trajectory``), the
        factor the mass-preserving action multiplies by (eq:DeforOpMP) and whose recursion the paper's
        gradient differentiates. It is a first-order approximation (in ``1/N``) of the determinant, not a bound
        on the determinant of the map the deformation applies: each factor ``1 - div/N`` drops the term
        ``det(D nu)/N^2`` of ``det(Id - D nu/N)`` (a divergence-free field gets factors near 1), so a swirl can
        fold the map while every factor stays positive. For folding use ``jacobian_determinant`` /
        ``min_jacobian``.
        """
        moving = self._check_velocity(velocity)
        return Fd.jacobian_trajectory(velocity, self.domain, self.scheme, moving).select(-self.domain.ndim - 1, -1)

    def jacobian_determinant(self, velocity: torch.Tensor) -> torch.Tensor:
        """``det D phi_{1,0}`` of the map the deformation applies, ``(..., *shape)``: folding where ``<= 0``.

        ``phi_{1,0}`` is the composition of the small steps ``Id - nu(t_i)/N`` of eq:ODEflow1b (``deformation``):
        ``interpolation="compose"`` samples the template at exactly these composed displacements, and
        ``"reinterpolate"`` applies the same composition one step at a time. Its Jacobian determinant by finite
        differences of the computed map (``functional.jacobian_determinant``: central inside, one-sided at the
        border, physical cell sides), so a value ``<= 0`` means the computed map folds there; ``jacobian``
        (the first-order product) can stay positive while it does. No autograd graph is recorded.
        """
        moving = self._check_velocity(velocity)
        with torch.no_grad():
            return Fd.displacement_determinant(self._displacement_10(velocity, moving), self.domain)

    def min_jacobian(self, velocity: torch.Tensor) -> torch.Tensor:
        """Minimum over the grid of ``jacobian_determinant``, ``(...)``: the computed map folds when ``<= 0``.

        Uses the determinant of the map actually applied, not the first-order product ``jacobian``: on the
        cellular swirl ``nu = 20 (sin(x/4) cos(y/4), -cos(x/4) sin(y/4))`` (64^2, ``[-16, 16]^2``, N = 4) the
        product's minimum is 0.944 while the map's determinant reaches -0.654 and is ``<= 0`` on 37% of the
        pixels. Cost: N two-channel interpolations (the product: N one-channel ones), no ``O(N n^2)`` storage.
        """
        return self.jacobian_determinant(velocity).amin(dim=self.domain.dims)

    def deformation(self, velocity: torch.Tensor) -> torch.Tensor:
        """``phi_{1,0}`` as physical points ``(..., d, *shape)`` (composed displacements; deformed-grid plots)."""

        moving = self._check_velocity(velocity)
        out = self._displacement_10(velocity, moving)
        d = self.domain.ndim
        for k, axis in enumerate(self.domain.axes(velocity.dtype, velocity.device)):   # + Id, no grid of points held
            out.select(-d - 1, k).add_(axis.view([-1 if j == k else 1 for j in range(d)]))
        return out

    def _displacement_10(self, velocity: torch.Tensor, moving: list) -> torch.Tensor:
        """``phi_{1,0} - Id`` (physical units) on the image's grid, ``(..., d, *shape)``."""
        return Fd.displacement_10(velocity, self.domain, moving)
