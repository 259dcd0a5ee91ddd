"""indreg.deform.functional: interpolation, finite differences, flow recursions."""
import pytest
import torch

from indreg import ImageDomain
from indreg.deform import functional as Fd


def test_warp_at_cell_centres_and_outside():
    dom = ImageDomain((12, 10))
    f = torch.rand(12, 10, dtype=torch.float64)
    torch.testing.assert_close(Fd.warp(f, dom.points(), dom), f, rtol=0, atol=1e-14)
    far = dom.points() + 100.0
    assert torch.equal(Fd.warp(f, far, dom), torch.zeros_like(f))
    torch.testing.assert_close(Fd.warp(f, far, dom, "border"), f[-1, -1].expand(12, 10))
    # linear functions are reproduced exactly between cell centres
    x, y = dom.points()
    lin = 2 * x - 3 * y
    pts = dom.points() + torch.tensor([0.3, -0.2], dtype=torch.float64).view(2, 1, 1)
    inner = (slice(1, -1), slice(1, -1))
    torch.testing.assert_close(Fd.warp(lin, pts, dom)[inner], (2 * pts[0] - 3 * pts[1])[inner])
    # batch dims broadcast
    assert Fd.warp(f.expand(3, 12, 10), dom.points(), dom).shape == (3, 12, 10)


def test_zero_steps_are_exact():
    for n, dtype in ((438, torch.float32), (37, torch.float64)):
        dom = ImageDomain((n, n))
        f = torch.rand(2, 1, n, n, dtype=dtype)
        assert torch.equal(
            Fd.template_trajectory(f[:, 0], torch.zeros(2, 3, 2, n, n, dtype=dtype), dom)[:, -1], f[:, 0])


@pytest.mark.parametrize("scheme,order", (("central", 2), ("forward", 1)))
def test_gradient_order(scheme, order):
    errors = []
    for n in (32, 64):
        dom = ImageDomain.paper(n)
        x, y = dom.points()
        f = torch.exp(-(x ** 2 + (y - 1) ** 2) / 18)
        exact = torch.stack([-x / 9 * f, -(y - 1) / 9 * f])
        errors.append(float((Fd.gradient(f, dom, scheme) - exact).abs().max()))
    rate = torch.log2(torch.tensor(errors[0] / errors[1]))
    assert abs(float(rate) - order) < 0.3, errors


def test_divergence_forward_is_minus_adjoint_of_gradient():
    dom = ImageDomain((9, 7), (0.0, 0.0), (3.0, 1.0))
    g = torch.Generator().manual_seed(0)
    f, v = torch.randn(9, 7, dtype=torch.float64, generator=g), torch.randn(2, 9, 7, dtype=torch.float64, generator=g)
    lhs = (Fd.gradient(f, dom, "forward") * v).sum()
    rhs = -(f * Fd.divergence(v, dom, "forward")).sum()
    torch.testing.assert_close(lhs, rhs)


def test_divergence_of_linear_field_is_exact():
    dom = ImageDomain.paper(16)
    x, y = dom.points()
    div = Fd.divergence(torch.stack([3 * x + y, -x + 0.5 * y]), dom)
    torch.testing.assert_close(div, torch.full_like(x, 3.5))


def test_bad_scheme():
    dom = ImageDomain.paper(8)
    with pytest.raises(ValueError, match="scheme"):
        Fd.gradient(dom.zeros(), dom, "upwind")
    with pytest.raises(ValueError, match="scheme"):
        Fd.divergence(dom.zeros(2), dom, "upwind")


