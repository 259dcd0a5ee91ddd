"""The final outputs of a run in its directory: arrays, ``metrics.json``, ``history.json``, the figures, and the
log's headline (``finish``); a failed run's record (``failed``).

Convention: arrays are saved as float64 ``.npy`` in the layout of ``indreg.registration.run.build_result``
(images ``(nx, ny)``, volumes ``(nx, ny, nz)``, a model's stacks with a leading axis, e.g. frames ``(K, nx, ny)``),
except that files read in another tool's convention (``data.convention``, 2D) get their images back in that layout
and the data as that tool holds them (:func:`as_given`: the user compares ``final.npy`` with a ground truth as
held); the vector fields (``velocity``, ``momentum``, ``deformation``: component 0 = x) stay in indreg's, which
``outputs.json`` says per file. SSIM / PSNR use the target's data range; a stack's figures of merit are the means
over its first axis.

Memory: a volume's outputs are written without a float64 copy of a whole array (:func:`save_array` converts in
chunks), its trajectory frame by frame (``problem.image_frames``: slab-wise, one fine volume at a time; only the
frames the figures show are kept, and only when figures or TensorBoard are on), its figures of merit in float64
chunks (``indreg.metrics``).
"""
from __future__ import annotations

import json
import logging
import math
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from .._outfiles import open_replacing, replacing
from ..options import CORRECTIONS
from ..registration.run import build_result, count_halvings, count_rejected
from ..tally import summary as warning_summary
from .baselines import tv_mu
from .config import to_plain
from .run_figures import to_numpy, write_figures

__all__ = ["figures_of_merit", "output_fom", "finish", "failed", "hyperparameters", "quality", "save_array",
           "save_frames", "save_rows", "write_outputs_record", "as_given", "VECTOR_FIELDS"]

log = logging.getLogger("indreg.experiments.register")

#: Values converted to float64 at a time when an array is written (32 MiB).
SAVE_CHUNK = 2 ** 22
#: Outputs that are vector fields (component 0 = x): no tool's convention here defines their layout (scikit-image's
#: coordinate maps are (row, column) pixel indices, ASTRA, TomoPy and IMOD have none); written in indreg's.
VECTOR_FIELDS = ("velocity", "momentum", "deformation")


def figures_of_merit(image, target_64, paper: bool = True, units=None) -> dict:
    """SSIM / PSNR against the target (data range of the target) and, for the paper's phantoms (``paper``:
    grey levels 0..1), also in the paper's convention (``ssim_paper`` / ``psnr_paper``: a fixed data range 2 / 1
    that means nothing for other units; docs/paper_notes.md). ``units`` (``indreg.units.Units``): the image, in
    the run's units, is scored in the target's (``units.to_target_units``)."""
    from .. import metrics

    x = image.detach() if image.dim() == 3 else image.detach().to("cpu", torch.float64)   # volumes: in chunks
    x = x if units is None else units.to_target_units(x)
    out = {"ssim": metrics.ssim(x, target_64), "psnr": metrics.psnr(x, target_64)}
    if paper:
        out.update(ssim_paper=metrics.ssim_paper(x, target_64), psnr_paper=metrics.psnr_paper(x, target_64))
    return out


def output_fom(image, truth, ndim: int) -> dict:
    """SSIM / PSNR of a model's output against its ground truth; a stack (one more axis than the domain's, e.g.
    frames) gets the means over its first axis."""
    if truth.dim() == ndim:
        return figures_of_merit(image, truth, paper=False)
    each = [figures_of_merit(a, b, paper=False) for a, b in zip(image, truth)]
    return {k: sum(e[k] for e in each) / len(each) for k in each[0]}


def hyperparameters(cfg: DictConfig, exp) -> dict:
    """The run's parameters shown in TensorBoard's HParams tab and in metrics.json (the model adds its own)."""
    o = exp.options
    return {"gamma": float(o["gamma"]), "sigma": float(o["sigma"]), "N": int(o["num_steps"]), "model": o["model"],
            "step_size": exp.solver.reported_step(), "action": o["action"], "solver": o["solver"],
            "template": exp.label, "size": int(exp.domain.shape[0]), "max_iter": int(o["max_iter"]),
            "dtype": cfg.dtype.value,
            "seed": int(cfg.seed), **exp.problem.hparams()}


def _json_float(v):
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


