"""The evaluation steps of the measured-data walk-throughs (examples/real_data_haadf.py, examples/real_data_walnut.py;
docs/evaluation.md): the split of the registered volume and its check, the flagged-voxel test of the uncertainty,
the edge validation's table on the missing range, and the files ``indreg-score`` reads to print their tables again.

Convention: volumes ``(nx, ny[, nz])`` as numpy arrays or tensors; ``T`` / ``Y``: operators and data (background
removed) by set (``fit``, ``validation``, ``test``); scores from ``indreg.evaluation.score`` (the walk-throughs'
own).
"""
from __future__ import annotations

import json
import shlex
from pathlib import Path

import numpy as np
import torch

from indreg.evaluation.score import relative_residual
from indreg.evaluation.parts import data_split, wedge_split

__all__ = ["split_check", "flagged_voxels", "extrapolation_table", "write_scored", "evaluation_png"]


def split_check(result) -> dict:
    """The split of ``result.deformed`` against the fitted operator, by the range of ``T^*`` (the result's) and,
    where the geometry is parallel, by the measured wedge: each part's share and how far the prior-filled part
    projects on the fitted tilts (relative to the volume's projections)."""
    T, f = result.problem.ray_transform, result.deformed.detach().double()
    out = {"range": data_split(f, T).summary()}
    try:
        out["wedge"] = wedge_split(f, T).summary()
    except TypeError:   # a fan beam: no wedge
        pass
    return out


def flagged_voxels(volume, sd, replacement, T, y, fraction: float = 0.05, draws: int = 20, seed: int = 0,
                   refit_draws: int = 5, refit_iterations: int = 30) -> dict:
    """Does the reported uncertainty flag the worst voxels? The ``fraction`` of voxels with the largest ``sd``
    replaced by ``replacement``'s (e.g. TV's), against as many voxels drawn at random (``draws`` times): the
    relative residual on the tilts ``T``, ``y`` (the missing wedge's) of each, and of the volume as it is. And a
    measure that needs no replacement: the residual left when only those voxels are fitted to the tilts
    (:func:`refitted`), against the first ``refit_draws`` random sets."""
    f = torch.as_tensor(np.asarray(volume, dtype=np.float64))
    s = torch.as_tensor(np.asarray(sd, dtype=np.float64)).reshape(-1)
    other = torch.as_tensor(np.asarray(replacement, dtype=np.float64)).reshape(-1)
    k = max(1, int(round(fraction * s.numel())))

    def replaced(idx) -> float:
        g = f.reshape(-1).clone()
        g[idx] = other[idx]
        return relative_residual(T, g.reshape(f.shape), y)

    rng = np.random.default_rng(seed)
    sets = [torch.as_tensor(rng.choice(s.numel(), k, replace=False)) for _ in range(draws)]
    random = [replaced(idx) for idx in sets]
    flagged = torch.topk(s, k).indices
    refit = [refitted(T, f, y, idx, refit_iterations) for idx in sets[:refit_draws]]
    return {"fraction": fraction, "voxels": k, "as_is": relative_residual(T, f, y),
            "flagged_replaced": replaced(flagged), "random_replaced_mean": float(np.mean(random)),
            "random_replaced_min": float(np.min(random)), "random_replaced_max": float(np.max(random)),
            "flagged_refitted": refitted(T, f, y, flagged, refit_iterations),
            "random_refitted_mean": float(np.mean(refit)), "random_refitted_min": float(np.min(refit)),
            "random_refitted_max": float(np.max(refit))}


def refitted(T, volume: torch.Tensor, y, voxels, iterations: int = 30) -> float:
    """The relative residual on ``T``, ``y`` after ``iterations`` of CGLS change only ``voxels`` (flat indices) of
    ``volume`` to fit them: how much of those tilts' error the voxels can hold, whatever the right values."""
    from indreg.evaluation.parts import cgls
    from indreg.forward.algebra import ImageOperator

    f = volume.to(torch.float64)
    mask = torch.zeros(f.numel(), dtype=f.dtype)
    mask[voxels] = 1.0
    mask = mask.reshape(f.shape)
    y = torch.as_tensor(y).to(f.dtype)
    d, _ = cgls(T * ImageOperator(T.domain, lambda x: x * mask), y - T(f), 0.0, iterations)
    return relative_residual(T, f + d, y)


def extrapolation_table(volumes: dict, T: dict, Y: dict, choice) -> dict:
    """Every volume's relative residual on the test tilts (the missing range) and the validation ones, the edge
    validation's ``choice`` (``indreg.registration.extrapolation.Extrapolation``) beside them."""
    rows = {name: {"test_residual": relative_residual(T["test"], v, Y["test"]),
                   "validation_residual": relative_residual(T["validation"], v, Y["validation"])}
            for name, v in volumes.items()}
    return {"rows": rows, **choice.summary()}


def write_scored(out: Path, stack: np.ndarray, degrees: np.ndarray, sets: dict, operator=None,
                 interpolation: str = "linear", pixel_angstrom: float = 1.0, volumes=(), background: float = 0.0,
                 length_unit: str = "nm") -> str:
    """``out/stack.npy`` + ``stack.tlt`` (the scored tilts as the walk-through scores them: binned, turned, in
    counts, background not removed), ``alignment.{xf,aln,json}`` of ``operator`` (an ``AlignedOperator`` over those
    tilts) when given, and the ``indreg-score`` command that prints the walk-through's table again from them
    (``sets``: name -> indices into ``stack``; ``volumes``: the MRC files to score, relative to ``out``'s
    parent). Returns the command."""
    from indreg.alignment.files import write_alignment

    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "stack.npy", np.ascontiguousarray(stack, dtype=np.float64))
    (out / "stack.tlt").write_text("".join(f"{a:.10g}\n" for a in degrees))
    cmd = ["indreg-score", f"{out.name}/stack.npy", *volumes, "--angles", f"{out.name}/stack.tlt",
           "--pixel-size", repr(float(pixel_angstrom)), "--length-unit", length_unit, "--background",
           repr(float(background))]
    if operator is not None:
        write_alignment(out, operator, pixel_size=pixel_angstrom, extra={"interpolation": interpolation})
        cmd += ["--alignment", f"{out.name}/alignment.json"]
    for name, idx in sets.items():
        cmd += ["--tilts", f"{name}=" + ",".join(str(int(i)) for i in idx)]
    (out / "sets.json").write_text(json.dumps({k: [int(i) for i in v] for k, v in sets.items()}))
    return shlex.join(cmd)


def evaluation_png(result, path: Path, box, unit: str, title: str, tilt=None) -> None:
    """``indreg.experiments.evaluation_figure`` of the registered volume: its data-determined and prior-filled parts on one
    scale, its standard deviation."""
    from indreg.experiments.evaluation_figure import evaluation_figure

    fig = evaluation_figure(result.deformed, result.data_part, result.prior_part, result.uncertainty, box, unit,
                            title, tilt)
    fig.savefig(path, dpi=100)
