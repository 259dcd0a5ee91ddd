"""Training of a learned initial momentum (rem:AltLDDMM): ``Lambda_Theta(template, FBP(g)) = m0``.

``model=oneshot`` (default): the network (``MomentumUNet``) is trained with the indirect loss
``||T(W(m0, I)) - g||^2 + gamma <m0, K m0>`` (``IndirectShootingLoss``) on a seeded synthetic data set
(``SyntheticDeformationDataset``), logs to TensorBoard, checkpoints and resumes, runs data parallel
(``torch.distributed``, DDP: gloo on CPU, nccl on CUDA; start with ``torchrun``), and at the end compares with
per-sample Algorithm 1 on held-out samples.
``model=unrolled``: ``K`` learned steps from the one-shot network's prediction: ``model.space=velocity`` (default)
``UnrolledDescent``, Algorithm 1's steps on the time-dependent momentum with learned step sizes and a correction
network; ``model.space=initial`` ``UnrolledMomentum``, updates of the initial momentum through the indirect
gradient. Steps ``[0, train.steps)`` train the one-shot network (as ``model=oneshot``), steps ``[train.steps,
train.steps + model.steps)`` the unrolled scheme (learning rate ``model.lr`` with a cosine decay, the one-shot
network fixed, its input scale, ``residual_scale`` or ``gradient_scale``, calibrated on the first training samples
when they start; the loss: ``2 E`` of Algorithm 1's objective at ``m_K`` plus ``model.supervised`` times the
squared distance of the deformed template to the target, or the indirect loss at the initial momentum). The benchmark
(``indreg.learn.benchmark``) then scores every scheme in and out of distribution (``eval.ood``).

Entry point: ``indreg-train-momentum [key=value ...]`` (Hydra config ``indreg/learn/conf/train_momentum.yaml``),
``torchrun --standalone --nproc_per_node=2 -m indreg.learn.train ...`` for DDP.

Batches: step ``s`` draws a global batch of ``batch_size * world_size`` distinct samples from a generator
seeded by ``(seed, s)``; rank ``r`` takes its slice. The batch sequence is thus a function of the step only
(exact resume, no sampler state) and the ranks see disjoint samples; DDP averages the gradients, so the
replicas stay identical (checked at the end: ``replica_max_abs_diff`` in ``metrics.json``).

Outputs in the run directory: ``tensorboard/`` (scalars ``train/loss``, ``train/data_fit``,
``train/regulariser``, ``train/ssim``, ``val/ssim``, ``val/loss``, images ``val/template``, ``val/fbp``,
``val/target``, ``val/prediction``; while the unrolled updates train, ``unrolled/loss``, ``unrolled/data_fit``,
``unrolled/regulariser``, ``unrolled/supervised``, ``unrolled/ssim`` instead of ``train/*``, and
``val/ssim_update_<k>``, images ``val/update_<k>``, the deformed template after ``k`` updates), ``checkpoint.pt``
(model, optimizer, step, RNG), ``metrics.json`` (``network``: the trained model, ``schemes``: every scheme, ``ood``:
out of distribution), ``figure.png`` (held-out examples: template, FBP, prediction with its SSIM, target; axes in
the domain's units).

Longer than 450 lines: one training loop with its checkpoint, resume and preflight checks, which share the config's
keys.
"""
from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from .._checks import check_finite, check_int, check_nonnegative, check_positive
from .._outfiles import open_replacing, replacing
from ..deform.kernel import GaussianKernel
from ..deform.shooting import GeodesicShooting
from ..domain import ImageDomain
from ..experiments import checkpoint as ckpt
from ..forward.geometry import ParallelBeamGeometry
from ..forward.ray_transform import RayTransform
from ..metrics import ssim
from ..options import check_value
from ..phantoms import ndim as get_phantom_ndim
from . import benchmark as bench
from .conf import CONFIG_DIR, CONFIG_NAME
from .dataset import SyntheticDeformationDataset
from .loss import IndirectShootingLoss
from .unet import MomentumUNet
from .descent import UnrolledDescent
from .unrolled import GRADIENTS, UnrolledMomentum

