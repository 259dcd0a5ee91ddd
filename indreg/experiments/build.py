"""Build one indirect registration experiment (domain, data, operators, problem, solver) from its config.

The data come from the config's data source (:mod:`indreg.experiments.sources`: simulated phantoms or files), in
float64 on the CPU; only then are template and data cast to ``cfg.dtype`` / ``cfg.device``. Simulated data are
generated device- and dtype-independently (noise drawn on the CPU with the run's seed), so the same config gives
the same data everywhere. Kernel, deformation, objective and solver are built by :func:`indreg.run.setup`, the
same code as ``indreg.register`` (``indreg.run.setup``).
"""
from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np
import torch
from omegaconf import DictConfig

from .. import run
from ..options import OptionError
from . import sources
from .config import ConfigError, registration_values


@dataclass
class Experiment:
    """Everything a run needs: the source's ``data`` (:class:`sources.Data`, float64 on the CPU), the ``setup``
    (``indreg.run.Setup``: problem, solver, resolved options, units, validation) and the inputs as the run uses
    them: ``template`` in the run's dtype / device, ``template_64`` / ``noisy_data_64`` in float64 on the CPU for
    metrics, baselines and figures (both through ``setup.units.apply``, the one transformation of the inputs).
    The source's and the setup's fields read through (``exp.domain``, ``exp.problem``, ...)."""
    data: sources.Data
    setup: run.Setup
    template: torch.Tensor
    template_64: torch.Tensor
    noisy_data_64: torch.Tensor

    domain = property(lambda self: self.data.domain)
    geometry = property(lambda self: self.data.geometry)
    ray_transform = property(lambda self: self.data.operator)
    label = property(lambda self: self.data.label)
    target_64 = property(lambda self: self.data.target_64)
    clean_data_64 = property(lambda self: self.data.clean_64)
    snr_db = property(lambda self: self.data.snr_db)
    paper = property(lambda self: self.data.paper)
    report = property(lambda self: self.data.report)
    targets = property(lambda self: self.data.targets)
    problem = property(lambda self: self.setup.problem)
    solver = property(lambda self: self.setup.solver)
    options = property(lambda self: self.setup.options)
    units = property(lambda self: self.setup.units)
    validation = property(lambda self: self.setup.validation)


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def build(cfg: DictConfig) -> Experiment:
    """The data source's data and operator, then kernel, problem and solver (``indreg.run.setup``, the same code
    as ``indreg.register``, with the config's registration options; errors name the config key)."""
    dtype = getattr(torch, cfg.dtype.value)
    device = run.resolve_device(cfg.device)
    data = sources.load(cfg)
    template = data.template_64.to(dtype=dtype, device=device)
    g = data.data_64.to(dtype=dtype, device=device)
    try:
        s = run.setup(template if data.template_known else None, g, data.operator, label=lambda o: o.config_key,
                      strict=False, dtype=dtype, device=device, **registration_values(cfg))
    except OptionError as e:
        raise ConfigError(f"invalid config value {e.label}={e.value!r}: expected {e.expected}") from None
    template_64, data_64 = s.units.apply(data.template_64, data.data_64)
    return Experiment(data=data, setup=s, template=s.units.apply(template, g)[0], template_64=template_64,
                      noisy_data_64=data_64)