def _npy(stack: ExitStack, path: Path, shape: tuple):
    """``path`` opened (in ``stack``; :func:`indreg._outfiles.open_replacing`: a fresh file renamed over ``path``
    when ``stack`` closes, no link followed) for a float64 ``.npy`` of ``shape``, its header written (``np.save``'s):
    the values follow in C order. Written, not memory-mapped: a mapped file's pages would count in the process's
    resident memory."""
    f = stack.enter_context(open_replacing(path))
    np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": tuple(shape)})
    return f


def save_array(path: Path, a) -> None:
    """``a`` (a tensor, any dtype / device) as a float64 ``.npy`` at ``path``, converted :data:`SAVE_CHUNK` values
    at a time (the file ``np.save`` of the float64 array writes, without that array)."""
    with ExitStack() as stack:
        save_rows(_npy(stack, path, a.shape), a)


def save_frames(path: Path, frames, count: int, keep=()) -> dict:
    """The ``count`` frames of the iterator ``frames`` (tensors of one shape) as one float64 ``.npy`` ``(count,
    *shape)`` at ``path``, written as they come; returns the frames of the indices ``keep`` (in their dtype)."""
    kept, f, i = {}, None, -1
    with ExitStack() as stack:
        for i, frame in enumerate(frames):
            if i >= count:
                raise ValueError(f"save_frames: expected {count} frames, got more")
            f = f or _npy(stack, path, (count, *frame.shape))
            save_rows(f, frame)
            if i in keep:
                kept[i] = frame
        if i + 1 != count:
            raise ValueError(f"save_frames: expected {count} frames, got {i + 1}")
    return kept


def save_rows(f, a) -> None:
    """``a``'s values in float64 (C order) written to the open file ``f``, :data:`SAVE_CHUNK` at a time."""
    flat = a.detach().reshape(-1)
    for i in range(0, flat.numel(), SAVE_CHUNK):
        f.write(to_numpy(flat[i:i + SAVE_CHUNK]).tobytes())


def write_json(out: Path, history: list, result: dict) -> None:
    """``history.json`` and ``metrics.json`` (non-finite floats as strings), each written to a fresh file renamed
    over the old one (no link followed)."""
    with open_replacing(out / "history.json", "w") as f:
        json.dump([{k: _json_float(v) for k, v in h.items()} for h in history], f)
    with open_replacing(out / "metrics.json", "w") as f:
        json.dump({k: _json_float(v) for k, v in result.items()}, f, indent=2)


def failed(out: Path, history: list) -> dict:
    """A run whose objective or gradient became non-finite: ``metrics.json`` and ``history.json`` say so."""
    last = history[-1]
    result = {"status": "failed", "iteration": last["iteration"], "objective": last["objective"],
              "grad_norm": last["grad_norm"], "evaluations": last["evaluations"],
              "warning": last["warning"] or "non-finite gradient norm"}
    write_json(out, history, result)
    log.error("failed at iteration %d: %s (%s is not overwritten: it keeps the last periodic checkpoint, if any)",
              result["iteration"], result["warning"], out / "checkpoint.pt")
    return result


