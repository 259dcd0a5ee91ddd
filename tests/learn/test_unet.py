"""Tests of MomentumUNet (indreg/learn/unet.py)."""
import pytest
import torch

from indreg.learn import MomentumUNet


def test_shapes_and_zero_initial_output():
    net = MomentumUNet(in_channels=2, width=4, levels=3, momentum_scale=0.5)
    x = torch.randn(3, 2, 16, 24)
    out = net(x)
    assert out.shape == (3, 2, 16, 24)
    assert not out.any()                       # zero-initialised head: identity deformation at start


def test_output_scale_and_gradient():
    torch.manual_seed(0)
    net = MomentumUNet(width=4, levels=2, momentum_scale=3.0)
    torch.nn.init.normal_(net.head.weight)
    x = torch.randn(2, 2, 8, 8)
    out = net(x)
    net.momentum_scale = 1.0
    torch.testing.assert_close(out, 3.0 * net(x))
    out.square().sum().backward()
    assert all(p.grad is not None for p in net.parameters())


def test_errors():
    with pytest.raises(ValueError, match="levels"):
        MomentumUNet(levels=0)
    with pytest.raises(ValueError, match="momentum_scale"):
        MomentumUNet(momentum_scale=0.0)
    net = MomentumUNet(width=4, levels=3)
    with pytest.raises(ValueError, match=r"divisible by 4"):
        net(torch.zeros(1, 2, 10, 16))
    with pytest.raises(ValueError, match=r"\(B, 2, nx, ny\)"):
        net(torch.zeros(1, 3, 16, 16))
