"""A simulated tilt series built over ranks (``indreg.experiments.split_setup``, gloo processes): every rank's
template and data, and rank 0's target, equal one process's phantoms and projection; the phantoms and the projector
by rows equal the rows of the whole (to rounding: a cell's mean may sum in another order)."""
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from indreg import ImageDomain, phantoms
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform

DOMAIN = ImageDomain((12, 10, 8), (-12.0, -10.0, -8.0), (12.0, 10.0, 8.0))   # uneven: 10 rows over 3 ranks


def _transform(tilt_axis):
    return TiltSeriesTransform(DOMAIN, TiltSeriesGeometry.uniform(-60, 60, 30, det_count=14, tilt_axis=tilt_axis))


def _rank(rank, world, store, tilt_axis, out):
    from indreg.experiments import split_setup
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    try:
        T = _transform(tilt_axis)
        template, target, clean = split_setup.simulated_rows("shepp_logan_3d", "shepp_logan_3d_swirl", T,
                                                             dist.group.WORLD)
        torch.save({"template": template, "target": target, "clean": clean,
                    "rows": split_setup.row_range(DOMAIN.shape[T.geometry.axis], dist.group.WORLD)},
                   f"{out}.{rank}")
    finally:
        dist.destroy_process_group()


@pytest.mark.parametrize("world, tilt_axis", [(2, "y"), pytest.param(3, "y", marks=pytest.mark.slow),
                                              pytest.param(3, "x", marks=pytest.mark.slow)])
def test_ranks_build_the_one_process_data(tmp_path, world, tilt_axis):
    out = tmp_path / "rank"
    mp.spawn(_rank, args=(world, tmp_path / "store", tilt_axis, out), nprocs=world)
    T = _transform(tilt_axis)
    target = phantoms.get("shepp_logan_3d_swirl", DOMAIN)
    whole = {"template": phantoms.get("shepp_logan_3d", DOMAIN), "target": target, "clean": T(target)}
    got = [torch.load(f"{out}.{r}") for r in range(world)]
    n = DOMAIN.shape[T.geometry.axis]
    assert [g["rows"] for g in got][0][0] == 0 and got[-1]["rows"][1] == n
    assert all(a["rows"][1] == b["rows"][0] for a, b in zip(got, got[1:]))             # contiguous shares
    for r, g in enumerate(got):
        for name in ("template", "clean"):
            torch.testing.assert_close(g[name], whole[name], rtol=1e-14, atol=1e-14)
        assert (g["target"] is None) == (r != 0)
    torch.testing.assert_close(got[0]["target"], whole["target"], rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_phantom_rows_are_rows_of_the_whole(axis):
    whole = phantoms.get("shepp_logan_3d_swirl", DOMAIN)
    n = DOMAIN.shape[axis]
    parts = [phantoms.get("shepp_logan_3d_swirl", DOMAIN, rows=(axis, a, b)) for a, b in ((0, 3), (3, 4), (4, n))]
    torch.testing.assert_close(torch.cat(parts, axis), whole, rtol=0, atol=1e-15)   # cell means: sums in another order


@pytest.mark.parametrize("tilt_axis", ["x", "y", "z"])
def test_projected_rows_are_rows_of_the_projection(tilt_axis):
    T = _transform(tilt_axis)
    f = torch.rand(DOMAIN.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    a, n = T.geometry.axis, DOMAIN.shape[T.geometry.axis]
    rows = torch.cat([T.project_rows(f.narrow(a, 0, 3)), T.project_rows(f.narrow(a, 3, n - 3))], 1)
    torch.testing.assert_close(rows, T(f), rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("rows, match", [((1, 4, 4), "0 <= start < stop"), ((3, 0, 2), "axis 0, 1 or 2"),
                                         ((1, 0, 11), "0 <= start < stop"), ([1, 0, 2], "a tuple")])
def test_bad_rows_are_one_line(rows, match):
    with pytest.raises(ValueError, match=match):
        phantoms.get("shepp_logan_3d", DOMAIN, rows=rows)


def test_rows_of_a_2d_phantom_are_refused():
    with pytest.raises(ValueError, match="only the 3D phantoms"):
        phantoms.get("j", ImageDomain.paper(16), rows=(0, 0, 4))


def test_bad_projected_rows_are_one_line():
    with pytest.raises(ValueError, match=r"volume rows must be .* along the tilt axis y, got \(12, 10\)"):
        _transform("y").project_rows(torch.zeros(12, 10))
