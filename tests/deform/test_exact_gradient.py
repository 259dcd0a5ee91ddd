"""backward="exact": the hand-written discrete adjoint equals autograd through the forward recursions."""
import math

import pytest
import torch

from indreg import ImageDomain
from indreg.deform import LDDMMDeformation
from indreg.deform import functional as Fd

ACTIONS = ("geometric", "mass_preserving")
INTERP = ("reinterpolate", "compose")
SCHEMES = ("central", "forward")


def random_problem(domain, num_steps, batch=(), amp=1.5, seed=0, dtype=torch.float64):
    """A random smooth velocity (a few random Fourier modes per time step and batch entry, max |nu| = ``amp``
    physical units, so the points move by up to about a cell per step), a smooth random template and
    incoming gradient."""
    g = torch.Generator().manual_seed(seed)
    x, y = domain.points(dtype)
    (x0, y0), (ex, ey) = domain.min_pt, domain.extent
    xs, ys = (x - x0) / ex, (y - y0) / ey  # in [0, 1]

    def field(*lead):
        k = torch.randint(1, 3, (*lead, 4, 2), generator=g).to(dtype)
        c = torch.randn(*lead, 4, 2, generator=g, dtype=dtype)
        phase = 2 * math.pi * torch.rand(*lead, 4, generator=g, dtype=dtype)
        arg = math.pi * (k[..., 0, None, None] * xs + k[..., 1, None, None] * ys) + phase[..., None, None]
        return torch.einsum("...mc,...mxy->...cxy", c, torch.cos(arg))  # (*lead, 2, nx, ny)

    v = field(*batch, num_steps + 1)
    v = amp * v / v.abs().amax()
    template = field()[0] ** 2 + 0.3 * field()[1]
    grad_out = field(*batch)[..., 0, :, :] * torch.exp(-(xs - 0.5) ** 2 - (ys - 0.5) ** 2)
    return v, template, grad_out


def grads(W, v, template, grad_out):
    v = v.clone().requires_grad_()
    template = template.clone().requires_grad_()
    out = W(v, template)
    (out * grad_out).sum().backward()
    return out.detach(), v.grad, template.grad


