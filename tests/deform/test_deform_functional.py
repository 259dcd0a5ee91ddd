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
