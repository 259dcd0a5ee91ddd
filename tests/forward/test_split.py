"""Baselines split into slabs along the tilt axis (indreg.forward.split): slab by slab in one process and over two
gloo processes, equal to the whole volume in float64."""
import os

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform, fbp, sirt, tv_reconstruction
from indreg.forward.split import (SlabSplit, SlabTransform, by_slabs, gather_rows, own_rows, rank_rows,
                                  slab_transforms, split_rows)
from indreg.forward.tv import divergence, gradient, intensity_scale

TV = dict(mu=0.05, num_iter=30, opnorm_iter=20, nonneg=True)


def _problem(tilt_axis="y", shape=(12, 13, 10)):
    """A small tilt series (an odd number of slices along y: unequal shares) and noisy data of a random volume."""
    gen = torch.Generator().manual_seed(0)
    domain = ImageDomain(shape, (-6.0, -6.5, -5.0), (6.0, 6.5, 5.0))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 15, det_count=16, tilt_axis=tilt_axis))
    x = torch.rand(shape, generator=gen, dtype=torch.float64)
    y = T(x) + 0.1 * torch.randn(T.range_shape, generator=gen, dtype=torch.float64)
    return T, y


def _close(a, b, rtol=1e-10):
    torch.testing.assert_close(a, b, rtol=rtol, atol=rtol * float(b.abs().max()))


