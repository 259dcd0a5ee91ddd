"""Held-out benchmark of learned momenta against Algorithm 1: one row of metrics per scheme, in and out of
distribution.

Schemes (keys of ``metrics.json``): ``oneshot`` (the U-Net ``Lambda(template, FBP)``), ``unrolled`` (``K``
learned steps: ``UnrolledDescent`` on Algorithm 1's time-dependent momentum, or ``UnrolledMomentum`` on the initial
momentum through the indirect gradient), ``oneshot+algorithm1_<k>`` (Algorithm 1 warm
started from the one-shot geodesic, ``k`` iterations: ``k = K``, and the smallest ``k`` whose estimated time per
sample (Algorithm 1's time per iteration) is at least the unrolled scheme's) and ``algorithm1`` (per sample from
zero, ``eval.algorithm1.max_iter`` iterations).

Notes
-----
every scheme runs per sample (batch 1) and is timed from the sinogram to the deformed template (the FBP
included); metrics are means over the samples: ``ssim``, ``psnr`` (dB, range of the target), ``residual``
(``||T f - g|| / ||g||``, Euclidean), ``min_jacobian`` (mean over samples of the minimum of ``det D phi_{1,0}``;
``min_jacobian_worst`` the smallest), ``seconds_per_sample``; ``per_sample_ssim`` lists the SSIMs. An
``UnrolledDescent``'s learned step sizes ``alpha_k`` are reported as ``step_sizes``, its heavy-ball coefficients
``beta_k`` as ``inertias``. Algorithm 1 computes the Jacobian only after its last iteration (the unrolled schemes
not at all): the times compare the steps.
"""
from __future__ import annotations

import math
import time
from contextlib import contextmanager

import numpy as np
import torch

from ..deform.lddmm import LDDMMDeformation
from ..forward.fbp import fbp
from ..forward.geometry import ParallelBeamGeometry
from ..forward.ray_transform import RayTransform
from ..metrics import psnr, ssim
from .dataset import SyntheticDeformationDataset
from .descent import UnrolledDescent, descent_terms
from .loss import IndirectShootingLoss
from .unrolled import UnrolledMomentum

__all__ = ["algorithm1_scheme", "evaluate", "evaluate_schemes", "network_momentum", "network_scheme", "network_terms",
           "ood_sets", "physics", "score", "summarise"]

UNROLLED = (UnrolledMomentum, UnrolledDescent)


def network_momentum(model, template: torch.Tensor, fbp_image: torch.Tensor, data, num_updates=None):
    """``m0 (B, 2, nx, ny)`` of a ``MomentumUNet`` (input: template and FBP) or an ``UnrolledMomentum`` stopped
    after ``num_updates`` updates (``None``: all, ``0``: its initial network); of an ``UnrolledDescent`` its
    initial network's (``num_updates=0``) or ``m_j`` ``(B, N+1, 2, nx, ny)`` after ``j = num_updates`` steps."""
    if isinstance(model, UnrolledDescent) and num_updates == 0:
        return model.oneshot(template, fbp_image)
    if isinstance(model, UNROLLED):
        return model(template, fbp_image, data, num_updates)
    return model(torch.stack([template, fbp_image], dim=1))


@contextmanager
def physics(model, loss):
    """Run an unrolled scheme with another ``IndirectShootingLoss`` (another geometry) inside the block."""
    if not isinstance(model, UNROLLED):
        yield model
        return
    saved, model.loss = model.loss, loss
    try:
        yield model
    finally:
        model.loss = saved


def score(deformed, velocity, deformation: LDDMMDeformation, ray, target, data) -> dict:
    """Metrics of one result: the deformed template ``(nx, ny)`` and its velocities ``(N+1, 2, nx, ny)``."""
    residual = ray(deformed) - data
    return {"ssim": ssim(deformed, target), "psnr": psnr(deformed, target),
            "residual": float(residual.norm() / data.norm()),
            "min_jacobian": float(deformation.min_jacobian(velocity))}


