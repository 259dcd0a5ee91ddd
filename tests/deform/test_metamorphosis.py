"""MetamorphosisDeformation: identity, reduction to LDDMM, pure source, analytic transport, exact adjoint gradient
(2D and 3D: one code path, tested on both; 3D on 8^3 volumes with N = 3, float64)."""
import pytest
import torch

from indreg import ImageDomain
from indreg.deform import LDDMMDeformation
from indreg.deform import functional as Fd
from indreg.deform.metamorphosis import MetamorphosisDeformation

INTERP = ("reinterpolate", "compose")
NDIM = (2, 3)
#: (grid size, time steps) of the random problems per dimension
SIZES = {2: (12, 4), 3: (8, 3)}


def random_problem(n=None, num_steps=None, amp=0.6, seed=0, dtype=torch.float64, ndim=2):
    """Random velocity (max |nu| ~ amp cells per unit time, every step moving), source, template, incoming G on
    an ``n^ndim`` grid (default ``SIZES[ndim]``)."""
    n = SIZES[ndim][0] if n is None else n
    num_steps = SIZES[ndim][1] if num_steps is None else num_steps
    g = torch.Generator().manual_seed(seed)
    dom = ImageDomain.paper(n, ndim=ndim)
    h, shape = dom.cell_sides[0], dom.shape
    v = amp * h * num_steps * (torch.rand(num_steps + 1, ndim, *shape, generator=g, dtype=dtype) - 0.5)
    z = torch.randn(num_steps + 1, *shape, generator=g, dtype=dtype)
    template = torch.rand(shape, generator=g, dtype=dtype)
    grad_out = torch.randn(shape, generator=g, dtype=dtype)
    return dom, v, z, template, grad_out


def gradients(M, v, z, template, grad_out):
    v, z, template = (x.clone().requires_grad_() for x in (v, z, template))
    return torch.autograd.grad((M(v, z, template) * grad_out).sum(), (v, z, template))


def relative(a, b):
    return float((a - b).norm() / b.norm())


# ---------------------------------------------------------------------------------------------- forward
@pytest.mark.parametrize("shape", ((12, 10), (8, 7, 6)))
@pytest.mark.parametrize("interpolation", INTERP)
def test_zero_velocity_and_source_is_identity(interpolation, shape):
    dom = ImageDomain(shape)
    template = torch.rand(shape, dtype=torch.float64)
    M = MetamorphosisDeformation(dom, 5, interpolation=interpolation)
    v, z = M.zero_velocity(), M.zero_source()
    assert v.shape == (6, len(shape), *shape) and z.shape == (6, *shape)
    assert torch.equal(M(v, z, template), template)
    assert torch.equal(M.trajectory(v, z, template), template.expand(6, *shape))
    deformed, intensity = M.parts(v, z, template)
    assert torch.equal(deformed, template) and not bool(intensity.ne(0).any())


@pytest.mark.parametrize("ndim", NDIM)
@pytest.mark.parametrize("interpolation", INTERP)
def test_zero_source_is_lddmm(interpolation, ndim):
    dom, v, z, template, grad_out = random_problem(ndim=ndim)
    n = SIZES[ndim][1]
    M = MetamorphosisDeformation(dom, n, interpolation=interpolation)
    W = LDDMMDeformation(dom, n, "geometric", "autograd", interpolation)
    zero = torch.zeros_like(z)
    torch.testing.assert_close(M(v, zero, template), W(v, template), rtol=0, atol=1e-14)
    torch.testing.assert_close(M.trajectory(v, zero, template), W.trajectory(v, template), rtol=0, atol=1e-14)
    # the same discrete map, so the exact gradients agree too (autograd through LDDMM's forward)
    gv, _, gi = gradients(M, v, zero, template, grad_out)
    vv, tt = v.clone().requires_grad_(), template.clone().requires_grad_()
    wv, wi = torch.autograd.grad((W(vv, tt) * grad_out).sum(), (vv, tt))
    assert relative(gv[1:], wv[1:]) < 1e-12 and relative(gi, wi) < 1e-12


@pytest.mark.parametrize("ndim", NDIM)
@pytest.mark.parametrize("interpolation", INTERP)
def test_pure_source_is_the_quadrature_of_the_source(interpolation, ndim):
    dom, _, z, template, _ = random_problem(ndim=ndim)
    n = SIZES[ndim][1]
    M = MetamorphosisDeformation(dom, n, interpolation=interpolation)
    path = M.trajectory(M.zero_velocity(), z, template)
    # f(t_i) = I + (1/N) sum_{j=1..i} zeta_j (right Riemann sum; zeta_0 does not enter)
    expected = template + torch.cumsum(torch.cat((torch.zeros_like(z[:1]), z[1:])), 0) / n
    torch.testing.assert_close(path, expected, rtol=0, atol=1e-14)
    torch.testing.assert_close(M(M.zero_velocity(), z, template), template + z[1:].sum(0) / n, rtol=0, atol=1e-14)
    deformed, intensity = M.parts(M.zero_velocity(), z, template)
    assert torch.equal(deformed, template)
    torch.testing.assert_close(intensity, z[1:].sum(0) / n, rtol=0, atol=1e-14)


