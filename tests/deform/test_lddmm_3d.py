"""LDDMM in 3D: the same code path as 2D on an ``ImageDomain`` of shape (nx, ny, nz).

Analytic flows (translation, rotation about z, identity, affine Jacobians), mass conservation, the kernel,
exact gradients (autograd, hand-written adjoint, finite differences, gradcheck), geodesic shooting.
"""
import math

import pytest
import torch

from indreg import ImageDomain
from indreg.deform import GaussianKernel, LDDMMDeformation
from indreg.deform.shooting import GeodesicShooting
from indreg.deform import functional as Fd

ACTIONS = ("geometric", "mass_preserving")
INTERP = ("reinterpolate", "compose")


def blob(domain, centre=(2.0, -1.0, 1.0), widths=(5.0, 3.0, 4.0), dtype=torch.float64):
    """An anisotropic Gaussian ``exp(-sum ((x_k - c_k) / w_k)^2 / 2)``."""
    return torch.exp(-sum(((p - c) / w) ** 2 for p, c, w in zip(domain.points(dtype), centre, widths)) / 2)


def smooth_velocity(domain, num_steps, amp=1.0, sigma=5.0, seed=0, dtype=torch.float64):
    """A kernel-smoothed random velocity ``(N+1, 3, nx, ny, nz)``, linear in time, max |v| = amp."""
    g = torch.Generator().manual_seed(seed)
    m0, m1 = (torch.randn(3, *domain.shape, dtype=torch.float64, generator=g) for _ in range(2))
    t = torch.linspace(0, 1, num_steps + 1, dtype=torch.float64).view(-1, 1, 1, 1, 1)
    v = GaussianKernel(domain, sigma)(m0 * (1 - t) + m1 * t)
    return (amp * v / v.abs().max()).to(dtype)


def constant_velocity(domain, num_steps, vector, dtype=torch.float64):
    v = torch.tensor(vector, dtype=dtype).view(1, 3, 1, 1, 1)
    return v.expand(num_steps + 1, 3, *domain.shape).contiguous()


# ------------------------------------------------------------------------------------------------ the kernel
@pytest.mark.parametrize("method", ("matrix", "fft"))
def test_kernel_of_a_delta_is_the_gaussian(method):
    dom = ImageDomain((12, 10, 8), (-6.0, -5.0, -4.0), (6.0, 5.0, 4.0))
    K = GaussianKernel(dom, 2.5, method=method)
    m = torch.zeros(3, *dom.shape, dtype=torch.float64)
    m[1, 5, 4, 3] = 1.0
    centre = [a[i] for a, i in zip(dom.axes(), (5, 4, 3))]
    expected = dom.cell_volume * torch.exp(-sum((p - c) ** 2 for p, c in zip(dom.points(), centre)) / (2 * 2.5 ** 2))
    out = K(m)
    torch.testing.assert_close(out[1], expected, rtol=1e-12, atol=1e-15)
    assert out[0].abs().max() == 0 and out[2].abs().max() == 0


def test_kernel_fft_equals_matrix_and_is_self_adjoint():
    dom = ImageDomain((9, 12, 7), (-4.0, -6.0, -3.0), (5.0, 6.0, 4.0))
    g = torch.Generator().manual_seed(0)
    f, h = (torch.randn(2, 3, *dom.shape, dtype=torch.float64, generator=g) for _ in range(2))
    Km, Kf = GaussianKernel(dom, 3.0, method="matrix"), GaussianKernel(dom, 3.0, method="fft")
    torch.testing.assert_close(Km(f), Kf(f), rtol=1e-11, atol=1e-12)
    lhs, rhs = (Km(f) * h).sum(), (f * Km(h)).sum()
    assert abs(float(lhs - rhs)) < 1e-11 * float(lhs.abs())
    assert bool((Km.inner_v(f, f) > 0).all())  # positive definite


def test_kernel_rejects_a_2d_field_on_a_3d_domain():
    K = GaussianKernel(ImageDomain.paper(8, 3), 6.0)
    with pytest.raises(ValueError, match="vector field"):
        K(torch.zeros(2, 8, 8, 8))


# ------------------------------------------------------------------------------------------------ finite differences
BOX = ImageDomain((7, 6, 5), (0.0, -1.0, 0.5), (3.0, 1.0, 3.0))  # unequal cell sides


