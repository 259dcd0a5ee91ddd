"""The experiment apps' Hydra configs (yaml), shipped with the package; see README.md in this folder.

:data:`CONFIG_DIR` is where they are (one source of truth for the checkout and the installed wheel): the apps find
it here without importing each other."""
from pathlib import Path

__all__ = ["CONFIG_DIR"]

#: This folder: the apps' yaml configs (the checkout's top-level ``configs`` is a link to it).
CONFIG_DIR = Path(__file__).resolve().parent