DTYPES = {"float32": torch.float32, "float64": torch.float64}
RESUME_HINT = "delete it or run without train.resume=true"
INITS = ("oneshot", "zero")
SPACES = ("velocity", "initial")     # model=unrolled: UnrolledDescent | UnrolledMomentum
MODEL_DIR = CONFIG_DIR / "model"      # the options of model=<name>
SNR_DB_MAX = 300.0          # = indreg.noise's bound on snr_db


# ------------------------------------------------------------------ set-up
def init_distributed(device_name: str) -> tuple:
    """``(rank, world_size, device)``; starts the process group when launched by torchrun (``WORLD_SIZE`` > 1)."""
    if device_name == "auto":
        device_name = "cuda" if torch.cuda.is_available() else "cpu"
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    device = torch.device(device_name)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return rank, world, device


def build(cfg, device, dtype) -> dict:
    """Domain, kernel, shooting layer, ray transform, loss and network from the config."""
    domain = ImageDomain.paper(int(cfg.domain.n))
    kernel = GaussianKernel(domain, float(cfg.kernel.sigma))
    shooting = GeodesicShooting(domain, kernel, int(cfg.shooting.num_steps), str(cfg.shooting.action),
                                backward=str(cfg.shooting.backward),
                                corrector_steps=int(cfg.shooting.corrector_steps),
                                checkpoint=bool(cfg.shooting.checkpoint))
    geometry = ParallelBeamGeometry.paper(int(cfg.geometry.num_angles), int(cfg.geometry.det_count))
    ray = RayTransform(domain, geometry)
    loss = IndirectShootingLoss(shooting, ray, float(cfg.train.gamma))
    scale = float(cfg.data.displacement) / (2 * math.pi * float(cfg.kernel.sigma) ** 2)
    torch.manual_seed(int(cfg.seed))      # same initial weights on every rank (DDP also broadcasts rank 0's)
    model = MomentumUNet(2, int(cfg.model.width), int(cfg.model.levels), momentum_scale=scale)
    if str(cfg.model.name) == "unrolled":
        m = cfg.model
        initial = model if str(m.init) == "oneshot" else None
        if str(m.space) == "velocity":
            model = UnrolledDescent(loss, int(m.updates), float(m.step_size), int(m.update_width),
                                    int(m.update_levels), bool(m.shared), bool(m.correction), initial, scale,
                                    bool(m.heavy_ball))
        else:
            model = UnrolledMomentum(loss, int(m.updates), int(m.update_width), int(m.update_levels), bool(m.shared),
                                     initial, scale, str(m.gradient))
    return {"domain": domain, "kernel": kernel, "shooting": shooting, "ray": ray, "loss": loss,
            "model": model.to(device=device, dtype=dtype)}


def datasets(cfg, parts: dict, dtype) -> tuple:
    """Training and held-out sets (different seeds: disjoint sample generators)."""
    common = dict(snr_db=float(cfg.data.snr_db), displacement=float(cfg.data.displacement),
                  smoothness=float(cfg.data.smoothness), dtype=dtype)
    train = SyntheticDeformationDataset(parts["shooting"], parts["ray"], int(cfg.data.num_train),
                                        seed=2 * int(cfg.data.seed), **common)
    val = SyntheticDeformationDataset(parts["shooting"], parts["ray"], int(cfg.data.num_val),
                                      seed=2 * int(cfg.data.seed) + 1, **common)
    return train, val


