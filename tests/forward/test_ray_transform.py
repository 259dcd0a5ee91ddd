"""RayTransform: shapes, adjointness, exact transpose in autograd, analytic ellipse and skimage agreement."""
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform

# A small non-square domain with oblique angles (both marching directions) for exact checks.
SMALL_DOMAIN = ImageDomain((7, 5), (-3.0, -2.0), (4.0, 3.0))
SMALL_GEOMETRY = ParallelBeamGeometry(angles=[0.0, 0.4, 1.3, 2.0, 2.9], det_count=9, det_min=-5.0, det_max=5.0)


@pytest.fixture(scope="module")
def small():
    return RayTransform(SMALL_DOMAIN, SMALL_GEOMETRY)


@pytest.fixture(scope="module")
def paper64():
    return RayTransform(ImageDomain.paper(64), ParallelBeamGeometry.paper(10, 92))


def dense_matrix(T):
    """Columns T(e_p) for every pixel basis image e_p: shape (num_angles*det_count, nx*ny)."""
    basis = torch.eye(SMALL_DOMAIN.shape[0] * SMALL_DOMAIN.shape[1], dtype=torch.float64)
    return T(basis.reshape(-1, *SMALL_DOMAIN.shape)).reshape(basis.shape[0], -1).T


def test_smoke_shapes(paper64):
    f = torch.rand(64, 64, dtype=torch.float64)
    y = paper64(f)
    assert y.shape == (10, 92) and y.dtype == torch.float64
    torch.testing.assert_close(paper64.A(f), y)
    assert paper64.adjoint(y).shape == (64, 64)
    torch.testing.assert_close(paper64.A_adjoint(y), paper64.transpose(y))  # deepinv: plain-sum adjoint
    x = torch.rand(64, 64, dtype=torch.float64)
    torch.testing.assert_close((paper64.A(x) * y).sum(), (x * paper64.A_adjoint(y)).sum())
    assert "nnz=" in repr(paper64)


def test_disk_line_integrals_in_physical_units(ellipses):
    """A unit disk of radius 8 has p(theta, s) = 2 sqrt(64 - s^2): 16 through the centre at every angle."""
    dom = ImageDomain.paper(128)
    geom = ParallelBeamGeometry(angles=[0.0, 0.3, math.pi / 4, 2.0], det_count=65, det_min=-16.0, det_max=16.0)
    disk = ellipses.rasterise([(1.0, 0.5, 0.5, 0.0, 0.0, 0.0)], dom, supersample=8)
    y = RayTransform(dom, geom)(disk)
    s = geom.det_points
    exact = 2 * torch.sqrt((64 - s ** 2).clamp(min=0))
    assert torch.allclose(y[:, 32], torch.full((4,), 16.0, dtype=torch.float64), rtol=0.01)
    assert float((y - exact).norm() / exact.norm() / 2) < 0.01


@pytest.mark.parametrize("name", ["small", "paper64"])
def test_adjointness_weighted_inner_products(name, request):
    T = request.getfixturevalue(name)
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, *T.domain.shape, generator=gen, dtype=torch.float64)
    y = torch.randn(3, *T.range_shape, generator=gen, dtype=torch.float64)
    tx = T(x)
    lhs, rhs = T.inner_data(tx, y), T.domain.inner(x, T.adjoint(y))
    assert lhs.shape == (3,)
    assert bool(((lhs - rhs).abs() <= 1e-10 * T.norm_data(tx) * T.norm_data(y)).all())
    assert T.adjointness_test() <= 1e-10
    assert T.adjointness_test(torch.float32) <= 1e-5


def test_adjoint_is_weighted_matrix_transpose(small):
    M = dense_matrix(small)
    y = torch.randn(*small.range_shape, dtype=torch.float64)
    torch.testing.assert_close(small.transpose(y).reshape(-1), M.T @ y.reshape(-1), rtol=1e-14, atol=1e-14)
    scale = SMALL_GEOMETRY.data_weight / SMALL_DOMAIN.cell_volume
    torch.testing.assert_close(small.adjoint(y), scale * small.transpose(y), rtol=1e-14, atol=0)
    assert small.adjoint_scale == pytest.approx(scale)


def test_operator_norm_matches_dense_svd(small):
    M = dense_matrix(small) * math.sqrt(SMALL_GEOMETRY.data_weight / SMALL_DOMAIN.cell_volume)
    assert small.operator_norm(num_iter=60) == pytest.approx(float(torch.linalg.matrix_norm(M, ord=2)), rel=1e-9)


