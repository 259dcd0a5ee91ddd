"""Pure functions of the LDDMM time discretisation: interpolation, finite differences, the flow recursions.

Everything here is plain torch and device / dtype agnostic, so the deformation operator (``lddmm.py``) and
later layers (geodesic shooting) share one implementation. The recursions are differentiable by autograd;
without a graph to record they run in place (reused buffers, ``out=``), and ``gradient_record`` /
``paper_gradient`` are the two halves of the paper's gradient (Algorithm 1, lines 7-10) without autograd;
``exact_record`` / ``exact_gradient`` those of the exact derivative of the discrete map (its discrete adjoint,
hand-written).

Convention:
    - Images ``(..., nx, ny)``, vector fields ``(..., 2, nx, ny)`` (component 0 = x, 1 = y), velocity
      fields ``(..., N+1, 2, nx, ny)`` at ``t_i = i / N``; physical units of ``ImageDomain``.
    - 3D: every function takes the same arguments on an ``ImageDomain`` of shape ``(nx, ny, nz)``, with
      images ``(..., nx, ny, nz)``, vector fields ``(..., 3, nx, ny, nz)`` (component 2 = z) and velocities
      ``(..., N+1, 3, nx, ny, nz)``: one code path, the number of image axes d read from ``domain.ndim`` (in
      the docstrings below ``(..., nx, ny)`` then reads ``(..., nx, ny, nz)`` and ``2`` components read 3).
      Interpolation is trilinear (``grid_sample`` on 5D tensors, ``grid_sampler_3d_backward`` for the exact
      adjoint), finite differences and divergences run over three axes, and ``jacobian_determinant`` is the
      3x3 determinant (``determinant``). ``grid_sample`` grids list the coordinates in reverse order
      (``[..., 0]`` = z, ``[..., 1]`` = y, ``[..., 2]`` = x).

    - In the recursions the batch dims of images and velocities must already agree (broadcast first).
    - Interpolation is bilinear (``grid_sample``, ``align_corners=False``: grid coordinates -1 and 1 are
      the domain's edges, so pixel centres sit exactly at the cell centres of ``ImageDomain``).
      Padding: ``"zeros"`` for images and transported gradients (the image is 0 outside the domain),
      ``"border"`` for Jacobian determinants and displacement fields (continued constantly).
    - Finite differences (``scheme``): ``"central"`` (default) or ``"forward"`` (the authors' code: forward
      differences for the gradient, divergence = minus the L2 adjoint of that gradient). Central differences
      are second-order accurate (forward: first order), so the paper's gradient converges faster to the
      continuous one. Against the exact derivative of the discrete (bilinear) map neither is uniformly
      closer: that derivative is the one-sided slope of the cell the displaced point falls in (an upwind
      difference), so the better match depends on the sign of the velocity. Measured paper-vs-autograd
      relative difference at 16^2/N=4, 32^2/N=8, 64^2/N=16, 128^2/N=32 on the smooth test problem:
      geometric central 0.35/0.18/0.089/0.045 vs forward 0.25/0.13/0.060/0.030; mass-preserving central
      0.30/0.13/0.069/0.046 vs forward 0.35/0.18/0.097/0.061 (on another random field geometric central won,
      0.043 vs 0.069 at 128^2). Central is the default.
"""
from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

from ..domain import ImageDomain

ACTIONS = ("geometric", "mass_preserving")
SCHEMES = ("central", "forward")
INTERPOLATIONS = ("reinterpolate", "compose")


# ----------------------------------------------------------------------------------------------------------
# interpolation
def _grid_units(domain: ImageDomain, dtype, device) -> torch.Tensor:
    """Factors ``2 / extent`` (x, y[, z]) turning physical displacements into grid_sample units, ``(d, 1, .., 1)``."""
    return torch.tensor([2.0 / e for e in domain.extent], dtype=dtype, device=device).view(-1, *(1,) * domain.ndim)