def check_config(cfg) -> None:
    """The options that Hydra does not check, before anything runs (a ``ValueError`` naming the key): the data
    set's and the training's numbers, the model's ``space``, ``init``, ``gradient``, ``step_size``,
    ``supervised``, ``lr``, ``step_lr``, ``updates`` and ``steps``, and the lists of ``eval.ood``."""
    try:
        _check_numbers(cfg)
    except TypeError as e:   # check_int's type error: the same one line
        raise ValueError(str(e)) from None
    if str(cfg.model.name) == "unrolled":
        for key, allowed in (("space", SPACES), ("init", INITS), ("gradient", GRADIENTS)):
            if str(cfg.model[key]) not in allowed:
                raise ValueError(f"model.{key} must be one of {', '.join(allowed)}, got {cfg.model[key]!r}")
    ood = cfg.eval.ood
    for key, example in (("num_angles", "[6, 20]"), ("snr_db", "[5.0]"), ("phantoms", "[j, v]")):
        if not isinstance(ood[key], Sequence) or isinstance(ood[key], str):
            raise ValueError(f"eval.ood.{key} must be a list (e.g. {example}, or []), got {ood[key]!r}")
    try:
        for value in ood.num_angles:
            check_int(value, "eval.ood.num_angles", 1)
        for value in ood.snr_db:
            if abs(check_finite(value, "eval.ood.snr_db")) > SNR_DB_MAX:
                raise ValueError(f"eval.ood.snr_db must hold values in [-{SNR_DB_MAX:g}, {SNR_DB_MAX:g}] dB, got "
                                 f"{value!r}")
        for name in ood.phantoms:
            if get_phantom_ndim(str(name)) != 2:
                raise ValueError(f"{name!r} is a 3D phantom and the training is 2D")
    except (TypeError, ValueError) as e:
        message = str(e) if str(e).startswith("eval.ood") else f"eval.ood.phantoms: {e}"
        raise ValueError(message) from None


def _check_numbers(cfg) -> None:
    """Counts are integers >= 1 (``model.steps`` >= 0), rates and sizes finite and > 0, ``data.snr_db`` finite:
    ``model.lr=0`` would divide by zero, ``data.num_train=0`` leave no batch, a NaN poison every sample."""
    d, t = cfg.data, cfg.train
    for name, key, value in (("sigma", "kernel.sigma", cfg.kernel.sigma), ("num_steps", "shooting.num_steps",
                             cfg.shooting.num_steps), ("action", "shooting.action", cfg.shooting.action)):
        check_value(name, value, key)   # the registration's option table: one check per option
    check_positive(cfg.kernel.sigma, "kernel.sigma")   # a number here: no 'auto' or None in the training
    for key in ("num_train", "num_val"):
        check_int(d[key], f"data.{key}", 1)
    check_finite(d.snr_db, "data.snr_db")
    if abs(float(d.snr_db)) > SNR_DB_MAX:
        raise ValueError(f"data.snr_db must be in [-{SNR_DB_MAX:g}, {SNR_DB_MAX:g}] dB, got {d.snr_db!r}")
    _check_problem(cfg)
    check_positive(d.displacement, "data.displacement")
    check_positive(d.smoothness, "data.smoothness")
    check_int(t.batch_size, "train.batch_size", 1)
    check_int(t.steps, "train.steps", 0)
    check_positive(t.lr, "train.lr")
    if str(cfg.model.name) == "unrolled":
        m = cfg.model
        check_int(m.updates, "model.updates", 1)
        check_int(m.steps, "model.steps", 0)
        for key in ("lr", "step_lr", "step_size"):
            check_positive(m[key], f"model.{key}")
        check_nonnegative(m.supervised, "model.supervised")


