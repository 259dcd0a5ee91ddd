"""Learned initial momenta for indirect registration (rem:AltLDDMM): networks (one-shot and unrolled), synthetic
data, loss, training."""
from .dataset import SyntheticDeformationDataset, random_momentum, random_template
from .loss import IndirectShootingLoss
from .unet import MomentumUNet
from .unrolled import UnrolledMomentum, indirect_gradient

__all__ = ["IndirectShootingLoss", "MomentumUNet", "SyntheticDeformationDataset", "UnrolledMomentum",
           "indirect_gradient", "random_momentum", "random_template"]
