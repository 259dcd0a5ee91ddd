"""The baselines of a run: FBP and TV (and SIRT for volumes) from the run's noisy data, cached in the run dir.

Convention: reconstructions are returned on the CPU as tensors of the domain's shape ``(nx, ny[, nz])`` (images
float64, volumes the run's dtype),
keyed ``fbp``, ``tv`` (and ``sirt``); TV's weight is absolute, ``baseline.tv_mu`` times the TV weight unit
(``indreg.forward.tv_weight_unit``: the data's intensity unit times the box's largest side squared).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

__all__ = ["tv_mu", "baselines"]

log = logging.getLogger(__name__)


def tv_mu(cfg: DictConfig, exp) -> float:
    """The TV baseline's absolute weight: ``baseline.tv_mu`` times the TV weight unit
    (``indreg.forward.tv_weight_unit``), so that the baseline is the same in any intensity and length units."""
    from ..forward import tv_weight_unit

    return float(cfg.baseline.tv_mu) * tv_weight_unit(exp.ray_transform, exp.noisy_data_64)


def baselines(cfg: DictConfig, exp, out: Path) -> dict:
    """FBP and TV reconstructions from the noisy data (images: float64, volumes: the run's dtype, on the run's
    device, returned on the CPU in that dtype: no float64 copy of a volume); cached in ``baselines.npz`` so that a resumed run does not recompute
    them. FBP and SIRT are linear in the data; TV's weight scales with them (:func:`tv_mu`). Volumes take the run's
    dtype: at 256^3 a float64 SIRT / TV iteration costs about twice a float32 one."""
    if not cfg.baseline.enabled:
        return {}
    b = cfg.baseline
    volume = exp.domain.ndim == 3
    mu = tv_mu(cfg, exp)
    key = np.array([b.fbp_filter.value, b.fbp_frequency_scaling, b.fbp_padding, repr(mu), b.tv_iterations,
                    b.sirt_iterations if volume else 0], dtype=str)
    cache = out / "baselines.npz"
    if cache.is_file():
        with np.load(cache) as z:
            if np.array_equal(z["key"], key):
                return {k: torch.from_numpy(z[k]) for k in z.files if k != "key"}
    from ..forward import fbp, sirt
    from ..forward.tv import tv_reconstruction

    t0 = time.perf_counter()
    T, g = exp.ray_transform, exp.noisy_data_64.to(exp.template.device, exp.template.dtype if volume else None)
    rec = {"fbp": fbp(T, g, filter=b.fbp_filter.value, frequency_scaling=b.fbp_frequency_scaling,
                      padding=b.fbp_padding)}
    if volume:  # electron tomography's iterative baseline
        rec["sirt"] = sirt(T, g, num_iter=b.sirt_iterations, nonneg=True)[0]
    rec["tv"] = tv_reconstruction(T, g, mu=mu, num_iter=b.tv_iterations)[0]
    rec = {k: v.detach().to("cpu", g.dtype if volume else torch.float64) for k, v in rec.items()}
    log.info("baselines (%s) in %.1f s", ", ".join(rec).upper().replace(
        "TV", f"TV {b.tv_iterations} iterations, mu {mu:.4g} = {b.tv_mu:g} x the TV weight unit"),
        time.perf_counter() - t0)
    np.savez(cache, key=key, **{k: v.numpy() for k, v in rec.items()})
    return rec