def _check_problem(cfg) -> None:
    """The domain, shooting, geometry, network and comparison numbers (``kernel.sigma`` and ``shooting.num_steps``:
    the option table's): ``domain.n`` at least the SSIM's 7-pixel window and divisible by the U-Nets'
    ``2^(levels - 1)``, counts >= 1."""
    m, a = cfg.model, cfg.eval.algorithm1
    for key in ("width", "levels") + (("update_width", "update_levels") if str(m.name) == "unrolled" else ()):
        check_int(m[key], f"model.{key}", 1)
    check_int(cfg.geometry.num_angles, "geometry.num_angles", 1)
    check_int(cfg.geometry.det_count, "geometry.det_count", 1)
    check_int(cfg.shooting.corrector_steps, "shooting.corrector_steps", 0)
    check_nonnegative(cfg.train.gamma, "train.gamma")
    check_int(a.num_samples, "eval.algorithm1.num_samples", 0)
    check_int(a.max_iter, "eval.algorithm1.max_iter", 0)
    check_positive(a.step_size, "eval.algorithm1.step_size")
    check_nonnegative(a.gamma, "eval.algorithm1.gamma")
    levels = max(int(m.levels), int(m.update_levels) if str(m.name) == "unrolled" else 1)
    n, factor = check_int(cfg.domain.n, "domain.n", 7), 2 ** (levels - 1)
    if n % factor:
        raise ValueError(f"domain.n must be divisible by {factor} (the U-Net's {levels} levels halve it "
                         f"{levels - 1} times), got {n}: e.g. domain.n={factor * -(-n // factor)}")


def schedule(cfg) -> tuple:
    """``(first, total)``: steps ``[0, first)`` train the one-shot network, ``[first, total)`` the unrolled updates."""
    steps = int(cfg.train.steps)
    if str(cfg.model.name) != "unrolled":
        return steps, steps
    first = steps if str(cfg.model.init) == "oneshot" else 0
    return first, first + int(cfg.model.steps)


def learning_rate(cfg, step: int, first: int, total: int) -> float:
    """``train.lr`` for the one-shot steps; for the unrolled steps ``model.lr`` on a cosine decay to zero (a function
    of the step only: exact resume)."""
    if step < first or str(cfg.model.name) != "unrolled":
        return float(cfg.train.lr)
    return float(cfg.model.lr) * 0.5 * (1 + math.cos(math.pi * (step - first) / max(1, total - first)))


def parameter_groups(cfg, model) -> list:
    """The optimizer's groups, each with its ``scale`` of the learning rate: an ``UnrolledDescent``'s step-size
    logits ``a_k`` and heavy-ball logits ``b_k`` learn at ``model.step_lr`` (instead of ``model.lr``; an
    O(1) change of them is a large change of the step, which ``model.lr`` would take thousands of steps to make),
    everything else at 1."""
    if not isinstance(model, UnrolledDescent):
        return [{"params": list(model.parameters()), "scale": 1.0}]
    fast = ("step_logits", "inertia_logits")
    rest = [p for name, p in model.named_parameters() if name not in fast]
    steps = [p for name, p in model.named_parameters() if name in fast]
    return [{"params": rest, "scale": 1.0}, {"params": steps, "scale": float(cfg.model.step_lr) / float(cfg.model.lr)}]


def batch_indices(step: int, seed: int, size: int, num_samples: int, rank: int, world: int) -> torch.Tensor:
    """This rank's slice of the global batch of step ``step`` (a function of ``(seed, step)`` only)."""
    gen = torch.Generator().manual_seed(int(seed) * 1_000_003 + step)
    perm = torch.randperm(num_samples, generator=gen)
    total = size * world
    if total > num_samples:
        perm = perm.repeat(math.ceil(total / num_samples))
    return perm[rank * size:(rank + 1) * size]


def gather(dataset, idx, device) -> dict:
    return {k: v[idx].to(device) for k, v in dataset.tensors.items()}


# ------------------------------------------------------------------ checkpoints
#: Keys that may change between a run and its resume (where it runs, how often it logs, how long it trains: a resume
#: may train longer, the comparison at the end); every other key defines the training and must be the same.
RESUMABLE = ("device", "eval", "train.resume", "train.log_every", "train.eval_every", "train.checkpoint_every",
             "train.steps", "model.steps")


