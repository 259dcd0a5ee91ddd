"""Tests of IndirectShootingLoss (indreg/learn/loss.py)."""
import math

import pytest
import torch

from indreg import GeodesicShooting, ImageDomain, IndirectShootingLoss, ParallelBeamGeometry, RayTransform
from indreg.deform.kernel import GaussianKernel


@pytest.fixture(scope="module")
def setup():
    dom = ImageDomain.paper(16)
    K = GaussianKernel(dom, 5.0)
    shoot = GeodesicShooting(dom, K, 3)
    gen = torch.Generator().manual_seed(0)
    m0 = 1e-3 * torch.randn(3, 2, 16, 16, generator=gen, dtype=torch.float64)
    tmpl = torch.rand(3, 16, 16, generator=gen, dtype=torch.float64)
    transforms = [RayTransform(dom, ParallelBeamGeometry.paper(a, 24)) for a in (4, 6)]
    return dom, shoot, m0, tmpl, transforms


def test_value_is_data_misfit_plus_gamma_energy(setup):
    dom, shoot, m0, tmpl, (T, _) = setup
    g = T(tmpl) + 0.1
    loss = IndirectShootingLoss(shoot, T, gamma=0.5, reduction="none")
    deformed = shoot(m0, tmpl)
    r = T(deformed) - g
    expected = T.geometry.data_weight * (r * r).sum(dim=(-2, -1)) + 0.5 * shoot.kernel.inner_v(m0, m0)
    torch.testing.assert_close(loss(m0, tmpl, g), expected)
    assert loss(m0, tmpl, g).shape == (3,)
    torch.testing.assert_close(IndirectShootingLoss(shoot, T, 0.5)(m0, tmpl, g), expected.mean())
    torch.testing.assert_close(IndirectShootingLoss(shoot, T, 0.5, "sum")(m0, tmpl, g), expected.sum())


def test_zero_loss_at_the_generating_momentum(setup):
    dom, shoot, m0, tmpl, (T, _) = setup
    g = T(shoot(m0, tmpl))
    terms = IndirectShootingLoss(shoot, T, gamma=0.0).terms(m0, tmpl, g)
    assert float(terms["data_fit"].abs().max()) < 1e-20
    assert (terms["regulariser"] > 0).all()


def test_per_sample_geometry_equals_separate_calls(setup):
    dom, shoot, m0, tmpl, transforms = setup
    index = torch.tensor([1, 0, 1])
    data = [transforms[k](tmpl[b]) + 0.05 * b for b, k in enumerate(index.tolist())]
    per_sample = IndirectShootingLoss(shoot, transforms, gamma=1e-2, reduction="none")(m0, tmpl, data, index)
    for b, k in enumerate(index.tolist()):
        single = IndirectShootingLoss(shoot, transforms[k], gamma=1e-2, reduction="none")(
            m0[b:b + 1], tmpl[b:b + 1], data[b][None])
        torch.testing.assert_close(per_sample[b], single[0])
    # one transform per sample, no index
    listed = [transforms[k] for k in index.tolist()]
    torch.testing.assert_close(IndirectShootingLoss(shoot, listed, 1e-2, "none")(m0, tmpl, data), per_sample)


def test_gradient_reaches_momentum_and_template(setup):
    dom, shoot, m0, tmpl, (T, _) = setup
    m = m0.clone().requires_grad_(True)
    t = tmpl.clone().requires_grad_(True)
    IndirectShootingLoss(shoot, T, gamma=1e-2)(m, t, T(tmpl) + 1.0).backward()
    assert m.grad.abs().sum() > 0 and t.grad.abs().sum() > 0


def test_errors(setup):
    dom, shoot, m0, tmpl, transforms = setup
    with pytest.raises(TypeError, match="shooting"):
        IndirectShootingLoss("x", transforms[0], 1.0)
    with pytest.raises(TypeError, match="linear operator"):
        IndirectShootingLoss(shoot, [], 1.0)
    with pytest.raises(TypeError, match=r"ray_transform\[1\] .*adjoint"):
        IndirectShootingLoss(shoot, [transforms[0], object()], 1.0)
    with pytest.raises(ValueError, match="reduction"):
        IndirectShootingLoss(shoot, transforms[0], 1.0, reduction="max")
    with pytest.raises(ValueError, match="gamma"):
        IndirectShootingLoss(shoot, transforms[0], -1.0)
    other = RayTransform(ImageDomain.paper(8), ParallelBeamGeometry.paper(4, 12))
    with pytest.raises(ValueError, match="domain"):
        IndirectShootingLoss(shoot, other, 1.0)
    loss = IndirectShootingLoss(shoot, transforms, 1.0)
    data = transforms[0](tmpl)
    with pytest.raises(ValueError, match="one per sample or an index"):
        loss(m0, tmpl, data)
    with pytest.raises(ValueError, match=r"index entries must lie in \[0, 1\]"):
        loss(m0, tmpl, data, torch.tensor([0, 2, 0]))
    with pytest.raises(ValueError, match=r"data must have shape \(B=3, 6, 24\)"):
        loss(m0, tmpl, data, torch.tensor([0, 1, 0]))
    with pytest.raises(ValueError, match=r"momentum must have shape \(B, 2, nx, ny\)"):
        IndirectShootingLoss(shoot, transforms[0], 1.0)(m0[0], tmpl, data)


