"""LDDMMDeformation: identity, analytic flows, the paper's gradient vs autograd, scales, batching, errors."""
import math

import pytest
import torch

from indreg import ImageDomain
from indreg.deform import GaussianKernel, LDDMMDeformation
from indreg.deform import functional as Fd

ACTIONS = ("geometric", "mass_preserving")
INTERP = ("reinterpolate", "compose")


def bump(domain, centre=(2.0, -1.0), sigma=3.0, dtype=torch.float64):
    x, y = domain.points(dtype)
    return torch.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma ** 2))


def smooth_problem(n, num_steps, amp=1.0, dtype=torch.float64, seed=1):
    """A smooth velocity (kernel-smoothed, linear in time, max |v| = amp), template and incoming gradient."""
    dom = ImageDomain.paper(n)
    g = torch.Generator().manual_seed(seed)
    # the same continuous field at every n: kernel-smoothed noise on a 16^2 grid, interpolated
    coarse = ImageDomain.paper(16)
    m0c, m1c = (torch.randn(2, 16, 16, dtype=torch.float64, generator=g) for _ in range(2))
    t = torch.linspace(0, 1, num_steps + 1, dtype=torch.float64).view(-1, 1, 1, 1)
    vc = GaussianKernel(coarse, 4.0)(m0c * (1 - t) + m1c * t)
    pts = dom.points().expand(num_steps + 1, 2, n, n)
    v = torch.stack([Fd.warp(vc[:, k], pts, coarse, "border") for k in range(2)], dim=1)
    v = (amp * v / v.abs().max()).to(dtype)
    template = (bump(dom, (2.0, -1.0), 4.0) + 0.5 * bump(dom, (-4.0, 3.0), 3.0)).to(dtype)
    x, y = dom.points(dtype)
    grad_out = bump(dom, (-1.0, 0.0), 5.0, dtype) * torch.cos(x / 4)
    return dom, v, template, grad_out


def grads(W, v, template, grad_out):
    v = v.clone().requires_grad_()
    template = template.clone().requires_grad_()
    (W(v, template) * grad_out).sum().backward()
    return v.grad, template.grad


# ---------------------------------------------------------------------------------------------- forward
@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_zero_velocity_is_identity(action, interpolation):
    dom = ImageDomain((12, 10))
    template = torch.rand(12, 10, dtype=torch.float64)
    W = LDDMMDeformation(dom, 5, action=action, interpolation=interpolation)
    v = W.zero_velocity()
    assert torch.equal(W(v, template), template)
    traj = W.trajectory(v, template)
    assert traj.shape == (6, 12, 10) and torch.equal(traj, template.expand(6, 12, 10))
    assert torch.equal(W.deformation(v), dom.points())
    assert float(W.min_jacobian(v)) == pytest.approx(1.0, rel=0, abs=1e-12)


def analytic_error(n, num_steps, flow, interpolation):
    dom = ImageDomain.paper(n)
    x, y = dom.points()
    if flow == "translation":
        c = (3.3, -2.1)
        v = torch.stack([torch.full_like(x, c[0]), torch.full_like(y, c[1])])
        exact = bump(dom, (1.0 + c[0], -1.0 + c[1]), 2.5)  # I(x - c) for I centred at (1, -1)
    else:  # rigid rotation v(x) = omega * J x, phi_{1,0} = rotation by -omega
        omega = 0.6
        v = omega * torch.stack([-y, x])
        cx, cy = 5.0, 1.0
        exact = bump(dom, (math.cos(omega) * cx - math.sin(omega) * cy,
                           math.sin(omega) * cx + math.cos(omega) * cy), 2.5)
        c = None
    template = bump(dom, (1.0, -1.0) if flow == "translation" else (5.0, 1.0), 2.5)
    W = LDDMMDeformation(dom, num_steps, interpolation=interpolation)
    out = W(v.expand(num_steps + 1, 2, n, n), template)
    return float((out - exact).abs().max())


@pytest.mark.parametrize("flow", ("translation", "rotation"))
@pytest.mark.parametrize("interpolation", INTERP)
def test_analytic_flows_converge(flow, interpolation):
    errors = [analytic_error(n, steps, flow, interpolation) for n, steps in ((32, 5), (64, 10), (128, 20))]
    print(f"\n{flow} {interpolation}: max error {errors}")
    assert errors[-1] < 0.06
    assert errors[1] < 0.7 * errors[0] and errors[2] < 0.7 * errors[1]