def training_config(cfg) -> dict:
    """The keys of ``cfg`` that define the training (all but :data:`RESUMABLE`), as plain data: what a checkpoint
    stores and a resume must match."""
    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(cfg, resolve=True) if not isinstance(cfg, dict) else dict(cfg)
    plain = {k: (dict(v) if isinstance(v, dict) else v) for k, v in plain.items() if k != "hydra"}
    for key in RESUMABLE:
        head, _, leaf = key.partition(".")
        if leaf:
            plain.get(head, {}).pop(leaf, None)
        else:
            plain.pop(head, None)
    return plain


def save_checkpoint(path: Path, model, optimizer, step: int, config: dict | None = None) -> None:
    """Atomic, checksummed write of model / optimizer state_dicts, step, RNG and the training's ``config``
    (:func:`training_config`; ``indreg.experiments.checkpoint``)."""
    ckpt.save(path, {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                     "rng": torch.get_rng_state(), "config": config})


def read_checkpoint(path: Path, config: dict | None = None) -> dict:
    """The verified payload of ``path``; with ``config`` (:func:`training_config` of this run) a checkpoint of
    another training is refused, one line naming the keys that differ (``CheckpointError``)."""
    payload = ckpt.load(path, keys=("model", "optimizer", "step", "rng"), hint=RESUME_HINT)
    if config is not None:
        saved = payload.get("config")
        if not isinstance(saved, dict):
            raise ckpt.CheckpointError(f"checkpoint {path} does not record its training's config (written by an "
                                       f"older indreg), so a resume cannot be checked; {RESUME_HINT}")
        mismatch = ckpt.problem_mismatch(saved, config)
        if mismatch:
            raise ckpt.CheckpointError(f"train.resume=true but the config differs from the checkpoint's "
                                       f"({path}): {'; '.join(mismatch)}; run with the checkpoint's values, or "
                                       f"{RESUME_HINT}")
    return payload


def apply_checkpoint(path: Path, payload: dict, model, optimizer) -> int:
    """Restore a payload of :func:`read_checkpoint` into ``model``, ``optimizer`` and the RNG; returns the step."""
    with ckpt.restoring(path, hint=RESUME_HINT):
        model.load_state_dict(payload["model"])
        optimizer.load_state_dict(payload["optimizer"])
        torch.set_rng_state(payload["rng"])
        return int(payload["step"])


def load_checkpoint(path: Path, model, optimizer, config: dict | None = None) -> int:
    """Restore what :func:`save_checkpoint` wrote; returns the step. A damaged, foreign or mismatched file (or, with
    ``config``, one of another training) raises ``CheckpointError`` (one line naming ``path``); nothing but tensors
    and plain data is unpickled."""
    return apply_checkpoint(path, read_checkpoint(path, config), model, optimizer)


# ------------------------------------------------------------------ evaluation
def predict(model, loss, batch: dict, num_updates=None) -> torch.Tensor:
    """Deformed templates of the network's momentum (``bench.network_terms``), no gradient."""
    with torch.no_grad():
        return bench.network_terms(model, model, loss, batch, num_updates)["deformed"]


