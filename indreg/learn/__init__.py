"""Learned initial momenta for indirect registration (rem:AltLDDMM): networks (one-shot and unrolled), synthetic
data, loss, training."""
from .dataset import SyntheticDeformationDataset, random_momentum, random_template
from .descent import UnrolledDescent, descent_gradient, descent_terms
from .loss import IndirectShootingLoss
from .unet import MomentumUNet
from .unrolled import UnrolledMomentum, indirect_gradient

__all__ = ["IndirectShootingLoss", "MomentumUNet", "SyntheticDeformationDataset", "UnrolledDescent", "UnrolledMomentum",
           "descent_gradient", "descent_terms", "indirect_gradient", "random_momentum", "random_template"]
