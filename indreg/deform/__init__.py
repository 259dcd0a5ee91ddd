"""LDDMM deformations: the Gaussian RKHS kernel, the deformation operator W(nu, I) and metamorphosis."""
from . import functional
from .kernel import GaussianKernel
from .lddmm import LDDMMDeformation
from .metamorphosis import MetamorphosisDeformation

__all__ = ["GaussianKernel", "LDDMMDeformation", "MetamorphosisDeformation", "functional"]