def _random(*shape, seed=0):
    return torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def test_gradient_from_padded_differences_3d():
    (hx, hy, hz), f = BOX.cell_sides, _random(*BOX.shape)
    p = torch.nn.functional.pad(f, (1, 1) * 3)
    central = torch.stack([(p[2:, 1:-1, 1:-1] - p[:-2, 1:-1, 1:-1]) / (2 * hx),
                           (p[1:-1, 2:, 1:-1] - p[1:-1, :-2, 1:-1]) / (2 * hy),
                           (p[1:-1, 1:-1, 2:] - p[1:-1, 1:-1, :-2]) / (2 * hz)])
    forward = torch.stack([(p[2:, 1:-1, 1:-1] - f) / hx, (p[1:-1, 2:, 1:-1] - f) / hy, (p[1:-1, 1:-1, 2:] - f) / hz])
    torch.testing.assert_close(Fd.gradient(f, BOX), central, rtol=0, atol=1e-13)
    torch.testing.assert_close(Fd.gradient(f, BOX, "forward"), forward, rtol=0, atol=1e-13)


def test_divergence_3d():
    """Exact on a linear field (central); forward: minus the transpose of the forward gradient."""
    x, y, z = BOX.points()
    field = torch.stack([3 * x + y, -x + 0.5 * y + z, 2 * z - y])
    torch.testing.assert_close(Fd.divergence(field, BOX), torch.full_like(x, 5.5))
    f, v = _random(*BOX.shape, seed=1), _random(3, *BOX.shape, seed=2)
    torch.testing.assert_close((Fd.gradient(f, BOX, "forward") * v).sum(), -(f * Fd.divergence(v, BOX, "forward")).sum())


@pytest.mark.parametrize("scheme", ("central", "forward"))
@pytest.mark.parametrize("shape", ((7, 6, 5), (2, 5, 4), (1, 1, 1)))
def test_growth_factors_and_divergence_adjoint_3d(scheme, shape):
    dom = ImageDomain(shape, (0.0, -1.0, 0.5), (3.0, 1.0, 3.0))
    v, g = _random(4, 3, *shape, seed=3), _random(4, *shape, seed=4)
    out = torch.empty(4, *shape, dtype=torch.float64)
    Fd._growth_into(out, v, dom, scheme, -0.25)
    torch.testing.assert_close(out, 1 - 0.25 * Fd.divergence(v, dom, scheme), rtol=0, atol=1e-13)
    lhs, rhs = (Fd.divergence(v, dom, scheme) * g).sum(), (v * Fd.divergence_adjoint(g, dom, scheme)).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------------ analytic flows
@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("backward", ("paper", "exact", "autograd"))
def test_zero_velocity_is_the_identity(action, backward):
    dom = ImageDomain.paper(10, 3)
    W = LDDMMDeformation(dom, num_steps=4, action=action, backward=backward)
    template = blob(dom)
    assert torch.equal(W(W.zero_velocity(), template), template)
    assert torch.equal(W.jacobian_determinant(W.zero_velocity()), torch.ones(dom.shape, dtype=torch.float64))


def test_translation_by_whole_cells_is_exact():
    """Constant velocity: ``phi_{1,0}(x) = x - v``; composed displacements are exact for a constant field, and
    a shift by whole cells samples the template at cell centres."""
    dom = ImageDomain((12, 10, 8), (-6.0, -5.0, -4.0), (6.0, 5.0, 4.0))  # unit cells
    W = LDDMMDeformation(dom, num_steps=5, interpolation="compose")
    template = blob(dom, (0.0, 0.0, 0.0), (2.0, 1.5, 1.0))
    shifted = torch.zeros_like(template)
    shifted[2:, :9, 1:] = template[:-2, 1:, :-1]  # I(x - v), v = (2, -1, 1), 0 outside
    out = W(constant_velocity(dom, 5, (2.0, -1.0, 1.0)), template)
    torch.testing.assert_close(out, shifted, rtol=0, atol=1e-12)


