"""indreg.deform.functional.sampling: the plane-wise trilinear sampler against grid_sample, its backward."""
import pytest
import torch
import torch.nn.functional as F

from indreg.deform.functional import sampling as S

SHAPE = (6, 7, 5)


@pytest.fixture
def one_thread():
    """``sample`` takes the plane-wise path with one CPU thread (``_planewise_applies``)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def grid_of(shape, batch, reach, dtype, seed=0):
    """Cell centres displaced uniformly by up to ``reach`` cells per axis (x, y, z), ``(batch, *shape, 3)``."""
    g = torch.Generator().manual_seed(seed)
    lin = [(torch.arange(n, dtype=dtype) * 2 + 1) / n - 1 for n in shape]
    centres = torch.stack(torch.meshgrid(*lin, indexing="ij")[::-1], dim=-1)
    cells = torch.tensor([2 * r / n for r, n in zip(reach, shape)][::-1], dtype=dtype)
    return centres + (torch.rand(batch, *shape, 3, generator=g, dtype=dtype) * 2 - 1) * cells


def reference(f, grid, padding_mode):
    return F.grid_sample(f, grid, mode="bilinear", padding_mode=padding_mode, align_corners=False)


@pytest.mark.parametrize("padding_mode", ("zeros", "border"))
@pytest.mark.parametrize("dtype,tol", ((torch.float64, 1e-13), (torch.float32, 1e-5)))
def test_planewise_equals_grid_sample(padding_mode, dtype, tol):
    """Points up to a cell along x and up to 4 cells along y, z (also outside the domain)."""
    f = torch.randn(2, 3, *SHAPE, dtype=dtype)
    grid = grid_of(SHAPE, 2, (0.999, 4.0, 4.0), dtype)
    out = S._planewise_sample(f, grid, padding_mode)
    torch.testing.assert_close(out, reference(f, grid, padding_mode), rtol=0, atol=tol)


@pytest.mark.parametrize("padding_mode", ("zeros", "border"))
def test_planewise_samples_a_slab_of_another_grid(padding_mode, one_thread):
    """The output's x planes those of the input, y and z another range (a slab's points in the whole image)."""
    f = torch.randn(1, 2, *SHAPE, dtype=torch.float64)
    grid = grid_of(SHAPE, 1, (0.999, 3.0, 3.0), torch.float64)[:, :, 2:5]
    assert S._planewise_applies(f, grid)
    out = S._planewise_sample(f, grid, padding_mode)
    assert out.shape == (1, 2, 6, 3, 5)
    torch.testing.assert_close(out, reference(f, grid, padding_mode), rtol=0, atol=1e-13)


@pytest.mark.parametrize("padding_mode", ("zeros", "border"))
def test_planewise_at_nodes_and_cell_edges(padding_mode):
    """On the nodes the values themselves; one cell away along x (``s = +-1`` up to rounding: the stencil's edge
    or, past it, the fallback) the neighbour plane (at the domain's edge 0 or the border value)."""
    f = torch.randn(1, 2, *SHAPE, dtype=torch.float64)
    grid = grid_of(SHAPE, 1, (0, 0, 0), torch.float64)
    torch.testing.assert_close(S._planewise_sample(f, grid, padding_mode), f, rtol=0, atol=1e-14)
    for sign in (1, -1):
        shifted = grid.clone()
        shifted[..., 2] += sign * 2 / SHAPE[0]
        torch.testing.assert_close(S.sample(f, shifted, padding_mode), reference(f, shifted, padding_mode),
                                   rtol=0, atol=1e-14)


def test_planewise_declines_beyond_a_cell_along_x(one_thread):
    f = torch.randn(1, 1, *SHAPE, dtype=torch.float64)
    grid = grid_of(SHAPE, 1, (0.5, 0, 0), torch.float64)
    grid[0, 2, 3, 1, 2] += 2.5 * 2 / SHAPE[0]
    assert S._planewise_sample(f, grid, "zeros") is None
    grid[0, 2, 3, 1, 2] = float("nan")
    assert S._planewise_sample(f, grid, "zeros") is None
    # sample falls back to grid_sample: the same values
    grid[0, 2, 3, 1, 2] = 3.0
    torch.testing.assert_close(S.sample(f, grid), reference(f, grid, "zeros"), rtol=0, atol=1e-14)


@pytest.mark.parametrize("padding_mode", ("zeros", "border"))
def test_sample_uses_planewise_in_3d_and_its_transpose_is_the_scatter(padding_mode, one_thread):
    """<S f, g> = <f, S^T g> with S^T = _sample_adjoint, and sample's autograd backward equal to it."""
    gen = torch.Generator().manual_seed(0)
    f = torch.randn(2, 3, *SHAPE, dtype=torch.float64, generator=gen).requires_grad_()
    grid = grid_of(SHAPE, 2, (0.9, 2.0, 2.0), torch.float64).requires_grad_()
    g = torch.randn(2, 3, *SHAPE, dtype=torch.float64, generator=gen)
    out = S.sample(f, grid, padding_mode)
    assert "_PlanewiseSample" in type(out.grad_fn.next_functions[0][0]).__name__
    back, slope = S._sample_adjoint(g, f.detach(), grid.detach(), padding_mode, True, True)
    # a sum's rounding scales with its terms' sizes, not with the sum (which may cancel): 7.6e-17 x size at most
    # over 200 seeds
    size = float((out * g).abs().sum())
    torch.testing.assert_close((out * g).sum(), (f * back).sum(), rtol=1e-13, atol=1e-15 * size)
    gf, gg = torch.autograd.grad(out, (f, grid), g)
    torch.testing.assert_close(gf, back, rtol=0, atol=0)
    torch.testing.assert_close(gg, slope, rtol=0, atol=0)


@pytest.mark.parametrize("padding_mode", ("zeros", "border"))
def test_planewise_sample_gradcheck(padding_mode, one_thread):
    f = torch.randn(1, 2, 4, 3, 5, dtype=torch.float64, requires_grad=True)
    grid = grid_of((4, 3, 5), 1, (0.8, 1.5, 1.5), torch.float64, seed=3).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: S.sample(a, b, padding_mode), (f, grid))
    assert torch.autograd.gradgradcheck(lambda a, b: S.sample(a, b, padding_mode), (f, grid))
