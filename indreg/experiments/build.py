"""Build one indirect registration experiment (domain, data, operators, problem, solver) from its config.

The data come from the config's data source (:mod:`indreg.experiments.sources`: simulated phantoms or files), in
float64 on the CPU; only then are template and data cast to ``cfg.dtype`` / ``cfg.device``. Simulated data are
generated device- and dtype-independently (noise drawn on the CPU with the run's seed), so the same config gives
the same data everywhere. Kernel, deformation, objective and solver are built by :func:`indreg.api.setup`, the
same code as ``indreg.register``.
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from omegaconf import DictConfig

from .. import api
from ..domain import ImageDomain
from . import sources


@dataclass
class Experiment:
    """Everything a run needs. Images ``(nx, ny)``, data ``(num_angles, det_count)``: float64 on the CPU
    (``*_64``, for metrics and figures); ``template`` and the problem's data in the run's dtype / device.
    ``target_64``, ``clean_data_64`` and ``snr_db`` are ``None`` for measured data without a ground truth."""
    domain: ImageDomain
    geometry: object
    ray_transform: object
    template: torch.Tensor
    template_64: torch.Tensor
    noisy_data_64: torch.Tensor
    problem: object
    solver: object
    label: str
    target_64: Optional[torch.Tensor] = None
    clean_data_64: Optional[torch.Tensor] = None
    snr_db: Optional[float] = None


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def options(cfg: DictConfig) -> dict:
    """The ``indreg.register`` options of the config (kernel, deformation and solver groups)."""
    s, d = cfg.solver, cfg.deformation
    name = s.name.value
    algorithm1 = name == "algorithm1"
    return {"sigma": cfg.kernel.sigma, "gamma": s.gamma, "tv_weight": s.tv_weight, "num_steps": d.num_steps,
            "action": d.action.value, "backward": d.backward.value, "interpolation": d.interpolation.value,
            "solver": s.optimizer.value if name == "torch_optim" else name, "max_iter": s.max_iter,
            "grad_tol": s.grad_tol, "step_halving": s.step_halving, "max_halvings": s.max_halvings,
            "step_size": s.step_size if algorithm1 else None, "lr": s.lr if name == "torch_optim" else None,
            "optimizer_kwargs": None if algorithm1 else dict(s.optimizer_kwargs), **_model_options(cfg)}


def _model_options(cfg: DictConfig) -> dict:
    """``model`` and, for metamorphosis, ``tau`` and the source's step (``indreg.register``'s options)."""
    d, s = cfg.deformation, cfg.solver
    if d.model.value != "metamorphosis":
        return {}
    algorithm1 = s.name.value == "algorithm1"
    return {"model": "metamorphosis", "tau": d.tau, "source_sigma": d.source_sigma, "source_mask": d.source_mask,
            "source_step_size": s.source_step_size if algorithm1 else None,
            "source_lr": None if algorithm1 else s.source_lr, "source_start": s.source_start if algorithm1 else 0}


def build(cfg: DictConfig) -> Experiment:
    """The data source's data and operator, then kernel, deformation, problem and solver (``api.setup``)."""
    dtype = getattr(torch, cfg.dtype.value)
    device = api.resolve_device(cfg.device)
    data = sources.load(cfg)
    template = data.template_64.to(dtype=dtype, device=device)
    g = data.data_64.to(dtype=dtype, device=device)
    s = api.setup(template, g, data.operator, dtype=dtype, device=device, **options(cfg))
    return Experiment(domain=data.domain, geometry=data.geometry, ray_transform=data.operator, template=template,
                      template_64=data.template_64, noisy_data_64=data.data_64, problem=s.problem, solver=s.solver,
                      label=data.label, target_64=data.target_64, clean_data_64=data.clean_64, snr_db=data.snr_db)