def test_translation_compose_is_exact_on_the_grid():
    # a translation by whole pixels composes to exact pixel shifts: one interpolation at nodes, exact
    dom = ImageDomain.paper(16)
    template = torch.rand(16, 16, dtype=torch.float64)
    v = torch.zeros(5, 2, 16, 16, dtype=torch.float64)
    v[:, 0] = 3 * dom.cell_sides[0]  # 3 pixels along x in total
    out = LDDMMDeformation(dom, 4, interpolation="compose")(v, template)
    torch.testing.assert_close(out[3:], template[:-3])
    assert torch.equal(out[:3], torch.zeros(3, 16, dtype=torch.float64))


@pytest.mark.parametrize("interpolation", INTERP)
def test_mass_preserving_conserves_mass(interpolation):
    dom, v, _, _ = smooth_problem(48, 10, amp=3.0)
    template = bump(dom, (0.0, 1.0), 3.0)
    W = LDDMMDeformation(dom, 10, action="mass_preserving", interpolation=interpolation)
    out = W(v, template)
    mass0, mass1 = float(template.sum()), float(out.sum())
    geo = LDDMMDeformation(dom, 10)(v, template)
    print(f"\nmass change {interpolation}: mp {mass1 / mass0 - 1:.2e}, geometric {float(geo.sum()) / mass0 - 1:.2e}")
    assert abs(mass1 / mass0 - 1) < 0.01
    assert abs(float(geo.sum()) / mass0 - 1) > 0.01  # the deformation is not volume-preserving


def test_deformation_and_min_jacobian():
    dom = ImageDomain.paper(32)
    x, y = dom.points()
    v = torch.stack([torch.full_like(x, 2.0), torch.zeros_like(y)]).expand(9, 2, 32, 32)
    W = LDDMMDeformation(dom, 8)
    torch.testing.assert_close(W.deformation(v), dom.points() - torch.tensor([2.0, 0.0]).view(2, 1, 1))
    # a contraction field v = -a x has div = -2a, |D phi_{1,0}| = exp(2a) > 1
    assert float(W.min_jacobian(-0.1 * torch.stack([x, y]).expand(9, 2, 32, 32))) > 1.1
    # one step Id - v/N = (3/8) Id: the first-order factor 1 - div(v)/N = 1 - 10/8 < 0, the map does not fold
    shrink = torch.zeros(9, 2, 32, 32, dtype=torch.float64)
    shrink[-1] = 5.0 * torch.stack([x, y])
    assert float(W.jacobian(shrink).amin()) < 0 and float(W.min_jacobian(shrink)) == pytest.approx(9 / 64, abs=1e-12)
    folding = torch.zeros(9, 2, 32, 32, dtype=torch.float64)
    folding[-1, 0] = 12.0 * x  # one step x -> -x / 2: an orientation flip
    assert float(W.min_jacobian(folding)) == pytest.approx(-0.5, abs=1e-12)


def swirl(domain, amplitude, num_steps, dtype=torch.float64):
    """The cellular swirl ``amplitude (sin(x/4) cos(y/4), -cos(x/4) sin(y/4))``, constant in time."""
    x, y = domain.points(dtype)
    v = amplitude * torch.stack([torch.sin(x / 4) * torch.cos(y / 4), -torch.cos(x / 4) * torch.sin(y / 4)])
    return v.expand(num_steps + 1, 2, *domain.shape)


def independent_deformation(v, domain):
    """``phi_{1,0}`` by eq:ODEflow1b written with ``warp`` on physical points (no grid-unit steps)."""
    points, n = domain.points(v.dtype), v.shape[-4] - 1
    u = torch.zeros_like(points)
    for i in range(1, n + 1):
        step = points - v[i] / n
        u = torch.stack([Fd.warp(u[k], step, domain, "border") for k in range(2)]) - v[i] / n
    return points + u