def rel(a, b):
    return float((a - b).norm() / b.norm())


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("interpolation", INTERP)
@pytest.mark.parametrize("action", ACTIONS)
def test_exact_equals_autograd(action, interpolation, scheme):
    """Batch dims, a shared template, hx != hy, zero steps: equal to autograd to 1e-10 (float64), the forward
    bit for bit that of the paper mode, and dL/dnu(t_0) exactly 0."""
    dom = ImageDomain((20, 14), (-8.0, -5.0), (8.0, 9.0))  # hx = 0.8, hy = 1.0
    v, template, grad_out = random_problem(dom, 5, batch=(2, 1), seed=1)
    v[..., 2, :, :, :] = 0  # a zero step (skipped by the forward) in every batch entry
    v[1, 0, 4] = 0  # and one in a single entry
    kw = dict(action=action, interpolation=interpolation, scheme=scheme)
    out, gv, gi = grads(LDDMMDeformation(dom, 5, backward="exact", **kw), v, template, grad_out)
    _, gv_ref, gi_ref = grads(LDDMMDeformation(dom, 5, backward="autograd", **kw), v, template, grad_out)
    paper = LDDMMDeformation(dom, 5, backward="paper", **kw)(v.clone().requires_grad_(), template)
    assert torch.equal(out, paper.detach())
    assert gv.shape == v.shape and gi.shape == template.shape
    assert rel(gv, gv_ref) < 1e-10 and rel(gi, gi_ref) < 1e-10, (rel(gv, gv_ref), rel(gi, gi_ref))
    assert gv[..., 2, :, :, :].abs().amax() > 0  # the derivative at a zero step exists and is used
    assert torch.equal(gv[..., 0, :, :, :], torch.zeros_like(gv[..., 0, :, :, :]))


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_batched_template_and_single_velocity(action, interpolation):
    """The other broadcast: one velocity for a batch of templates; the velocity gradient is summed back."""
    dom = ImageDomain((12, 16))
    v, template, _ = random_problem(dom, 4, seed=2)
    _, t2, grad_out = random_problem(dom, 4, batch=(3,), seed=3)
    templates = torch.stack([template, t2, template.flip(0)])
    kw = dict(action=action, interpolation=interpolation)
    _, gv, gi = grads(LDDMMDeformation(dom, 4, backward="exact", **kw), v, templates, grad_out)
    _, gv_ref, gi_ref = grads(LDDMMDeformation(dom, 4, backward="autograd", **kw), v, templates, grad_out)
    assert gv.shape == v.shape and gi.shape == templates.shape
    assert rel(gv, gv_ref) < 1e-10 and rel(gi, gi_ref) < 1e-10


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_gradcheck_exact_mode(action, interpolation):
    dom = ImageDomain((8, 6), (-4.0, -3.0), (4.0, 4.5))
    v, template, _ = random_problem(dom, 3, amp=0.7, seed=4)
    W = LDDMMDeformation(dom, 3, action=action, backward="exact", interpolation=interpolation)
    assert torch.autograd.gradcheck(W, (v.requires_grad_(), template.requires_grad_()))


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_directional_derivative_matches_central_differences(action, interpolation):
    dom = ImageDomain.paper(24)
    v, template, grad_out = random_problem(dom, 6, amp=2.0, seed=5)
    direction, dtemp, _ = random_problem(dom, 6, seed=6)
    W = LDDMMDeformation(dom, 6, action=action, backward="exact", interpolation=interpolation)
    _, gv, gi = grads(W, v, template, grad_out)
    eps = 1e-6
    loss = lambda vv, ii: float((W(vv, ii) * grad_out).sum())  # noqa: E731
    fd_v = (loss(v + eps * direction, template) - loss(v - eps * direction, template)) / (2 * eps)
    fd_i = (loss(v, template + eps * dtemp) - loss(v, template - eps * dtemp)) / (2 * eps)
    assert abs(float((gv * direction).sum()) - fd_v) <= 1e-6 * abs(fd_v)
    assert abs(float((gi * dtemp).sum()) - fd_i) <= 1e-8 * abs(fd_i)


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_zero_velocity(action, interpolation):
    """nu = 0: the template bit for bit, and the derivative there (every step skipped by the forward) equals
    autograd's, which interpolates every step."""
    dom = ImageDomain((10, 12))
    _, template, grad_out = random_problem(dom, 3, seed=7)
    v = torch.zeros(4, 2, 10, 12, dtype=torch.float64)
    kw = dict(action=action, interpolation=interpolation)
    out, gv, gi = grads(LDDMMDeformation(dom, 3, backward="exact", **kw), v, template, grad_out)
    _, gv_ref, gi_ref = grads(LDDMMDeformation(dom, 3, backward="autograd", **kw), v, template, grad_out)
    assert torch.equal(out, template)
    assert rel(gv, gv_ref) < 1e-10 and rel(gi, gi_ref) < 1e-10
    if action == "geometric":
        assert torch.equal(gi, grad_out)  # the identity's transpose


@pytest.mark.parametrize("interpolation", INTERP)
@pytest.mark.parametrize("action", ACTIONS)
def test_backward_twice_through_a_retained_graph(action, interpolation):
    """The first backward consumes the record; the second recomputes it: the same gradients."""
    dom = ImageDomain.paper(16)
    v, template, grad_out = random_problem(dom, 4, seed=8)
    v, template = v.requires_grad_(), template.requires_grad_()
    out = LDDMMDeformation(dom, 4, action=action, backward="exact", interpolation=interpolation)(v, template)
    first = torch.autograd.grad((out * grad_out).sum(), (v, template), retain_graph=True)
    second = torch.autograd.grad((out * grad_out).sum(), (v, template))
    for a, b in zip(first, second):
        assert torch.equal(a, b)


@pytest.mark.parametrize("interpolation", INTERP)
@pytest.mark.parametrize("action", ACTIONS)
def test_one_input_requiring_grad(action, interpolation):
    """Only the velocity or only the template requires grad: the same gradients as the joint call."""
    dom = ImageDomain.paper(16)
    v, template, grad_out = random_problem(dom, 4, seed=9)
    W = LDDMMDeformation(dom, 4, action=action, backward="exact", interpolation=interpolation)
    _, gv, gi = grads(W, v, template, grad_out)
    vv = v.clone().requires_grad_()
    (W(vv, template) * grad_out).sum().backward()
    tt = template.clone().requires_grad_()
    (W(v, tt) * grad_out).sum().backward()
    assert torch.equal(vv.grad, gv) and torch.equal(tt.grad, gi)


