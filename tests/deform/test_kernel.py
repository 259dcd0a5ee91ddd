"""GaussianKernel: Riemann sum of int K(x - y) m(y) dy, exact (no wrap-around), symmetric, positive definite."""
import pytest
import torch

from indreg import ImageDomain
from indreg.deform import GaussianKernel
from indreg.deform.kernel import SIGMA_MIN

METHODS = ("matrix", "fft")


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
    assert K.resolved_method(torch.device("cpu")) == "matrix"
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
    with pytest.raises(TypeError, match="sigma must be a positive number, got 'a'"):
        GaussianKernel(dom, "a")
    K = GaussianKernel(dom, 1.0)
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, 8, 8\)"):
        K(torch.zeros(3, 8, 8))
    with pytest.raises(ValueError, match="non-finite"):
        K(torch.full((2, 8, 8), float("nan")))
    for dtype in (torch.float16, torch.bfloat16):
        with pytest.raises(TypeError, match=f"vector field must be float32 or float64, got {dtype}"):
            K(torch.zeros(2, 8, 8, dtype=dtype))


@pytest.mark.parametrize("method", ("matrix", "fft"))
def test_extreme_sigmas_are_representable(method):
    # the smallest accepted sigma is the discrete delta, a huge one the constant kernel: both finite
    dom = ImageDomain.paper(8)
    m = torch.randn(2, 8, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(GaussianKernel(dom, SIGMA_MIN, method)(m), dom.cell_volume * m)
    constant = dom.cell_volume * m.sum(dim=(-2, -1), keepdim=True).expand(2, 8, 8)
    torch.testing.assert_close(GaussianKernel(dom, 1e300, method)(m), constant)
