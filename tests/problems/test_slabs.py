"""Slab-wise data term (indreg.problems.slabs): the whole-volume gradient, slab by slab and across processes."""
import pytest
import torch

import indreg
from indreg import ImageDomain
from indreg.deform import CoarseVelocityDeformation, GaussianKernel, LDDMMDeformation, coarse_domain
from indreg.deform.functional import upsample, upsample_adjoint
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.forward.ray_transform import matmul_columns
from indreg.problems import IndirectRegistration
from indreg.problems.slabs import (SlabwiseRegistration, choose_slab_size, slab_ranges, slab_refusal,
                                   upsample_rows, upsample_rows_adjoint)


def _parts(shape=(16, 12, 8), factor=2, action="geometric", tilt_axis="y", num_steps=3, dtype=torch.float64,
           seed=0):
    """A small tilt-series problem (random template and data) and a momentum that moves it by a few cells."""
    gen = torch.Generator().manual_seed(seed)
    domain = ImageDomain(shape, (-8.0, -6.0, -4.0), (8.0, 6.0, 4.0))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 20, det_count=20, tilt_axis=tilt_axis))
    coarse = coarse_domain(domain, factor)
    W = CoarseVelocityDeformation(domain, coarse, num_steps=num_steps, action=action)
    K = GaussianKernel(coarse, 2.0)
    template = torch.rand(shape, generator=gen, dtype=dtype)
    data = torch.rand(T.range_shape, generator=gen, dtype=dtype) * 4
    m = torch.randn(num_steps + 1, 3, *coarse.shape, generator=gen, dtype=dtype)
    m *= 1.5 / float(K.apply(m).abs().max())
    return (T, W, K, template, data, 1e-3), m


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("start,stop", [(0, 12), (0, 1), (3, 7), (11, 12)])
def test_upsample_rows_are_rows_of_upsample_and_adjoint(axis, start, stop):
    gen = torch.Generator().manual_seed(2)
    coarse, fine = (6, 4, 3), [16, 12, 9]
    fine[axis] = 12
    f = torch.randn(3, *coarse, generator=gen, dtype=torch.float64)
    whole = upsample(f, tuple(fine)).narrow(axis + 1, start, stop - start)
    rows = upsample_rows(f, tuple(fine), axis, start, stop)
    torch.testing.assert_close(rows, whole, rtol=0, atol=1e-14)
    g = torch.randn(rows.shape, generator=gen, dtype=torch.float64)
    lhs = float((rows * g).sum())
    rhs = float((f * upsample_rows_adjoint(g, coarse, tuple(fine), axis, start, stop)).sum())
    assert lhs == pytest.approx(rhs, rel=1e-13)


@pytest.mark.parametrize("action", ["geometric", "mass_preserving"])
@pytest.mark.parametrize("tilt_axis", ["y", "x"])
@pytest.mark.parametrize("slab_size", [1, 3, 5, 12])
def test_slabwise_gradient_equals_the_whole_volume_one(action, tilt_axis, slab_size):
    args, m = _parts(action=action, tilt_axis=tilt_axis)
    whole = IndirectRegistration(*args)
    slabs = SlabwiseRegistration(*args, slab_size=slab_size)
    terms_w, h_w, _ = whole.l2_gradient(m)
    terms_s, h_s, _ = slabs.l2_gradient(m)
    assert terms_w["data_fit"] > 10 * terms_w["regulariser"] > 0
    for key in ("objective", "data_fit", "regulariser"):
        assert terms_s[key] == pytest.approx(terms_w[key], rel=1e-12)
    assert float((h_s - h_w).norm() / h_w.norm()) < 1e-12
    assert slabs.evaluate(m)["objective"] == pytest.approx(whole.evaluate(m)["objective"], rel=1e-12)
    torch.testing.assert_close(slabs.deformed(m), whole.deformed(m), rtol=0, atol=1e-12)
    torch.testing.assert_close(slabs.trajectory(m), whole.trajectory(m), rtol=0, atol=1e-12)
    frames = list(slabs.image_frames((m,)))   # one frame at a time: the trajectory's frames, bit for bit
    assert len(frames) == m.shape[0] and torch.equal(torch.stack(frames), slabs.trajectory(m))
    assert torch.is_grad_enabled()


