"""3D baselines: slice-wise FBP of a tilt series, SIRT (any nonnegative LinearOperator), TV in 3D."""
import math

import pytest
import torch

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform, phantoms
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform, fbp, sirt, tv_reconstruction
from indreg.forward.tv import divergence, gradient, total_variation

BALL = [(1.5, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)]     # value 1.5, radius 8 on [-16, 16]^3


def ball_setup(n, lo, hi, step):
    dom = ImageDomain.paper(n, 3)
    T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(lo, hi, step, det_count=3 * n // 2))
    return dom, T, phantoms.ellipsoid_tilt_series(BALL, dom, T.geometry)


def test_fbp_ball_full_and_limited_range():
    """Noiseless analytic data: 1.5 inside the ball over a half-turn of tilts; a centred ball's centre at
    (covered range / 180 degrees) of its value over +-60 degrees (each tilt weighted by its step)."""
    dom, T, y = ball_setup(32, -90, 88, 2)
    rec = fbp(T, y, "ram-lak", 1.0)
    r = dom.points().pow(2).sum(0).sqrt()
    assert rec.shape == dom.shape
    assert float(rec[r < 6].mean()) == pytest.approx(1.5, rel=0.01)
    assert float(rec[r > 10].abs().mean()) < 0.03
    dom, T, y = ball_setup(32, -60, 60, 2)
    rec = fbp(T, y, "ram-lak", 1.0)
    centre = rec[15:17, 15:17, 15:17].mean()
    assert float(centre) == pytest.approx(1.5 * 122 / 180, rel=0.02)   # 61 tilts x 2 degrees


def test_fbp_is_the_2d_fbp_per_slice_and_batched():
    dom = ImageDomain((10, 4, 8), (-5.0, -2.0, -4.0), (5.0, 2.0, 4.0))
    T = TiltSeriesTransform(dom, TiltSeriesGeometry([-50.0, -20.0, 0.0, 10.0, 45.0], 14, angle_unit="deg"))
    y = torch.rand(2, *T.range_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rec = fbp(T, y)
    assert rec.shape == (2, *dom.shape)
    T2 = T.slice_transform
    for j in range(dom.shape[1]):
        torch.testing.assert_close(rec[:, :, j, :], fbp(T2, y[:, :, j, :]), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="data must have shape"):
        fbp(T, y[..., :-1])


@pytest.mark.parametrize("nonneg", [False, True])
def test_sirt_residual_decreases_monotonically(nonneg):
    dom, T, y = ball_setup(16, -60, 60, 4)
    y = y + 0.2 * torch.randn(y.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x, hist = sirt(T, y, num_iter=25, nonneg=nonneg)
    res = hist["residual"]
    assert res.shape == (25,) and hist["data_residual"].shape == (25,)
    assert bool((res[1:] <= res[:-1] * (1 + 1e-12)).all())
    assert float(res[-1]) < 0.2 * float(res[0])
    if nonneg:
        assert float(x.min()) >= 0.0
    truth = phantoms.ellipsoid_phantom(dom, BALL)
    assert float(dom.norm(x - truth)) < 0.5 * float(dom.norm(truth))


def test_sirt_2d_batched_and_bad_operator():
    dom = ImageDomain.paper(16)
    T = RayTransform(dom, ParallelBeamGeometry(12, 24))
    f = torch.rand(3, 16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    x, hist = sirt(T, T(f), num_iter=5)
    assert x.shape == (3, 16, 16) and hist["residual"].shape == (5, 3)
    x1, _ = sirt(T, T(f)[1], num_iter=5)
    torch.testing.assert_close(x[1], x1, rtol=1e-12, atol=1e-12)

    class Negated:
        domain, range_shape = T.domain, T.range_shape
        __call__ = staticmethod(lambda v: -T(v))
        adjoint = staticmethod(lambda v: -T.adjoint(v))
        inner_data = staticmethod(T.inner_data)

    with pytest.raises(ValueError, match="nonnegative matrix"):
        sirt(Negated(), T(f[0]), num_iter=2)
    with pytest.raises(ValueError, match="y must have shape"):
        sirt(T, f, num_iter=2)
    with pytest.raises(ValueError, match="num_iter must be"):
        sirt(T, T(f), num_iter=0)


def test_tv_gradient_divergence_adjoint_in_3d():
    dom = ImageDomain((5, 6, 7), (-1.0, -2.0, 0.0), (1.5, 1.0, 3.5))
    gen = torch.Generator().manual_seed(4)
    f = torch.randn(2, *dom.shape, dtype=torch.float64, generator=gen)
    p = torch.randn(2, 3, *dom.shape, dtype=torch.float64, generator=gen)
    g = gradient(f, dom)
    assert g.shape == (2, 3, *dom.shape)
    lhs = dom.cell_volume * (g * p).sum(dim=(-4, -3, -2, -1))
    rhs = -dom.inner(f, divergence(p, dom))
    torch.testing.assert_close(lhs, rhs, rtol=1e-13, atol=1e-13)
    a, b, c = 0.5, -2.0, 3.0                     # linear f: exact interior gradient, TV = |(a, b, c)| |interior|
    x, y, z = dom.points()
    lin = gradient(a * x + b * y + c * z, dom)[:, :-1, :-1, :-1]
    for k, value in enumerate((a, b, c)):
        torch.testing.assert_close(lin[k], torch.full_like(lin[k], value), rtol=1e-12, atol=1e-12)
    assert total_variation(f, dom).shape == (2,)


def test_tv_2d_unchanged():
    """The d-dimensional gradient / divergence equal the 2D formulas exactly (bit for bit)."""
    dom = ImageDomain((6, 5), (-3.0, -1.0), (3.0, 4.0))
    f = torch.randn(2, 6, 5, dtype=torch.float64)
    p = torch.randn(2, 2, 6, 5, dtype=torch.float64)
    hx, hy = dom.cell_sides
    gx = torch.diff(f, dim=-2, append=torch.zeros_like(f[..., :1, :])) / hx
    gy = torch.diff(f, dim=-1, append=torch.zeros_like(f[..., :, :1])) / hy
    assert torch.equal(gradient(f, dom), torch.stack((gx, gy), dim=-3))
    px, py = p[..., 0, :, :], p[..., 1, :, :]
    div = (torch.diff(px, dim=-2, prepend=torch.zeros_like(px[..., :1, :])) / hx
           + torch.diff(py, dim=-1, prepend=torch.zeros_like(py[..., :, :1])) / hy)
    assert torch.equal(divergence(p, dom), div)


def test_tv_reconstruction_3d_decreases_objective():
    dom, T, y = ball_setup(12, -60, 60, 6)
    x, hist = tv_reconstruction(T, y, mu=0.05, num_iter=40, nonneg=True, opnorm_iter=20)
    obj = hist["objective"]
    assert x.shape == dom.shape and float(x.min()) >= 0
    assert float(obj[-1]) < 0.1 * float(obj[0])
    truth = phantoms.ellipsoid_phantom(dom, BALL)
    assert float(dom.norm(x - truth)) < 0.5 * float(dom.norm(truth))


def test_sirt_start_image_and_flag_errors():
    dom = ImageDomain.paper(16)
    T = RayTransform(dom, ParallelBeamGeometry(6, 24))
    y = T(torch.rand(2, 16, 16, dtype=torch.float64))
    for bad in (dom.zeros(0), dom.zeros(3, 2), dom.zeros()):
        with pytest.raises(ValueError, match=r"^x0 must have shape \(2, 16, 16\) \(the data's batch dims"):
            sirt(T, y, num_iter=1, x0=bad)
    with pytest.raises(TypeError, match="^nonneg must be True or False, got None"):
        sirt(T, y, num_iter=1, nonneg=None)
    x, _ = sirt(T, y, num_iter=1, x0=dom.zeros(2, dtype=torch.float32))  # the start follows the data's dtype
    assert x.dtype == torch.float64