def heldout_figure(model, parts: dict, dataset, device, count: int = 4, title: str = ""):
    """``count`` held-out examples, one row each: template, FBP(g), the prediction ``W(Lambda(template, FBP),
    template)`` (its SSIM against the target) and the target, on one grey scale a row (the range of template,
    prediction and target; FBP's values beyond it are clipped), with its colour bar."""
    from matplotlib.figure import Figure

    from ..experiments.figures import show_image

    k = min(count, len(dataset))
    batch = gather(dataset, torch.arange(k), device)
    prediction = predict(model, parts["loss"], batch)
    d = parts["domain"]
    extent = (d.min_pt[0], d.max_pt[0], d.min_pt[1], d.max_pt[1])
    fig = Figure(figsize=(11.5, 2.7 * k + 0.5), layout="constrained")
    for i, row in enumerate(fig.subplots(k, 4, squeeze=False)):
        target = batch["target"][i]
        row_images = torch.stack([batch["template"][i], prediction[i], target])
        lo, hi = float(row_images.min()), float(row_images.max())
        shown = [("template", batch["template"][i]), ("FBP", batch["fbp"][i]),
                 (f"prediction (SSIM {ssim(prediction[i], target):.3f})", prediction[i]), ("target", target)]
        for ax, (label, image) in zip(row, shown):
            im = show_image(ax, image.detach().to("cpu", torch.float64).numpy(), f"{i + 1}: {label}",
                            lo, hi, extent, colorbar=False)
        fig.colorbar(im, ax=list(row), fraction=0.03, pad=0.02)
    if title:
        fig.suptitle(title)
    return fig


def validation(parts: dict, model, dataset, device, num_updates=None) -> dict:
    """Held-out ``loss`` and mean ``ssim`` of the network stopped after ``num_updates`` updates (batched)."""
    batch = gather(dataset, torch.arange(len(dataset)), device)
    with torch.no_grad():
        terms = bench.network_terms(model, model, parts["loss"], batch, num_updates)
    return {"loss": float(terms["loss"].mean()), "ssim": float(np.mean([ssim(d, t) for d, t in zip(
        terms["deformed"], batch["target"])]))}


def replica_difference(model, world: int) -> float:
    """Max over ranks of ``max |theta_rank - theta_rank0|`` (0 when DDP kept the replicas identical)."""
    flat = torch.cat([p.detach().reshape(-1) for p in model.parameters()])
    if world == 1:
        return 0.0
    reference = flat.clone()
    dist.broadcast(reference, src=0)
    diff = (flat - reference).abs().max()
    dist.all_reduce(diff, op=dist.ReduceOp.MAX)
    return float(diff)


# ------------------------------------------------------------------ training
def log_validation(writer, parts, model, dataset, device, step: int, unrolled: bool) -> dict:
    """Scalars ``val/loss``, ``val/ssim`` and images of sample 0; while the updates train, also
    ``val/ssim_update_<k>`` and ``val/update_<k>`` after ``k = 0..K`` updates. Returns the scalars."""
    updates = None if unrolled else 0
    scores = validation(parts, model, dataset, device, updates)
    for name, value in scores.items():
        writer.add_scalar(f"val/{name}", value, step)
    item = gather(dataset, torch.tensor([0]), device)
    images = {"template": item["template"][0], "fbp": item["fbp"][0], "target": item["target"][0],
              "prediction": predict(model, parts["loss"], item, updates)[0]}
    if unrolled:
        for k in range(model.num_updates + 1):
            writer.add_scalar(f"val/ssim_update_{k}", validation(parts, model, dataset, device, k)["ssim"], step)
            images[f"update_{k}"] = predict(model, parts["loss"], item, k)[0]
    for name, image in images.items():
        a = torch.rot90(image.detach().float().cpu(), 1, (0, 1)).clamp(0.0, 1.0)
        writer.add_image(f"val/{name}", a[None], step, dataformats="CHW")
    return scores


def training_terms(cfg, net, model, parts, batch, unrolled: bool) -> dict:
    """The loss terms of a batch: the one-shot network's ``m0``, or the unrolled scheme's ``m_K``; an
    ``UnrolledDescent`` adds ``model.supervised`` times ``supervised``, the distance of its deformed template to
    the target, ``||W(K m_K, I) - target||^2`` (L2 in the domain's units)."""
    terms = bench.network_terms(net, model, parts["loss"], batch, None if unrolled else 0)
    weight = float(cfg.model.get("supervised", 0.0))
    if not (unrolled and isinstance(model, UnrolledDescent) and weight > 0):
        return terms
    distance = parts["domain"].cell_volume * (terms["deformed"] - batch["target"]).square().flatten(1).sum(1)
    return dict(terms, supervised=distance, loss=terms["loss"] + weight * distance)


