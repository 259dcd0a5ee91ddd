"""A tiny batched indirect problem for the unrolled schemes' tests (test_unrolled.py, test_descent.py)."""
import torch

from indreg import GeodesicShooting, ImageDomain, IndirectShootingLoss, ParallelBeamGeometry, RayTransform
from indreg.deform.kernel import GaussianKernel


def small_problem(n=8, angles=3, num_steps=2, batch=2, seed=0):
    dom = ImageDomain.paper(n)
    T = RayTransform(dom, ParallelBeamGeometry.paper(angles, 12 if n == 8 else 24))
    loss = IndirectShootingLoss(GeodesicShooting(dom, GaussianKernel(dom, 5.0), num_steps), T, gamma=1e-2)
    gen = torch.Generator().manual_seed(seed)
    template = torch.rand(batch, n, n, generator=gen, dtype=torch.float64)
    fbp = torch.rand(batch, n, n, generator=gen, dtype=torch.float64)
    data = T(torch.rand(batch, n, n, generator=gen, dtype=torch.float64))
    return loss, template, fbp, data
