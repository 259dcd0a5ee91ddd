"""``indreg-align``'s path for a slab specimen (wider than the detector): what the stack is (``--specimen``), the
line integrals of bright-field intensities (``--intensities``), the alignment (``indreg.alignment.slab``: the
stretched cross-correlation, then leave-one-out projection matching through the wide box), the tilt axis' angle by
common lines (``indreg.alignment.axis_search``), the gold beads' fit where the stack holds them
(``indreg.alignment.fiducials``, ``--fiducials``) and the reconstruction on the wide box.

Notes
-----
- ``--specimen auto`` asks the detector's border (``indreg.units.border.check_border``): ``"specimen"`` (no vacuum:
  the specimen runs beyond the detector) takes this path, ``"vacuum"`` or ``"unclear"`` the compact one.
- The shifts come back as the maps of the quarter-turned stack, ``p = M q + d`` with ``M = R(alpha)`` and ``d =
  R(alpha) v`` (``indreg.alignment.xcorr``'s Notes), in its full-size pixels.
"""
from __future__ import annotations

import logging

import numpy as np

__all__ = ["SPECIMENS", "line_integrals", "slab_alignment", "slab_background", "specimen_kind", "wide_reconstruction"]

log = logging.getLogger("indreg.align")

SPECIMENS = ("auto", "compact", "slab")


def specimen_kind(stack: np.ndarray, radians: np.ndarray, spec: str) -> tuple:
    """``("slab" | "compact", reason)`` for ``--specimen spec`` (module Notes)."""
    if spec not in SPECIMENS:
        raise ValueError(f"--specimen must be one of {', '.join(SPECIMENS)}, got {spec!r}")
    if spec != "auto":
        return spec, "given (--specimen)"
    import torch

    from ..units.border import check_border
    from .moments import binned_within

    small = binned_within(stack)[0]
    check = check_border(torch.from_numpy(np.ascontiguousarray(small, dtype=np.float64)), radians)
    kind = "slab" if check.kind == "specimen" else "compact"
    return kind, f"the detector's border: {check.describe()}"


def line_integrals(stack: np.ndarray, radians: np.ndarray) -> tuple:
    """``(p, how)``: ``-ln(I / I0)`` of bright-field intensities (``indreg.units.transmission.line_integrals``: I0 from
    vacuum at the border, else the slab law), float32."""
    import torch

    from ..units.transmission import line_integrals as _line_integrals

    p, t = _line_integrals(torch.from_numpy(np.ascontiguousarray(stack, dtype=np.float64)), radians,
                           label="--intensities")
    return p.numpy().astype(np.float32), t.how


def slab_alignment(lines: np.ndarray, radians: np.ndarray, rest: float, steps: list, rounds: int,
                   fine_rounds: int, thickness, bound: tuple, search_axis: bool, fiducials: str = "auto") -> dict:
    """Align the quarter-turned stack of line integrals ``lines`` (tilt axis ``rest`` degrees from Y) coarse to
    fine over the binnings ``steps``; with ``search_axis`` the angle by common lines after the coarsest level
    (kept where determined); with ``fiducials="auto"`` the gold beads then fix the shifts (and, with
    ``search_axis``, the angle) at full size where they can (``indreg.alignment.fiducials``), in place of the finer
    levels. Returns ``M`` ``(K, 2, 2)``, ``d`` ``(K, 2)`` (module Notes), the ``SlabAlignment``, the axis search
    (or None), the beads' fit (or None), the angle used."""
    from dataclasses import replace

    from .axis_search import search_axis_angle
    from .fiducials import fiducial_alignment
    from .slab import binned, slab_projection_matching

    def progress(r):
        log.info("slab: bin %d, round %s: largest move %.2f px, mean peak %.3f, %.0f s", r["bin"], r["round"],
                 r.get("largest_move_px", 0.0), r["peak_mean"], r["seconds"])

    counts = [rounds] + [fine_rounds] * (len(steps) - 1)
    result = slab_projection_matching(lines, radians, rest, steps[:1], counts[:1], thickness, bound, None, progress)
    search = None
    if search_axis:
        b = steps[min(1, len(steps) - 1)]
        search = search_axis_angle(binned(lines, b), radians, rest, result.shifts / b)
        log.info("slab: %s", search.describe())
        if search.determined:
            rest = search.angle_deg
        else:
            log.warning("slab: the tilt-axis angle is not determined by common lines (%s): the given %.2f deg kept",
                        search.reason, rest)
    beads = None if fiducials == "off" else fiducial_alignment(lines, radians, rest, result.shifts, search_axis)
    if beads is not None:
        log.info("fiducials: %s", beads.describe())
    if beads is not None and beads.determined:
        rest = beads.angle_deg if beads.angle_deg is not None else rest
        at = np.abs(beads.shifts) >= np.array(result.bound) - 1e-6
        result = replace(result, shifts=beads.shifts, at_bound=at)
    elif len(steps) > 1 or search is not None and search.determined:
        result = slab_projection_matching(lines, radians, rest, steps[1:] or steps[-1:], counts[1:] or [1],
                                          result.thickness, bound, result.shifts, progress, result.centre)
    from .xcorr import _rotation

    R = _rotation(rest)
    M = np.tile(R, (len(radians), 1, 1))
    return {"M": M, "d": result.shifts @ R.T, "result": result, "search": search, "fiducials": beads,
            "rest": rest}


def wide_reconstruction(aligned: np.ndarray, radians: np.ndarray, thickness: float, centre: float, iters: int):
    """Nonnegative SIRT of the aligned stack ``(K, ny, nx)`` (unit voxels) on the wide box of a slab ``thickness``
    px deep about ``centre``: the volume ``(nx_wide, ny, nz)`` and its relative data residual."""
    import torch

    from ..forward.sirt import sirt
    from .slab import slab_operators

    T, _ = slab_operators(radians, aligned.shape[2], aligned.shape[1], thickness, centre)
    data = torch.from_numpy(np.ascontiguousarray(aligned, dtype=np.float32))
    x, history = sirt(T, data, num_iter=iters, nonneg=True)
    return x, float(history["data_residual"][-1] / T.inner_data(data, data).sqrt())


def slab_background(stack: np.ndarray, radians: np.ndarray, spec: str, otherwise) -> float:
    """A slab's level for ``--background``: ``auto`` the slab law's intercept over the views' means (a slab's line
    integrals have no offset; ``indreg.units.border.background_level``), else ``otherwise(stack, spec)``."""
    if spec != "auto":
        return otherwise(stack, spec)
    import torch

    from ..units.border import background_level

    level, _, how = background_level(torch.from_numpy(np.ascontiguousarray(stack, dtype=np.float64)), radians)
    log.info("background: %s (%.6g subtracted)", how, level)
    return float(level)
