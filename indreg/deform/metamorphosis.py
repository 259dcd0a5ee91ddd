"""Metamorphosis: the image path of eq:FlowEq:Intensity / eq:DirectMatchingMetamorphosisPDE, with its exact gradient.

Metamorphosis lets the flow of ``nu`` also change intensities: the image path ``f(t)`` solves

    d/dt f(t, x) + <grad f(t, x), nu(t, x)> = zeta(t, x),   f(0) = I          (eq:DirectMatchingMetamorphosisPDE)

whose solution is the template transported by the flow plus the source accumulated along the flow,

    f(1) = I o phi_{1,0} + int_0^1 zeta(t) o phi_{1,t} dt                       (eq:FlowEq:Intensity, eq:Metam:ODE)

(``phi_{1,t}`` carries a point at time 1 back to where it was at time ``t``; ``nu = 0`` gives
``f(1) = I + int zeta``, ``zeta = 0`` gives LDDMM's geometric action ``W(nu, I) = I o phi_{1,0}``).

Discretisation (``t_i = i / N``, the small steps ``b_i = Id - nu(t_i)/N`` of eq:ODEflow1b):

    f_0 = I,   f_i = f_{i-1} o b_i + (1/N) zeta_i,   i = 1..N                   ("reinterpolate")

i.e. ``f_N = I o b_1 o .. o b_N + (1/N) sum_{i=1..N} zeta_i o b_{i+1} o .. o b_N``: a right Riemann sum of
the source, each ``zeta_i`` transported from its time ``t_i`` to 1 (``zeta_0`` and ``nu(t_0)`` do not enter).
``"compose"`` splits ``f_N = P + S_N``: the template part ``P = I o (Id + u_N)`` with the composed
displacement ``u_N = phi_{1,0} - Id`` of ``functional.displacements_t0`` (LDDMM's compose mode, no
accumulated blur), the source part by the recursion ``S_0 = 0``, ``S_i = S_{i-1} o b_i + (1/N) zeta_i``.

2D and 3D share one code path (as ``functional``): d = ``domain.ndim`` image axes, images ``(..., *shape)``,
sources ``(..., N+1, *shape)``, velocities ``(..., N+1, d, *shape)``; interpolation is bilinear / trilinear and
its exact transposes are ``grid_sampler_2d_backward`` / ``grid_sampler_3d_backward`` (``functional.sampling``).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from .._checks import broadcast_shapes, check_int, check_nonempty, check_same, check_tensor
from ..domain import ImageDomain
from . import functional as Fd
from .functional.differences import _differenced
from .functional.sampling import _sample_adjoint
from .lddmm import LDDMMDeformation

BACKWARDS = ("adjoint", "autograd")


@dataclass(frozen=True)
class _Config:
    domain: ImageDomain
    interpolation: str


# ----------------------------------------------------------------------------------------------------------
# forward recursions
def _transport(start: torch.Tensor, source: torch.Tensor, steps: "Fd._Steps", n: int, out: list | None = None):
    """``x_i = x_{i-1} o b_i + (1/N) zeta_i`` from ``x_0 = start (..., *shape)``; returns ``x_N`` (and appends
    ``x_0..x_{N-1}`` to ``out``). Differentiable by autograd when ``steps`` records."""
    c = -steps.ndim - 1  # the time axis of the source, the channel axis of a sampled image
    x, zeta = start, source.unbind(c)
    for i in range(1, n + 1):
        if out is not None:
            out.append(x)
        x = torch.add(steps.move(x.unsqueeze(c), i, "zeros").squeeze(c), zeta[i], alpha=1.0 / n)
    return x


def metamorphosis_trajectory(template: torch.Tensor, velocity: torch.Tensor, source: torch.Tensor,
                             domain: ImageDomain, interpolation: str = "reinterpolate",
                             moving: list | None = None) -> torch.Tensor:
    """``f_i`` for ``i = 0..N``, ``(..., N+1, *shape)``, for inputs whose batch dims already agree.

    ``"reinterpolate"``: the recursion ``f_i = f_{i-1} o b_i + zeta_i / N``; ``"compose"``: ``f_i = I o (Id + u_i)
    + S_i`` (module docstring). Differentiable by plain autograd.
    """
    Fd._check_interpolation(interpolation)
    c = -domain.ndim - 1
    n = velocity.shape[c - 1] - 1
    steps = Fd._Steps(velocity, domain, -1.0, moving)
    frames = []
    if interpolation == "reinterpolate":
        frames.append(_transport(template, source, steps, n, frames))
        return torch.stack(frames, dim=c)
    accumulated = []
    accumulated.append(_transport(torch.zeros_like(template), source, steps, n, accumulated))
    return Fd.template_trajectory(template, velocity, domain, "compose", moving) + torch.stack(accumulated, dim=c)


def _forward_record(template, velocity, source, config, moving) -> tuple:
    """``f_N`` and what the backward reads: the transported images ``x_0..x_{N-1}`` and, for ``"compose"``,
    the displacements ``u_0..u_N`` (grid units). No autograd."""
    c = -config.domain.ndim - 1
    n = velocity.shape[c - 1] - 1
    steps = Fd._Steps(velocity, config.domain, -1.0, moving)
    frames = []
    if config.interpolation == "reinterpolate":
        return _transport(template, source, steps, n, frames), torch.stack(frames, dim=c), None
    displacements = Fd.displacements_t0(velocity, config.domain)
    part = Fd._sample_displaced(template.unsqueeze(c), displacements.select(c - 1, -1), config.domain,
                                "zeros").squeeze(c)
    accumulated = _transport(torch.zeros_like(template), source, steps, n, frames)
    return part + accumulated, torch.stack(frames, dim=c), displacements


# ----------------------------------------------------------------------------------------------------------
# the adjoint recursion (backward)
def _sample_vjp(grad: torch.Tensor, f: torch.Tensor, grid: torch.Tensor, padding_mode: str) -> tuple:
    """Exact vector-Jacobian product of ``functional.sample(f, grid)``, ``f (..., C, *shape)``, ``grid (..., *shape,
    d)``: ``(A^T grad, d<grad, f o grid>/d grid)``, the bilinear / trilinear scatter and the cell slopes of ``f`` at
    the points times ``grad`` (``grid_sample``'s own backward, ``sampling._sample_adjoint``), the grid derivative
    returned planar ``(..., d, *shape)`` in grid units with component 0 = x (``grid_sample``'s order reversed)."""
    d = grid.shape[-1]
    grad_f, grad_grid = _sample_adjoint(grad, f, grid, padding_mode, True, True)
    return grad_f, grad_grid.movedim(-1, -d - 1).flip(-d - 1)


def _node_slopes(grad: torch.Tensor, f: torch.Tensor, padding_mode: str, ndim: int) -> torch.Tensor:
    """``_sample_vjp``'s grid derivative at the identity grid (a step with ``nu_i = 0``), where bilinear /
    trilinear interpolation has a kink at every node: the mean of the two one-sided slopes, i.e. central
    differences of ``f (..., C, *shape)`` (``ndim`` image axes) continued by ``padding_mode``, times ``grad``,
    summed over channels, planar ``(..., ndim, *shape)`` in grid units."""
    c, shape = -ndim - 1, f.shape[-ndim:]
    mode = "constant" if padding_mode == "zeros" else "replicate"
    p = F.pad(f.reshape(-1, *f.shape[c:]), (1, 1) * ndim, mode=mode)
    p = p.reshape(*f.shape[:-ndim], *(s + 2 for s in shape))
    # d/d(grid x_k) = (extent_k / 2) d/dx_k and h_k = extent_k / n_k: the central quotient times n_k / 4
    return torch.stack([(grad * torch.sub(*_differenced(p, k, ndim, "central"))).sum(c) * (0.25 * n)
                        for k, n in enumerate(shape)], dim=c)


def _step_vjp(grad, f, steps, i, padding_mode) -> tuple:
    """VJP of ``f o b_i`` (``f (..., C, *shape)``): ``(A_i^T grad, d/dw_i)`` with ``w_i = -nu(t_i)/N`` in grid
    units, planar ``(..., d, *shape)``."""
    if steps.moves(i):
        return _sample_vjp(grad, f, steps.grid(i), padding_mode)
    return grad, _node_slopes(grad, f, padding_mode, steps.ndim)


def _grid_to_velocity(grad_w: torch.Tensor, domain: ImageDomain, n: int) -> torch.Tensor:
    """``dL/dnu_i`` from ``dL/dw_i``, ``w_i = -(nu_i / N) (2 / extent)`` (grid units), ``(..., d, *shape)``."""
    return grad_w * Fd._grid_units(domain, grad_w.dtype, grad_w.device) * (-1.0 / n)


def adjoint_gradient(grad_out, template, velocity, source, frames, displacements, domain, moving) -> tuple:
    """``(dL/dnu, dL/dzeta, dL/dI)`` (torch entries) from ``G = dL/df_N`` by the adjoint recursion
    (equations in ``MetamorphosisDeformation``'s docstring). ``frames``: ``x_0..x_{N-1}`` of the transport
    recursion, ``(..., N, *shape)``; ``displacements``: ``u_0..u_N`` (``"compose"``) or None. No autograd."""
    c = -domain.ndim - 1  # the time axis of images / sources; that of velocities is c - 1
    n = velocity.shape[c - 1] - 1
    steps = Fd._Steps(velocity, domain, -1.0, moving)
    grad_w, grad_z = torch.zeros_like(velocity), torch.zeros_like(source)
    lam, x = grad_out.unsqueeze(c), frames.unbind(c)
    for i in range(n, 0, -1):  # lambda_{i-1} = A_i^T lambda_i; dL/dzeta_i = lambda_i / N
        torch.div(lam.squeeze(c), n, out=grad_z.select(c, i))
        lam, slope = _step_vjp(lam, x[i - 1].unsqueeze(c), steps, i, "zeros")
        grad_w.select(c - 1, i).copy_(slope)
    grad_i = lam.squeeze(c)
    if displacements is not None:
        grad_i = _template_part_adjoint(grad_out, template, displacements, grad_w, steps, domain)
    return _grid_to_velocity(grad_w, domain, n), grad_z, grad_i


def _template_part_adjoint(grad_out, template, displacements, grad_w, steps, domain) -> torch.Tensor:
    """Adds the template part ``P = I o (Id + u_N)`` of ``"compose"`` to ``grad_w`` (in place); returns ``dL/dI``.

    ``dL/du_N = G (D I)(Id + u_N)``, then the displacement recursion ``u_i = u_{i-1} o (Id + w_i) + w_i``
    backwards: ``dL/dw_i += ubar_i + (D u_{i-1})(Id + w_i)^T ubar_i``, ``ubar_{i-1} = A_i^T ubar_i`` (border
    padding, as the forward)."""
    c = -domain.ndim - 1
    u, w = displacements.unbind(c - 1), grad_w.unbind(c - 1)
    g, image = grad_out.unsqueeze(c), template.unsqueeze(c)
    if bool(u[-1].ne(0).any()):
        grad_i, ubar = _sample_vjp(g, image, Fd.displaced_grid(u[-1], domain), "zeros")
    else:  # P = I exactly (functional._sample_displaced skips the identity)
        grad_i, ubar = g, _node_slopes(g, image, "zeros", domain.ndim)
    for i in range(len(u) - 1, 0, -1):
        w[i].add_(ubar)
        ubar, slopes = _step_vjp(ubar, u[i - 1], steps, i, "border")
        w[i].add_(slopes)
    return grad_i.squeeze(c)


class _MetamorphosisFunction(torch.autograd.Function):
    """``f_N(nu, zeta, I)`` with the adjoint recursion as backward (no graph of the time loop is kept).

    The forward keeps its record on ``ctx``: the transported images ``x_0..x_{N-1}`` and, for ``"compose"``,
    the displacements ``u_0..u_N`` (``O(N n^2)``: half a velocity field, 1.5 for ``"compose"``); it is dropped
    once the backward has used it (a second backward through a retained graph recomputes it). Double backward
    is not supported (``once_differentiable``): use ``backward="autograd"``.
    """

    @staticmethod
    def forward(velocity, source, template, config, moving):
        f1, frames, displacements = _forward_record(template, velocity, source, config, moving)
        return f1, frames, (frames.new_empty(0) if displacements is None else displacements)

    @staticmethod
    def setup_context(ctx, inputs, output):
        velocity, source, template, config, moving = inputs
        ctx.mark_non_differentiable(output[1], output[2])
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(velocity, source, template)
        ctx.config, ctx.moving = config, moving
        ctx.record = (output[1], output[2] if config.interpolation == "compose" else None)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out, _grad_frames, _grad_displacements):
        if grad_out is None:
            return None, None, None, None, None
        velocity, source, template = ctx.saved_tensors
        c = ctx.config
        record = ctx.record or _forward_record(template, velocity, source, c, ctx.moving)[1:]
        ctx.record = None
        grad_v, grad_z, grad_i = adjoint_gradient(grad_out, template, velocity, source, *record, c.domain,
                                                  ctx.moving)
        needs = ctx.needs_input_grad
        return (grad_v if needs[0] else None, grad_z if needs[1] else None, grad_i if needs[2] else None,
                None, None)


class MetamorphosisDeformation(torch.nn.Module):
    """The metamorphosis image path ``f(1) = M(nu, zeta, I)`` on the time grid ``t_i = i / N`` (eq:FlowEq:Intensity).

    ``f(1)`` solves ``d/dt f + <grad f, nu> = zeta``, ``f(0) = I`` (eq:DirectMatchingMetamorphosisPDE): the
    template transported by the flow of ``nu`` plus the source ``zeta`` accumulated along it (module docstring
    for the discretisation). ``zeta = 0`` is LDDMM's geometric action ``W(nu, I)`` (``LDDMMDeformation``, the
    same recursion in both interpolation modes); ``nu = 0`` is ``I + (1/N) sum_{i=1..N} zeta_i``.

    - ``interpolation="reinterpolate"``: ``f_i = f_{i-1} o b_i + (1/N) zeta_i`` (re-interpolate every step, as
      Algorithm 1); ``"compose"``: template part ``I o (Id + u_N)`` interpolated once (LDDMM's compose mode),
      source part re-interpolated.
    - ``backward="adjoint"``: a custom autograd Function whose backward is the adjoint recursion below (exact
      derivative of the discrete map, no graph of the time loop; memory ``O(N n^2)``); ``"autograd"``: plain
      autograd through the discrete forward (keeps the graph; for checks and double backward).

    Gradient (``G = dL/df_N`` in torch entries; ``A_i`` = bilinear interpolation at the points ``b_i(x) =
    x - nu_i(x)/N``, ``A_i^T`` its scatter with the same weights; ``D x`` = the slope of the bilinear interpolant
    of ``x`` in the cell the point falls in). Reinterpolate, with ``f_{i-1}`` the path:

        lambda_N = G,   lambda_{i-1} = A_i^T lambda_i                                     (i = N..1)
        dL/dzeta_i = (1/N) lambda_i,   dL/dnu_i = -(1/N) lambda_i (D f_{i-1})(b_i),   dL/dI = lambda_0,

    and ``dL/dzeta_0 = dL/dnu_0 = 0``. Compose: the same for the source part (``S_{i-1}`` in place of
    ``f_{i-1}``), plus the template part ``P = I o (Id + u_N)``, ``u_i = u_{i-1} o b_i - nu_i/N``:

        ubar_N = G (D I)(Id + u_N),   ubar_{i-1} = A_i^T ubar_i  (border padding),
        dL/dnu_i += -(1/N) (ubar_i + (D u_{i-1})(b_i)^T ubar_i),   dL/dI = A_{u_N}^T G.

    ``lambda_i`` is the discrete ``|D phi_{t_i,1}| (G o phi_{t_i,1})`` (``A^T`` is the discrete mass-preserving
    action), so these discretise the continuous L2 gradients (times the weight ``cell_volume / N``)
    ``d/dzeta(t) = |D phi_{t,1}| (G o phi_{t,1})`` and ``d/dnu(t) = -|D phi_{t,1}| (G o phi_{t,1}) grad f(t)``:
    eq:GradGoalFunctionalVRHKS with the path ``f(t)`` in place of ``I o phi_{t,0}``, plus the source gradient.
    At a step with ``nu_i = 0`` everywhere the forward skips the interpolation (exact identity), where the
    interpolant has a kink at every node: the backward then takes the mean of the one-sided slopes (central
    differences, zero / border continuation), so the gradient at ``nu = 0`` is the paper's central-difference
    one. Elsewhere it is the derivative autograd computes through the discrete map, to rounding
    (tests/deform/test_metamorphosis.py::test_adjoint_equals_autograd).

    Gradient scale: ``dL/dzeta_i = (cell_volume / N) * (its L2([0,1], L2) gradient)``, as ``dL/dnu_i``
    (``LDDMMDeformation``, "Gradient scale").

    Parameters
    ----------
    domain : ImageDomain
        The images' grid (2D or 3D).
    num_steps : int
        Time steps N (>= 1).
    backward : {"adjoint", "autograd"}
        The backward (above).
    interpolation : {"reinterpolate", "compose"}
        How the template part is interpolated (above).

    Raises
    ------
    TypeError
        ``domain`` is no ``ImageDomain``.
    ValueError
        An unknown ``backward`` or ``interpolation``, ``num_steps < 1``.

    Notes
    -----
    ``velocity (..., N+1, 2, nx, ny)`` (component 0 = x, physical units per unit time), ``source (..., N+1,
    nx, ny)`` (image units per unit time), ``template (..., nx, ny)``; batch dims broadcast (gradients are
    summed back to each input's shape); output ``(..., nx, ny)``. 3D (a domain of shape ``(nx, ny, nz)``):
    ``velocity (..., N+1, 3, nx, ny, nz)``, ``source (..., N+1, nx, ny, nz)``, ``template`` and output
    ``(..., nx, ny, nz)``, trilinear interpolation (the same code path; "bilinear" above reads "trilinear").
    float32 / float64, any device (the inputs'). Images and sources are 0 outside the domain.

    Examples
    --------
    >>> from indreg import phantoms
    >>> dom = ImageDomain.paper(32)
    >>> M = MetamorphosisDeformation(dom, num_steps=10)
    >>> template = phantoms.get("j", dom)
    >>> torch.allclose(M(M.zero_velocity(), M.zero_source(), template), template)   # no motion, no source
    True
    >>> source = M.zero_source() + 0.5                      # zeta = 0.5 for t in [0, 1]: adds 0.5 in total
    >>> torch.allclose(M(M.zero_velocity(), source, template), template + 0.5)
    True
    """

    def __init__(self, domain: ImageDomain, num_steps: int = 20, backward: str = "adjoint",
                 interpolation: str = "reinterpolate"):
        super().__init__()
        if not isinstance(domain, ImageDomain):
            raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
        for name, value, allowed in (("backward", backward, BACKWARDS),
                                     ("interpolation", interpolation, Fd.INTERPOLATIONS)):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
        self.domain, self.num_steps = domain, check_int(num_steps, "num_steps", 1)
        self.backward, self.interpolation, self.action = backward, interpolation, "geometric"
        self._config = _Config(domain, interpolation)
        self.lddmm = LDDMMDeformation(domain, self.num_steps, "geometric", "paper", interpolation)

    def extra_repr(self) -> str:
        return (f"shape={self.domain.shape}, num_steps={self.num_steps}, backward={self.backward!r}, "
                f"interpolation={self.interpolation!r}")

    def velocity_shape(self, *batch) -> tuple:
        """Shape ``(*batch, N+1, d, *shape)`` of a velocity field."""
        return (*batch, self.num_steps + 1, self.domain.ndim, *self.domain.shape)

    def source_shape(self, *batch) -> tuple:
        """Shape ``(*batch, N+1, *shape)`` of a source term."""
        return (*batch, self.num_steps + 1, *self.domain.shape)

    def zero_velocity(self, *batch, dtype=torch.float64, device=None) -> torch.Tensor:
        """The zero velocity field ``(*batch, N+1, d, *shape)``."""
        return torch.zeros(self.velocity_shape(*batch), dtype=dtype, device=device)

    def zero_source(self, *batch, dtype=torch.float64, device=None) -> torch.Tensor:
        """The zero source ``(*batch, N+1, *shape)``."""
        return torch.zeros(self.source_shape(*batch), dtype=dtype, device=device)

    def _check(self, velocity, source, template) -> tuple:
        """Validates the inputs (before any work); returns the step flags and the common batch shape."""
        moving = self.lddmm._check(velocity, template)
        d = self.domain.ndim
        if isinstance(source, torch.Tensor) and source.dim() > d and source.shape[-d - 1] != self.num_steps + 1:
            layout = "(..., N+1, nx, ny)" if d == 2 else "(..., N+1, nx, ny, nz)"
            raise ValueError(f"source must have num_steps + 1 = {self.num_steps + 1} time points on axis {-d - 1} "
                             f"(shape {layout}), got shape {tuple(source.shape)}")
        check_tensor(source, "source", (self.num_steps + 1, *self.domain.shape))
        check_nonempty(source, "source", d + 1)
        check_same(velocity, source, "velocity", "source")
        try:
            batch = broadcast_shapes(velocity.shape[:-d - 2], source.shape[:-d - 1], template.shape[:-d])
        except RuntimeError:
            raise ValueError(f"batch dims of velocity {tuple(velocity.shape[:-d - 2])}, source "
                             f"{tuple(source.shape[:-d - 1])} and template {tuple(template.shape[:-d])} "
                             f"do not broadcast") from None
        return moving, batch

    def _expand(self, velocity, source, template, batch) -> tuple:
        d = self.domain.ndim
        return (velocity.expand(*batch, *velocity.shape[-d - 2:]), source.expand(*batch, *source.shape[-d - 1:]),
                template.expand(*batch, *template.shape[-d:]))

    def forward(self, velocity: torch.Tensor, source: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
        """``f(1)``, ``(..., *shape)``."""
        moving, batch = self._check(velocity, source, template)
        v, z, t = self._expand(velocity, source, template, batch)
        recording = torch.is_grad_enabled() and any(x.requires_grad for x in (velocity, source, template))
        if recording and self.backward == "adjoint":
            return _MetamorphosisFunction.apply(v, z, t, self._config, moving)[0]
        if recording:
            path = metamorphosis_trajectory(t, v, z, self.domain, self.interpolation, moving)
            return path.select(-self.domain.ndim - 1, -1)
        with torch.no_grad():
            return _forward_record(t, v, z, self._config, moving)[0]

    def trajectory(self, velocity: torch.Tensor, source: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
        """``f(t_i)`` for ``i = 0..N``, ``(..., N+1, *shape)`` (differentiable by plain autograd)."""
        moving, batch = self._check(velocity, source, template)
        v, z, t = self._expand(velocity, source, template, batch)
        return metamorphosis_trajectory(t, v, z, self.domain, self.interpolation, moving)

    def parts(self, velocity: torch.Tensor, source: torch.Tensor, template: torch.Tensor) -> tuple:
        """``(W(nu, I), f(1) - W(nu, I))``: the pure deformation of the template (LDDMM's geometric action) and
        the intensity part, the source accumulated along the flow (``S_N``; the map is linear in
        ``(I, zeta)``). No autograd graph is recorded."""
        with torch.no_grad():
            f1 = self.forward(velocity, source, template)
            deformed = self.lddmm(velocity, template)
        return deformed, f1 - deformed

    def deformation(self, velocity: torch.Tensor) -> torch.Tensor:
        """``phi_{1,0}`` as physical points ``(..., d, *shape)`` (``LDDMMDeformation.deformation``)."""
        return self.lddmm.deformation(velocity)

    def min_jacobian(self, velocity: torch.Tensor) -> torch.Tensor:
        """Minimum of ``det D phi_{1,0}`` (``LDDMMDeformation.min_jacobian``): the flow folds when ``<= 0``."""
        return self.lddmm.min_jacobian(velocity)
