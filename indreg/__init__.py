"""indreg: indirect image registration with large diffeomorphic deformations (LDDMM) in PyTorch."""
from .domain import ImageDomain

__all__ = ["ImageDomain"]
__version__ = "0.1.0"
