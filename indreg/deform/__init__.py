"""LDDMM deformations: the Gaussian RKHS kernel, the deformation operator W(nu, I) (also with a velocity on a coarser
grid) and metamorphosis."""
from . import functional
from .coarse import CoarseVelocityDeformation, coarse_domain
from .kernel import GaussianKernel
from .lddmm import LDDMMDeformation
from .metamorphosis import MetamorphosisDeformation

__all__ = ["CoarseVelocityDeformation", "GaussianKernel", "LDDMMDeformation", "MetamorphosisDeformation",
           "coarse_domain", "functional"]