def train(cfg, run_dir) -> dict:
    """Train (resuming from ``<run_dir>/checkpoint.pt`` when ``train.resume``), evaluate, return the metrics."""
    # Longer than 80 lines: one training loop with its checkpoint, validation and logging steps in their order.
    rank, world, device = init_distributed(str(cfg.device))
    dtype = DTYPES[str(cfg.dtype)]
    if world > 1:                          # every rank writes where rank 0 does (Hydra dirs may differ)
        holder = [str(run_dir)]
        dist.broadcast_object_list(holder, src=0)
        run_dir = holder[0]
    run_dir = Path(run_dir)
    checkpoint = run_dir / "checkpoint.pt"
    ckpt.check_location(checkpoint, bool(cfg.train.resume), hint=RESUME_HINT)   # writable, no planted links
    config = training_config(cfg)
    saved = read_checkpoint(checkpoint, config) if bool(cfg.train.resume) and checkpoint.exists() else None
    parts = build(cfg, device, dtype)
    model = parts["model"]
    train_set, val_set = datasets(cfg, parts, dtype)
    optimizer = torch.optim.Adam(parameter_groups(cfg, model), lr=float(cfg.train.lr))
    start = apply_checkpoint(checkpoint, saved, model, optimizer) if saved is not None else 0
    net = model
    if world > 1:     # the one-shot phase leaves the updates unused, the unrolled phase the one-shot network
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device] if device.type == "cuda" else None,
                                                        find_unused_parameters=isinstance(model, bench.UNROLLED))
    writer = None
    if rank == 0:
        from torch.utils.tensorboard import SummaryWriter
        writer = SummaryWriter(str(run_dir / "tensorboard"), purge_step=start + 1)  # drop stale events
    first, steps = schedule(cfg)
    size = int(cfg.train.batch_size)
    t0 = time.perf_counter()
    for step in range(start, steps):
        unrolled = step >= first
        if unrolled and step == first and isinstance(model, bench.UNROLLED):
            calibration = gather(train_set, torch.arange(min(size, len(train_set))), device)
            model.calibrate(calibration["template"], calibration["fbp"], calibration["data"])
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(cfg, step, first, steps) * group["scale"]
        idx = batch_indices(step, int(cfg.seed), size, len(train_set), rank, world)
        batch = gather(train_set, idx, device)
        terms = training_terms(cfg, net, model, parts, batch, unrolled)
        optimizer.zero_grad(set_to_none=True)
        terms["loss"].mean().backward()
        optimizer.step()
        done = step + 1
        names = [k for k in ("loss", "data_fit", "regulariser", "supervised") if k in terms]
        stats = torch.stack([terms[k].detach().mean() for k in names])
        if world > 1:
            dist.all_reduce(stats)
            stats /= world
        if rank == 0 and (done % int(cfg.train.log_every) == 0 or done == steps):
            prefix = "unrolled" if unrolled and isinstance(model, bench.UNROLLED) else "train"
            for name, value in zip(names, stats.tolist()):
                writer.add_scalar(f"{prefix}/{name}", value, done)
            scores = [ssim(d, t) for d, t in zip(terms["deformed"].detach(), batch["target"])]
            writer.add_scalar(f"{prefix}/ssim", float(np.mean(scores)), done)
            print(f"step {done}/{steps} {prefix} loss {stats[0]:.4g} data_fit {stats[1]:.4g} "
                  f"({time.perf_counter() - t0:.1f} s)", flush=True)
        if rank == 0 and (done % int(cfg.train.eval_every) == 0 or done == steps):
            scores = log_validation(writer, parts, model, val_set, device, done,
                                    unrolled and isinstance(model, bench.UNROLLED))
            print(f"step {done}/{steps} val loss {scores['loss']:.4g} ssim {scores['ssim']:.4f}", flush=True)
        if rank == 0 and (done % int(cfg.train.checkpoint_every) == 0 or done == steps):
            save_checkpoint(checkpoint, model, optimizer, done, config)
    metrics = {"model": str(cfg.model.name), "steps": steps, "resumed_from": start, "world_size": world,
               "train_seconds": time.perf_counter() - t0,
               "replica_max_abs_diff": replica_difference(model, world)}
    if rank == 0:
        t1 = time.perf_counter()
        metrics.update(bench.evaluate(cfg, parts, model, val_set, device, dtype))
        metrics["eval_seconds"] = time.perf_counter() - t1
        writer.add_text("eval/metrics", json.dumps(metrics, indent=2), steps)
        with replacing(run_dir / "figure.png") as figure:   # a fresh file renamed over it: no link followed
            title = (f"held-out examples after {steps} steps: mean SSIM {metrics['network']['ssim']:.3f} "
                     f"(template {metrics['network']['template_ssim']:.3f})")
            heldout_figure(model, parts, val_set, device, title=title).savefig(figure, dpi=100)
        writer.close()
        with open_replacing(run_dir / "metrics.json", "w") as f:
            f.write(json.dumps(metrics, indent=2))
        print(json.dumps({k: v for k, v in metrics.items() if k != "ood"}, indent=2), flush=True)
        print(f"outputs in {run_dir.resolve()} (figure: figure.png, metrics.json, tensorboard/)", flush=True)
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return metrics


