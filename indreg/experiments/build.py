"""Build one indirect registration experiment (domain, data, operators, problem, solver) from its config.

The data come from the config's data source (:mod:`indreg.experiments.sources`: simulated phantoms or files), in
float64 on the CPU; only then are template and data cast to ``cfg.dtype`` / ``cfg.device``. A volume's run keeps
no float64 copy of a fine array: its source's arrays (template, data, target, noise-free data, the model's ground
truths) are cast to the run's dtype on the CPU once loaded, so that the figures of merit, baselines and figures
read them there (``indreg.metrics`` compares volumes in float64 chunks). Simulated data are
generated device- and dtype-independently (noise drawn on the CPU with the run's seed), so the same config gives
the same data everywhere. Kernel, deformation, objective and solver are built by :func:`indreg.registration.run.setup`, the
same code as ``indreg.register`` (``indreg.registration.run.setup``).
"""
from __future__ import annotations

import random
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import torch
from omegaconf import DictConfig

from ..registration import run
from ..options import OptionError
from . import sources
from .config import ConfigError, registration_values


@dataclass
class Experiment:
    """Everything a run needs: the source's ``data`` (:class:`sources.Data`, on the CPU), the ``setup``
    (``indreg.registration.run.Setup``: problem, solver, resolved options, units, validation) and the inputs as the run uses
    them: ``template`` in the run's dtype / device, ``template_64`` / ``noisy_data_64`` on the CPU for metrics,
    baselines and figures (both through ``setup.units.apply``, the one transformation of the inputs). Images:
    ``data`` and the ``_64`` arrays in float64; volumes: in the run's dtype (:func:`fine_arrays_in`). A run on a wide
    box (``setup.box``) computes there (``wide_transform``) and shows, saves and scores the field of view
    (:meth:`field`).
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
    box = property(lambda self: self.setup.box)

    @cached_property
    def wide_transform(self):
        """The operator on the run's box: the wide box's (``setup.box``, a specimen wider than the field of view),
        else the source's own."""
        return self.data.operator if self.box is None else self.box.widen(self.data.operator)

    def field(self, image):
        """An image on the field of view, the source's domain (what figures, files and scores show).

        Parameters
        ----------
        image : torch.Tensor or None
            Any image of the run.

        Returns
        -------
        torch.Tensor or None
            An image of the wide box (trailing axes ``box.domain.shape``) cropped, anything else as it is.
        """
        box = self.box
        if box is None or image is None or tuple(image.shape[image.dim() - box.domain.ndim:]) != \
                tuple(box.domain.shape):
            return image
        return box.crop(image)


def _rank0() -> bool:
    """Whether this process is rank 0 of ``torchrun`` (or runs alone): the one that shows progress."""
    import os

    return int(os.environ.get("RANK", "0")) == 0


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def build(cfg: DictConfig) -> Experiment:
    """The data source's data and operator, then kernel, problem and solver (``indreg.registration.run.setup``, the same code
    as ``indreg.register``, with the config's registration options; errors name the config key)."""
    dtype = getattr(torch, cfg.dtype.value)
    device = run.resolve_device(cfg.device)
    data = sources.load(cfg)
    if data.domain.ndim == 3:
        data = fine_arrays_in(data, dtype)
    template = data.template_64.to(dtype=dtype, device=device)
    g = data.data_64.to(dtype=dtype, device=device)
    try:
        s = run.setup(template if data.template_known else None, g, data.operator, label=lambda o: o.config_key,
                      strict=False, dtype=dtype, device=device, progress=bool(cfg.logging.progress) and _rank0(),
                      **registration_values(cfg))
    except OptionError as e:
        raise ConfigError(f"invalid config value {e.label}={e.value!r}: expected {e.expected}") from None
    template_64, data_64 = s.units.apply(data.template_64, data.data_64)
    if data.target_64 is not None and data.template_known:   # SSIM / PSNR in the target's units
        s.units.locate_target(template_64, data.target_64)
    return Experiment(data=data, setup=s, template=s.units.apply(template, g)[0], template_64=template_64,
                      noisy_data_64=data_64)


def fine_arrays_in(data: sources.Data, dtype: torch.dtype) -> sources.Data:
    """``data`` with its arrays (template, data, target, noise-free data, ``targets``) in ``dtype`` on the CPU: a
    volume's run holds no float64 copy of a fine array (at 256^3 each float64 volume is 128 MiB; the float32 ones
    are what the run computes with, and float32 to float64 is exact for the figures of merit)."""
    def cast(t):
        return None if t is None else t.to("cpu", dtype)

    return replace(data, template_64=cast(data.template_64), data_64=cast(data.data_64),
                   target_64=cast(data.target_64), clean_64=cast(data.clean_64),
                   targets={k: cast(v) for k, v in data.targets.items()})