@pytest.mark.parametrize("scheme", ("central", "forward"))
@pytest.mark.parametrize("shape", ((9, 7), (2, 5), (1, 1)))
def test_growth_factors_equal_one_plus_scaled_divergence(scheme, shape):
    dom = ImageDomain(shape, (0.0, 0.0), (3.0, 1.0))
    v = torch.randn(4, 2, *shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = torch.empty(4, *shape, dtype=torch.float64)
    Fd._growth_into(out, v, dom, scheme, -0.25)
    torch.testing.assert_close(out, 1 - 0.25 * Fd.divergence(v, dom, scheme), rtol=0, atol=1e-13)


@pytest.mark.parametrize("shape", ((9, 7), (1, 2)))
def test_gradient_from_padded_differences(shape):
    """gradient() reads its differences from the zero-padded image: explicit formulas, any size."""
    dom = ImageDomain(shape, (0.0, 0.0), (3.0, 1.0))
    (hx, hy), f = dom.cell_sides, torch.rand(*shape, dtype=torch.float64)
    p = torch.nn.functional.pad(f, (1, 1, 1, 1))
    central = torch.stack([(p[2:, 1:-1] - p[:-2, 1:-1]) / (2 * hx), (p[1:-1, 2:] - p[1:-1, :-2]) / (2 * hy)])
    forward = torch.stack([(p[2:, 1:-1] - f) / hx, (p[1:-1, 2:] - f) / hy])
    torch.testing.assert_close(Fd.gradient(f, dom), central, rtol=0, atol=1e-14)
    torch.testing.assert_close(Fd.gradient(f, dom, "forward"), forward, rtol=0, atol=1e-14)


def test_step_flags():
    v = torch.zeros(2, 4, 2, 5, 5)
    v[1, 2, 0, 3, 3] = -1e-3  # one nonzero entry in one batch entry marks the step as moving
    assert Fd.step_flags(v) == ([False, False, True, False], True)
    v[0, 3, 1, 0, 0] = float("nan")
    assert Fd.step_flags(v)[1] is False
    v[0, 3, 1, 0, 0] = float("-inf")
    assert Fd.step_flags(v)[1] is False


def test_out_buffers_only_without_autograd():
    dom = ImageDomain.paper(8)
    v = torch.zeros(3, 2, 8, 8, requires_grad=True)
    with pytest.raises(RuntimeError, match="out="):
        Fd.template_trajectory(dom.zeros(), v, dom, out=torch.empty(3, 8, 8))
    with pytest.raises(RuntimeError, match="out="):
        Fd.jacobian_trajectory(v, dom, out=torch.empty(3, 8, 8))


# (input shape, grid shape, bands expected with 2 threads for (shape) arguments of _bands): an image, a volume
BAND_CASES = {
    "2d": ((1, 1, 128, 96), (1, 128, 128, 2), {(128, 128): 2, (64, 64): 1, (127, 128): 1}),
    "3d": ((1, 1, 64, 20, 16), (1, 64, 20, 16, 3), {(64, 20, 16): 2}),
}


@pytest.mark.parametrize("padding_mode", ("zeros", "border"))
@pytest.mark.parametrize("case", BAND_CASES)
def test_sample_in_row_bands_is_exact(padding_mode, case):
    """With several CPU threads a large single image (volume) is sampled in bands (slabs) of rows: the same
    values, and the same gradients (the input's summed over the bands)."""
    f_shape, grid_shape, bands = BAND_CASES[case]
    g = torch.Generator().manual_seed(0)
    f = torch.rand(f_shape, dtype=torch.float64, generator=g)
    grid = torch.rand(grid_shape, dtype=torch.float64, generator=g) * 2.2 - 1.1
    weight = torch.rand(*grid_shape[:1], 1, *grid_shape[1:-1], dtype=torch.float64, generator=g)

    def value_and_grads():
        a, b = f.clone().requires_grad_(), grid.clone().requires_grad_()
        out = Fd.sample(a, b, padding_mode)
        return (out.detach(), *torch.autograd.grad((out * weight).sum(), (a, b)))

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        single = value_and_grads()
        torch.set_num_threads(2)
        assert {shape: Fd._bands(f, *shape) for shape in bands} == bands
        banded = value_and_grads()
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(banded[0], single[0]) and torch.equal(banded[2], single[2])
    torch.testing.assert_close(banded[1], single[1], rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("dtype", (torch.float32, torch.float64))
def test_jacobian_determinant_of_affine_maps_is_exact(dtype):
    # finite differences (central inside, one-sided at the border) are exact for affine maps, on any cell sides
    dom = ImageDomain((12, 9), (-3.0, 1.0), (5.0, 4.0))
    a = torch.tensor([[[1.3, -0.4], [0.7, 0.2]], [[0.0, 1.0], [-1.0, 0.0]], [[-0.5, 0.1], [0.3, 2.0]]],
                     dtype=torch.float64)  # (3, 2, 2): a general map, a rotation by 90 deg, an orientation flip
    x = dom.points()
    points = torch.einsum("bij,jxy->bixy", a, x) + torch.tensor([0.5, -2.0], dtype=torch.float64).view(2, 1, 1)
    det = Fd.jacobian_determinant(points.to(dtype).expand(2, 3, 2, 12, 9), dom)
    assert det.shape == (2, 3, 12, 9) and det.dtype == dtype
    expected = torch.linalg.det(a).to(dtype).view(3, 1, 1).expand(2, 3, 12, 9)
    torch.testing.assert_close(det, expected, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)
    assert torch.equal(Fd.jacobian_determinant(dom.points(dtype), dom), torch.ones(12, 9, dtype=dtype))


def test_jacobian_determinant_matches_independent_differences():
    # a smooth nonlinear map: the same values as torch.gradient's differences of phi itself
    dom = ImageDomain((20, 15), (-2.0, -1.0), (2.0, 2.0))
    x, y = dom.points()
    phi = torch.stack([x + 0.3 * torch.sin(2 * y) * x, y - 0.2 * torch.cos(x * y)])
    (dx1, dy1), (dx2, dy2) = (torch.gradient(phi[k], spacing=dom.cell_sides, edge_order=1) for k in range(2))
    torch.testing.assert_close(Fd.jacobian_determinant(phi, dom), dx1 * dy2 - dy1 * dx2, rtol=1e-12, atol=1e-12)
    small = ImageDomain((6, 5))  # the in-place products keep autograd's derivative correct
    noise = torch.randn(2, 6, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    points = (small.points() + 0.1 * noise).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: Fd.jacobian_determinant(p, small), (points,))
    # a single cell along an axis: no difference there (the map's derivative along it is taken as 1)
    thin = ImageDomain((1, 15), (0.0, -1.0), (1.0, 2.0))
    pts = thin.points() * torch.tensor([1.0, 3.0], dtype=torch.float64).view(2, 1, 1)
    torch.testing.assert_close(Fd.jacobian_determinant(pts, thin), torch.full((1, 15), 3.0, dtype=torch.float64))


def test_displacement_10_is_the_last_composed_displacement():
    dom = ImageDomain((16, 12))
    v = torch.randn(5, 2, 16, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    v[2] = 0  # a skipped step
    last = Fd.displacements_t0(v, dom)[-1] / Fd._grid_units(dom, torch.float64, None)
    torch.testing.assert_close(Fd.displacement_10(v, dom), last, rtol=1e-12, atol=1e-12)
    vr = v.clone().requires_grad_()
    recorded = Fd.displacement_10(vr, dom)
    assert recorded.requires_grad
    torch.testing.assert_close(recorded.detach(), last, rtol=1e-12, atol=1e-12)