def network_terms(net, model, loss: IndirectShootingLoss, batch: dict, num_updates=None) -> dict:
    """The per-sample terms of ``loss`` (``loss``, ``data_fit``, ``regulariser``, ``deformed``) at the momentum of
    ``net`` (``model``, or its DDP wrapper) stopped after ``num_updates`` steps: the initial momentum shot, or an
    ``UnrolledDescent``'s time-dependent momentum deformed (``descent_terms``)."""
    template, fbp_image, data = batch["template"], batch["fbp"], batch["data"]
    if isinstance(model, UnrolledDescent):
        if num_updates == 0:
            return loss.terms(net(template, fbp_image, data, oneshot=True), template, data)
        return descent_terms(loss, net(template, fbp_image, data, num_updates), template, data, model.deformation)
    if isinstance(model, UnrolledMomentum):
        return loss.terms(net(template, fbp_image, data, num_updates), template, data)
    return loss.terms(net(torch.stack([template, fbp_image], dim=1)), template, data)


def network_scheme(model, shooting, num_updates=None):
    """A scheme ``run(item, ray) -> (deformed, velocity)`` (batch-1 item): FBP, the network, one shot (or an
    ``UnrolledDescent``'s steps and the deformation of their momentum)."""
    @torch.no_grad()
    def run(item, ray):
        fbp_image = fbp(ray, item["data"])
        m0 = network_momentum(model, item["template"], fbp_image, item["data"], num_updates)
        if m0.dim() == 5:
            velocity = shooting.kernel.apply(m0)
            return model.deformation(velocity, item["template"])[0], velocity[0]
        result = shooting(m0, item["template"], return_all=True)
        return result.deformed[0], result.velocity[0]
    return run


def algorithm1_scheme(cfg, parts: dict, iterations: int, warm_start=None):
    """Algorithm 1 with ``iterations`` iterations from zero, or from the geodesic of ``warm_start`` (a scheme of
    ``network_scheme``'s kind whose shot momenta start the iteration)."""
    from ..solvers import Algorithm1, IndirectRegistration, SolverState

    shooting = parts["shooting"]
    deformation = LDDMMDeformation(parts["domain"], shooting.num_steps, str(cfg.shooting.action))

    def run(item, ray):
        problem = IndirectRegistration(ray, deformation, parts["kernel"], item["template"][0], item["data"][0],
                                       gamma=float(cfg.eval.algorithm1.gamma))
        momentum = problem.zero_momentum()
        if warm_start is not None:
            with torch.no_grad():
                fbp_image = fbp(ray, item["data"])
                m0 = network_momentum(warm_start, item["template"], fbp_image, item["data"], 0)
                momentum = shooting(m0, item["template"], return_all=True).momentum[0]
        state = SolverState(momentum=momentum, iteration=0)
        Algorithm1(problem, step_size=float(cfg.eval.algorithm1.step_size), max_iter=iterations,
                   jacobian_every=iterations).run(state)       # no Jacobian per iteration: only the steps timed
        return problem.deformed(state.momentum), problem.velocity(state.momentum)
    return run


def summarise(rows: list, seconds: float) -> dict:
    out = {k: float(np.mean([r[k] for r in rows])) for k in ("ssim", "psnr", "residual", "min_jacobian")}
    out.update(min_jacobian_worst=min(r["min_jacobian"] for r in rows), seconds_per_sample=seconds / len(rows),
               num_samples=len(rows), per_sample_ssim=[r["ssim"] for r in rows])
    return out


def evaluate_schemes(schemes: dict, parts: dict, dataset, device, ray=None, counts: dict | None = None) -> dict:
    """``{name: metrics}`` of each scheme ``run(item, ray)`` on the first ``counts[name]`` samples (default all) of
    ``dataset``, whose sinograms come from ``ray`` (default the training geometry)."""
    ray = parts["ray"] if ray is None else ray
    deformation = parts["shooting"].deformation
    out = {}
    for name, run in schemes.items():
        rows, seconds = [], 0.0
        for i in range(min(len(dataset), (counts or {}).get(name, len(dataset)))):
            item = {k: v[i:i + 1].to(device) for k, v in dataset.tensors.items()}
            start = time.perf_counter()
            deformed, velocity = run(item, ray)
            seconds += time.perf_counter() - start
            rows.append(score(deformed, velocity, deformation, ray, item["target"][0], item["data"][0]))
        if rows:
            out[name] = summarise(rows, seconds)
    return out


