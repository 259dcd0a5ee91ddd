"""LDDMM deformations: the Gaussian RKHS kernel and the deformation operator W(nu, I)."""
from . import functional
from .kernel import GaussianKernel
from .lddmm import LDDMMDeformation

__all__ = ["GaussianKernel", "LDDMMDeformation", "functional"]