@pytest.mark.parametrize("tilt_axis", ["x", "y", "z"])
def test_slab_transform_is_the_rows_of_the_whole(tilt_axis):
    T, y = _problem(tilt_axis)
    x = torch.rand(T.domain.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    slabs = slab_transforms(T, 5)
    n = T.domain.shape[T.geometry.axis]
    assert [(s.split.start, s.split.stop) for s in slabs] == [(a, min(a + 5, n)) for a in range(0, n, 5)]
    for Ts in slabs:
        assert Ts.domain.cell_sides == T.domain.cell_sides and Ts.adjoint_scale == T.adjoint_scale
        _close(Ts(own_rows(x, Ts.domain)), Ts.data_rows(T(x)), 1e-14)
        _close(Ts.adjoint(Ts.data_rows(y)), own_rows(T.adjoint(y), Ts.domain), 1e-14)
        assert Ts.slice_transform is T.slice_transform                       # the projector is shared


@pytest.mark.parametrize("tilt_axis", ["x", "y", "z"])
def test_fbp_and_sirt_slab_by_slab_equal_the_whole_volume(tilt_axis):
    T, y = _problem(tilt_axis)
    _close(by_slabs(fbp, T, y, 4), fbp(T, y))
    run = lambda op, data: sirt(op, data, num_iter=8, nonneg=True)[0]   # noqa: E731
    _close(by_slabs(run, T, y, 4), run(T, y))
    batch = torch.stack([y, 2 * y])                                          # batch dims kept
    _close(by_slabs(fbp, T, batch, 6), fbp(T, batch))


def test_bad_splits_are_one_line():
    T, _ = _problem()
    with pytest.raises(ValueError, match="slab_size must be an integer >= 1"):
        slab_transforms(T, 0)
    with pytest.raises(TypeError, match="needs a TiltSeriesTransform"):
        slab_transforms(RayTransform(ImageDomain.paper(8), ParallelBeamGeometry(4, 12)), 2)
    with pytest.raises(ValueError, match="does not cut the tilt axis"):
        SlabTransform(T, SlabSplit(12, 0, 0, 4))


def test_rank_rows_are_contiguous_balanced_shares():
    assert [rank_rows(13, r, 3) for r in range(3)] == [(0, 5), (5, 9), (9, 13)]
    assert [rank_rows(4, r, 4) for r in range(4)] == [(0, 1), (1, 2), (2, 3), (3, 4)]


# ------------------------------------------------------------------------------------------------- two processes
def _on_rank(rank, body, world, store, out):
    """``body(T, y, Ts)`` (the whole problem and this rank's split of it) in a gloo group of ``world`` ranks; what it
    returns saved as ``out/rank{rank}.pt``."""
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    try:
        T, y = _problem()
        torch.save(body(T, y, split_rows(T, dist.group.WORLD)), os.path.join(out, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


def _two_ranks_body(T, y, Ts):
    """One rank: its rows of FBP, SIRT and TV and of the gradient / divergence of random fields, gathered on 0."""
    ys = Ts.data_rows(y)
    gen = torch.Generator().manual_seed(2)
    f = torch.randn(T.domain.shape, generator=gen, dtype=torch.float64)
    p = torch.randn(3, *T.domain.shape, generator=gen, dtype=torch.float64)
    x_sirt, h_sirt = sirt(Ts, ys, num_iter=8, nonneg=True)
    x_tv, h_tv = tv_reconstruction(Ts, ys, **TV)
    g, d = gradient(own_rows(f, Ts.domain), Ts.domain), divergence(own_rows(p, Ts.domain), Ts.domain)
    return {"rows": (Ts.split.start, Ts.split.stop), "fbp": gather_rows(fbp(Ts, ys), Ts),
            "sirt": gather_rows(x_sirt, Ts), "sirt_history": h_sirt, "tv": gather_rows(x_tv, Ts),
            "tv_history": h_tv, "gradient": gather_rows(g, Ts), "divergence": gather_rows(d, Ts),
            "intensity_scale": intensity_scale(Ts, ys),
            "adjoint": (Ts.domain.inner(g, own_rows(p, Ts.domain)).sum(), Ts.domain.inner(own_rows(f, Ts.domain), d))}


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory):
    out = tmp_path_factory.mktemp("ranks")
    mp.start_processes(_on_rank, args=(_two_ranks_body, 2, str(out / "store"), str(out)), nprocs=2,
                       start_method="spawn")
    return [torch.load(out / f"rank{r}.pt", weights_only=False) for r in range(2)]


def test_two_ranks_fbp_sirt_tv_equal_one_process(two_ranks):
    zero, one = two_ranks
    assert zero["rows"] == (0, 7) and one["rows"] == (7, 13)
    assert one["fbp"] is None and one["tv"] is None                         # gathered on rank 0 only
    T, y = _problem()
    _close(zero["fbp"], fbp(T, y))
    x, hist = sirt(T, y, num_iter=8, nonneg=True)
    _close(zero["sirt"], x)
    for key in ("residual", "data_residual"):
        _close(zero["sirt_history"][key], hist[key])
        assert torch.equal(one["sirt_history"][key], zero["sirt_history"][key])   # every rank the same
    x, hist = tv_reconstruction(T, y, **TV)
    _close(zero["tv"], x)
    _close(zero["tv_history"]["objective"], hist["objective"])
    assert zero["tv_history"]["opnorm"] == pytest.approx(hist["opnorm"], rel=1e-12)
    assert torch.equal(one["tv_history"]["objective"], zero["tv_history"]["objective"])
    assert zero["intensity_scale"] == one["intensity_scale"] == pytest.approx(intensity_scale(T, y), rel=1e-12)


def test_two_ranks_gradient_and_divergence_across_the_split(two_ranks):
    """The one-slice halo: the whole volume's differences, and ``<grad f, p> = -<f, div p>`` over the ranks."""
    zero, one = two_ranks
    T, _ = _problem()
    gen = torch.Generator().manual_seed(2)
    f = torch.randn(T.domain.shape, generator=gen, dtype=torch.float64)
    p = torch.randn(3, *T.domain.shape, generator=gen, dtype=torch.float64)
    _close(zero["gradient"], gradient(f, T.domain), 1e-14)
    _close(zero["divergence"], divergence(p, T.domain), 1e-14)
    lhs, rhs = zero["adjoint"]
    assert float(lhs) == pytest.approx(-float(rhs), rel=1e-12)
    assert float(lhs) == pytest.approx(float(T.domain.inner(gradient(f, T.domain), p).sum()), rel=1e-12)
    assert torch.equal(one["adjoint"][0], lhs)


def _three_ranks_body(T, y, Ts):
    """A middle rank sends and receives in each halo: the differences and a short TV over three ranks."""
    f = torch.randn(2, *T.domain.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    g = gradient(own_rows(f, Ts.domain), Ts.domain)                          # batch dims too
    x, hist = tv_reconstruction(Ts, Ts.data_rows(y), **dict(TV, num_iter=5))
    return {"rows": (Ts.split.start, Ts.split.stop), "gradient": gather_rows(g, Ts),
            "divergence": gather_rows(divergence(g, Ts.domain), Ts), "tv": gather_rows(x, Ts), "history": hist}


@pytest.mark.slow
def test_three_ranks_halo_and_tv(tmp_path):
    mp.start_processes(_on_rank, args=(_three_ranks_body, 3, str(tmp_path / "store"), str(tmp_path)), nprocs=3,
                       start_method="spawn")
    res = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in range(3)]
    assert [r["rows"] for r in res] == [(0, 5), (5, 9), (9, 13)]
    T, y = _problem()
    f = torch.randn(2, *T.domain.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    g = gradient(f, T.domain)
    _close(res[0]["gradient"], g, 1e-14)
    _close(res[0]["divergence"], divergence(g, T.domain), 1e-14)
    x, hist = tv_reconstruction(T, y, **dict(TV, num_iter=5))
    _close(res[0]["tv"], x)
    _close(res[1]["history"]["objective"], hist["objective"])