def test_data_is_validated_against_the_range(setup):
    # each bad input fails before the shooting with a one-line error naming data (or data[b])
    dom, shoot, m0, tmpl, transforms = setup
    T = transforms[0]
    loss = IndirectShootingLoss(shoot, T, 1.0)
    good = T(tmpl)
    nan = good.clone()
    nan[1, 2, 3] = float("nan")
    for bad, error, match in (
            (good[:2], ValueError, r"data must have shape \(B=3, 4, 24\), got \(2, 4, 24\)"),
            (good[0], ValueError, r"data must have shape \(B=3, 4, 24\), got \(4, 24\)"),
            (good[..., :20], ValueError, r"data must have shape \(B=3, 4, 24\), got \(3, 4, 20\)"),
            (good.float(), TypeError, "data has dtype torch.float32 but momentum has dtype torch.float64"),
            (good.half(), TypeError, "data must be float32 or float64, got torch.float16"),
            (good.long(), TypeError, "data must have a floating dtype"),
            (nan, ValueError, "data contains non-finite values"),
            (good.numpy(), TypeError, "data must be a tensor .* or a list of B tensors, got ndarray")):
        with pytest.raises(error, match=match):
            loss(m0, tmpl, bad)
    per_sample = IndirectShootingLoss(shoot, transforms, 1.0)
    index = [1, 0, 1]
    data = [transforms[k](tmpl[b]) for b, k in enumerate(index)]
    for b, bad, error, match in (
            (0, data[1], ValueError, r"data\[0\] must have shape \(\.\.\., 6, 24\), got \(4, 24\)"),
            (2, data[2][None], ValueError, r"data\[2\] must have shape \(6, 24\), got \(1, 6, 24\)"),
            (1, data[1].float(), TypeError, r"data\[1\] has dtype torch.float32 but momentum"),
            (1, data[1] * math.inf, ValueError, r"data\[1\] contains non-finite")):
        with pytest.raises(error, match=match):
            per_sample(m0, tmpl, [bad if j == b else d for j, d in enumerate(data)], index)
    with pytest.raises(ValueError, match=r"data must hold one sinogram per sample \(3\), got 2"):
        per_sample(m0, tmpl, data[:2], index)
    with pytest.raises(TypeError, match="momentum must be float32 or float64, got torch.bfloat16"):
        loss(m0.bfloat16(), tmpl, good)
    # data_fit checks too, against the deformed templates
    with pytest.raises(TypeError, match="data has dtype torch.float32 but deformed has dtype torch.float64"):
        loss.data_fit(tmpl, good.float())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_data_on_another_device(setup):
    dom, shoot, m0, tmpl, (T, _) = setup
    with pytest.raises(ValueError, match="data is on cuda:0 but momentum is on cpu"):
        IndirectShootingLoss(shoot, T, 1.0)(m0, tmpl, T(tmpl).cuda())


def test_index_and_gamma_are_type_checked(setup):
    # issue #19: index=[0.7] silently used transform 0
    dom, shoot, m0, tmpl, transforms = setup
    loss = IndirectShootingLoss(shoot, transforms, 1.0)
    data = [transforms[0](tmpl[b]) for b in range(3)]
    for bad, match in (([0.7, 0.0, 0.0], "float32"), (torch.tensor([0.0, 1.0, 0.0]), "float32"),
                       ([True, False, True], "bool")):
        with pytest.raises(TypeError, match=f"^index must hold integers \\(transform numbers\\), got dtype torch.{match}"):
            loss(m0, tmpl, data, bad)
    with pytest.raises(TypeError, match="^index must be a \\(B,\\) integer tensor or list, got str"):
        loss(m0, tmpl, data, "012")
    # a shared transform has only transform 0
    with pytest.raises(ValueError, match=r"^index entries must lie in \[0, 0\], got \[0, 1, 0\]"):
        IndirectShootingLoss(shoot, transforms[0], 1.0)(m0, tmpl, transforms[0](tmpl), [0, 1, 0])
    for bad in (False, "0", None):
        with pytest.raises(TypeError, match="^gamma must be a finite number >= 0, got "):
            IndirectShootingLoss(shoot, transforms[0], bad)
    assert IndirectShootingLoss(shoot, transforms[0], 0).gamma == 0.0
    with pytest.raises(ValueError, match=r"^momentum is empty \(shape \(0, 2, 16, 16\)\)"):
        IndirectShootingLoss(shoot, transforms[0], 1.0)(m0[:0], tmpl[:0], transforms[0](tmpl[:0]))