@pytest.mark.parametrize("interpolation,tol", [("reinterpolate", 0.12), ("compose", 0.025)])
def test_translation_matches_the_shifted_template(interpolation, tol):
    """A shift by fractions of a cell: interpolation blur only (reinterpolate: once per step; measured 0.093 /
    0.017, the blur of the 2D code at the same resolution)."""
    dom = ImageDomain((20, 20, 20), (-10.0, -10.0, -10.0), (10.0, 10.0, 10.0))
    v = (1.3, -0.7, 2.1)
    W = LDDMMDeformation(dom, num_steps=8, interpolation=interpolation)
    template = blob(dom, (0.0, 1.0, -1.0), (3.5, 3.0, 3.2))
    expected = blob(dom, (v[0], 1.0 + v[1], -1.0 + v[2]), (3.5, 3.0, 3.2))
    out = W(constant_velocity(dom, 8, v), template)
    error = float((out - expected).norm() / expected.norm())
    assert error < tol, error
    assert float((template - expected).norm() / expected.norm()) > 5 * error
    phi = W.deformation(constant_velocity(dom, 8, v))
    torch.testing.assert_close(phi, dom.points() - torch.tensor(v, dtype=torch.float64).view(3, 1, 1, 1))


def test_rotation_about_z():
    """``nu(x) = w (-y, x, 0)`` for unit time rotates by ``w`` about the z axis: ``phi_{1,0} = R(-w)``, so the
    deformed template is ``I(R(-w) x)``: the template rotated by ``w``."""
    dom = ImageDomain((24, 24, 16), (-12.0, -12.0, -8.0), (12.0, 12.0, 8.0))
    w, n = 0.25, 10
    x, y, z = dom.points()
    v = (w * torch.stack((-y, x, torch.zeros_like(z)))).expand(n + 1, 3, *dom.shape)
    widths, centre = (4.0, 2.0, 3.0), (2.0, 0.0, 1.0)
    template = blob(dom, centre, widths)
    c, s = math.cos(w), math.sin(w)
    xr, yr = c * x + s * y, -s * x + c * y  # R(-w) (x, y)
    expected = torch.exp(-(((xr - centre[0]) / widths[0]) ** 2 + ((yr - centre[1]) / widths[1]) ** 2
                           + ((z - centre[2]) / widths[2]) ** 2) / 2)
    W = LDDMMDeformation(dom, num_steps=n, interpolation="compose")
    out = W(v, template)
    error = float((out - expected).norm() / expected.norm())
    assert error < 0.03, error
    assert float((template - expected).norm() / expected.norm()) > 10 * error
    det = W.jacobian_determinant(v)[4:-4, 4:-4]  # a rotation preserves volume (inside: the border is clamped)
    torch.testing.assert_close(det, torch.ones_like(det), rtol=0, atol=0.02)


@pytest.mark.parametrize("interpolation,ratio", [("reinterpolate", 0.2), ("compose", 0.05)])
def test_mass_preserving_action_conserves_the_integral(interpolation, ratio):
    """The integral is conserved up to the discretisation (first-order Jacobian recursion, interpolation
    blur: the same errors as in 2D), while the geometric action changes it by ~40 %."""
    dom = ImageDomain.paper(20, 3)
    template = blob(dom, (0.0, 0.0, 0.0), (3.0, 2.5, 3.5))
    x, y, z = dom.points()
    expanding = torch.stack((0.3 * x, -0.1 * y, 0.2 * z)) * torch.exp(-(x ** 2 + y ** 2 + z ** 2) / 200)
    v = expanding.expand(11, 3, *dom.shape)
    mass = float(template.sum())
    geometric = LDDMMDeformation(dom, 10, interpolation=interpolation)(v, template)
    preserved = LDDMMDeformation(dom, 10, "mass_preserving", interpolation=interpolation)(v, template)
    geometric_change = abs(float(geometric.sum()) - mass) / mass
    assert geometric_change > 0.3
    assert abs(float(preserved.sum()) - mass) / mass < ratio * geometric_change


@pytest.mark.parametrize("dtype", (torch.float32, torch.float64))
def test_jacobian_determinant_of_an_affine_map_is_exact(dtype):
    dom = ImageDomain((7, 8, 9), (-3.0, -4.0, -2.0), (4.0, 4.0, 5.0))
    A = torch.tensor([[1.1, 0.2, -0.1], [0.05, 0.9, 0.3], [-0.2, 0.1, 1.2]], dtype=torch.float64)
    points = torch.einsum("ab,b...->a...", A, dom.points()) + torch.tensor([0.5, -1.0, 2.0]).view(3, 1, 1, 1)
    det = Fd.jacobian_determinant(points.to(dtype), dom)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(det, torch.full(dom.shape, float(torch.linalg.det(A)), dtype=dtype), rtol=tol, atol=tol)


