"""The baselines of a run: FBP, SIRT and TV from the run's noisy data, cached in the run dir.

Convention: reconstructions are returned on the CPU as tensors of the domain's shape ``(nx, ny[, nz])`` (images
float64, volumes the run's dtype),
keyed ``fbp``, ``sirt`` and ``tv``; TV's weight is absolute, ``baseline.tv_mu`` times the TV weight unit
(``indreg.forward.tv_weight_unit``: the data's intensity unit times the box's largest side squared).
A tilt series whose registration is split (``indreg.problems.slabs``) splits its baselines along the tilt axis too
(``indreg.forward.split``): over the ranks of ``torchrun`` every rank reconstructs its rows (TV with a one-slice
halo) and rank 0 gathers them (the other ranks get ``{}``); in one process, slab-wise registrations run FBP and SIRT
slab by slab with the registration's ``slab_size`` (TV whole: its differences couple the slabs). Each is the
whole-volume reconstruction to float rounding.
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from .._outfiles import open_replacing

__all__ = ["tv_mu", "baselines"]

log = logging.getLogger(__name__)


def tv_mu(cfg: DictConfig, exp) -> float:
    """The TV baseline's absolute weight: ``baseline.tv_mu`` times the TV weight unit
    (``indreg.forward.tv_weight_unit``), so that the baseline is the same in any intensity and length units."""
    from ..forward import tv_weight_unit

    return float(cfg.baseline.tv_mu) * tv_weight_unit(exp.ray_transform, exp.noisy_data_64)


def baselines(cfg: DictConfig, exp, out: Path) -> dict:
    """FBP, SIRT and TV reconstructions from the noisy data (images: float64, volumes: the run's dtype, on the run's
    device, returned on the CPU in that dtype: no float64 copy of a volume); cached in ``baselines.npz`` so that a
    resumed run does not recompute them. FBP and SIRT are linear in the data; TV's weight scales with them
    (:func:`tv_mu`). Volumes take the run's dtype: at 256^3 a float64 SIRT / TV iteration costs about twice a
    float32 one. Under ``torchrun`` every rank calls it: the split is in the module docstring; rank 0 alone reads
    and writes the cache."""
    if not cfg.baseline.enabled:
        return {}
    b = cfg.baseline
    volume = exp.domain.ndim == 3
    mu = tv_mu(cfg, exp)
    key = np.array([b.fbp_filter.value, b.fbp_frequency_scaling, b.fbp_padding, repr(mu), b.tv_iterations,
                    b.sirt_iterations], dtype=str)
    group, rank = _group()
    cache = out / "baselines.npz"
    names = ("fbp", "sirt", "tv")
    rec = _cached(cache, key, names, tuple(exp.domain.shape)) if rank == 0 else None
    if _broadcast(rec is not None, group):
        return rec or {}
    t0 = time.perf_counter()
    T, g = exp.wide_transform, exp.noisy_data_64.to(exp.template.device, exp.template.dtype if volume else None)
    how, rec = _split(cfg, exp, T, g, mu, group, rank)
    if rank != 0:
        return {}
    rec = {k: exp.field(v).detach().to("cpu", g.dtype if volume else torch.float64) for k, v in rec.items()}
    how += "" if exp.box is None else f", on the wide box {tuple(exp.box.domain.shape)} (the field of view kept)"
    log.info("baselines (%s) in %.1f s%s", ", ".join(rec).upper().replace(
        "TV", f"TV {b.tv_iterations} iterations, mu {mu:.4g} = {b.tv_mu:g} x the TV weight unit"),
        time.perf_counter() - t0, how)
    with open_replacing(cache) as f:   # a fresh file renamed over the cache: no link followed
        np.savez(f, key=key, **{k: v.numpy() for k, v in rec.items()})
    return rec


def _reconstruct(cfg: DictConfig, T, g: torch.Tensor, mu: float, fbp_and_sirt=None) -> dict:
    """FBP, SIRT (nonnegative) and TV of ``T`` and ``g``; ``fbp_and_sirt(method, T, g)`` runs the two slab-wise ones
    (default: ``method(T, g)``)."""
    from ..forward import fbp, sirt
    from ..forward.tv import tv_reconstruction

    b = cfg.baseline
    run = fbp_and_sirt or (lambda method, op, data: method(op, data))
    rec = {"fbp": run(lambda op, data: fbp(op, data, filter=b.fbp_filter.value,
                                           frequency_scaling=b.fbp_frequency_scaling, padding=b.fbp_padding), T, g)}
    with _bar(cfg, "SIRT", None if fbp_and_sirt else b.sirt_iterations) as bar:   # by slabs: iterations per slab
        rec["sirt"] = run(lambda op, data: sirt(op, data, num_iter=b.sirt_iterations, nonneg=True,
                                                callback=lambda i, x: bar.update(1))[0], T, g)
    with _bar(cfg, "TV", b.tv_iterations) as bar:
        rec["tv"] = tv_reconstruction(T, g, mu=mu, num_iter=b.tv_iterations, callback=lambda i, x: bar.update(1))[0]
    return rec


def _bar(cfg: DictConfig, name: str, total):
    """A progress bar (tqdm) of a baseline's iterations, on a terminal with ``logging.progress`` only."""
    from tqdm import tqdm

    return tqdm(total=total, desc=f"baseline {name}", dynamic_ncols=True, leave=False,
                disable=not (cfg.logging.progress and sys.stderr.isatty()))


