"""Learned initial momenta for indirect registration (rem:AltLDDMM): network, synthetic data, loss, training."""
from .dataset import SyntheticDeformationDataset, random_momentum, random_template
from .loss import IndirectShootingLoss
from .unet import MomentumUNet

__all__ = ["IndirectShootingLoss", "MomentumUNet", "SyntheticDeformationDataset", "random_momentum",
           "random_template"]
