"""Experiment plumbing: Hydra structured configs, the ``indreg-register`` app, TensorBoard, figures, checkpoints.

Importing this package is cheap; the app lives in :mod:`indreg.experiments.register`.
"""
