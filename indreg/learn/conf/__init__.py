"""The Hydra config of ``indreg-train-momentum``, shipped with the package: ``train_momentum.yaml`` and its group
``model`` (``model=oneshot`` | ``model=unrolled``). :data:`CONFIG_DIR` is where they are (the checkout and the
installed wheel alike); the training app reads no other app's config."""
from pathlib import Path

__all__ = ["CONFIG_DIR", "CONFIG_NAME"]

#: This folder: the training app's yaml configs.
CONFIG_DIR = Path(__file__).resolve().parent
#: The app's config file, ``train_momentum.yaml``.
CONFIG_NAME = "train_momentum"
