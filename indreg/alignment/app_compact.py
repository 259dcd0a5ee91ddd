"""``indreg-align``'s path for a compact specimen (inside the detector at every tilt): the tilt axis' rest from the
stack's moment conditions (``--axis-from-stack``) and projection matching coarse to fine
(``indreg.alignment.fit.projection_matching``), as ``indreg.alignment.app``'s module docstring describes."""
from __future__ import annotations

import logging
import math
import time

import numpy as np

from .app import _bin, _binned_operator, _in_stack_pixels, _operator, _rotation, working_set

__all__ = ["compact_alignment"]

log = logging.getLogger("indreg.align")


def _stack_rest(stack: np.ndarray, radians: np.ndarray, rest: float) -> tuple:
    """``--axis-from-stack``: the tilt axis' angle in the quarter-turned ``stack`` (less its background) from its
    moment conditions where they determine it, else ``rest`` with a warning; and a record of the estimate."""
    from .moments import MAX_PIXELS, SCAN_DEG, estimate_axis_angle

    if abs(rest) >= SCAN_DEG - 1:
        log.warning("--axis-from-stack: the given angle is %.2f deg from a quarter turn, beyond the estimate's scan "
                    "(+-%g): kept", rest, SCAN_DEG - 1)
        return rest, {"estimated": False, "reason": "beyond the scan"}
    log.info("--axis-from-stack: estimating the angle from the stack's moment conditions (%d tilts of %d x %d px, "
             "binned to at most %d px a side; measured 14 s at 64^2, 78 s at 128^2 on two cores)", *stack.shape,
             MAX_PIXELS)
    try:
        e = estimate_axis_angle(stack, radians)
    except ValueError as err:
        log.warning("--axis-from-stack: not estimated (%s): the given angle kept", err)
        return rest, {"estimated": False, "reason": str(err)}
    log.info("--axis-from-stack: %s", e.describe())
    record = {"estimated": True, "rest_deg": e.angle_deg, "se_deg": e.se_deg if math.isfinite(e.se_deg) else None,
              "determined": e.determined, "given_rest_deg": rest}
    if not e.determined:
        log.warning("--axis-from-stack: the tilt-axis angle is not determined by the data (%s): the given angle "
                    "kept", e.describe())
        return rest, record
    return e.angle_deg, record


def compact_alignment(args, rotated, radians, rest, steps, level, thickness, raw_bytes, budget, start) -> tuple:
    """The compact specimen's estimation (module Convention): ``(M, d, history, from_stack, op, x, data,
    at_bound)``."""
    import torch

    from .fit import bounds, projection_matching

    K, ny, nx = rotated.shape
    from_stack = None
    if args.axis_from_stack:   # binned first (the estimate's bound), so no full-size copy less the background
        from .moments import binned_within

        rest, from_stack = _stack_rest(binned_within(rotated)[0] - level, radians, rest)
    M, d = np.tile(_rotation(rest), (K, 1, 1)), np.zeros((K, 2))
    mode = "shifts+axis" if args.refine_axis else "shifts"
    if args.refine_axis:
        log.warning("--refine-axis: the refined tilt-axis angle is not validated: projection matching's SIRT "
                    "reconstruction takes up a turn of the axis, and the angle stays near its start "
                    "(docs/alignment.md, issue #39); measure it beforehand where it matters")
    history = []
    for i, bl in enumerate(steps):
        binned, delta = _bin(rotated, bl)
        binned -= level
        nz = max(thickness // bl, 4)
        rounds = args.rounds if i == 0 else args.fine_rounds
        log.info("level %d/%d: binned by %d, %d x %d px, volume %d x %d x %d, %d rounds (working set ~%.2f GiB of "
                 "%.2f)", i + 1, len(steps), bl, binned.shape[2], binned.shape[1], binned.shape[2], binned.shape[1],
                 nz, rounds, (3 * raw_bytes + working_set(binned.shape[2], binned.shape[1], nz, K,
                                                          args.interpolation)) / 2**30, budget / 2**30)
        data = torch.from_numpy(binned)
        op0 = _binned_operator(_operator(binned, radians, nz, 0.0).operator, M, d, bl, delta, radians)

        def progress(r, rec, bl=bl, rounds=rounds):
            log.info("bin %d, round %d/%d: SIRT residual %.4f, largest shift update %.3f px (binned), %.0f s", bl,
                     r + 1, rounds, rec[0], rec[1], time.perf_counter() - start)

        op, x, records = projection_matching(op0, data, mode, rounds, args.iters, args.interpolation, progress,
                                             args.max_shift)
        M, d = _in_stack_pixels(op, bl, delta)
        history.append({"bin": bl, "shape": list(binned.shape), "rounds": records})
    at = (op.shifts.abs() >= bounds(op) - 1e-9).any(dim=1)
    return M, d, history, from_stack, op, x, data, [int(k) for k in torch.nonzero(at).flatten()]