def finish(cfg, exp, state, rec, history, seconds, out: Path, writer, status: str) -> dict:
    """Final outputs: arrays, metrics.json, history.json, figure.png, TensorBoard images and hparams, from the
    result that ``indreg.register`` would return (``indreg.registration.run.build_result``).

    Without a target (measured data) SSIM / PSNR, ``target.npy`` and ``data_clean.npy`` are absent; the relative
    data residual ``residual = ||T f - g|| / ||g||`` is always reported. The model's own outputs (e.g. a source and
    the parts of f(1)) are saved by name; those it scores (``problem.scored``) get SSIM / PSNR."""
    # Longer than 80 lines: the end of a run in its order (result, metrics, files, figures, record, the last line),
    # each a call sharing the run's arrays.
    from .tblog import METRICS

    problem, it = exp.problem, state.iteration
    log.info("writing the outputs (arrays, metrics, figures, TensorBoard) in %s", out)
    volume = exp.domain.ndim == 3   # the trajectory frame by frame (save_frames), not N + 1 volumes at once
    from ..registration.once import evaluation_options

    r = build_result(problem, state, history, seconds, status, units=exp.units, validation=exp.validation,
                     trajectory=not volume, orientation=exp.setup.orientation, solver=exp.solver, box=exp.box,
                     evaluation=evaluation_options(exp.options))
    wide = r.deformed
    if exp.box is not None:   # a wide box: files, figures and scores of the field of view; final_wide.npy whole
        r = replace(r, **{k: exp.field(getattr(r, k)) for k in ("deformed", "velocity", "momentum", "deformation",
                                                                 "trajectory", "data_part", "prior_part",
                                                                 "uncertainty")},
                    outputs={k: exp.field(v) for k, v in r.outputs.items()})
    target = exp.target_64
    result = {}
    if target is not None:
        def fom(image):
            return figures_of_merit(image, target, exp.paper, exp.units)

        result.update(fom(r.deformed))
        for name, image in rec.items():
            result.update({f"{name}_{k}": v for k, v in fom(image).items()})
        result.update({f"template_{k}": v for k, v in fom(exp.template_64).items()})
        for name in problem.scored:
            result.update({f"{name}_{k}": v for k, v in fom(r.outputs[name]).items()})
    for name, truth in exp.targets.items():   # a model's outputs against their own ground truths
        if name in r.outputs:
            result.update({f"{name}_{k}": v for k, v in output_fom(r.outputs[name], truth, exp.domain.ndim).items()})
    result.update(r.terms)
    result.update({
        "status": r.status, "residual": r.residual, "iterations": it,
        "seconds_per_iteration": seconds / max(len(history), 1), "seconds": seconds, "min_jacobian": r.min_jacobian,
        "grad_norm": history[-1]["grad_norm"] if history else float("nan"),
        "evaluations": history[-1]["evaluations"] if history else 0,
        "warnings": r.warnings, "warnings_by_kind": r.warnings_by_kind, "objective_rises": r.objective_rises,
        "poor_fit": bool(r.poor_fit), "rejected_steps": count_rejected(history), "halvings": count_halvings(history),
        **exp.units.as_dict(), **({"tv_mu_absolute": tv_mu(cfg, exp)} if "tv" in rec else {}),
        "device": str(exp.template.device), "hparams": hyperparameters(cfg, exp), "config": to_plain(cfg)})
    result.update(r.holdout)
    result["sigma"] = float(exp.options["sigma"])
    if exp.setup.sigma_scores:   # sigma="auto": each width's held-out residual
        result["sigma_auto"] = {f"{w:.6g}": v for w, v in exp.setup.sigma_scores.items()}
    if _convention(exp).name != "indreg":   # the files' layout, in which the arrays are written (as_given)
        result["layout"] = _convention(exp).name
    result.update(r.evaluation)
    for name, summary in r.corrections.items():   # the in-the-fit corrections' estimates, and their plots
        result[name] = summary
        plot = getattr(CORRECTIONS.get(name), "plot", None)
        if plot is not None:
            with replacing(out / f"{name}.png") as path:   # alignment.png: shifts per tilt, the tilt-axis angle
                plot(summary, path)
    result.update(exp.report)
    if exp.snr_db is not None:
        result.update({"snr_db": exp.snr_db, "snr_convention": cfg.noise.convention.value})
    arrays = {"final": r.deformed, "velocity": r.velocity, "momentum": r.momentum, "deformation": r.deformation,
              "template": exp.template_64, "data": exp.noisy_data_64, **rec, **r.outputs}
    arrays.update({} if volume else {"trajectory": r.trajectory})
    arrays.update({} if exp.box is None else {"final_wide": wide})
    arrays.update({k: v for k, v in (("data_part", r.data_part), ("prior_part", r.prior_part),
                                     ("uncertainty", r.uncertainty)) if v is not None})
    if target is not None:
        arrays["target"] = target
    if exp.clean_data_64 is not None:
        arrays["data_clean"] = exp.clean_data_64
    arrays = {name: a for name, a in arrays.items() if a is not None}   # deformation: None beyond max_memory
    for name, a in arrays.items():
        save_array(out / f"{name}.npy", as_given(name, a, exp))
    frames = None
    if volume:   # the registered volume for IMOD / ChimeraX too (voxel size in the header)
        from ..io import write_volume
        from .run_figures import shown_frames
        with replacing(out / "final.mrc") as path:
            write_volume(path, r.deformed.detach().cpu().numpy(), exp.domain)
        shown = shown_frames(r.velocity.shape[0] - 1) if cfg.logging.figure or writer.enabled else ()
        frames = save_frames(out / "trajectory.npy", (exp.field(f) for f in problem.image_frames(state.iterate)),
                             r.velocity.shape[0], shown)
    write_json(out, history, result)
    write_figures(cfg, exp, r, rec, quality(result, exp, r.outputs), out, writer, it, frames, result, wide)
    writer.baselines(result, rec, it)
    writer.metrics(result, it)
    writer.hparams(result["hparams"], {k: result[k] for k in (*METRICS, "residual", "holdout_residual")
                                                        if k in result})
    write_outputs_record(out, exp, arrays, corrections=tuple(r.corrections))
    done = f"{r.status}: {it} iterations" if r.status != "completed" else f"done: {it} iterations"
    done += " (poor fit: see the warning)" if r.poor_fit else ""
    if "sigma_auto" in result:
        done += f" with sigma {result['sigma']:.4g} (sigma=auto)"
    if target is not None:
        paper = f" (paper convention {result['ssim_paper']:.4f} / {result['psnr_paper']:.2f})" if exp.paper else ""
        log.info("%s, %s%s; FBP %s; SIRT %s; TV %s; %s", done, quality(result, exp, r.outputs), paper,
                 _pair(result, "fbp"), _pair(result, "sirt"), _pair(result, "tv"),
                 warning_summary(r.warnings, r.warnings_by_kind))
    else:
        log.info("%s, objective %.6g, relative data residual %.4f, min Jacobian %.4g; %s", done,
                 result["objective"], result["residual"], result["min_jacobian"],
                 warning_summary(r.warnings, r.warnings_by_kind))
    if r.holdout:
        log.info("held-out angles %s: relative residual %.4f (least %.4f at iteration %s)",
                 r.holdout["holdout_indices"], r.holdout["holdout_residual"], r.holdout["holdout_best_residual"],
                 r.holdout["holdout_best_iteration"])
    return result


