"""The experiment apps' Hydra configs (yaml), shipped with the package; see README.md in this folder."""