def test_jacobian_determinant_of_affine_velocity_is_exact():
    # nu(x) = B x with Id - B/N mapping the cell centres' hull into itself (|c| <= b): every step is affine
    # and reproduced exactly by bilinear interpolation, phi_{1,0} = (Id - B/N)^N, det = det(Id - B/N)^N
    dom, n = ImageDomain.paper(32), 8
    x, y = dom.points()
    b, c, b2 = 0.8, -0.5, 0.4
    v = torch.stack([b * x + c * y, b2 * y]).expand(n + 1, 2, 32, 32)
    for interpolation in INTERP:
        W = LDDMMDeformation(dom, n, interpolation=interpolation)
        exact = ((1 - b / n) * (1 - b2 / n)) ** n
        torch.testing.assert_close(W.jacobian_determinant(v), torch.full_like(x, exact), rtol=0, atol=1e-12)
        # the first-order product says (1 - (b + b2)/N)^N instead
        torch.testing.assert_close(W.jacobian(v), torch.full_like(x, (1 - (b + b2) / n) ** n), rtol=0, atol=1e-12)


def test_jacobian_determinant_of_rotation():
    # nu = w (-y, x): each step is the linear map Id - w J / N with det 1 + (w/N)^2, so the discrete map's
    # determinant is (1 + (w/N)^2)^N -> 1 (a rotation) where no step reaches the border's padding
    dom = ImageDomain.paper(32)
    x, y = dom.points()
    inner = (x ** 2 + y ** 2) < 8 ** 2
    for n in (8, 20):
        v = 0.5 * torch.stack([-y, x]).expand(n + 1, 2, 32, 32)
        det = LDDMMDeformation(dom, n).jacobian_determinant(v)
        torch.testing.assert_close(det[inner], torch.full_like(det[inner], (1 + (0.5 / n) ** 2) ** n),
                                   rtol=0, atol=1e-6)
        assert float((det - 1).abs().max()) < 0.07


@pytest.mark.parametrize("interpolation", INTERP)
def test_swirl_folds_and_min_jacobian_says_so(interpolation):
    dom = ImageDomain.paper(64)
    for amplitude, n, expected in ((20.0, 4, -0.654), (80.0, 20, -74.16)):
        v = swirl(dom, amplitude, n)
        W = LDDMMDeformation(dom, n, interpolation=interpolation)
        det = W.jacobian_determinant(v)
        fraction = float((det <= 0).double().mean())
        print(f"\nswirl {amplitude:g} N={n}: first-order product min {float(W.jacobian(v).amin()):.4f}, "
              f"map det min {float(det.amin()):.4f}, {100 * fraction:.1f}% of pixels <= 0")
        assert float(W.min_jacobian(v)) == pytest.approx(expected, abs=0.01) and fraction > 0.2
        assert float(W.jacobian(v).amin()) > 0.9  # the first-order product does not see the folding


@pytest.mark.parametrize("interpolation", INTERP)
def test_jacobian_determinant_is_that_of_the_applied_map(interpolation):
    dom = ImageDomain.paper(32)
    v = swirl(dom, 6.0, 6)
    W = LDDMMDeformation(dom, 6, interpolation=interpolation)
    phi = independent_deformation(v, dom)
    torch.testing.assert_close(W.deformation(v), phi, rtol=1e-12, atol=1e-12)
    (dx1, dy1), (dx2, dy2) = (torch.gradient(phi[k], spacing=dom.cell_sides, edge_order=1) for k in range(2))
    torch.testing.assert_close(W.jacobian_determinant(v), dx1 * dy2 - dy1 * dx2, rtol=1e-10, atol=1e-10)
    template = bump(dom, (1.0, -2.0), 4.0)
    applied = Fd.warp(template, phi, dom)  # I o phi_{1,0}: exact for "compose", up to the steps' blur otherwise
    error = float(dom.norm(W(v, template) - applied) / dom.norm(applied))
    # reinterpolation: 4.6% (the blur of 6 interpolations) where the template itself is 76% away
    assert error < (1e-12 if interpolation == "compose" else 0.06)


def test_smooth_field_determinant_is_close_to_first_order_product():
    for n, steps in ((32, 8), (64, 16)):
        dom, v, _, _ = smooth_problem(n, steps)
        W = LDDMMDeformation(dom, steps)
        det, product = W.jacobian_determinant(v), W.jacobian(v)
        assert float(det.amin()) > 0.8
        assert float(((det - product) / product).abs().amax()) < 0.005


