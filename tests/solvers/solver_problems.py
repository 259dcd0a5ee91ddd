"""Small indirect registration problems built from the real pieces (32^2, N = 5, float64)."""
import torch

from indreg import ImageDomain, phantoms
from indreg.deform.kernel import GaussianKernel
from indreg.deform.lddmm import LDDMMDeformation
from indreg.forward import ParallelBeamGeometry, RayTransform
from indreg.solvers import IndirectRegistration

N = 5


def make_problem(n=32, num_steps=N, action="geometric", backward="paper", gamma=1e-6, sigma=6.0,
                 tv_weight=0.0, dtype=torch.float64):
    """Suite-1-like problem: J -> V, 10 angles (ODL partition), noise-free data."""
    dom = ImageDomain.paper(n)
    T = RayTransform(dom, ParallelBeamGeometry.paper(10, int(round(n * 92 / 64))))
    K = GaussianKernel(dom, sigma)
    W = LDDMMDeformation(dom, num_steps=num_steps, action=action, backward=backward)
    template = phantoms.get("j", dom).to(dtype)
    data = T(phantoms.get("v", dom).to(dtype))
    return IndirectRegistration(T, W, K, template, data, gamma, tv_weight=tv_weight)


def smooth_momentum(problem, scale=0.5, seed=0):
    """A momentum whose velocity ``K m`` moves pixels by about ``scale`` cells over [0, 1]."""
    gen = torch.Generator().manual_seed(seed)
    m = torch.randn(problem.momentum_shape, generator=gen, dtype=torch.float64).to(problem.template.dtype)
    nu = problem.velocity(m)
    h = problem.domain.cell_sides[0]
    return m * (scale * h / float(nu.abs().max()))
