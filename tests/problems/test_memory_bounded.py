"""What keeps a slab-wise registration within ``max_memory`` outside its loop: every piece gives the whole-volume
numbers (the deformation field and the residual slab by slab, the tilt series projected in chunks, the probe on the
operator's own system matrix, the chunked finiteness check), and the result leaves out, in one line each, the
volumes that do not fit."""
import logging

import pytest
import torch

from indreg import _checks
from indreg.forward import tilt_series
from indreg.problems import IndirectRegistration
from indreg.problems.slabs import SlabwiseRegistration
from indreg.registration.budget import result_pieces

from test_slabs import _parts


@pytest.mark.parametrize("tilt_axis", ["x", "y"])
def test_slabwise_deformation_field_and_residual_equal_the_whole_volume_ones(tilt_axis):
    args, m = _parts(tilt_axis=tilt_axis)
    whole, slabs = IndirectRegistration(*args), SlabwiseRegistration(*args, slab_size=5)
    nu = whole.velocity(m)
    torch.testing.assert_close(slabs.deformation_field(nu), whole.deformation_field(nu), rtol=0, atol=1e-12)
    points = whole.image_domain.points(torch.float64)
    torch.testing.assert_close(whole.deformation_field(torch.zeros_like(nu)), points, rtol=0, atol=1e-14)
    assert slabs.relative_residual((m,)) == pytest.approx(whole.relative_residual((m,)), rel=1e-12)


@pytest.mark.parametrize("tilt_axis", ["y", "z"])
def test_a_tilt_series_is_projected_in_chunks_to_the_same_numbers(monkeypatch, tilt_axis):
    args, _ = _parts(tilt_axis=tilt_axis)
    T, f = args[0], args[3].clone().requires_grad_(True)
    whole = T(f)
    (g,) = torch.autograd.grad((whole * 1.5).sum(), f)
    monkeypatch.setattr(tilt_series, "COPY_CHUNK_BYTES", 2 * 8 * 16 * 12)   # two slices a chunk
    chunked = T(f)
    torch.testing.assert_close(chunked, whole, rtol=1e-13, atol=1e-13)   # to rounding (the summation's order)
    (g2,) = torch.autograd.grad((chunked * 1.5).sum(), f)
    torch.testing.assert_close(g2, g, rtol=1e-13, atol=1e-13)


def test_on_rows_shares_the_system_matrix_and_projects_alike():
    from indreg import ImageDomain

    args, _ = _parts()
    T, f = args[0], args[3]
    d = T.domain
    rows = ImageDomain((16, 5, 8), (-8.0, -2.5, -4.0), (8.0, 2.5, 4.0))   # 5 of the 12 slices along y
    small = T.on_rows(rows)
    assert small.system is T.system
    torch.testing.assert_close(small(f[:, 3:8]), T(f)[:, 3:8], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="on_rows needs a 3D domain with the slices"):
        T.on_rows(ImageDomain((14, 5, 8), d.min_pt, d.max_pt))


@pytest.mark.parametrize("make", [lambda t: t, lambda t: t.transpose(0, 2), lambda t: t.permute(1, 2, 0)])
def test_all_finite_in_chunks(monkeypatch, make):
    monkeypatch.setattr(_checks, "FINITE_CHUNK", 10)
    base = torch.ones(7, 5, 3)
    assert _checks.all_finite(make(base))
    for index in ((0, 0, 0), (6, 4, 2), (3, 2, 1)):
        bad = base.clone()
        bad[index] = float("nan")
        assert not _checks.all_finite(make(bad))


def test_the_result_keeps_what_fits_and_names_what_does_not(caplog):
    args, m = _parts()
    slabs = SlabwiseRegistration(*args, slab_size=5)
    assert result_pieces(slabs, True) == (True, True)              # half the free memory: everything fits
    from indreg.registration.budget import _held

    v = slabs.volume_bytes()
    slabs.max_memory = _held(slabs) + v + 3 * v + v // 2     # the reconstruction and phi fit, 4 frames do not
    with caplog.at_level(logging.INFO, logger="indreg"):
        assert result_pieces(slabs, True) == (True, False)
        slabs.max_memory = _held(slabs) + 2 * v
        assert result_pieces(slabs, True) == (False, False)
    lines = [r.getMessage() for r in caplog.records]
    assert sum("the trajectory is not kept in the result: it needs" in line for line in lines) == 2
    assert sum("the deformation phi_(1,0) is not kept" in line for line in lines) == 1
    assert result_pieces(IndirectRegistration(*args), True) == (True, True)   # the whole-volume path: no bound
