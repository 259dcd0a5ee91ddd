"""ImageDomain: cell-centred geometry, L2 inner products, grid_sample mapping, bad input."""
import math

import pytest
import torch

from indreg import ImageDomain


def test_paper_domain_cells():
    dom = ImageDomain.paper(64)
    assert dom.shape == (64, 64)
    assert dom.cell_sides == (0.5, 0.5)
    assert dom.cell_volume == 0.25
    x, y = dom.axes()
    assert x[0].item() == -15.75 and x[-1].item() == 15.75
    assert torch.allclose(x.mean(), torch.tensor(0.0, dtype=x.dtype))


def test_points_axis_order():
    dom = ImageDomain((4, 6), (0.0, -3.0), (2.0, 3.0))
    p = dom.points()
    assert p.shape == (2, 4, 6)
    # axis 0 is x (varies along array axis 0), axis 1 is y (varies along array axis 1)
    assert torch.equal(p[0, :, 0], torch.tensor([0.25, 0.75, 1.25, 1.75], dtype=torch.float64))
    assert torch.equal(p[1, 0, :], torch.tensor([-2.5, -1.5, -0.5, 0.5, 1.5, 2.5], dtype=torch.float64))


def test_inner_is_riemann_sum_of_integral():
    # <f, f> for f = 1 equals the area of the domain; for f(x, y) = x the integral of x^2 over [-1,1]^2 is 4/3.
    dom = ImageDomain((200, 200), (-1.0, -1.0), (1.0, 1.0))
    one = torch.ones(dom.shape, dtype=torch.float64)
    assert dom.inner(one, one).item() == pytest.approx(4.0)
    x = dom.points()[0]
    assert dom.norm(x).item() ** 2 == pytest.approx(4.0 / 3.0, rel=1e-4)


def test_3d_cells_points_and_inner():
    dom = ImageDomain((4, 6, 8), (0.0, -3.0, -2.0), (2.0, 3.0, 2.0))
    assert dom.ndim == 3 and dom.dims == (-3, -2, -1)
    assert dom.cell_sides == (0.5, 1.0, 0.5) and dom.cell_volume == 0.25
    p = dom.points()
    assert p.shape == (3, 4, 6, 8)
    assert torch.equal(p[2, 0, 0, :], torch.linspace(-1.75, 1.75, 8, dtype=torch.float64))
    # integral of z^2 over the box: 2 * 6 * (2^3 / 3 * 2 / 2) = 32, midpoint rule on z^2 is exact up to h^2/12
    z = p[2]
    assert dom.norm(z).item() ** 2 == pytest.approx(2 * 6 * (16 / 3 - 4 * 0.25 / 12), rel=1e-12)
    assert ImageDomain((4, 4, 4)).min_pt == (-16.0, -16.0, -16.0)
    assert ImageDomain.paper(8, ndim=3).shape == (8, 8, 8)


def test_3d_to_grid_matches_grid_sample_at_cell_centres():
    dom = ImageDomain((3, 5, 4), (-2.0, 0.0, 1.0), (3.0, 14.0, 2.0))
    f = torch.randn(3, 5, 4, dtype=torch.float64)
    grid = dom.to_grid(dom.points().movedim(0, -1))
    sampled = torch.nn.functional.grid_sample(f[None, None], grid[None], align_corners=False)[0, 0]
    assert torch.allclose(sampled, f, atol=1e-12)


def test_inner_keeps_batch_dims():
    dom = ImageDomain.paper(8)
    f = torch.randn(3, 2, 8, 8, dtype=torch.float64)
    out = dom.inner(f, f)
    assert out.shape == (3, 2)
    assert torch.allclose(out[1, 0], dom.cell_volume * (f[1, 0] ** 2).sum())


def test_to_grid_matches_grid_sample_at_cell_centres():
    dom = ImageDomain((5, 7), (-2.0, 0.0), (3.0, 14.0))
    f = torch.randn(5, 7, dtype=torch.float64)
    grid = dom.to_grid(dom.points().movedim(0, -1))
    sampled = torch.nn.functional.grid_sample(f[None, None], grid[None], align_corners=False)[0, 0]
    assert torch.allclose(sampled, f, atol=1e-12)


@pytest.mark.parametrize("kwargs, match", [
    (dict(shape=(0, 4)), "shape entry"),
    (dict(shape=(4, 4, 4, 4)), r"shape must have 2 entries \(nx, ny\) or 3"),
    (dict(shape=(4, 4, 4), min_pt=(0.0, 0.0)), r"min_pt must have 3 entries \(x, y, z\)"),
    (dict(shape=(4, 4), min_pt=(1.0, 0.0), max_pt=(1.0, 1.0)), "min_pt must be < max_pt"),
    (dict(shape=(4.5, 4)), "integer"),
    (dict(shape=(None, 4)), r"shape entry must be an integer >= 1, got None"),
    (dict(shape=(4, 4), min_pt=(-math.inf, 0.0)), r"min_pt must be finite, got \(-inf, 0\.0\)"),
    (dict(shape=(4, 4), max_pt=(1.0, math.inf)), "max_pt must be finite"),
    (dict(shape=(4, 4), max_pt=(math.nan, 1.0)), "max_pt must be finite"),
    (dict(shape=(4, 4), min_pt=(-1e308, 0.0), max_pt=(1e308, 1.0)), "max_pt - min_pt must be finite"),
    (dict(shape=(4, 4), min_pt="ab"), r"min_pt must be 2 finite numbers \(x, y\), got 'ab'"),
    (dict(shape=(4, 4), min_pt=(0.0, 0.0, 0.0)), "min_pt must have 2 entries"),
    # float() took "-1" and True; a string shape was iterated by characters
    (dict(shape=(4, 4), min_pt=("-1", "-1")), r"^min_pt must be 2 finite numbers \(x, y\), got \('-1', '-1'\)"),
    (dict(shape=(4, 4), max_pt=(True, 1.0)), r"^max_pt must be 2 finite numbers \(x, y\), got \(True, 1.0\)"),
    (dict(shape=(4, 4), max_pt=(1 + 0j, 1.0)), r"^max_pt must be 2 finite numbers"),
    (dict(shape="44"), r"^shape must be 2 or 3 integers \(nx, ny\[, nz\]\), got '44'"),
    (dict(shape=(True, 4)), r"^shape entry must be an integer >= 1, got True"),
])
def test_invalid_domain(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        ImageDomain(**kwargs)


def test_check_image_errors():
    dom = ImageDomain.paper(8)
    with pytest.raises(ValueError, match=r"\(\.\.\., 8, 8\)"):
        dom.check_image(torch.zeros(8, 9))
    with pytest.raises(TypeError, match="floating dtype"):
        dom.check_image(torch.zeros(8, 8, dtype=torch.int64))
    for dtype in (torch.float16, torch.bfloat16):
        with pytest.raises(TypeError, match=f"image must be float32 or float64, got {dtype}"):
            dom.check_image(torch.zeros(8, 8, dtype=dtype))
    bad = torch.zeros(8, 8)
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        dom.check_image(bad)