def test_jacobian_determinant_batch_dtypes_and_no_graph():
    dom = ImageDomain.paper(16)
    v = torch.stack([swirl(dom, a, 4) for a in (0.0, 3.0, 12.0)]).view(3, 1, 5, 2, 16, 16)
    W = LDDMMDeformation(dom, 4)
    det = W.jacobian_determinant(v)
    assert det.shape == (3, 1, 16, 16) and W.min_jacobian(v).shape == (3, 1)
    for b in range(3):
        torch.testing.assert_close(det[b, 0], W.jacobian_determinant(v[b, 0]))
    assert torch.equal(det[0, 0], torch.ones(16, 16, dtype=torch.float64))
    det32 = W.jacobian_determinant(v.float())
    assert det32.dtype == torch.float32
    torch.testing.assert_close(det32.double(), det, rtol=0, atol=1e-5)
    assert not W.jacobian_determinant(v.clone().requires_grad_()).requires_grad


# ---------------------------------------------------------------------------------------------- gradients
def compare_paper_autograd(n, num_steps, action="geometric", scheme="central", amp=1.0):
    dom, v, template, grad_out = smooth_problem(n, num_steps, amp)
    out = {}
    for backward in ("paper", "autograd"):
        W = LDDMMDeformation(dom, num_steps, action=action, backward=backward, scheme=scheme)
        out[backward] = grads(W, v, template, grad_out)
    a, b = out["paper"][0][1:], out["autograd"][0][1:]  # the discrete map does not depend on nu(t_0)
    assert float(out["autograd"][0][0].abs().max()) == 0.0
    cos = float((a * b).sum() / (a.norm() * b.norm()))
    rel = float((a - b).norm() / b.norm())
    ta, tb = out["paper"][1], out["autograd"][1]
    return cos, rel, float((ta - tb).norm() / tb.norm())


@pytest.mark.parametrize("action", ACTIONS)
def test_paper_vs_autograd_rates(action):
    results = [compare_paper_autograd(n, steps, action) for n, steps in ((16, 4), (32, 8), (64, 16))]
    print(f"\n{action}: (cos, rel. difference velocity grad, rel. difference template grad) {results}")
    assert results[2][0] >= 0.99 and results[1][0] >= 0.98
    rels, template_rels = [r[1] for r in results], [r[2] for r in results]
    assert rels[1] < 0.75 * rels[0] and rels[2] < 0.75 * rels[1]
    assert template_rels[1] < 0.75 * template_rels[0] and template_rels[2] < 0.75 * template_rels[1]


def test_paper_vs_autograd_time_step():
    """At a fixed grid the template-gradient difference is first order in 1/N (the transports use
    nu(t_0..t_{N-1}) where the discrete map uses nu(t_1..t_N), Remark re:inverse_linear_deformation)."""
    rels = [compare_paper_autograd(32, steps)[2] for steps in (4, 8, 16)]
    print(f"\ntemplate gradient rel. difference at 32^2, N=4, 8, 16: {rels}")
    assert rels[2] < rels[1] < 0.75 * rels[0]


def literal_lines_8_9(n, num_steps):
    """The geometric paper gradient with Algorithm 1's lines 8 and 9 carried separately (|D phi_{t_i,1}| with
    border padding, G o phi_{t_i,1} with zero padding), and the package's fused transport of their product."""
    dom, v, template, grad_out = smooth_problem(n, num_steps, amp=3.0)
    traj = Fd.template_trajectory(template, v, dom)
    x, N = dom.points(), num_steps
    jac, g_t = torch.ones_like(grad_out), grad_out
    literal = [None] * (N + 1)
    for i in range(N, -1, -1):
        if i < N:
            jac = (1 + Fd.divergence(v[i], dom) / N) * Fd.warp(jac, x + v[i] / N, dom, "border")
            g_t = Fd.warp(g_t, x + v[i] / N, dom)
        literal[i] = -jac * g_t * Fd.gradient(traj[i], dom) / N
    fused, fused_template = Fd.paper_gradient(grad_out, v, Fd.gradient_record(template, v, dom), dom)
    return torch.stack(literal), jac * g_t, fused, fused_template