def _split(cfg: DictConfig, exp, T, g: torch.Tensor, mu: float, group, rank: int) -> tuple:
    """``(how, reconstructions)``: over the ranks of ``group`` (rank 0 gets the gathered volumes, the others
    ``{}``), slab by slab in one process for a slab-wise registration, or whole."""
    from ..forward.split import by_slabs, gather_rows, split_rows
    from ..forward.tilt_series import TiltSeriesTransform

    if type(T) is not TiltSeriesTransform or not getattr(exp.problem, "splits_over_ranks", False):
        return "", _reconstruct(cfg, T, g, mu) if rank == 0 else {}   # whole, on rank 0
    if group is not None:
        Ts = split_rows(T, group)
        rec = {k: gather_rows(v, Ts) for k, v in _reconstruct(cfg, Ts, Ts.data_rows(g), mu).items()}
        return f" over {Ts.split.world} ranks", rec
    size = exp.problem.slab_size
    return f" (FBP, SIRT by slabs of {size} slices)", _reconstruct(
        cfg, T, g, mu, lambda method, op, data: by_slabs(method, op, data, size))


def _group() -> tuple:
    """``(group, rank)``: ``torch.distributed``'s group of several ranks, or ``(None, 0)``."""
    from ..ranks import default_group

    group = default_group()
    if group is None:
        return None, 0
    import torch.distributed as dist
    return group, dist.get_rank(group)


def _cached(cache: Path, key: np.ndarray, names: tuple, shape: tuple) -> dict | None:
    """The reconstructions ``names`` of ``cache`` when its key is ``key`` and each is a finite float array of
    ``shape``, else None (recomputed). A damaged or crafted cache (not a zip, object arrays: never unpickled,
    other names, shapes or values) is only a warning: the baselines are recomputed and the cache rewritten."""
    if not cache.is_file():
        return None
    try:
        with np.load(cache, allow_pickle=False) as z:
            if "key" not in z.files or not np.array_equal(z["key"], key):
                return None
            rec = {k: z[k] for k in z.files if k != "key"}
    except Exception as e:   # not a zip, a truncated member, an object array, ...
        log.warning("%s is unreadable (%s: %s): recomputing the baselines", cache, type(e).__name__,
                    " ".join(str(e).split()))
        return None
    if sorted(rec) != sorted(names) or not all(
            a.dtype.kind == "f" and a.shape == shape and np.isfinite(a).all() for a in rec.values()):
        log.warning("%s does not hold finite %s arrays of shape %s: recomputing the baselines", cache,
                    "/".join(names), shape)
        return None
    return {k: torch.from_numpy(rec[k]) for k in names}


def _broadcast(flag: bool, group) -> bool:
    """Rank 0's ``flag`` on every rank of ``group`` (``flag`` itself without one)."""
    if group is None:
        return flag
    import torch.distributed as dist
    holder = [flag]
    dist.broadcast_object_list(holder, src=0, group=group)
    return bool(holder[0])
