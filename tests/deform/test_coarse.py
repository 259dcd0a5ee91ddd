"""CoarseVelocityDeformation: the velocity and the flow on a coarser grid, phi_{1,0} interpolated to the image's."""
import pytest
import torch

from indreg import ImageDomain, phantoms
from indreg.deform import CoarseVelocityDeformation, LDDMMDeformation, coarse_domain
from indreg.deform import functional as Fd
from indreg.deform.functional import identity_grid, sample, upsample, upsample_adjoint

ACTIONS = ("geometric", "mass_preserving")


def _problem(ndim, n=8, factor=2, num_steps=3, scale=1.5, seed=0):
    """A random velocity (max |nu| = ``scale``) on the coarse grid and a random template on the fine one
    (float64)."""
    gen = torch.Generator().manual_seed(seed)
    fine = ImageDomain.paper(n, ndim)
    coarse = coarse_domain(fine, factor)
    v = torch.randn(num_steps + 1, ndim, *coarse.shape, generator=gen, dtype=torch.float64)
    v *= scale / float(v.abs().max())
    template = torch.randn(*fine.shape, generator=gen, dtype=torch.float64)
    return fine, coarse, v, template


@pytest.mark.parametrize("coarse_shape,fine_shape", [((8, 8), (16, 16)), ((8, 6, 4), (32, 24, 16)),
                                                     ((5, 7), (13, 20))])
def test_upsample_interpolates_between_the_coarse_cell_centres(coarse_shape, fine_shape):
    """P is grid_sample at the fine cell centres with border padding (any ratio), and P^T its transpose."""
    gen = torch.Generator().manual_seed(1)
    f = torch.randn(2, 3, *coarse_shape, generator=gen, dtype=torch.float64)
    fine = ImageDomain(fine_shape)
    grid = identity_grid(fine, torch.float64).expand(2, *fine_shape, len(fine_shape))
    torch.testing.assert_close(upsample(f, fine_shape), sample(f, grid, "border"), rtol=0, atol=1e-13)
    g = torch.randn(2, 3, *fine_shape, generator=gen, dtype=torch.float64)
    lhs, rhs = (upsample(f, fine_shape) * g).sum(), (f * upsample_adjoint(g, coarse_shape)).sum()
    assert float(lhs) == pytest.approx(float(rhs), rel=1e-12)
    assert upsample(f, coarse_shape) is f and upsample_adjoint(f, coarse_shape) is f


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("action", ACTIONS)
def test_same_grid_is_the_compose_deformation_bit_for_bit(ndim, action):
    dom = ImageDomain.paper(8, ndim)
    _, _, v, template = _problem(ndim, factor=1)
    grad_out = torch.randn_like(template)
    out, grads = [], []
    for W in (CoarseVelocityDeformation(dom, dom, 3, action),
              LDDMMDeformation(dom, 3, action, "exact", "compose")):
        x = v.clone().requires_grad_(True)
        t = template.clone().requires_grad_(True)
        y = W(x, t)
        y.backward(grad_out)
        out.append(y.detach())
        grads.append((x.grad, t.grad))
    assert torch.equal(out[0], out[1])
    assert torch.equal(grads[0][0], grads[1][0]) and torch.equal(grads[0][1], grads[1][1])


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("action", ACTIONS)
def test_exact_backward_is_autograd_and_passes_gradcheck(ndim, action):
    fine, coarse, v, template = _problem(ndim, n=8 if ndim == 3 else 12)
    exact = CoarseVelocityDeformation(fine, coarse, 3, action, "exact")
    plain = CoarseVelocityDeformation(fine, coarse, 3, action, "autograd")
    grad_out = torch.randn_like(template)
    results = []
    for W in (exact, plain):
        x, t = v.clone().requires_grad_(True), template.clone().requires_grad_(True)
        W(x, t).backward(grad_out)
        results.append((x.grad, t.grad))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12 * float(b.abs().max()))
    assert bool(results[0][0][0].eq(0).all())  # the discrete map does not use nu(t_0)
    with torch.no_grad():
        assert torch.equal(exact(v, template), plain(v, template))
    fine, coarse, v, template = _problem(ndim, n=4 if ndim == 3 else 8)  # gradcheck: one evaluation per entry
    exact = CoarseVelocityDeformation(fine, coarse, 3, action, "exact")
    assert torch.autograd.gradcheck(exact, (v.requires_grad_(True), template.requires_grad_(True)))