def test_fused_transport_matches_lines_8_and_9():
    """rho_i = |D phi_{t_i,1}| G o phi_{t_i,1} carried as one field differs from the product of the separately
    carried factors by interpolation error only: small, first order under refinement."""
    rels = []
    for n, steps in ((16, 4), (32, 8), (64, 16)):
        literal, literal_template, fused, fused_template = literal_lines_8_9(n, steps)
        rels.append((float((fused - literal).norm() / literal.norm()),
                     float((fused_template - literal_template).norm() / literal_template.norm())))
    print(f"\nfused vs literal lines 8-9, rel. difference (velocity, template) at 16^2/N=4, 32^2/N=8, 64^2/N=16: {rels}")
    assert rels[0][0] < 0.01 and rels[0][1] < 0.02
    for k in range(2):
        assert rels[1][k] < 0.75 * rels[0][k] and rels[2][k] < 0.75 * rels[1][k]


def assembled_paper_gradient(dom, v, template, grad_out, action, scheme):
    """The paper's gradient assembled independently from warp / gradient / divergence (reinterpolation)."""
    N, x = v.shape[0] - 1, dom.points(v.dtype)
    images = Fd.template_trajectory(template, v, dom)
    frames = images * Fd.jacobian_trajectory(v, dom, scheme) if action == "mass_preserving" else images
    carried = [None] * (N + 1)  # geometric: rho_i = |D phi_{t_i,1}| G o phi_{t_i,1}; mass-preserving: G o phi_{t_i,1}
    carried[N] = grad_out
    for i in range(N - 1, -1, -1):
        moved = Fd.warp(carried[i + 1], x + v[i] / N, dom)
        carried[i] = (1 + Fd.divergence(v[i], dom, scheme) / N) * moved if action == "geometric" else moved
    if action == "geometric":
        grad_v = [-carried[i] * Fd.gradient(images[i], dom, scheme) / N for i in range(N + 1)]
    else:
        grad_v = [frames[i] * Fd.gradient(carried[i], dom, scheme) / N for i in range(N + 1)]
    return torch.stack(grad_v), carried[0]


@pytest.mark.parametrize("scheme", ("central", "forward"))
@pytest.mark.parametrize("action", ACTIONS)
def test_paper_gradient_equals_its_formula(action, scheme):
    """LDDMMDeformation's backward is the paper's formula to rounding, on a domain with unequal cell sides
    (hx = 4/3, hy = 1) and a batch of two velocities sharing one template."""
    dom = ImageDomain((24, 16), (-16.0, -8.0), (16.0, 8.0))
    g = torch.Generator().manual_seed(3)
    v = GaussianKernel(dom, 3.0)(torch.randn(2, 5, 2, 24, 16, dtype=torch.float64, generator=g))
    v = 2.0 * v / v.abs().max()
    template, grad_out = bump(dom, (2.0, -1.0), 4.0), bump(dom, (-1.0, 1.0), 5.0) * torch.cos(dom.points()[0] / 4)
    W = LDDMMDeformation(dom, 4, action=action, scheme=scheme)
    gv, gi = grads(W, v, template, grad_out.expand(2, 24, 16))
    for b in range(2):
        expected_v, expected_i = assembled_paper_gradient(dom, v[b], template, grad_out, action, scheme)
        torch.testing.assert_close(gv[b], expected_v, rtol=0, atol=1e-12 * float(expected_v.abs().max()))
        if b == 0:
            total_i = expected_i
        else:
            total_i = total_i + expected_i
    torch.testing.assert_close(gi, total_i, rtol=0, atol=1e-12 * float(total_i.abs().max()))


def test_gradient_record_and_its_consumption():
    dom, v, template, grad_out = smooth_problem(16, 4, amp=2.0)
    record = Fd.gradient_record(template, v, dom)
    torch.testing.assert_close(record[:, 0], Fd.template_trajectory(template, v, dom), rtol=0, atol=0)
    torch.testing.assert_close(record[:, 1], 1 + Fd.divergence(v, dom) / 4, rtol=0, atol=1e-14)
    mp = Fd.gradient_record(template, v, dom, "mass_preserving")
    torch.testing.assert_close(mp[:, 0], Fd.deformed_trajectory(template, v, dom, "mass_preserving"))
    kept = record.clone()
    _, grad_i = Fd.paper_gradient(grad_out, v, record, dom, need_velocity=False)
    assert torch.equal(record, kept)  # only the template gradient: the record is left as it is
    grad_v, grad_i2 = Fd.paper_gradient(grad_out, v, record, dom)
    assert grad_v is record and torch.equal(grad_i, grad_i2)  # the record became the velocity gradient
    with pytest.raises(ValueError, match="record must be shaped like the velocity"):
        Fd.paper_gradient(grad_out, v, record[:, 0], dom)