PROG = "indreg-train-momentum"


def _task(cfg) -> None:
    """The Hydra task; a damaged or foreign checkpoint ends in one line on stderr and exit status 1."""
    from hydra.core.hydra_config import HydraConfig

    from ..experiments import cli

    try:
        train(cfg, HydraConfig.get().runtime.output_dir)
    except ckpt.CheckpointError as e:
        cli.exit_error(PROG, str(e))
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        _leave_rank()


def _leave_rank() -> None:
    """End a torchrun rank whose outputs are written and whose process group is destroyed, without the interpreter's
    finalisation: there gloo's worker threads, torn down with the interpreter, now and then abort the process
    ("terminate called without an active exception", SIGABRT, and torchrun reports the run failed; seen once in
    CI with torch 2.13.0 on two CPU ranks, pytorch/pytorch#179291 describes the race)."""
    import logging
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(0)


def base_config(overrides=()):
    """``train_momentum.yaml`` without Hydra's sections, the model chosen by ``model=<name>`` in ``overrides``
    (default ``oneshot``, ``indreg/learn/conf/model/``) under ``model``: every key this app reads. An unknown model
    gets no keys (the composition then names the options)."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(CONFIG_DIR / f"{CONFIG_NAME}.yaml")
    cfg.pop("hydra")
    cfg.pop("defaults")
    name = next((o.split("=", 1)[1] for o in overrides if o.startswith("model=")), "oneshot")
    path = MODEL_DIR / f"{name}.yaml"
    cfg.model = OmegaConf.load(path) if path.is_file() else {}
    return cfg


def main() -> None:
    """Console entry point ``indreg-train-momentum`` (Hydra parses ``sys.argv``; config
    ``indreg/learn/conf/train_momentum.yaml``). The command line is checked first (``indreg.experiments.cli``; Hydra's
    ``--experimental-rerun`` and its prefixes, which unpickle a file, and Hydra settings that run code or write
    outside the run directory exit 2: :func:`indreg.experiments.cli.guard`)."""
    import sys

    import hydra

    from ..experiments import cli

    cli.guard(sys.argv[1:], PROG)
    cli.preflight(sys.argv[1:], PROG, CONFIG_DIR, CONFIG_NAME, validate=check_config, base=base_config(sys.argv[1:]))
    hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=CONFIG_NAME)(_task)()


if __name__ == "__main__":
    main()
