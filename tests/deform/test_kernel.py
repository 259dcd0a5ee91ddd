"""GaussianKernel: Riemann sum of int K(x - y) m(y) dy, exact (no wrap-around), symmetric, positive definite;
the low-rank form equal to the dense one to rounding."""
import math

import pytest
import torch

from indreg import ImageDomain
from indreg.deform import GaussianKernel
from indreg.deform.kernel import SIGMA_MIN

METHODS = ("matrix", "lowrank", "fft")


def gaussian(domain, centre, sigma, dtype=torch.float64):
    x, y = domain.points(dtype)
    return torch.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma ** 2))


@pytest.mark.parametrize("method", METHODS)
def test_delta_gives_sampled_gaussian_times_cell_volume(method):
    dom = ImageDomain((24, 20), (-16.0, -10.0), (16.0, 10.0))
    K = GaussianKernel(dom, sigma=3.0, method=method)
    m = torch.zeros(2, *dom.shape, dtype=torch.float64)
    m[0, 5, 7] = 1.0
    m[1, 20, 3] = -2.0
    x, y = dom.axes()
    expected = torch.stack([gaussian(dom, (x[5], y[7]), 3.0), -2.0 * gaussian(dom, (x[20], y[3]), 3.0)])
    torch.testing.assert_close(K(m), dom.cell_volume * expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("method", METHODS)
def test_no_wrap_around_at_the_border(method):
    # sigma comparable to the domain: a periodic (unpadded) convolution would put ~exp(-1/128) ~ 1
    # at the opposite border, the exact value is exp(-31^2 / 128) ~ 5e-4
    dom = ImageDomain.paper(32)
    K = GaussianKernel(dom, sigma=8.0, method=method)
    m = torch.zeros(2, 32, 32, dtype=torch.float64)
    m[:, 0, 0] = 1.0
    out = K(m)
    x, y = dom.axes()
    expected = dom.cell_volume * gaussian(dom, (x[0], y[0]), 8.0)
    torch.testing.assert_close(out[0], expected, rtol=1e-12, atol=1e-15)
    assert float(out[0, -1, -1]) < 1e-6


def test_fft_and_matrix_agree():
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        dom = ImageDomain((33, 40))
        f = torch.randn(3, 2, 33, 40, dtype=dtype, generator=torch.Generator().manual_seed(0))
        a = GaussianKernel(dom, 2.0, method="matrix")(f)
        b = GaussianKernel(dom, 2.0, method="fft")(f)
        assert a.dtype == dtype and a.shape == f.shape
        assert float((a - b).abs().max() / a.abs().max()) < tol


@pytest.mark.parametrize("method", METHODS)
def test_symmetric_and_positive_definite(method):
    dom = ImageDomain.paper(20)
    K = GaussianKernel(dom, sigma=2.5, method=method)
    g = torch.Generator().manual_seed(1)
    f, h = (torch.randn(4, 2, 20, 20, dtype=torch.float64, generator=g) for _ in range(2))
    lhs = dom.cell_volume * (K(f) * h).sum(dim=(-3, -2, -1))
    rhs = dom.cell_volume * (f * K(h)).sum(dim=(-3, -2, -1))
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(K.inner_v(f, h), rhs, rtol=1e-12, atol=1e-12)
    assert bool((K.inner_v(f, f) > 0).all())
    # the 1D Gaussian Toeplitz matrices are positive definite, hence so is their Kronecker product
    assert float(torch.linalg.eigvalsh(K.toeplitz(0)).min()) > 0


def test_batch_dims_dtype_and_auto():
    dom = ImageDomain.paper(16)
    K = GaussianKernel(dom, 6.0)
    assert K.resolved_method(torch.device("cpu")) == "matrix"  # small: the dense matrices are cheapest
    f = torch.randn(2, 3, 2, 16, 16, dtype=torch.float32)
    out = K(f)
    assert out.shape == f.shape and out.dtype == torch.float32
    torch.testing.assert_close(out[1, 2], K(f[1, 2]))


def test_bad_input():
    dom = ImageDomain.paper(8)
    for sigma in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="sigma"):
            GaussianKernel(dom, sigma)
    with pytest.raises(ValueError, match="method"):
        GaussianKernel(dom, 1.0, method="direct")
    for sigma in (1e-300, SIGMA_MIN / 2):  # sigma^2 underflows: the kernel would be NaN
        with pytest.raises(ValueError, match=r"sigma must be >= 1.49e-154 \(below, sigma\^2 underflows"):
            GaussianKernel(dom, sigma)
    for sigma in ("a", "6", True, None, [1.0]):  # a string or a bool is not a width, even when float() takes it
        with pytest.raises(TypeError, match=f"sigma must be a positive number, got {sigma!r}".replace("[", r"\[")):
            GaussianKernel(dom, sigma)
    K = GaussianKernel(dom, 1.0)
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, 8, 8\)"):
        K(torch.zeros(3, 8, 8))
    for shape in ((2, 7, 8), (8,), (2, 8, 8, 1)):  # apply: the trailing dims must be the domain's shape
        with pytest.raises(ValueError, match=rf"f must have shape \(\.\.\., 8, 8\), got \({shape[0]}"):
            K.apply(torch.zeros(shape))
    with pytest.raises(TypeError, match="f must be a torch.Tensor, got list"):
        K.apply([[0.0] * 8] * 8)
    with pytest.raises(ValueError, match="non-finite"):
        K(torch.full((2, 8, 8), float("nan")))
    for dtype in (torch.float16, torch.bfloat16):
        with pytest.raises(TypeError, match=f"vector field must be float32 or float64, got {dtype}"):
            K(torch.zeros(2, 8, 8, dtype=dtype))