def test_float32_and_once_differentiable():
    dom = ImageDomain.paper(16)
    v, template, grad_out = random_problem(dom, 4, seed=10)
    W = LDDMMDeformation(dom, 4, action="mass_preserving", backward="exact", interpolation="compose")
    _, gv32, gi32 = grads(W, v.float(), template.float(), grad_out.float())
    _, gv, gi = grads(W, v, template, grad_out)
    assert gv32.dtype == torch.float32
    assert rel(gv32.double(), gv) < 1e-4 and rel(gi32.double(), gi) < 1e-4
    vv = v.clone().requires_grad_()
    (g,) = torch.autograd.grad((W(vv, template) ** 2).sum(), vv, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable|double backward|twice"):
        g.sum().backward()


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("shape", ((7, 5), (3, 4), (2, 6), (1, 3)))
def test_divergence_adjoint_is_the_transpose(scheme, shape):
    """<div v, g> = <v, div^T g> (plain sums), also on grids of 1 and 2 cells along an axis."""
    dom = ImageDomain(shape, (-1.0, -2.0), (2.0, 1.5))
    g = torch.Generator().manual_seed(11)
    v = torch.randn(3, 2, *shape, dtype=torch.float64, generator=g)
    w = torch.randn(3, *shape, dtype=torch.float64, generator=g)
    lhs = (Fd.divergence(v, dom, scheme) * w).sum()
    rhs = (v * Fd.divergence_adjoint(w, dom, scheme)).sum()
    assert abs(float(lhs - rhs)) <= 1e-13 * float(v.norm() * w.norm())


def test_exact_gradient_consumes_the_record():
    dom = ImageDomain.paper(12)
    v, template, grad_out = random_problem(dom, 3, seed=12)
    out, record = Fd.exact_record(template, v, dom)
    kept = record.slots.clone()
    _, gi = Fd.exact_gradient(grad_out, template, v, record, dom, need_velocity=False)
    assert torch.equal(record.slots, kept)  # only the template gradient: the record is left as it is
    gv, gi2 = Fd.exact_gradient(grad_out, template, v, record, dom)
    assert gv is record.slots and torch.equal(gi, gi2)
    with pytest.raises(ValueError, match="record.slots must be shaped like the velocity"):
        Fd.exact_gradient(grad_out, template, v, Fd.ExactRecord(record.slots[:, 0]), dom)


@pytest.mark.parametrize("action", ACTIONS)
def test_geodesic_shooting_with_the_exact_backward(action):
    """The shooting layer hands its velocities to the deformation: with backward="exact" the momentum
    gradient is that of backward="autograd"."""
    from indreg.deform import GaussianKernel
    from indreg.deform.shooting import GeodesicShooting

    dom = ImageDomain.paper(16)
    kernel = GaussianKernel(dom, 5.0)
    _, template, grad_out = random_problem(dom, 1, seed=13)
    m0 = 0.05 * random_problem(dom, 0, seed=14)[0][0]
    got = {}
    for backward in ("exact", "autograd"):
        shoot = GeodesicShooting(dom, kernel, 4, action=action, backward=backward)
        m = m0.clone().requires_grad_()
        (shoot(m, template) * grad_out).sum().backward()
        got[backward] = m.grad
    assert rel(got["exact"], got["autograd"]) < 1e-10


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_cuda_equals_autograd(action, interpolation):
    dom = ImageDomain((20, 14), (-8.0, -5.0), (8.0, 9.0))
    v, template, grad_out = (x.cuda() for x in random_problem(dom, 5, batch=(2,), seed=15))
    kw = dict(action=action, interpolation=interpolation)
    _, gv, gi = grads(LDDMMDeformation(dom, 5, backward="exact", **kw), v, template, grad_out)
    _, gv_ref, gi_ref = grads(LDDMMDeformation(dom, 5, backward="autograd", **kw), v, template, grad_out)
    assert gv.is_cuda and rel(gv, gv_ref) < 1e-10 and rel(gi, gi_ref) < 1e-10


@pytest.mark.parametrize("action", ACTIONS)
def test_row_bands_with_threads(action):
    """With several CPU threads a single image's adjoint runs in row bands: the same gradient up to rounding."""
    dom = ImageDomain.paper(128)  # large enough for bands (functional._bands)
    v, template, grad_out = random_problem(dom, 3, seed=16)
    W = LDDMMDeformation(dom, 3, action=action, backward="exact")
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        _, gv1, gi1 = grads(W, v, template, grad_out)
        torch.set_num_threads(2)
        assert Fd._bands(grad_out[None, None], 128, 128) == 2
        _, gv2, gi2 = grads(W, v, template, grad_out)
    finally:
        torch.set_num_threads(threads)
    assert rel(gv2, gv1) < 1e-13 and rel(gi2, gi1) < 1e-13