@pytest.mark.parametrize("block_bytes", [8, 200])
def test_slabwise_gradient_with_the_projector_in_column_blocks(monkeypatch, block_bytes):
    """With the slab's slices outgrowing ``COLUMN_BLOCK_BYTES`` the projector runs by blocks of columns (1 and 5
    pixels a block for 5 slices of 16 x 8 in float64): the whole-volume gradient still, to 1e-12."""
    from indreg.problems import slabs as module

    monkeypatch.setattr(module, "COLUMN_BLOCK_BYTES", block_bytes)
    args, m = _parts()
    calls = []
    monkeypatch.setattr(module, "matmul_columns", lambda blocks, x: calls.append(len(blocks))
                        or matmul_columns(blocks, x))
    terms_w, h_w, _ = IndirectRegistration(*args).l2_gradient(m)
    terms_s, h_s, _ = SlabwiseRegistration(*args, slab_size=5).l2_gradient(m)
    assert calls and set(calls) == {-(-16 * 8 // max(1, block_bytes // 40))}
    assert terms_s["objective"] == pytest.approx(terms_w["objective"], rel=1e-12)
    assert float((h_s - h_w).norm() / h_w.norm()) < 1e-12


@pytest.mark.parametrize("threads", [1, 2])
def test_slabwise_gradient_float32_any_thread_count(threads):
    """float32, the plane-wise sampler (one thread) or grid_sample's row bands (two): the whole path's gradient
    to float rounding."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        args, m = _parts(shape=(16, 16, 8), dtype=torch.float32)
        _, h_w, _ = IndirectRegistration(*args).l2_gradient(m)
        _, h_s, _ = SlabwiseRegistration(*args, slab_size=5).l2_gradient(m)
    finally:
        torch.set_num_threads(before)
    assert h_s.dtype == torch.float32
    assert float((h_s - h_w).norm() / h_w.norm()) < 1e-5


def _tilt_series_inputs(n=16, num_tilts=11):
    domain = ImageDomain.paper(n, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 120 / (num_tilts - 1), det_count=n,
                                                               det_min=-16.0, det_max=16.0))
    template = indreg.phantoms.get("shepp_logan_3d", domain)
    return T, template, T(indreg.phantoms.get("shepp_logan_3d_swirl", domain))


RUN = {"velocity_factor": 2, "sigma": 3.0, "num_steps": 3, "max_iter": 3, "dtype": torch.float64}


def test_register_slabwise_equals_whole_volume():
    T, template, data = _tilt_series_inputs()
    whole = indreg.register(template, data, T, **RUN)
    assert type(whole.problem) is IndirectRegistration          # the default: whole-volume where it fits
    slabs = indreg.register(template, data, T, slab_size=3, **RUN)
    assert isinstance(slabs.problem, SlabwiseRegistration) and len(slabs.problem.slab_ranges) == 6
    assert slabs.objective == pytest.approx(whole.objective, rel=1e-10)
    torch.testing.assert_close(slabs.momentum, whole.momentum, rtol=0, atol=1e-10 * float(whole.momentum.abs().max()))
    torch.testing.assert_close(slabs.deformed, whole.deformed, rtol=0, atol=1e-10)
    tight = indreg.register(template, data, T, max_memory=10 * 16 ** 3 * 8, **RUN)   # 10 scalars a voxel
    assert isinstance(tight.problem, SlabwiseRegistration) and tight.problem.slab_size < 16


def test_choose_slab_size_from_the_memory_bound():
    shape = (1024, 256, 1024)
    assert choose_slab_size(shape, 1, 4, max_memory=64 * 2 ** 30) == 256             # a whole gradient fits
    s = choose_slab_size(shape, 1, 4, max_memory=8 * 2 ** 30)
    assert 1 <= s < 256 and 2 * 4 * 2 ** 28 + s * 20 * 4 * 2 ** 20 <= 8 * 2 ** 30
    assert choose_slab_size(shape, 1, 4, max_memory=1) == 1
    assert slab_ranges(10, 4) == [(0, 4), (4, 8), (8, 10)]


@pytest.mark.parametrize("change, options, match", [
    ("operator", {"slab_size": 4},
     r"slab_size must be None here: .* ScaledOperator is not a single-axis tilt series.*got 4"),
    ("velocity_factor", {"slab_size": 4}, "no coarse velocity grid"),
    ("tv", {"slab_size": 4}, "TV term couples neighbouring slices"),
    ("lbfgs", {"slab_size": 4}, "solver 'lbfgs' differentiates by autograd"),
])
def test_a_split_that_cannot_be_made_is_one_line(change, options, match):
    T, template, data = _tilt_series_inputs(8, 5)
    run = dict(RUN, max_iter=1)
    if change == "operator":
        T = 2.0 * T
    elif change == "velocity_factor":
        run["velocity_factor"] = 1
    elif change == "tv":
        run["tv_weight"] = 0.1
    else:
        run["solver"] = "lbfgs"
    with pytest.raises(ValueError, match=match) as e:
        indreg.register(template, data, T, **options, **run)
    assert "\n" not in str(e.value)
    assert type(indreg.register(template, data, T, max_memory=1, **run).problem) is not SlabwiseRegistration


def test_refusals_and_bad_slab_size():
    args, _ = _parts()
    assert slab_refusal(args[0], args[1]) is None
    assert "backward is 'autograd'" in slab_refusal(args[0], args[1].replace(backward="autograd"))
    assert "no coarse velocity grid" in slab_refusal(args[0], LDDMMDeformation(args[0].domain, 3))
    with pytest.raises(ValueError, match="slab_size must be an integer >= 1"):
        SlabwiseRegistration(*args, slab_size=0)
    with pytest.raises(ValueError, match="cannot be evaluated slab-wise: tv_weight > 0"):
        SlabwiseRegistration(*args, tv_weight=0.1, slab_size=2)


def test_one_process_has_no_group(monkeypatch):
    """``distributed`` None or True without torchrun (``WORLD_SIZE`` unset or 1): one process, no group."""
    from indreg.problems.slabs import process_group
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert process_group(None, "cpu") is None and process_group(True, "cpu") is None
    assert process_group(False, "cpu") is None
    args, _ = _parts()
    p = SlabwiseRegistration(*args, slab_size=5)
    assert (p.rank, p.world, list(p.own)) == (0, 1, [0, 1, 2]) and p.slab_ranges == [(0, 5), (5, 10), (10, 12)]
    assert p.allreduce_bytes == (3 * 8 * 6 * 4 + 1) * 8


def test_ranks_own_contiguous_balanced_shares():
    from indreg.problems.slabs import _share
    for count, world in ((7, 3), (8, 2), (5, 5), (64, 8)):
        shares = [_share(count, r, world) for r in range(world)]
        assert [i for s in shares for i in s] == list(range(count))
        assert max(map(len, shares)) - min(map(len, shares)) <= 1