@pytest.mark.parametrize("method", METHODS)
def test_extreme_sigmas_are_representable(method):
    # the smallest accepted sigma is the discrete delta, a huge one the constant kernel: both finite
    dom = ImageDomain.paper(8)
    m = torch.randn(2, 8, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(GaussianKernel(dom, SIGMA_MIN, method)(m), dom.cell_volume * m)
    constant = dom.cell_volume * m.sum(dim=(-2, -1), keepdim=True).expand(2, 8, 8)
    torch.testing.assert_close(GaussianKernel(dom, 1e300, method)(m), constant)


def gaussian_field(domain, centre, tau, dtype=torch.float64):
    """``exp(-|x - centre|^2 / (2 tau^2))`` at the cell centres of a 2D or 3D domain."""
    points = domain.points(dtype)
    return torch.exp(-sum((p - c) ** 2 for p, c in zip(points, centre)) / (2 * tau ** 2))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", [(64, 48), (40, 36, 32)])
def test_gaussian_blob_gives_the_closed_form_convolution(method, shape):
    # int exp(-|x - y|^2 / 2 sigma^2) exp(-|y - c|^2 / 2 tau^2) dy
    #   = (2 pi sigma^2 tau^2 / (sigma^2 + tau^2))^(d/2) exp(-|x - c|^2 / 2 (sigma^2 + tau^2));
    # the midpoint sum of the integrand (width 1.2, cells <= 0.875) is exact to rounding, and for |x| < 3 its
    # mass beyond the boundary (>= 12) is ~exp(-37)
    d = len(shape)
    dom = ImageDomain(shape, (-16.0,) * d, (16.0, 12.0, 12.0)[:d])
    sigma, tau, centre = 2.0, 1.5, (1.0, -0.5, 0.25)[:d]
    out = GaussianKernel(dom, sigma, method).apply(gaussian_field(dom, centre, tau))
    s2 = sigma ** 2 + tau ** 2
    expected = (2 * math.pi * sigma ** 2 * tau ** 2 / s2) ** (d / 2) * gaussian_field(dom, centre, math.sqrt(s2))
    inside = (dom.points().abs() < 3.0).all(dim=0)
    torch.testing.assert_close(out[inside], expected[inside], rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 2e-14), (torch.float32, 2e-6)])
@pytest.mark.parametrize("shape, extent", [((24, 16, 12), (32.0, 18.0, 7.0)), ((40, 28), (32.0, 12.0)),
                                           ((16, 16, 16), (32.0, 32.0, 32.0))])
@pytest.mark.parametrize("sigma_cells", [0.02, 0.7, 3.0, 12.0, 300.0])
def test_lowrank_equals_the_dense_form(dtype, tol, shape, extent, sigma_cells):
    # sigma from far below a cell (the delta) to far above the domain (nearly constant); non-cubic grids and
    # cells; the difference is the dense form's own rounding level (its float32 error against float64 ~4e-7)
    dom = ImageDomain(shape, tuple(-e / 2 for e in extent), tuple(e / 2 for e in extent))
    sigma = sigma_cells * dom.cell_sides[0]
    f = torch.randn(2, len(shape), *shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    dense = GaussianKernel(dom, sigma, "matrix").apply(f).to(dtype)
    low = GaussianKernel(dom, sigma, "lowrank").apply(f.to(dtype))
    assert low.dtype == dtype and low.shape == f.shape
    assert float((low - dense).abs().max() / dense.abs().max()) < tol


def test_rank_does_not_grow_with_the_resolution():
    # the eigenvalues decay like exp(-(pi sigma k / extent)^2 / 2): r depends on extent / sigma, not on n
    ranks = {n: GaussianKernel(ImageDomain.paper(n, 3), 3.0).rank(0) for n in (64, 128, 256)}
    assert ranks == {64: 22, 128: 22, 256: 22}
    K = GaussianKernel(ImageDomain.paper(128, 3), 3.0)
    assert K.rank(0, torch.float64) == 36
    lam = K.eigenpairs(0)[0]
    assert bool((lam[:-1] >= lam[1:]).all()) and float(lam[36]) <= torch.finfo(torch.float64).eps * float(lam[0])


def test_auto_picks_by_cost():
    et = GaussianKernel(ImageDomain.paper(128, 3), 3.0)  # the ET preset: r = 22 << n = 128
    assert et.resolved_method(torch.device("cpu")) == "lowrank"
    assert et.cost("lowrank") < et.cost("matrix") / 2
    narrow = GaussianKernel(ImageDomain.paper(64, 3), 0.2)  # sigma < a cell: no eigenvalue to drop
    assert narrow.rank(0) == 64 and narrow.resolved_method(torch.device("cpu")) == "matrix"
    f = torch.randn(2, 3, 16, 16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    for sigma in (0.5, 6.0):
        K = GaussianKernel(ImageDomain.paper(16, 3), sigma)
        method = K.resolved_method(f.device, f.dtype)
        assert torch.equal(K(f), GaussianKernel(K.domain, sigma, method)(f))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", [(7, 6), (6, 5, 4)])
def test_gradcheck(method, shape):
    dom = ImageDomain(shape, (-4.0,) * len(shape), (4.0,) * len(shape))
    K = GaussianKernel(dom, 2.0, method)
    f = torch.randn(2, *shape, dtype=torch.float64, generator=torch.Generator().manual_seed(4), requires_grad=True)
    assert torch.autograd.gradcheck(K.apply, (f,))