@pytest.mark.parametrize("action", ACTIONS)
def test_backward_twice_through_a_retained_graph(action):
    """The first backward consumes the forward's record; a second one recomputes it: same gradients."""
    dom, v, template, grad_out = smooth_problem(16, 4, amp=2.0)
    v, template = v.requires_grad_(), template.clone().requires_grad_()
    out = LDDMMDeformation(dom, 4, action=action)(v, template)
    first = torch.autograd.grad((out * grad_out).sum(), (v, template), retain_graph=True)
    second = torch.autograd.grad((out * grad_out).sum(), (v, template))
    for a, b in zip(first, second):
        assert torch.equal(a, b)


def test_paper_mode_without_autograd():
    """Without a graph to record the paper mode runs the plain forward: same values, a fresh tensor."""
    dom, v, template, _ = smooth_problem(16, 4, amp=2.0)
    W = LDDMMDeformation(dom, 4)
    with torch.no_grad():
        plain = W(v, template)
    recorded = W(v.clone().requires_grad_(), template)
    assert torch.equal(plain, recorded.detach()) and plain.is_contiguous()
    assert plain.untyped_storage().nbytes() == plain.numel() * plain.element_size()  # not a view of a trajectory


@pytest.mark.parametrize("action", ACTIONS)
def test_paper_vs_autograd_schemes(action):
    """Both finite-difference schemes converge to the exact discrete derivative; which one is closer
    depends on the sign of nu (autograd's bilinear slope is the upwind one-sided difference)."""
    rel = {scheme: [compare_paper_autograd(n, steps, action, scheme)[1] for n, steps in ((16, 4), (32, 8))]
           for scheme in ("central", "forward")}
    print(f"\n{action}: rel. difference paper vs autograd at 16^2/N=4, 32^2/N=8: {rel}")
    for scheme in rel:
        assert rel[scheme][1] < 0.75 * rel[scheme][0]


@pytest.mark.parametrize("backward", ("paper", "exact", "autograd"))
@pytest.mark.parametrize("action", ACTIONS)
def test_directional_derivative_matches_finite_differences(backward, action):
    dom, v, template, grad_out = smooth_problem(32, 8, amp=1.0)
    _, direction, _, _ = smooth_problem(32, 8, amp=1.0, seed=7)
    direction[0] = 0  # the discrete map does not depend on nu(t_0); the paper's gradient there is not 0
    W = LDDMMDeformation(dom, 8, action=action, backward=backward)
    gv, gi = grads(W, v, template, grad_out)
    eps = 1e-7
    loss = lambda vv, ii: float((W(vv, ii) * grad_out).sum())  # noqa: E731
    fd_v = (loss(v + eps * direction, template) - loss(v - eps * direction, template)) / (2 * eps)
    dtemp = bump(dom, (3.0, 2.0), 4.0)
    fd_i = (loss(v, template + eps * dtemp) - loss(v, template - eps * dtemp)) / (2 * eps)
    ad_v, ad_i = float((gv * direction).sum()), float((gi * dtemp).sum())
    if backward != "paper":  # the exact derivative of the discrete map
        assert abs(ad_v - fd_v) <= 1e-5 * abs(fd_v), (ad_v, fd_v)
        assert abs(ad_i - fd_i) <= 1e-5 * abs(fd_i), (ad_i, fd_i)
    else:  # the paper's gradient: a consistent approximation, error relative to |gradient| |direction|
        assert abs(ad_v - fd_v) <= 0.03 * float(gv.norm() * direction.norm()), (ad_v, fd_v)
        assert abs(ad_i - fd_i) <= 0.03 * float(gi.norm() * dtemp.norm()), (ad_i, fd_i)
        assert abs(ad_i - fd_i) <= 0.1 * abs(fd_i), (ad_i, fd_i)


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_gradcheck_autograd_mode(action, interpolation):
    dom, v, template, _ = smooth_problem(8, 2, amp=1.3)
    W = LDDMMDeformation(dom, 2, action=action, backward="autograd", interpolation=interpolation)
    assert torch.autograd.gradcheck(W, (v.requires_grad_(), template.requires_grad_()))