@pytest.mark.parametrize("ndim", NDIM)
@pytest.mark.parametrize("interpolation", INTERP)
def test_translation_by_one_cell_per_step(interpolation, ndim):
    """nu = (N h, 0[, 0]): every step moves the image one cell along x, so f(1) = I shifted by N cells plus each
    zeta_i / N shifted by N - i cells (zeros shifted in): the exact solution of the transport equation."""
    n, num_steps = (16, 4) if ndim == 2 else (10, 3)
    dom = ImageDomain.paper(n, ndim=ndim)
    g = torch.Generator().manual_seed(3)
    template = torch.rand(dom.shape, generator=g, dtype=torch.float64)
    z = torch.randn(num_steps + 1, *dom.shape, generator=g, dtype=torch.float64)
    v = torch.zeros(num_steps + 1, ndim, *dom.shape, dtype=torch.float64)
    v[:, 0] = num_steps * dom.cell_sides[0]

    def shift(f, k):
        return torch.cat((torch.zeros_like(f[:k]), f[:n - k])) if k else f

    expected = shift(template, num_steps) + sum(shift(z[i], num_steps - i) for i in range(1, num_steps + 1)) / num_steps
    M = MetamorphosisDeformation(dom, num_steps, interpolation=interpolation)
    torch.testing.assert_close(M(v, z, template), expected, rtol=0, atol=1e-12)
    deformed, intensity = M.parts(v, z, template)
    torch.testing.assert_close(deformed, shift(template, num_steps), rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("ndim", NDIM)
@pytest.mark.parametrize("interpolation", INTERP)
@pytest.mark.parametrize("seed", (0, 1))
def test_adjoint_equals_autograd(interpolation, seed, ndim):
    dom, v, z, template, grad_out = random_problem(seed=seed, ndim=ndim)
    n = SIZES[ndim][1]
    adjoint = gradients(MetamorphosisDeformation(dom, n, "adjoint", interpolation), v, z, template, grad_out)
    autograd = gradients(MetamorphosisDeformation(dom, n, "autograd", interpolation), v, z, template, grad_out)
    for a, b in zip(adjoint, autograd):
        assert relative(a, b) < 1e-10
    assert not bool(adjoint[0][0].ne(0).any()) and not bool(adjoint[1][0].ne(0).any())  # t_0 does not enter


@pytest.mark.parametrize("ndim", NDIM)
@pytest.mark.parametrize("interpolation", INTERP)
def test_gradient_at_zero_velocity_uses_central_slopes(interpolation, ndim):
    """At nu = 0: lambda_i = G, dL/dzeta_i = G / N, dL/dnu_i = -(1/N) G grad_central(f(t_{i-1}))."""
    dom, _, z, template, grad_out = random_problem(ndim=ndim)
    n = SIZES[ndim][1]
    M = MetamorphosisDeformation(dom, n, interpolation=interpolation)
    gv, gz, gi = gradients(M, M.zero_velocity(), z, template, grad_out)
    path = M.trajectory(M.zero_velocity(), z, template)
    for i in range(1, n + 1):
        expected = -(1 / n) * grad_out * Fd.gradient(path[i - 1], dom, "central")  # physical units
        torch.testing.assert_close(gv[i], expected, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(gz[i], grad_out / n, rtol=0, atol=1e-15)
    torch.testing.assert_close(gi, grad_out, rtol=0, atol=1e-15)


@pytest.mark.parametrize("ndim", NDIM)
@pytest.mark.parametrize("interpolation", INTERP)
def test_directional_derivatives_match_central_differences(interpolation, ndim):
    dom, v, z, template, grad_out = random_problem(seed=2, ndim=ndim)
    M = MetamorphosisDeformation(dom, SIZES[ndim][1], interpolation=interpolation)
    gv, gz, gi = gradients(M, v, z, template, grad_out)
    g = torch.Generator().manual_seed(5)
    dv, dz, di = torch.randn(v.shape, generator=g, dtype=v.dtype), torch.randn(z.shape, generator=g, dtype=z.dtype), \
        torch.randn(template.shape, generator=g, dtype=template.dtype)
    dv[0] = 0  # nu(t_0) does not enter the map

    def loss(e):
        with torch.no_grad():
            return float((M(v + e * dv, z + e * dz, template + e * di) * grad_out).sum())

    eps = 1e-6
    numeric = (loss(eps) - loss(-eps)) / (2 * eps)
    analytic = float((gv * dv).sum() + (gz * dz).sum() + (gi * di).sum())
    assert abs(numeric - analytic) <= 1e-6 * abs(analytic)
    for name, d, grad in (("velocity", (dv, 0, 0), gv), ("source", (0, dz, 0), gz)):
        def part(e, d=d):
            with torch.no_grad():
                return float((M(v + e * d[0], z + e * d[1], template) * grad_out).sum())
        numeric = (part(eps) - part(-eps)) / (2 * eps)
        analytic = float((grad * (d[0] if name == "velocity" else d[1])).sum())
        assert abs(numeric - analytic) <= 1e-6 * abs(analytic), name


@pytest.mark.parametrize("ndim", [2, pytest.param(3, marks=pytest.mark.slow)])
@pytest.mark.parametrize("interpolation", INTERP)
def test_gradcheck(interpolation, ndim):
    dom, v, z, template, _ = random_problem(n=6 if ndim == 2 else 4, num_steps=2, seed=4, ndim=ndim)
    M = MetamorphosisDeformation(dom, 2, interpolation=interpolation)
    inputs = tuple(x.clone().requires_grad_() for x in (v, z, template))
    assert torch.autograd.gradcheck(lambda a, b, c: M(a, b, c), inputs, eps=1e-6, atol=1e-7)


def test_backward_twice_through_a_retained_graph():
    dom, v, z, template, grad_out = random_problem()
    M = MetamorphosisDeformation(dom, 4)
    v = v.clone().requires_grad_()
    out = (M(v, z, template) * grad_out).sum()
    first, = torch.autograd.grad(out, v, retain_graph=True)
    second, = torch.autograd.grad(out, v)
    assert torch.equal(first, second)


def test_batch_equals_single_calls_with_a_shared_template():
    dom, v, z, template, grad_out = random_problem()
    v2 = torch.stack((v, 0.5 * v.flip(-1)))
    z2 = torch.stack((z, -z))
    M = MetamorphosisDeformation(dom, 4)
    vb, zb, tb = v2.clone().requires_grad_(), z2.clone().requires_grad_(), template.clone().requires_grad_()
    out = M(vb, zb, tb)
    (out * grad_out).sum().backward()
    grad_t = torch.zeros_like(template)
    for k in range(2):
        torch.testing.assert_close(out[k], M(v2[k], z2[k], template), rtol=0, atol=1e-15)
        gv, gz, gi = gradients(M, v2[k], z2[k], template, grad_out)
        torch.testing.assert_close(vb.grad[k], gv, rtol=0, atol=1e-15)
        torch.testing.assert_close(zb.grad[k], gz, rtol=0, atol=1e-15)
        grad_t += gi
    torch.testing.assert_close(tb.grad, grad_t, rtol=0, atol=1e-14)


def test_float32_close_to_float64():
    dom, v, z, template, grad_out = random_problem()
    M = MetamorphosisDeformation(dom, 4)
    g64 = gradients(M, v, z, template, grad_out)
    g32 = gradients(M, v.float(), z.float(), template.float(), grad_out.float())
    for a, b in zip(g32, g64):
        assert a.dtype == torch.float32 and relative(a.double(), b) < 1e-5


def test_bad_input():
    dom, v, z, template, _ = random_problem()
    M = MetamorphosisDeformation(dom, 4)
    with pytest.raises(ValueError, match="source must have num_steps \\+ 1 = 5"):
        M(v, z[:3], template)
    with pytest.raises(ValueError, match="source must have shape"):
        M(v, z[..., :5], template)
    bad = z.clone()
    bad[2, 1, 1] = float("nan")
    with pytest.raises(ValueError, match="source contains non-finite"):
        M(v, bad, template)
    with pytest.raises(TypeError, match="velocity has dtype torch.float64 but source has dtype torch.float32"):
        M(v, z.float(), template)
    with pytest.raises(ValueError, match="velocity must have num_steps"):
        M(v[:3], z, template)
    with pytest.raises(ValueError, match="do not broadcast"):
        M(v.expand(2, *v.shape), z.expand(3, *z.shape), template)
    with pytest.raises(ValueError, match="interpolation must be one of"):
        MetamorphosisDeformation(dom, 4, interpolation="cubic")
    with pytest.raises(ValueError, match="backward must be one of"):
        MetamorphosisDeformation(dom, 4, backward="paper")


def test_bad_input_3d():
    dom, v, z, template, _ = random_problem(ndim=3)
    M = MetamorphosisDeformation(dom, 3)
    with pytest.raises(ValueError, match=r"source must have num_steps \+ 1 = 4 time points on axis -4 "
                                         r"\(shape \(\.\.\., N\+1, nx, ny, nz\)\)"):
        M(v, z[:2], template)
    with pytest.raises(ValueError, match="source must have shape"):
        M(v, z[..., :5], template)
    with pytest.raises(ValueError, match="velocity must have shape"):
        M(v[:, :2], z, template)


def test_empty_batch_is_refused():
    dom, v, z, template, _ = random_problem()
    M = MetamorphosisDeformation(dom, 4)
    for call in (M, M.trajectory, M.parts):
        with pytest.raises(ValueError, match=r"^velocity is empty \(shape \(0, 5, 2, 12, 12\)\)"):
            call(v[None][:0], z, template)
        with pytest.raises(ValueError, match=r"^source is empty \(shape \(0, 5, 12, 12\)\)"):
            call(v, z[None][:0], template)
        with pytest.raises(ValueError, match=r"^template is empty \(shape \(0, 12, 12\)\)"):
            call(v, z, template[None][:0])
