"""The whole registration on a CUDA device equals the same run on the CPU (float64): 2D parallel beam, a 3D tilt
series with the velocity on a coarser grid, metamorphosis and the torch.optim solver. Skipped without a GPU
(``scripts/gpu_check.sh`` runs them where one is lent)."""
import pytest
import torch

import indreg
from indreg import noise, phantoms

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def _pair(template, data, T, **options):
    cpu = indreg.register(template, data, T, device="cpu", **options)
    gpu = indreg.register(template, data, T, device="cuda", **options)
    return cpu, gpu


def _assert_same_run(cpu, gpu, tol=1e-8):
    assert gpu.deformed.device.type == "cuda" and cpu.iterations == gpu.iterations
    for a, b in zip(cpu.history, gpu.history):
        assert b["objective"] == pytest.approx(a["objective"], rel=tol)
    torch.testing.assert_close(gpu.deformed.cpu(), cpu.deformed, rtol=tol, atol=tol * float(cpu.deformed.abs().max()))


@pytest.fixture(scope="module")
def tiny2d():
    T = indreg.RayTransform(indreg.ImageDomain.paper(32), indreg.ParallelBeamGeometry.paper(8, 46))
    return T, phantoms.get("j", T.domain), noise.add_white_noise(T(phantoms.get("v", T.domain)), 15.0, seed=0)[0]


@pytest.mark.parametrize("options", [{}, {"model": "metamorphosis"}, {"solver": "lbfgs"}],
                         ids=["lddmm", "metamorphosis", "lbfgs"])
def test_cuda_register_2d_equals_cpu(tiny2d, options):
    T, template, data = tiny2d
    _assert_same_run(*_pair(template, data, T, num_steps=4, max_iter=6, **options))


def test_cuda_register_3d_tilt_series_equals_cpu():
    domain = indreg.ImageDomain.paper(16, ndim=3)
    geometry = indreg.TiltSeriesGeometry.uniform(-60, 60, 10, det_count=16, det_min=-16.0, det_max=16.0)
    T = indreg.TiltSeriesTransform(domain, geometry)
    template, target = phantoms.shepp_logan_3d(domain), phantoms.shepp_logan_3d_swirl(domain)
    data = T(target)
    _assert_same_run(*_pair(template, data, T, num_steps=4, max_iter=4, velocity_factor=2))