def _convention(exp):
    """The convention the run's arrays are written in: the files' (2D) or indreg's."""
    from ..io import conventions

    name = getattr(exp.data, "convention", "indreg") if exp.domain.ndim == 2 else "indreg"
    return conventions.get_convention(name)


def as_given(name: str, a, exp):
    """An output in the layout of the user's files (``data.convention``, 2D; ``indreg.io.conventions``).

    Parameters
    ----------
    name : str
        The output's name (its file's stem): ``data`` / ``data_clean`` are written as that tool holds a sinogram
        (``sinogram_from_indreg``: its axis order, pixel sums), every image or stack of images ``(..., nx, ny)``
        turned or transposed (``images_from_indreg``), the :data:`VECTOR_FIELDS` as they are.
    a : torch.Tensor
        The output in indreg's layout.
    exp : Experiment
        The run (its data's convention and domain).

    Returns
    -------
    torch.Tensor
        ``a`` in that layout (a view where it can be).
    """
    from ..io import conventions

    c = _convention(exp)
    if c.name == "indreg" or name in VECTOR_FIELDS:
        return a
    if name in ("data", "data_clean"):
        g = a / exp.domain.cell_sides[0] if c.pixel_units else a
        return g.transpose(-2, -1) if c.sinogram == "bin_angle" else g
    return conventions.images_from_indreg(a, c) if tuple(a.shape[-2:]) == tuple(exp.domain.shape) else a


#: The figures a finished run may write, in the order its last line names them.
FIGURES = ("figure.png", "parts.png", "frames.png", "frames.gif", "alignment.png", "evaluation.png")

#: The registration app's outputs besides its arrays (``<name>.npy``) and figures; what ``outputs.json`` lists.
OWN_FILES = ("metrics.json", "history.json", "final.mrc", "trajectory.npy", "checkpoint.pt", "baselines.npz",
             "tensorboard", ".hydra", "outputs.json")


def own_names(out: Path, arrays=(), corrections=()) -> list:
    """The names of the run's own outputs in ``out`` (:data:`OWN_FILES`, the arrays, the figures, the corrections'
    plots, the log files of this process's logging in ``out`` and Hydra's config directory): the record lists
    these only."""
    names = [*OWN_FILES, *FIGURES, *(f"{a}.npy" for a in arrays), *(f"{c}.png" for c in corrections)]
    for handler in logging.getLogger().handlers:
        path = Path(getattr(handler, "baseFilename", "") or "/")
        if isinstance(handler, logging.FileHandler) and path.parent == Path(out).resolve():
            names.append(path.name)
    try:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized() and HydraConfig.get().output_subdir:
            names.append(str(HydraConfig.get().output_subdir))
    except (ImportError, ValueError):
        pass
    return names


