"""Build one indirect registration experiment (domain, data, operators, problem, solver) from its config.

The data come from the config's data source (:mod:`indreg.experiments.sources`: simulated phantoms or files), in
float64 on the CPU; only then are template and data cast to ``cfg.dtype`` / ``cfg.device``. Simulated data are
generated device- and dtype-independently (noise drawn on the CPU with the run's seed), so the same config gives
the same data everywhere. Kernel, deformation, objective and solver are built by :func:`indreg.run.setup`, the
same code as ``indreg.register`` (``indreg.run.setup``).
"""
from __future__ import annotations

import random
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch
from omegaconf import DictConfig

from .. import run
from ..domain import ImageDomain
from ..options import OptionError
from . import sources
from .config import ConfigError, registration_values


@dataclass
class Experiment:
    """Everything a run needs. Images ``(nx, ny)``, data ``(num_angles, det_count)``: float64 on the CPU
    (``*_64``, for metrics and figures); ``template`` and the problem's data in the run's dtype / device.
    ``target_64``, ``clean_data_64`` and ``snr_db`` are ``None`` for measured data without a ground truth.
    ``template_64`` / ``noisy_data_64`` are the inputs as the run uses them (``units``: the template's scale and
    the data's background, ``indreg.run.prepare``); ``paper``: the paper's simulated suites (``psnr_paper``);
    ``validation`` the held-out angles (``validation.holdout``) or None; ``report``: the data's numbers for
    metrics.json (``sources.Data.report``); ``targets``: ground truths of the model's outputs (``sources.Data``)."""
    domain: ImageDomain
    geometry: object
    ray_transform: object
    template: torch.Tensor
    template_64: torch.Tensor
    noisy_data_64: torch.Tensor
    problem: object
    solver: object
    label: str
    options: dict
    target_64: Optional[torch.Tensor] = None
    clean_data_64: Optional[torch.Tensor] = None
    snr_db: Optional[float] = None
    units: run.Units = field(default_factory=run.Units)
    paper: bool = False
    validation: object = None
    report: dict = field(default_factory=dict)
    targets: dict = field(default_factory=dict)


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
    u = s.units   # the template's scale and the data's background, as the run uses them
    return Experiment(domain=data.domain, geometry=data.geometry, ray_transform=data.operator,
                      template=template * u.template_scale, template_64=data.template_64 * u.template_scale,
                      noisy_data_64=data.data_64 - u.background, problem=s.problem, solver=s.solver,
                      label=data.label, options=s.options, target_64=data.target_64, clean_data_64=data.clean_64,
                      snr_db=data.snr_db, units=u, paper=data.paper, validation=s.validation, report=data.report,
                      targets=data.targets)