def ood_sets(cfg, parts: dict, dtype) -> dict:
    """``{name: (dataset, ray transform)}``: the held-out set with one change each (``eval.ood``)."""
    ood, common = cfg.eval.ood, dict(displacement=float(cfg.data.displacement),
                                     smoothness=float(cfg.data.smoothness), dtype=dtype,
                                     seed=2 * int(cfg.data.seed) + 1)
    count, snr = int(cfg.data.num_val), float(cfg.data.snr_db)
    variants = {f"angles_{a}": (int(a), snr, None) for a in ood.num_angles}
    variants.update({f"snr_{s:g}": (int(cfg.geometry.num_angles), float(s), None) for s in ood.snr_db})
    if len(ood.phantoms):
        variants["phantoms"] = (int(cfg.geometry.num_angles), snr, list(ood.phantoms))
    out = {}
    for name, (angles, snr_db, templates) in variants.items():
        ray = RayTransform(parts["domain"], ParallelBeamGeometry.paper(angles, int(cfg.geometry.det_count)))
        out[name] = (SyntheticDeformationDataset(parts["shooting"], ray, count, snr_db=snr_db, templates=templates,
                                                 **common), ray)
    return out


def evaluate(cfg, parts: dict, model, val_set, device, dtype) -> dict:
    """The benchmark: ``network`` (the trained model), ``schemes`` and ``ood`` (``indreg.learn.benchmark``)."""
    name, shooting = str(cfg.model.name), parts["shooting"]
    schemes = {}
    if not isinstance(model, UNROLLED) or model.initial is not None:
        schemes["oneshot"] = network_scheme(model, shooting, 0)
    if isinstance(model, UNROLLED):
        schemes["unrolled"] = network_scheme(model, shooting)
    alg1 = int(cfg.eval.algorithm1.num_samples)
    if alg1 > 0:
        schemes["algorithm1"] = algorithm1_scheme(cfg, parts, int(cfg.eval.algorithm1.max_iter))
    counts = {"algorithm1": alg1}
    results = evaluate_schemes(schemes, parts, val_set, device, counts=counts)
    if "oneshot" in schemes and "unrolled" in schemes:        # the cheap alternative: a warm-started Algorithm 1
        iterations = {model.num_updates}
        if alg1 > 0:
            per_iteration = results["algorithm1"]["seconds_per_sample"] / int(cfg.eval.algorithm1.max_iter)
            extra = results["unrolled"]["seconds_per_sample"] - results["oneshot"]["seconds_per_sample"]
            iterations.add(max(1, math.ceil(extra / per_iteration)))
        warm = {f"oneshot+algorithm1_{k}": algorithm1_scheme(cfg, parts, k, model) for k in sorted(iterations)}
        results.update(evaluate_schemes(warm, parts, val_set, device))
        schemes.update(warm)
    ood = {}
    for variant, (dataset, ray) in ood_sets(cfg, parts, dtype).items():
        with physics(model, IndirectShootingLoss(shooting, ray, float(cfg.train.gamma))):
            ood[variant] = evaluate_schemes(schemes, parts, dataset, device, ray, counts)
    network = dict(results["unrolled" if name == "unrolled" else "oneshot"])
    network["template_ssim"] = float(np.mean([ssim(t, f) for t, f in zip(val_set.tensors["template"],
                                                                          val_set.tensors["target"])]))
    metrics = {"network": network, "schemes": results, "ood": ood}
    if isinstance(model, UnrolledDescent):
        metrics["step_sizes"] = model.step_sizes.tolist()       # the learned alpha_k
        if model.heavy_ball:
            metrics["inertias"] = model.inertias.tolist()       # the learned beta_k
    if alg1 > 0:
        count = results["algorithm1"]["num_samples"]        # the network on the same samples, side by side
        metrics["algorithm1"] = dict(results["algorithm1"], network_ssim_same_samples=float(
            np.mean(network["per_sample_ssim"][:count])))
    return metrics