@pytest.mark.parametrize("ndim", [2, 3])
def test_central_differences_of_the_velocity_gradient(ndim):
    """<dL/dnu, dv> against (L(nu + eps dv) - L(nu - eps dv)) / (2 eps) for L = <W(nu, I), G>."""
    fine, coarse, v, template = _problem(ndim, n=8 if ndim == 3 else 16, seed=3)
    W = CoarseVelocityDeformation(fine, coarse, 3)
    template = phantoms.get("shepp_logan_3d" if ndim == 3 else "shepp_logan", fine).double()
    grad_out = torch.randn_like(template)
    x = v.clone().requires_grad_(True)
    W(x, template).backward(grad_out)
    dv = torch.randn_like(v)
    dv[0] = 0
    eps = 1e-6
    with torch.no_grad():
        fd = ((W(v + eps * dv, template) - W(v - eps * dv, template)) * grad_out).sum() / (2 * eps)
    assert float((x.grad * dv).sum()) == pytest.approx(float(fd), rel=1e-6)


@pytest.mark.parametrize("ndim", [2, 3])
def test_a_constant_velocity_translates(ndim):
    """nu = c on the coarse grid: phi_{1,0} = Id - c on the fine grid (border padding keeps the constant), so W
    is the template translated by c."""
    fine, coarse, _, _ = _problem(ndim)
    c = torch.tensor([0.7, -0.4, 0.3][:ndim], dtype=torch.float64)
    v = c.view(1, ndim, *(1,) * ndim).expand(4, ndim, *coarse.shape).clone()
    W = CoarseVelocityDeformation(fine, coarse, 3)
    template = phantoms.get("shepp_logan_3d" if ndim == 3 else "shepp_logan", fine).double()
    points = fine.points(torch.float64)
    expected = points - c.view(ndim, *(1,) * ndim)
    torch.testing.assert_close(W.deformation(v), expected, rtol=0, atol=1e-12)
    from indreg.deform.functional import warp
    torch.testing.assert_close(W(v, template), warp(template, expected, fine), rtol=0, atol=1e-10)
    torch.testing.assert_close(W.jacobian_determinant(v), torch.ones(fine.shape, dtype=torch.float64), atol=1e-12,
                               rtol=0)


@pytest.mark.parametrize("ndim", [2, 3])
def test_zero_velocity_is_the_identity_and_shapes(ndim):
    fine, coarse, _, template = _problem(ndim)
    W = CoarseVelocityDeformation(fine, coarse, 3, "mass_preserving")
    v = W.zero_velocity()
    assert v.shape == (4, ndim, *coarse.shape) == W.velocity_shape()
    assert torch.equal(W(v, template), template) and torch.equal(W(v.requires_grad_(True), template), template)
    assert torch.equal(W.deformation(v.detach()), fine.points(torch.float64))
    assert float(W.min_jacobian(v.detach())) == pytest.approx(1.0)
    assert W.trajectory(v.detach(), template).shape == (4, *fine.shape)
    assert W.jacobian(v.detach()).shape == fine.shape


def test_trajectory_ends_at_the_deformed_template():
    fine, coarse, v, template = _problem(2)
    W = CoarseVelocityDeformation(fine, coarse, 3)
    traj = W.trajectory(v, template)
    assert torch.equal(traj[0], template) and torch.equal(traj[-1], W(v, template))


def test_replace_keeps_the_velocity_grid():
    fine, coarse, _, _ = _problem(2)
    W = CoarseVelocityDeformation(fine, coarse, 3).replace(backward="autograd", num_steps=5)
    assert isinstance(W, CoarseVelocityDeformation) and W.velocity_domain == coarse and W.num_steps == 5
    assert W.backward == "autograd" and "velocity_shape=(4, 4)" in repr(W)