def test_autograd_backward_is_transpose_and_double_backward(small):
    f = torch.randn(2, *SMALL_DOMAIN.shape, dtype=torch.float64, requires_grad=True)
    y = torch.randn(2, *small.range_shape, dtype=torch.float64)
    (g,) = torch.autograd.grad((small(f) * y).sum(), f, create_graph=True)
    torch.testing.assert_close(g, small.transpose(y))
    v = torch.randn_like(f)
    yq = y.clone().requires_grad_(True)
    (g2,) = torch.autograd.grad((small(f) * yq).sum(), f, create_graph=True)
    (h,) = torch.autograd.grad((g2 * v).sum(), yq)
    torch.testing.assert_close(h, small(v))


def test_gradcheck_and_gradgradcheck():
    T = RayTransform(ImageDomain((4, 3), (-2.0, -1.0), (2.0, 2.0)),
                     ParallelBeamGeometry(angles=[0.2, 1.1, 2.5], det_count=5, det_min=-3.0, det_max=3.0))
    f = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    y = torch.randn(*T.range_shape, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(T, (f,))
    assert torch.autograd.gradgradcheck(T, (f,))
    assert torch.autograd.gradcheck(T.adjoint, (y,))
    assert torch.autograd.gradgradcheck(T.adjoint, (y,))
    assert torch.autograd.gradgradcheck(lambda x: T(x).pow(3).sum(), (f,))


def test_batch_dims_equal_per_sample_calls(paper64):
    f = torch.rand(2, 3, 64, 64, dtype=torch.float64)
    y = paper64(f)
    assert y.shape == (2, 3, 10, 92)
    back = paper64.adjoint(y)
    assert back.shape == (2, 3, 64, 64)
    for a in range(2):
        for b in range(3):
            torch.testing.assert_close(y[a, b], paper64(f[a, b]), rtol=1e-13, atol=1e-13)
            torch.testing.assert_close(back[a, b], paper64.adjoint(y[a, b]), rtol=1e-13, atol=1e-13)
    assert paper64.inner_data(y, y).shape == (2, 3)


def test_float32(paper64):
    f = torch.rand(4, 64, 64, dtype=torch.float64)
    y32 = paper64(f.float())
    assert y32.dtype == torch.float32
    torch.testing.assert_close(y32.double(), paper64(f), rtol=1e-5, atol=1e-5)
    assert paper64.adjoint(y32).dtype == torch.float32


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(paper64):
    f = torch.rand(2, 64, 64, dtype=torch.float64)
    y = paper64(f.cuda())
    assert y.device.type == "cuda"
    torch.testing.assert_close(y.cpu(), paper64(f))
    torch.testing.assert_close(paper64.adjoint(y).cpu(), paper64.adjoint(paper64(f)))


def test_shepp_logan_matches_analytic_ellipse_radon(ellipses):
    """Projection of the rasterised (4x4 supersampled) phantom vs the closed form: < 2% relative L2 (1.3%)."""
    dom = ImageDomain.paper(256)
    geom = ParallelBeamGeometry.paper(10, 362)
    phantom = ellipses.rasterise(ellipses.shepp_logan, dom)
    exact = ellipses.radon(ellipses.shepp_logan, geom)
    err = float((RayTransform(dom, geom)(phantom) - exact).norm() / exact.norm())
    assert err < 0.02


def test_agrees_with_skimage_radon(ellipses):
    """skimage: image = rot90(f) (rows = y descending), theta in degrees = ours, bins of one pixel around
    the centre pixel, sums in pixel units (times h). Odd n puts skimage's rotation centre at our origin.
    Both are linear-interpolation projectors, so they agree to discretisation error: 0.74% relative L2
    measured at n = 65 (each is about 6% from the analytic transform at that size); tolerance 1.5%."""
    from skimage.transform import radon

    n = 65
    dom = ImageDomain.paper(n)
    h = dom.cell_sides[0]
    bins = n + math.ceil(math.sqrt(2) * n - n)
    centre = bins // 2
    degrees = np.arange(0.0, 180.0, 180.0 / 32)
    geom = ParallelBeamGeometry(angles=np.deg2rad(degrees), det_count=bins,
                                det_min=(-centre - 0.5) * h, det_max=(bins - centre - 0.5) * h)
    f = ellipses.rasterise(ellipses.shepp_logan, dom)
    ours = RayTransform(dom, geom)(f).numpy()
    theirs = radon(np.rot90(f.numpy()), degrees, circle=False).T * h
    assert np.linalg.norm(theirs - ours) / np.linalg.norm(ours) < 0.015


@pytest.mark.parametrize("bad, error, match", [
    (torch.zeros(64, 63, dtype=torch.float64), ValueError, r"shape \(\.\.\., 64, 64\)"),
    (torch.zeros(64, dtype=torch.float64), ValueError, "shape"),
    (torch.zeros(64, 64, dtype=torch.int64), TypeError, "floating dtype"),
    (torch.zeros(64, 64, dtype=torch.float16), TypeError, "float32 or float64"),
    (torch.full((64, 64), math.nan, dtype=torch.float64), ValueError, "non-finite"),
    (np.zeros((64, 64)), TypeError, "torch.Tensor"),
])
def test_forward_input_errors(paper64, bad, error, match):
    with pytest.raises(error, match=match):
        paper64(bad)


def test_adjoint_and_inner_errors(paper64):
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 10, 92\)"):
        paper64.adjoint(torch.zeros(92, 10, dtype=torch.float64))
    with pytest.raises(TypeError, match="floating dtype"):
        paper64.adjoint(torch.zeros(10, 92, dtype=torch.int32))
    with pytest.raises(ValueError, match="non-finite"):
        paper64.transpose(torch.full((10, 92), math.inf))
    with pytest.raises(TypeError, match="dtype"):
        paper64.inner_data(torch.zeros(10, 92), torch.zeros(10, 92, dtype=torch.float64))
    with pytest.raises(ValueError, match="num_iter"):
        paper64.operator_norm(num_iter=0)