def to_grid_units(v: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """A displacement / velocity field ``(..., d, *shape)`` in physical units expressed in grid units."""
    return v * _grid_units(domain, v.dtype, v.device)


def identity_grid(domain: ImageDomain, dtype=torch.float64, device=None) -> torch.Tensor:
    """The cell centres in ``grid_sample`` coordinates, ``(*shape, d)`` in reversed order: ``[..., 0]`` = y,
    ``[..., 1]`` = x (2D); ``[..., 0]`` = z, ``[..., 1]`` = y, ``[..., 2]`` = x (3D)."""
    device = torch.device("cpu") if device is None else torch.device(device)
    return _identity_grid(domain, dtype, device)


@functools.lru_cache(maxsize=32)
def _identity_grid(domain, dtype, device):
    return domain.to_grid(domain.points(dtype, device).movedim(0, -1))


def displaced_grid(w: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """``grid_sample`` grid ``(..., *shape, d)`` of the points ``x + w(x)``, ``w (..., d, *shape)`` in grid units."""
    return identity_grid(domain, w.dtype, w.device) + w.movedim(-domain.ndim - 1, -1).flip(-1)


def sample(f: torch.Tensor, grid: torch.Tensor, padding_mode: str = "zeros") -> torch.Tensor:
    """Bilinear (2D) / trilinear (3D) interpolation of ``f (..., C, *shape)`` at ``grid (..., *out_shape, d)``
    (same batch dims; d = ``grid.shape[-1]``, 2 or 3).

    Returns ``(..., C, *out_shape)``. Adjoint (what autograd uses): a scatter of the incoming values with the
    interpolation weights. ``grid_sample`` parallelises over the batch only; a single image on a CPU with ``k``
    threads is sampled as ``k`` bands of output rows (along x; the image expanded, not copied): the same
    values, ``k`` threads at work (at 256^2 with 2 threads: 2x faster forward, 1.7x backward).
    """
    d = grid.shape[-1]
    batch, (c, *shape), out_shape = f.shape[:-d - 1], f.shape[-d - 1:], grid.shape[-d - 1:-1]
    f, grid = f.reshape(-1, c, *shape), grid.reshape(-1, *out_shape, d)
    bands = _bands(f, *out_shape)
    if bands > 1:
        f, grid = f.expand(bands, c, *shape), grid.reshape(bands, out_shape[0] // bands, *out_shape[1:], d)
    out = F.grid_sample(f, grid, mode="bilinear", padding_mode=padding_mode, align_corners=False)
    return out.reshape(*batch, c, *out_shape)


def _bands(f: torch.Tensor, *out_shape: int) -> int:
    """Number of row bands (along x) for ``sample``: the CPU thread count for one single-channel image whose
    row count it divides, with at least 8192 output pixels per band (measured: smaller bands lose to the
    thread overhead, 96^2 with 2 threads 28 vs 25 us; 128^2 wins, 28 vs 44 us), else 1 (banding a batch or
    several channels would copy the grid or the output)."""
    threads = torch.get_num_threads()
    if f.device.type != "cpu" or f.shape[0] != 1 or f.shape[1] != 1 or threads < 2 or out_shape[0] % threads \
            or math.prod(out_shape) < 8192 * threads:
        return 1
    return threads


def warp(f: torch.Tensor, points: torch.Tensor, domain: ImageDomain, padding_mode: str = "zeros") -> torch.Tensor:
    """``f o points``: interpolation of the image ``f (..., *shape)`` at ``points (..., d, *out_shape)``.

    ``points`` are physical coordinates (component 0 = x, 1 = y[, 2 = z]); batch dims of ``f`` and ``points``
    broadcast. Outside the domain ``f`` is 0 (``padding_mode="zeros"``) or continued from its border
    (``"border"``). Returns ``(..., *out_shape)``.
    """
    d = domain.ndim
    batch = torch.broadcast_shapes(f.shape[:-d], points.shape[:-d - 1])
    f = f.expand(*batch, *f.shape[-d:])
    grid = domain.to_grid(points.expand(*batch, *points.shape[-d - 1:]).movedim(-d - 1, -1))
    return sample(f.unsqueeze(-d - 1), grid, padding_mode).squeeze(-d - 1)


# ----------------------------------------------------------------------------------------------------------
# finite differences
def gradient(f: torch.Tensor, domain: ImageDomain, scheme: str = "central") -> torch.Tensor:
    """Spatial gradient of an image ``(..., *shape)`` -> ``(..., d, *shape)``, the image being 0 outside.

    ``"central"``: ``(f[i+1] - f[i-1]) / (2h)``; ``"forward"``: ``(f[i+1] - f[i]) / h``; zero padding.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    d = domain.ndim
    p, factors = F.pad(f, (1, 1) * d), _difference_factors(domain, scheme)
    return torch.stack([torch.sub(*_differenced(p, axis, d, scheme)) * c for axis, c in enumerate(factors)],
                       dim=-d - 1)


def _difference_factors(domain: ImageDomain, scheme: str) -> tuple:
    """The difference quotients' factors ``1/(2 h)`` (central) or ``1/h`` (forward) per axis (x, y[, z])."""
    return tuple((0.5 if scheme == "central" else 1.0) / h for h in domain.cell_sides)


def _differenced(p: torch.Tensor, axis: int, ndim: int, scheme: str) -> tuple:
    """Views ``(ahead, behind)`` of a zero-padded image ``p (..., nx+2, ny+2[, nz+2])`` (``ndim`` image axes)
    whose difference is the finite difference (before the quotient's factor) of the image along ``axis``
    (0: x, 1: y, 2: z) at every cell: ``f[k+1] - f[k-1]`` (central) or ``f[k+1] - f[k]`` (forward). No edge
    cases: the padding is the image's zero continuation."""
    ahead, behind = [slice(1, -1)] * ndim, [slice(1, -1)] * ndim
    ahead[axis], behind[axis] = slice(2, None), slice(None, -2) if scheme == "central" else slice(1, -1)
    return p[(Ellipsis, *ahead)], p[(Ellipsis, *behind)]


def _central_diff(f: torch.Tensor, dim: int, h: float) -> torch.Tensor:
    """Central differences along ``dim``, one-sided at both ends (zero for a single sample)."""
    n = f.shape[dim]
    if n == 1:
        return torch.zeros_like(f)
    first = f.narrow(dim, 1, 1) - f.narrow(dim, 0, 1)
    last = f.narrow(dim, n - 1, 1) - f.narrow(dim, n - 2, 1)
    inner = (f.narrow(dim, 2, n - 2) - f.narrow(dim, 0, n - 2)) / 2
    return torch.cat((first, inner, last), dim=dim) / h


def divergence(v: torch.Tensor, domain: ImageDomain, scheme: str = "central") -> torch.Tensor:
    """Divergence of a vector field ``(..., d, *shape)`` -> ``(..., *shape)``.

    ``"central"``: central differences, one-sided at the border (no assumption on the field outside);
    ``"forward"``: minus the L2 adjoint of the forward-difference ``gradient``, i.e. backward differences
    with the field 0 before the first sample (the authors' ODL choice).
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    d, out = domain.ndim, None
    for axis, (vk, h) in enumerate(zip(v.unbind(-d - 1), domain.cell_sides)):
        dim = axis - d
        if scheme == "central":
            term = _central_diff(vk, dim, h)
        else:  # backward differences, the field 0 before the first sample
            term = (vk - F.pad(vk, (0, 0) * (d - 1 - axis) + (1, 0)).narrow(dim, 0, vk.shape[dim])) / h
        out = term if out is None else out + term
    return out


def _growth_into(out: torch.Tensor, v: torch.Tensor, domain: ImageDomain, scheme: str, c: float) -> torch.Tensor:
    """``1 + c * divergence(v, domain, scheme)`` written into ``out (..., *shape)`` (no autograd).

    The factors ``1 -/+ div nu(t_i)/N`` of the Jacobian recursions (``c = -/+ 1/N``). Vectorised over all
    leading dims (e.g. all time steps at once), two passes over memory per axis; equal to the composed
    expression up to rounding.
    """
    d = domain.ndim
    one = out.new_ones(())
    if scheme == "central" and min(out.shape[-d:]) < 3:
        return out.copy_(1 + c * divergence(v, domain, scheme))
    for axis, (vk, h) in enumerate(zip(v.unbind(-d - 1), domain.cell_sides)):
        _add_difference(out, vk, axis - d, c / h, scheme, one if axis == 0 else None)
    return out


def _add_difference(out: torch.Tensor, f: torch.Tensor, dim: int, a: float, scheme: str, one) -> None:
    """``out += a * (difference of f along dim)`` in place (``out = one + ...`` when ``one`` is given): backward
    differences with ``f`` 0 before the first sample (``"forward"``), or central inside and one-sided at both
    ends (``"central"``, as ``_central_diff``; at least 3 samples)."""
    n = out.shape[dim]

    def put(o, ahead, behind, alpha):  # o (+)= alpha * (ahead - behind)
        (o.add_(ahead, alpha=alpha) if one is None else torch.add(one, ahead, alpha=alpha, out=o)).sub_(
            behind, alpha=alpha)

    if scheme == "forward":
        if one is None:
            out.add_(f, alpha=a)
        else:
            torch.add(one, f, alpha=a, out=out)
        out.narrow(dim, 1, n - 1).sub_(f.narrow(dim, 0, n - 1), alpha=a)
        return
    put(out.narrow(dim, 1, n - 2), f.narrow(dim, 2, n - 2), f.narrow(dim, 0, n - 2), 0.5 * a)
    put(out.narrow(dim, 0, 1), f.narrow(dim, 1, 1), f.narrow(dim, 0, 1), a)
    put(out.narrow(dim, n - 1, 1), f.narrow(dim, n - 1, 1), f.narrow(dim, n - 2, 1), a)



# ----------------------------------------------------------------------------------------------------------
# flow recursions (eq:ODEflow1b forward in time, eq:ODEflow2b backward in time)
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


@functools.lru_cache(maxsize=32)
def _planar_identity_grid(domain, dtype, device):
    return _identity_grid(domain, dtype, device).movedim(-1, 0).contiguous()


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


def jacobian_determinant(points: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """``|D phi|`` of a map given by its values ``phi(x)`` at the cell centres, ``points (..., d, *shape)`` ->
    ``(..., *shape)`` (a 2x2 or 3x3 determinant).

    ``D phi = Id + D u`` with the displacement ``u = phi - Id`` differentiated by finite differences in
    physical units (``_central_diff``: central inside, one-sided at the border, zero along an axis of one
    cell); differencing ``u`` rather than ``phi`` is the same formula (differences of ``Id`` are exact) with
    less cancellation in float32. Exact for affine maps. Plain tensor ops (differentiable by autograd).

    Convention: component 0 of ``points`` = x, 1 = y (, 2 = z) in physical units of ``domain``; any batch
    dims, float dtype and device (the input's).
    """
    u = points - domain.points(points.dtype, points.device)
    return displacement_determinant(u, domain)


def displacement_determinant(u: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """``det(Id + D u)`` for a displacement ``u (..., d, *shape)`` in physical units; ``u`` is not modified.

    Row ``a`` of ``D u`` is the gradient of component ``a`` (one difference per axis, ``domain.cell_sides``);
    in 2D the determinant is ``(1 + d1 u1)(1 + d2 u2) - d2 u1 d1 u2``, formed in place; in 3D the cofactor
    expansion along the first row (``determinant``).
    """
    d = domain.ndim
    derivative = [[_central_diff(u.select(-d - 1, a), axis - d, h) for axis, h in enumerate(domain.cell_sides)]
                  for a in range(d)]
    for a in range(d):
        derivative[a][a].add_(1)
    if d == 2:
        (d11, d12), (d21, d22) = derivative
        return d11.mul_(d22).sub_(d12.mul_(d21))
    return determinant(derivative)


def determinant(m: list) -> torch.Tensor:
    """The determinant of a 2x2 or 3x3 matrix field given by its entries ``m[a][b]`` (tensors of one shape),
    out of place (differentiable by autograd): ``m00 m11 - m01 m10``, or in 3D the cofactor expansion
    ``m00 (m11 m22 - m12 m21) - m01 (m10 m22 - m12 m20) + m02 (m10 m21 - m11 m20)``."""
    if len(m) == 2:
        return m[0][0] * m[1][1] - m[0][1] * m[1][0]
    return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))


def _sample_displaced(f: torch.Tensor, u: torch.Tensor, domain: ImageDomain, padding_mode: str) -> torch.Tensor:
    """``f o (Id + u)``, skipping the interpolation when ``u`` is exactly zero and no graph is recorded."""
    k = domain.ndim + 1
    if not (torch.is_grad_enabled() and u.requires_grad) and not bool(u.ne(0).any()):
        return f.expand(*u.shape[:-k], *f.shape[-k:])
    return sample(f.expand(*u.shape[:-k], *f.shape[-k:]), displaced_grid(u, domain), padding_mode)



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


def _check_action(action: str) -> None:
    if action not in ACTIONS:
        raise ValueError(f"action must be one of {ACTIONS}, got {action!r}")


# ----------------------------------------------------------------------------------------------------------
# the paper's gradient (Algorithm 1, lines 8-10)
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
    record = velocity.new_empty(torch.broadcast_shapes(template.shape[:-d], velocity.shape[:t]) + velocity.shape[t:])
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


def _padded_scratch(like: torch.Tensor, ndim: int) -> tuple:
    """A zero-padded image buffer ``(..., 1, nx+2, ny+2[, nz+2])`` for images like ``like (..., *shape)``
    (``ndim`` image axes), and its interior."""
    padded = like.new_zeros(*like.shape[:-ndim], 1, *(n + 2 for n in like.shape[-ndim:]))
    return padded, padded[(Ellipsis, *[slice(1, -1)] * ndim)]


def _differences_into(out: torch.Tensor, p: torch.Tensor, scheme: str, ndim: int) -> torch.Tensor:
    """The finite differences along every axis (before the quotients' factors) of the zero-padded image
    ``p (..., 1, nx+2, ny+2[, nz+2])`` into ``out (..., d, *shape)``."""
    for axis, o in enumerate(out.unbind(-ndim - 1)):
        torch.sub(*_differenced(p.squeeze(-ndim - 1), axis, ndim, scheme), out=o)
    return out


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



# ----------------------------------------------------------------------------------------------------------
# the exact derivative of the discrete map (a hand-written discrete adjoint of the recursions above)
_PADDING = {"zeros": 0, "border": 1}


def divergence_adjoint(g: torch.Tensor, domain: ImageDomain, scheme: str = "central") -> torch.Tensor:
    """The transpose of ``divergence``: ``(..., nx, ny)`` -> ``(..., 2, nx, ny)``, ``<div v, g> = <v, div^T g>``
    (plain sums over the entries). ``"forward"``: ``div`` is minus the transpose of the forward-difference
    ``gradient``, so ``div^T g = -gradient(g, "forward")`` (zero padding); ``"central"``: per axis the
    transpose of ``_central_diff``."""
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    d = domain.ndim
    out = g.new_zeros(*g.shape[:-d], d, *g.shape[-d:])
    return _add_divergence_adjoint(out, g, domain, scheme, 1.0)


def _add_divergence_adjoint(out: torch.Tensor, g: torch.Tensor, domain: ImageDomain, scheme: str,
                            c: float) -> torch.Tensor:
    """``out (..., d, *shape) += c div^T g`` in place: each difference quotient of ``divergence`` scattered back
    onto the samples it reads. ``"forward"``: ``(g[j] - g[j+1]) / h`` (``g`` 0 after the last sample);
    ``"central"``: ``(g[j-1] - g[j+1]) / 2h`` from the inner quotients ``(f[k+1] - f[k-1]) / 2h`` plus the
    one-sided ones at both ends, ``(f[1] - f[0]) / h`` and ``(f[n-1] - f[n-2]) / h`` (none for one sample)."""
    d = domain.ndim
    for k, h in enumerate(domain.cell_sides):
        dim = k - d
        o, n, a = out.select(-d - 1, k), g.shape[dim], c / h
        if scheme == "forward":
            o.add_(g, alpha=a)
            o.narrow(dim, 0, n - 1).sub_(g.narrow(dim, 1, n - 1), alpha=a)
            continue
        if n == 1:
            continue
        first, last = g.narrow(dim, 0, 1), g.narrow(dim, n - 1, 1)
        o.narrow(dim, 0, 1).sub_(first, alpha=a)
        o.narrow(dim, 1, 1).add_(first, alpha=a)
        o.narrow(dim, n - 1, 1).add_(last, alpha=a)
        o.narrow(dim, n - 2, 1).sub_(last, alpha=a)
        if n > 2:
            inner = g.narrow(dim, 1, n - 2)
            o.narrow(dim, 0, n - 2).sub_(inner, alpha=0.5 * a)
            o.narrow(dim, 2, n - 2).add_(inner, alpha=0.5 * a)
    return out


def _sample_adjoint(grad: torch.Tensor, f: torch.Tensor, grid: torch.Tensor, padding_mode: str,
                    need_input: bool, need_grid: bool) -> tuple:
    """The two transposes of ``sample(f, grid, padding_mode)`` applied to ``grad (..., C, *shape)``, in one pass:
    ``(S^T grad, d<grad, S(f)>/d grid)``, i.e. the scatter of ``grad`` with the interpolation weights
    ``(..., C, *shape)`` and the grid gradient ``(..., *shape, d)`` (reversed order: ``[..., 0]`` = y,
    ``[..., 1]`` = x in 2D, ``[..., 0]`` = z, ``[..., 1]`` = y, ``[..., 2]`` = x in 3D; grid units: the one-sided
    slope of ``f`` across the cell each point falls in). Either is None when not needed.
    ``grid_sampler_2d_backward`` / ``grid_sampler_3d_backward`` parallelise over the batch only: a single
    image on a CPU with ``k`` threads is done as ``k`` bands of rows (as ``sample``), whose ``k`` scatters are
    summed (the same values up to the order of the sums)."""
    d = grid.shape[-1]
    batch, (c, *shape) = grad.shape[:-d - 1], grad.shape[-d - 1:]
    if not (need_input or need_grid):
        return None, None
    grad, f = grad.reshape(-1, c, *shape), f.expand(*batch, c, *shape).reshape(-1, c, *shape)
    grid, bands = grid.expand(*batch, *shape, d).reshape(-1, *shape, d), _bands(grad, *shape)
    if bands > 1:
        grad, f, grid = grad.reshape(bands, c, shape[0] // bands, *shape[1:]), f.expand(bands, c, *shape), \
            grid.reshape(bands, shape[0] // bands, *shape[1:], d)
    backward = torch.ops.aten.grid_sampler_2d_backward if d == 2 else torch.ops.aten.grid_sampler_3d_backward
    gi, gg = backward(grad, f, grid, 0, _PADDING[padding_mode], False, [need_input, need_grid])
    if need_input and bands > 1:
        gi = gi.sum(0)
    return (gi.reshape(*batch, c, *shape) if need_input else None), \
        (gg.reshape(*batch, *shape, d) if need_grid else None)


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
    batch = torch.broadcast_shapes(template.shape[:-d], velocity.shape[:c - 1])
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

    Convention:
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
    d = domain.ndim
    c = -d - 1
    slots, n = record.slots.unbind(c - 1), velocity.shape[c - 1] - 1
    mass = action == "mass_preserving"
    lam = grad_out * record.jacobians.select(c, n) if mass else grad_out
    skipped = not bool(slots[n].ne(0).any()) and not bool(record.slots.ne(0).any())  # exact_record's identity
    grad_i, slope = _sample_adjoint(lam.unsqueeze(c), template.unsqueeze(c), displaced_grid(slots[n], domain),
                                    "zeros", need_template and not skipped, need_velocity)
    if need_template and skipped:
        grad_i = lam.unsqueeze(c)
    if need_velocity:
        kappa = torch.stack([slope[..., d - 1 - k] for k in range(d)], dim=c)  # dL/du_N, planar (x, y[, z])
        mu = grad_out * record.image if mass else None
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
    return grad_i.squeeze(c) if need_template else None


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

