"""Build one indirect registration experiment (domain, data, operators, problem, solver) from its config.

The data are generated device- and dtype-independently: phantoms and ``T f_true`` in float64 on the CPU, noise
drawn on the CPU by ``indreg.noise.add_white_noise`` with the run's seed; only then are template and data cast
to ``cfg.dtype`` / ``cfg.device``. The same config therefore gives the same data everywhere.
"""
from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np
import torch
from omegaconf import DictConfig

from .. import phantoms
from ..domain import ImageDomain
from ..forward import ParallelBeamGeometry, RayTransform


@dataclass
class Experiment:
    """Everything a run needs. Images ``(nx, ny)``, data ``(num_angles, det_count)``: float64 on the CPU
    (``*_64``, for metrics and figures); ``template`` and the problem's data in the run's dtype / device."""
    domain: ImageDomain
    geometry: ParallelBeamGeometry
    ray_transform: RayTransform
    template: torch.Tensor
    target_64: torch.Tensor
    template_64: torch.Tensor
    clean_data_64: torch.Tensor
    noisy_data_64: torch.Tensor
    snr_db: float
    problem: object
    solver: object


def resolve_device(name: str) -> torch.device:
    """``auto``: CUDA when available, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device={name!r} was requested but CUDA is not available (use device=auto or cpu)")
    return device


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def make_geometry(cfg: DictConfig) -> ParallelBeamGeometry:
    g = cfg.geometry
    if g.partition.value == "paper":
        return ParallelBeamGeometry.paper(g.num_angles, g.det_count, det_min=g.det_min, det_max=g.det_max)
    return ParallelBeamGeometry(num_angles=g.num_angles, det_count=g.det_count, det_min=g.det_min, det_max=g.det_max)


def make_data(cfg: DictConfig, T: RayTransform, target_64: torch.Tensor) -> tuple:
    """Noise-free and noisy data (float64, CPU) and the realised SNR in dB (``cfg.noise.convention``)."""
    from ..noise import add_white_noise, snr_db

    clean = T(target_64)
    n = cfg.noise
    if n.snr_db is None and n.std is None:
        return clean, clean.clone(), float("inf")
    seed = cfg.seed if n.seed is None else n.seed
    noisy, noise = add_white_noise(clean, snr_db=n.snr_db, std=n.std, convention=n.convention.value, seed=seed)
    return clean, noisy, float(snr_db(clean, noise, convention=n.convention.value))


def make_solver(cfg: DictConfig, problem):
    from ..solvers import Algorithm1, TorchOptimSolver

    s = cfg.solver
    if s.name.value == "algorithm1":
        return Algorithm1(problem, step_size=s.step_size, max_iter=s.max_iter, grad_tol=s.grad_tol,
                          step_halving=s.step_halving)
    return TorchOptimSolver(problem, optimizer=s.optimizer.value, lr=s.lr, max_iter=s.max_iter,
                            grad_tol=s.grad_tol, **dict(s.optimizer_kwargs))


def build(cfg: DictConfig) -> Experiment:
    """Domain, geometry, ray transform, phantoms, noisy data, kernel, deformation, problem and solver."""
    from ..deform import GaussianKernel, LDDMMDeformation
    from ..solvers import IndirectRegistration

    dtype = getattr(torch, cfg.dtype.value)
    device = resolve_device(cfg.device)
    p = cfg.phantom
    domain = ImageDomain((p.size, p.size), (-p.half_width,) * 2, (p.half_width,) * 2)
    geometry = make_geometry(cfg)
    T = RayTransform(domain, geometry)
    target_64 = phantoms.get(p.target.value, domain)
    template_64 = phantoms.get(p.template.value, domain)
    clean, noisy, snr = make_data(cfg, T, target_64)
    template = template_64.to(dtype=dtype, device=device)
    data = noisy.to(dtype=dtype, device=device)
    kernel = GaussianKernel(domain, cfg.kernel.sigma)
    d = cfg.deformation
    deformation = LDDMMDeformation(domain, num_steps=d.num_steps, action=d.action.value,
                                   backward=d.backward.value, interpolation=d.interpolation.value)
    problem = IndirectRegistration(T, deformation, kernel, template, data, cfg.solver.gamma,
                                   tv_weight=cfg.solver.tv_weight)
    return Experiment(domain=domain, geometry=geometry, ray_transform=T, template=template, target_64=target_64,
                      template_64=template_64, clean_data_64=clean, noisy_data_64=noisy, snr_db=snr,
                      problem=problem, solver=make_solver(cfg, problem))