def write_outputs_record(out: Path, exp, arrays: dict, corrections=()) -> dict | None:
    """``outputs.json``: the run's own outputs (:func:`own_names`) with their format, the tool that wrote each and
    its version (``indreg.io.provenance``), and for the arrays and ``final.mrc`` the conventions: axis order, the
    voxel size and origin (the centre of voxel 0) in the domain's length unit, data layout (module Notes).
    A record that cannot be written is a warning (``None``), never the end of a finished run."""
    try:
        return _write_outputs_record(out, exp, arrays, corrections)
    except (OSError, ValueError) as e:
        log.warning("outputs.json not written: %s", " ".join(str(e).split()))
        return None


def _write_outputs_record(out: Path, exp, arrays: dict, corrections) -> dict:
    from ..io.conventions import describe_layout
    from ..io.provenance import write_record

    d = exp.domain
    h = list(d.cell_sides)
    grid = {"voxel_size": h, "origin": [a + c / 2 for a, c in zip(d.min_pt, h)], "length_unit": "the domain's"}
    image = {"axis_order": "(nx, ny, nz), axis 0 = x" if d.ndim == 3 else "(nx, ny), axis 0 = x", **grid}
    data = {"axis_order": "(tilts, rows, columns)" if d.ndim == 3 else "(angles, detector bins)",
            "values": "line integrals in the domain's length unit times the image's"}
    grid_axes = "(nx, ny, nz)" if d.ndim == 3 else "(nx, ny)"
    layouts = {"trajectory": f"(N + 1 time steps, *{grid_axes})", "velocity": f"(N + 1, d components, *{grid_axes})",
               "momentum": f"(N + 1, d components, *{grid_axes})",
               "deformation": f"(d components, *{grid_axes}): phi_(1,0), points in the domain's length unit"}
    images = {"final", "template", "target", "fbp", "tv", "sirt", "data_part", "prior_part", "uncertainty"}
    layouts.update({name: image["axis_order"] for name in images})
    c = _convention(exp)
    if c.name != "indreg":   # the files' convention (as_given)
        image["axis_order"] = f"{c.name}'s: {describe_layout(c)}"
        layouts.update({name: f"(N + 1 time steps, ...) of images {c.name}'s: {describe_layout(c)}" if
                        name == "trajectory" else image["axis_order"] for name in ("trajectory", *images)})
        data = {"axis_order": "(detector bins, angles)" if c.sinogram == "bin_angle" else "(angles, detector bins)",
                "values": "pixel sums (line integrals in pixels)" if c.pixel_units else data["values"],
                "convention": c.name}
        image["convention"] = c.name
    conventions = {f"{name}.npy": data if name.startswith("data") else {**image, "axis_order": layouts.get(
        name, f"(..., *{grid_axes}): a model's output, its leading axes its own")} for name in (*arrays, "trajectory")}
    for name in VECTOR_FIELDS:   # indreg's layout whatever the files' convention
        conventions[f"{name}.npy"] = {**grid, "axis_order": layouts[name]}
    conventions["final.mrc"] = {"voxel_size_unit": "the domain's length unit (MRC readers: Angstrom)"}
    if exp.box is not None:   # the whole wide box: its own grid
        w = exp.box.domain
        conventions["final_wide.npy"] = {**image, "voxel_size": list(w.cell_sides), "origin": [
            a + c / 2 for a, c in zip(w.min_pt, w.cell_sides)], "note": "the wide box (data.wide_box); the other "
            "images are its field of view"}
    return write_record(out / "outputs.json", out, own_names(out, (*arrays, "trajectory"), corrections), conventions,
                        run="indreg-register")


def quality(result: dict, exp, outputs: dict) -> str:
    """The run's figures of merit in one phrase (the log's headline, the figures' titles): the model's own summary
    where it has one, a stack of outputs with its truth (e.g. frames: the means over the frames), else the
    reconstruction's SSIM / PSNR against the target, else the relative data residual."""
    for name, truth in exp.targets.items():
        if name in outputs and truth.dim() > exp.domain.ndim and f"{name}_ssim" in result:
            return (f"SSIM {result[f'{name}_ssim']:.4f}, PSNR {result[f'{name}_psnr']:.2f} dB (means over the "
                    f"{truth.shape[0]} {name})")
    if exp.target_64 is not None:
        return f"SSIM {result['ssim']:.4f}, PSNR {result['psnr']:.2f} dB"
    return f"relative data residual {result['residual']:.4f}"


def _pair(result: dict, name: str) -> str:
    if f"{name}_ssim" not in result:
        return "off"
    return f"{result[f'{name}_ssim']:.4f} / {result[f'{name}_psnr']:.2f}"