def test_paper_mode_is_once_differentiable():
    dom, v, template, _ = smooth_problem(8, 2)
    v.requires_grad_()
    out = LDDMMDeformation(dom, 2)(v, template)
    (g,) = torch.autograd.grad((out ** 2).sum(), v, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable|double backward|twice"):
        g.sum().backward()


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize("interpolation", INTERP)
def test_gradient_scale_relation(action, interpolation):
    """(N / cell_volume) * dL/dnu_i is the L2 gradient at t_i: resolution and N independent."""
    l2 = []
    for n, steps in ((32, 8), (64, 16), (128, 32)):
        dom, v, template, _ = smooth_problem(n, steps, amp=1.0)
        target = bump(dom, (0.0, 0.0), 4.0)
        W = LDDMMDeformation(dom, steps, action=action, interpolation=interpolation)
        v.requires_grad_()
        loss = 0.5 * dom.norm(W(v, template) - target) ** 2  # L2 gradient w.r.t. W: W - target
        (gv,) = torch.autograd.grad(loss, v)
        g_l2 = gv * steps / dom.cell_volume
        # the L2 gradient at t = 1 from the formulas (|D phi_{1,1}| = 1, G o phi_{1,1} = G):
        traj = W.trajectory(v, template).detach()
        resid = (traj[-1] - target)
        if action == "geometric":
            expected = -resid * Fd.gradient(traj[-1], dom)
        else:
            expected = traj[-1] * Fd.gradient(resid, dom)
        torch.testing.assert_close(g_l2[-1], expected, rtol=1e-10, atol=1e-12)
        # sample the L2 gradient at t = 0.5 at physical points shared by both grids
        pts = ImageDomain.paper(8).points(dtype=v.dtype)
        l2.append(torch.stack([Fd.warp(g_l2[steps // 2, k], pts, dom) for k in range(2)]))
    rel = [float((l2[k] - l2[2]).norm() / l2[2].norm()) for k in (0, 1)]
    print(f"\nL2 gradient at t=0.5, 32^2/N=8 and 64^2/N=16 vs 128^2/N=32: rel. differences {rel}")
    assert rel[1] < 0.7 * rel[0] and rel[1] < 0.2


# ---------------------------------------------------------------------------------------------- batching
@pytest.mark.parametrize("backward", ("paper", "exact", "autograd"))
@pytest.mark.parametrize("action", ACTIONS)
def test_batch_equals_single_calls_and_shared_template(backward, action):
    dom, v0, template, grad_out = smooth_problem(16, 4)
    _, v1, _, _ = smooth_problem(16, 4, seed=3)
    v = torch.stack([v0, v1, -v0]).view(3, 1, 5, 2, 16, 16)
    W = LDDMMDeformation(dom, 4, action=action, backward=backward)
    templates = torch.stack([template, template.flip(0), template.T]).view(3, 1, 16, 16)
    gv, gi = grads(W, v, templates, grad_out)
    assert W(v, templates).shape == (3, 1, 16, 16) and gv.shape == v.shape and gi.shape == templates.shape
    for b in range(3):
        gvb, gib = grads(W, v[b, 0], templates[b, 0], grad_out)
        torch.testing.assert_close(W(v[b, 0], templates[b, 0]), W(v, templates)[b, 0])
        torch.testing.assert_close(gv[b, 0], gvb)
        torch.testing.assert_close(gi[b, 0], gib)
    # a single template shared across the batch: its gradient is the sum over the batch
    gv_s, gi_s = grads(W, v, template, grad_out)
    assert gi_s.shape == template.shape
    torch.testing.assert_close(gi_s, sum(grads(W, v[b, 0], template, grad_out)[1] for b in range(3)))
    assert W.trajectory(v, template).shape == (3, 1, 5, 16, 16)
    assert W.min_jacobian(v).shape == (3, 1) and W.deformation(v).shape == (3, 1, 2, 16, 16)


@pytest.mark.parametrize("backward", ("paper", "exact", "autograd"))
def test_float32(backward):
    dom, v, template, grad_out = smooth_problem(16, 4)
    W = LDDMMDeformation(dom, 4, action="mass_preserving", backward=backward)
    g32 = grads(W, v.float(), template.float(), grad_out.float())
    g64 = grads(W, v, template, grad_out)
    assert g32[0].dtype == torch.float32 and W(v.float(), template.float()).dtype == torch.float32
    torch.testing.assert_close(g32[0].double(), g64[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(g32[1].double(), g64[1], rtol=1e-4, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    dom, v, template, grad_out = smooth_problem(16, 4)
    W = LDDMMDeformation(dom, 4)
    gc = grads(W, v.cuda(), template.cuda(), grad_out.cuda())
    torch.testing.assert_close(gc[0].cpu(), grads(W, v, template, grad_out)[0])


def test_bad_input():
    dom = ImageDomain.paper(8)
    W = LDDMMDeformation(dom, 4)
    v, template = W.zero_velocity(), dom.zeros()
    with pytest.raises(ValueError, match="num_steps"):
        LDDMMDeformation(dom, 0)
    with pytest.raises(TypeError, match="num_steps"):
        LDDMMDeformation(dom, 2.5)
    for bad in (None, "a", math.nan, math.inf):
        with pytest.raises(TypeError, match=f"num_steps must be an integer >= 1, got {bad!r}"):
            LDDMMDeformation(dom, bad)
    with pytest.raises(ValueError, match="action"):
        LDDMMDeformation(dom, 4, action="affine")
    with pytest.raises(ValueError, match="backward"):
        LDDMMDeformation(dom, 4, backward="adjoint")
    with pytest.raises(ValueError, match="interpolation"):
        LDDMMDeformation(dom, 4, interpolation="cubic")
    with pytest.raises(ValueError, match="5 time points"):
        W(torch.zeros(4, 2, 8, 8, dtype=torch.float64), template)
    with pytest.raises(ValueError, match="velocity"):
        W(torch.zeros(5, 2, 8, 9, dtype=torch.float64), template)
    with pytest.raises(ValueError, match="template"):
        W(v, torch.zeros(8, 9, dtype=torch.float64))
    with pytest.raises(ValueError, match="do not broadcast"):
        W(torch.zeros(2, 5, 2, 8, 8, dtype=torch.float64), torch.zeros(3, 8, 8, dtype=torch.float64))
    with pytest.raises(ValueError, match="non-finite"):
        W(v.clone().fill_(float("nan")), template)
    with pytest.raises(ValueError, match="non-finite"):
        W(v, template.clone().fill_(float("inf")))
    with pytest.raises(TypeError, match="dtype"):
        W(v.float(), template)
    for dtype in (torch.float16, torch.bfloat16):  # the projector refuses them too
        with pytest.raises(TypeError, match=f"velocity must be float32 or float64, got {dtype}"):
            W(v.to(dtype), template.to(dtype))
        with pytest.raises(TypeError, match=f"template must be float32 or float64, got {dtype}"):
            W(v, template.to(dtype))
        with pytest.raises(TypeError, match=f"velocity must be float32 or float64, got {dtype}"):
            W.min_jacobian(v.to(dtype))


@pytest.mark.parametrize("backward", ("paper", "exact", "autograd"))
def test_template_only_requires_grad(backward):
    """Gradients w.r.t. the template alone (velocity fixed) equal those of the joint call."""
    dom, v, template, grad_out = smooth_problem(16, 4)
    W = LDDMMDeformation(dom, 4, backward=backward)
    t = template.clone().requires_grad_()
    (W(v, t) * grad_out).sum().backward()
    torch.testing.assert_close(t.grad, grads(W, v, template, grad_out)[1])


def test_empty_batch_is_refused():
    # issue #19: an empty batch ended in an amax() IndexError deep in functional.step_flags
    dom = ImageDomain.paper(8)
    W = LDDMMDeformation(dom, 4)
    v, template = W.zero_velocity(), dom.zeros()
    for call in (lambda x: W(x, template), lambda x: W.trajectory(x, template), W.jacobian, W.min_jacobian,
                 W.jacobian_determinant, W.deformation):
        with pytest.raises(ValueError, match=r"^velocity is empty \(shape \(0, 5, 2, 8, 8\)\): give at least one "
                                             r"item of shape \(5, 2, 8, 8\)"):
            call(v[None][:0])
    with pytest.raises(ValueError, match=r"^template is empty \(shape \(0, 8, 8\)\)"):
        W(v, template[None][:0])
    with pytest.raises(ValueError, match=r"^template is empty"):
        W(v.requires_grad_(True), template[None][:0])