def test_jacobian_determinant_of_a_linear_flow():
    """``nu(x) = B x`` constant in time: ``phi_{1,0} = exp(-B)`` (up to O(1/N)), determinant ``exp(-tr B)``."""
    dom = ImageDomain.paper(16, 3)
    B = torch.tensor([[0.1, 0.05, 0.0], [0.0, -0.05, 0.02], [0.03, 0.0, 0.15]], dtype=torch.float64)
    v = torch.einsum("ab,b...->a...", B, dom.points()).expand(21, 3, *dom.shape)
    W = LDDMMDeformation(dom, num_steps=20)
    det = W.jacobian_determinant(v)[3:-3, 3:-3, 3:-3]
    expected = math.exp(-float(B.trace()))
    torch.testing.assert_close(det, torch.full_like(det, expected), rtol=0.01, atol=0)
    assert float(W.min_jacobian(v)) > 0


def test_wrong_velocity_layout_is_a_clear_error():
    W = LDDMMDeformation(ImageDomain.paper(8, 3), num_steps=2)
    template = torch.zeros(8, 8, 8, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"velocity must have shape \(\.\.\., 3, 3, 8, 8, 8\)"):
        W(torch.zeros(3, 2, 8, 8, 8, dtype=torch.float64), template)
    with pytest.raises(ValueError, match="time points on axis -5"):
        W(torch.zeros(4, 3, 8, 8, 8, dtype=torch.float64), template)
    with pytest.raises(ValueError, match="template"):
        W(W.zero_velocity(), torch.zeros(8, 8, dtype=torch.float64))


# ------------------------------------------------------------------------------------------------ gradients
def _problem(n=8, num_steps=3, amp=1.5, seed=0):
    dom = ImageDomain.paper(n, 3)
    v = smooth_velocity(dom, num_steps, amp, sigma=6.0, seed=seed)
    template = blob(dom, (2.0, -1.0, 1.0), (6.0, 5.0, 7.0)) + 0.5 * blob(dom, (-4.0, 3.0, -2.0), (5.0, 6.0, 4.0))
    grad_out = blob(dom, (-1.0, 0.0, 2.0), (8.0, 7.0, 6.0)) * torch.cos(dom.points()[0] / 4)
    return dom, v, template, grad_out


def _grads(W, v, template, grad_out):
    v, template = v.clone().requires_grad_(), template.clone().requires_grad_()
    out = W(v, template)
    gv, gi = torch.autograd.grad(out, (v, template), grad_out)
    return out.detach(), gv, gi


@pytest.mark.parametrize("action,scheme", [("geometric", "central"), ("mass_preserving", "central"),
                                           ("mass_preserving", "forward")])
@pytest.mark.parametrize("interpolation", INTERP)
def test_exact_equals_autograd(action, scheme, interpolation):
    dom, v, template, grad_out = _problem()
    out_e, gv_e, gi_e = _grads(LDDMMDeformation(dom, 3, action, "exact", interpolation, scheme), v, template, grad_out)
    out_a, gv_a, gi_a = _grads(LDDMMDeformation(dom, 3, action, "autograd", interpolation, scheme), v, template,
                               grad_out)
    torch.testing.assert_close(out_e, out_a, rtol=1e-12, atol=1e-14)
    assert float((gv_e - gv_a).norm() / gv_a.norm()) < 1e-10
    assert float((gi_e - gi_a).norm() / gi_a.norm()) < 1e-10


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_paper_gradient_is_close_to_the_exact_one(action, interpolation):
    """The paper's backward discretises the continuous gradient: close to, not equal to, the exact one."""
    dom, v, template, grad_out = _problem(n=16, num_steps=6, amp=1.0)
    _, gv_p, _ = _grads(LDDMMDeformation(dom, 6, action, "paper", interpolation), v, template, grad_out)
    _, gv_e, _ = _grads(LDDMMDeformation(dom, 6, action, "exact", interpolation), v, template, grad_out)
    gv_p, gv_e = gv_p[1:], gv_e[1:]  # the discrete map does not use nu(t_0)
    cosine = float((gv_p * gv_e).sum() / (gv_p.norm() * gv_e.norm()))
    assert cosine > 0.9, cosine


@pytest.mark.parametrize("backward", ("exact", "autograd"))
def test_directional_derivative_matches_central_differences(backward):
    dom, v, template, grad_out = _problem()
    W = LDDMMDeformation(dom, 3, "mass_preserving", backward)
    direction = smooth_velocity(dom, 3, 1.0, sigma=6.0, seed=5)
    _, gv, _ = _grads(W, v, template, grad_out)
    eps = 1e-5
    with torch.no_grad():
        plus, minus = ((W(v + s * eps * direction, template) * grad_out).sum() for s in (1, -1))
    fd = float(plus - minus) / (2 * eps)
    assert abs(float((gv * direction).sum()) - fd) < 1e-7 * max(1.0, abs(fd)), (float((gv * direction).sum()), fd)