@pytest.mark.parametrize("kwargs,match", [
    ({"backward": "paper"}, r"backward must be one of \('exact', 'autograd'\)"),
    ({"interpolation": "reinterpolate"}, r"interpolation must be 'compose'"),
    ({"velocity_domain": ImageDomain((4, 4), (-8.0, -8.0), (8.0, 8.0))}, r"velocity_domain must be a grid of the box"),
    ({"velocity_domain": ImageDomain.paper(16)}, r"velocity_domain must be a grid of the box"),
    ({"velocity_domain": (4, 4)}, r"velocity_domain must be an ImageDomain"),
])
def test_bad_arguments(kwargs, match):
    fine = ImageDomain.paper(8)
    args = {"velocity_domain": coarse_domain(fine, 2), **kwargs}
    with pytest.raises((ValueError, TypeError), match=match):
        CoarseVelocityDeformation(fine, **args)


def test_a_fine_velocity_is_refused_naming_it():
    fine, coarse, _, template = _problem(2)
    W = CoarseVelocityDeformation(fine, coarse, 3)
    with pytest.raises(ValueError, match=r"velocity must have shape \(\.\.\., 4, 2, 4, 4\)"):
        W(torch.zeros(4, 2, 8, 8, dtype=torch.float64), template)


@pytest.mark.parametrize("factor,match", [(3, "must divide every axis"), (0, "integer >= 1"), (2.0, "integer >= 1")])
def test_coarse_domain_checks_the_factor(factor, match):
    with pytest.raises(ValueError, match=match):
        coarse_domain(ImageDomain.paper(8), factor)


def _swirl(domain, amplitude, num_steps):
    """The cellular swirl ``amplitude (sin(x/4) cos(y/4), -cos(x/4) sin(y/4))``, constant in time."""
    x, y = domain.points(torch.float64)
    v = torch.stack((torch.sin(x / 4) * torch.cos(y / 4), -torch.cos(x / 4) * torch.sin(y / 4)))
    return (amplitude * v).expand(num_steps + 1, *v.shape).clone()


@pytest.mark.parametrize("amplitude", [2.0, 5.0, 8.0])
def test_min_jacobian_on_the_velocity_grid_is_the_fine_maps(amplitude):
    """The folding check runs on the coarse map: on a smooth swirl (coarse cells of 1 unit, the swirl's scale 4)
    its determinant is the interpolated map's on the image's grid inside (minima within 0.035, 4 cells from the
    border; 0.93 / 0.43 / 0.30-0.33 at amplitudes 2 / 5 / 8);
    at the border, where P continues constantly and the differences are one-sided, the fine map reads lower
    (docs/3d.md)."""
    fine = ImageDomain.paper(64)
    coarse = coarse_domain(fine, 2)
    W = CoarseVelocityDeformation(fine, coarse, 4)
    v = _swirl(coarse, amplitude, 4)
    det_fine = W.jacobian_determinant(v)
    det_coarse = Fd.displacement_determinant(Fd.displacement_10(v, coarse, W._check_velocity(v)), coarse)
    assert float(W.min_jacobian(v)) == pytest.approx(float(det_coarse.amin()), rel=1e-12) and det_coarse.amin() > 0
    inner_fine, inner_coarse = float(det_fine[4:-4, 4:-4].amin()), float(det_coarse[2:-2, 2:-2].amin())
    assert inner_fine < 0.99 and inner_coarse == pytest.approx(inner_fine, abs=0.035)


def test_min_jacobian_on_the_velocity_grid_sees_folding():
    """The swirl of amplitude 20 folds the map (LDDMMDeformation.min_jacobian's example): the coarse check says so."""
    fine = ImageDomain.paper(64)
    coarse = coarse_domain(fine, 2)
    v = _swirl(coarse, 20.0, 4)
    W = CoarseVelocityDeformation(fine, coarse, 4)
    assert float(W.min_jacobian(v)) <= 0 and float(W.jacobian_determinant(v).amin()) <= 0
