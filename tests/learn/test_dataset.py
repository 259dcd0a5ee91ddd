"""Tests of the synthetic data set (indreg/learn/dataset.py)."""
import torch

from indreg import GeodesicShooting, ImageDomain, ParallelBeamGeometry, RayTransform
from indreg.deform.kernel import GaussianKernel
from indreg.forward import fbp
from indreg.learn import SyntheticDeformationDataset
from indreg.noise import snr_db


def make(seed, n=5, **kw):
    dom = ImageDomain.paper(24)
    shoot = GeodesicShooting(dom, GaussianKernel(dom, 5.0), 4)
    T = RayTransform(dom, ParallelBeamGeometry.paper(6, 34))
    return shoot, T, SyntheticDeformationDataset(shoot, T, n, snr_db=8.0, seed=seed, batch_size=2, **kw)


def test_items_shapes_and_consistency():
    shoot, T, ds = make(0)
    assert len(ds) == 5
    item = ds[3]
    assert set(item) == {"template", "target", "data", "fbp", "momentum", "index"}
    assert item["template"].shape == item["target"].shape == item["fbp"].shape == (24, 24)
    assert item["data"].shape == (6, 34) and item["momentum"].shape == (2, 24, 24) and int(item["index"]) == 3
    assert item["template"].dtype == torch.float32
    t = ds.tensors
    target = shoot(t["momentum"].double(), t["template"].double())
    torch.testing.assert_close(t["target"], target.float())
    noise = t["data"].double() - T(target)
    torch.testing.assert_close(snr_db(T(target), noise), torch.full((5,), 8.0, dtype=torch.float64),
                               atol=1e-4, rtol=0)
    torch.testing.assert_close(t["fbp"], fbp(T, t["data"]))
    # deformations are real: the target differs from the template, velocity peaks within the requested range
    assert ((t["target"] - t["template"]).abs().amax(dim=(-2, -1)) > 0.1).all()
    vmax = shoot.kernel.apply(t["momentum"].double()).abs().amax(dim=(-3, -2, -1))
    assert ((vmax >= 1.5 - 1e-6) & (vmax <= 3.0 + 1e-6)).all()


def test_seeded():
    _, _, a = make(3, n=3)
    _, _, b = make(3, n=3)
    _, _, c = make(4, n=3)
    for k in a.tensors:
        assert torch.equal(a.tensors[k], b.tensors[k])
    assert not torch.equal(a.tensors["template"], c.tensors["template"])


def test_named_templates():
    _, _, ds = make(0, n=2, templates=["j"])
    assert torch.equal(ds.tensors["template"][0], ds.tensors["template"][1])