@pytest.mark.parametrize("action,interpolation", [("geometric", "reinterpolate"), ("mass_preserving", "compose")])
def test_gradcheck_exact(action, interpolation):
    dom, v, template, _ = _problem(n=8, num_steps=2, amp=1.0)
    W = LDDMMDeformation(dom, 2, action, "exact", interpolation)
    assert torch.autograd.gradcheck(lambda a, b: W(a, b), (v.requires_grad_(), template.requires_grad_()),
                                    fast_mode=True, atol=1e-6, rtol=1e-4)


def test_batched_3d_velocities_share_the_template():
    dom, v, template, grad_out = _problem()
    W = LDDMMDeformation(dom, 3, backward="exact")
    vb = torch.stack((v, 0.5 * v)).requires_grad_()
    out = W(vb, template)
    assert out.shape == (2, 8, 8, 8)
    torch.testing.assert_close(out[1], W(0.5 * v, template))
    (gv,) = torch.autograd.grad(out, vb, grad_out.expand(2, *dom.shape))
    torch.testing.assert_close(gv[0], _grads(W, v, template, grad_out)[1])


# ------------------------------------------------------------------------------------------------ shooting
def _momentum(domain, kernel, max_velocity, seed):
    """A smooth momentum supported near the centre whose velocity ``K m`` reaches ``max_velocity``."""
    g = torch.Generator().manual_seed(seed)
    m = kernel(torch.randn(3, *domain.shape, dtype=torch.float64, generator=g))
    m = m * torch.exp(-sum(p ** 2 for p in domain.points()) / (2 * 4.0 ** 2))
    return m * (max_velocity / float(kernel(m).abs().max()))


def test_geodesic_shooting_3d():
    dom = ImageDomain((16, 16, 16), (-8.0, -8.0, -8.0), (8.0, 8.0, 8.0))
    K = GaussianKernel(dom, 3.0)
    shoot = GeodesicShooting(dom, K, num_steps=8)
    template = blob(dom, (0.0, 0.0, 0.0), (3.0, 2.0, 2.5))
    zero = torch.zeros(3, *dom.shape, dtype=torch.float64)
    assert torch.equal(shoot(zero, template), template)
    m0 = _momentum(dom, K, 1.2, seed=3)
    result = shoot(m0, template, return_all=True)
    assert result.velocity.shape == (9, 3, *dom.shape) and result.deformation.shape == (3, *dom.shape)
    energy = shoot.energy(result.momentum)
    # the V norm is conserved on a geodesic, up to the discretisation (measured 3.7 %; 2D analogue 2.4 %)
    assert float((energy - energy[0]).abs().max() / energy[0]) < 0.05
    assert float((result.deformed - template).norm() / template.norm()) > 0.1  # a real deformation
    # the exact derivative through shooting and the deformation: directional derivative vs central differences
    m = m0.clone().requires_grad_()
    (g,) = torch.autograd.grad((shoot(m, template) * template).sum(), m)
    direction = _momentum(dom, K, 1.0, seed=4)
    eps = 1e-6  # piecewise-trilinear maps: central differences converge slowly (kinks), 1e-4 is off by 2e-5
    with torch.no_grad():
        fd = float(((shoot(m0 + eps * direction, template) - shoot(m0 - eps * direction, template)) * template).sum())
    fd /= 2 * eps
    assert abs(float((g * direction).sum()) - fd) < 1e-7 * max(1.0, abs(fd))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("action", ACTIONS)
def test_exact_equals_autograd_on_cuda(action):
    dom, v, template, grad_out = _problem()
    v, template, grad_out = v.cuda(), template.cuda(), grad_out.cuda()
    out_e, gv_e, gi_e = _grads(LDDMMDeformation(dom, 3, action, "exact"), v, template, grad_out)
    out_a, gv_a, gi_a = _grads(LDDMMDeformation(dom, 3, action, "autograd"), v, template, grad_out)
    assert out_e.device.type == "cuda"
    torch.testing.assert_close(out_e, out_a, rtol=1e-12, atol=1e-14)
    assert float((gv_e - gv_a).norm() / gv_a.norm()) < 1e-10
    assert float((gi_e - gi_a).norm() / gi_a.norm()) < 1e-10