def test_constructor_errors():
    with pytest.raises(TypeError, match="ImageDomain"):
        RayTransform((64, 64), ParallelBeamGeometry.paper(10, 92))
    with pytest.raises(TypeError, match="ParallelBeamGeometry"):
        RayTransform(ImageDomain.paper(64), None)


def test_copy_and_pickle_after_use(paper64):
    """A used transform (cached CSR tensors) can be deep-copied and pickled; the copy computes the same."""
    import copy
    import pickle

    f = torch.rand(64, 64, dtype=torch.float64)
    y = paper64(f)
    for clone in (copy.deepcopy(paper64), pickle.loads(pickle.dumps(paper64))):
        torch.testing.assert_close(clone(f), y)
        torch.testing.assert_close(clone.adjoint(y), paper64.adjoint(y))


def _every_csr(op, dtype):
    """Every CSR tensor the operator hands to torch in ``dtype`` on the CPU: ``A``, ``A^T`` and ``A``'s column
    blocks."""
    system = op.system
    mats = list(system.get(dtype, torch.device("cpu")))
    mats += [m for _, _, m in system.column_blocks(dtype, torch.device("cpu"), 1000)]
    return mats


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_csr_arrays_have_spare_memory_behind_their_end(paper64, dtype):
    # MKL's AVX-512 CSR kernels read up to 60 bytes past the column indices (ray_transform.SPARE): a segfault where
    # the array ended at an unmapped page (torch 2.15.0)
    from indreg.forward.ray_transform import SPARE

    for mat in _every_csr(paper64, dtype):
        for t in (mat.crow_indices(), mat.col_indices(), mat.values()):
            assert t.untyped_storage().nbytes() >= (t.storage_offset() + t.numel() + SPARE) * t.element_size()


_GUARD_PAGE = r"""
import ctypes, mmap, sys
import numpy as np, torch
from indreg.forward.ray_transform import _torch_csr

def before_unmapped_page(values):
    # values copied to the very end of a readable page, the page after it unreadable
    page = mmap.PAGESIZE
    n = -(-values.nbytes // page) * page
    buf = mmap.mmap(-1, n + page)
    base = ctypes.addressof(ctypes.c_char.from_buffer(buf))
    assert ctypes.CDLL(None).mprotect(ctypes.c_void_p(base + n), page, 0) == 0
    view = np.frombuffer(buf, dtype=values.dtype, count=values.size, offset=n - values.nbytes)
    view[:] = values
    return torch.from_numpy(view)

rng = np.random.default_rng(0)
m, n, per = 2000, 5000, 100
crow = torch.arange(0, m * per + 1, per, dtype=torch.int32)
col = np.sort(rng.integers(0, n, (m, per)), axis=1).astype(np.int32).ravel()
val = rng.random(m * per, dtype=np.float32)
A = _torch_csr(crow, before_unmapped_page(col), before_unmapped_page(val), (m, n))
x = torch.rand(n, generator=torch.Generator().manual_seed(0))
dense = torch.zeros(m, n).index_put_((torch.arange(m).repeat_interleave(per), torch.from_numpy(col).long()),
                                      torch.from_numpy(val), accumulate=True)
assert torch.allclose(torch.mv(A, x), dense @ x, rtol=1e-4, atol=1e-3)
assert torch.allclose(torch.mm(A, x[:, None].repeat(1, 3)), (dense @ x)[:, None].repeat(1, 3), rtol=1e-4, atol=1e-3)
print("ok")
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mprotect of a guard page: Linux")
def test_products_of_arrays_ending_before_an_unmapped_page():
    # the crash itself, in a child process: column indices and values ending exactly where an unreadable page
    # starts; the CSR tensors made of them (``_torch_csr``) must multiply correctly
    run = subprocess.run([sys.executable, "-c", _GUARD_PAGE], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-2000:]
