"""The evaluation of a run's result (``indreg.registration.run.build_result``): its split into the data-determined
and the prior-filled part, and its per-voxel uncertainty, as the options ``split`` and ``uncertainty`` ask.

Convention: the split is of the reconstruction against the operator of the fitted data (the held-out angles
excluded, the alignment included); the uncertainty re-optimises the run's problem (:mod:`.uncertainty`).
"""
from __future__ import annotations

import logging
import math
import time

import torch

__all__ = ["evaluate", "MAX_VOXELS", "unsupported"]

log = logging.getLogger("indreg")

#: ``"auto"`` turns the split and the uncertainty off above this many voxels (their cost: 100 projections and
#: back-projections for the split, 40 iterations for the uncertainty).
MAX_VOXELS = 2 ** 21


def unsupported(problem) -> str:
    """Why the evaluation does not apply to ``problem`` (several time points, slab-wise over processes), ``""``
    when it does."""
    if hasattr(problem, "frame_times") and problem.frame_times() is not None:
        return "several time points"
    if getattr(problem, "group", None):
        return "a registration over several processes"
    if not hasattr(problem, "ray_transform") or not hasattr(problem, "data"):
        return f"a problem without one operator and its data ({type(problem).__name__})"
    return ""


def _wanted(value, problem, image: torch.Tensor, needs_holdout: bool, validation) -> bool:
    if value is False:
        return False
    why = unsupported(problem)
    if value is True and why:
        log.warning("the evaluation is off for %s", why)
    if why:
        return False
    if value == "auto":
        return image.numel() <= MAX_VOXELS and (validation is not None or not needs_holdout)
    return True


def evaluate(problem, iterate: tuple, image: torch.Tensor, solver=None, options: dict | None = None,
             validation=None) -> dict:
    """``{"data_part", "prior_part", "uncertainty", "summary"}`` of the reconstruction ``image`` of ``iterate``
    (tensors or None; ``summary`` the numbers for ``metrics.json``).

    Parameters
    ----------
    problem : RegistrationProblem
        The run's problem.
    iterate : tuple
        The final iterate (after the model's finish).
    image : torch.Tensor
        Its reconstruction.
    solver : optional
        The run's solver (its last step sizes start the uncertainty's re-optimisations).
    options : dict, optional
        ``split``, ``uncertainty``, ``uncertainty_samples``, ``uncertainty_noise`` (the option table's; default:
        theirs).
    validation : optional
        The held-out angles (``indreg.evaluation.validation.Validation``): ``uncertainty="auto"`` runs only with them.

    Returns
    -------
    dict
    """
    from .parts import data_split
    from .uncertainty import SAMPLES, registration_uncertainty

    o = {"split": "auto", "uncertainty": "auto", "uncertainty_samples": SAMPLES, "uncertainty_noise": None,
         **(options or {})}
    out = {"data_part": None, "prior_part": None, "uncertainty": None, "summary": {}}
    if _wanted(o["split"], problem, image, False, validation):
        t0 = time.perf_counter()
        s = data_split(image.detach(), problem.ray_transform, max_iter=100)
        out.update(data_part=s.data, prior_part=s.prior)
        out["summary"].update(s.summary(), split_seconds=time.perf_counter() - t0)
    if _wanted(o["uncertainty"], problem, image, True, validation):
        steps = getattr(solver, "step_sizes", None)
        steps = list(steps) if steps is not None and len(steps) == len(iterate) else None
        held_out = None if validation is None else (validation.operator, validation.data)
        u = registration_uncertainty(problem, iterate, steps, samples=o["uncertainty_samples"],
                                     noise_sd=o["uncertainty_noise"], held_out=held_out)
        out["uncertainty"] = u.sd
        out["summary"].update(u.summary())
        if math.isfinite(u.seconds):
            log.info("uncertainty: %d re-optimisations of %d iterations in %.1f s, mean standard deviation %.4g",
                     u.samples, u.iterations, u.seconds, float(u.sd.mean()))
    return out
