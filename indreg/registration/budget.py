"""The result's whole volumes within ``max_memory``: a slab-wise registration (``SlabwiseRegistration``) bounds its
loop by ``max_memory``; after it the result adds the reconstruction (one volume), the deformation ``phi_{1,0}``
(``d`` volumes) and, for ``indreg.register``, the trajectory (``N + 1`` volumes: 11 GiB at 1024 x 1024 x 256 in
float32 with N = 10). What the problem already holds (the template's padded copy, the projector, the coarse arrays)
and the reconstruction are counted first; the deformation and the trajectory are kept, in that order, only where
they fit in what is left, and each one left out is named in one line before the result is built (with how much
it would need and how to get it: ``problem.deformation_field``, ``problem.image_frames`` one frame at a time).
A problem without a ``max_memory`` (the whole-volume path) keeps everything.
"""
from __future__ import annotations

import logging
import math

log = logging.getLogger("indreg")

__all__ = ["result_pieces"]

GIB = 2 ** 30


def _held(problem) -> int:
    """Bytes the problem holds after its loop besides the inputs: the padded template, the projector, 8 coarse
    velocity-sized arrays (``indreg.problems.slabs.choose_slab_size``'s accounting)."""
    from ..problems.slabs import projector_bytes

    itemsize = problem.template.element_size()
    return (problem.volume_bytes() + projector_bytes(problem.ray_transform, problem.template)
            + 8 * math.prod(problem.momentum_shape) * itemsize)


def result_pieces(problem, trajectory: bool) -> tuple:
    """``(deformation, trajectory)``: whether the result's deformation and trajectory are built (module docstring);
    each left out is logged in one line."""
    budget = getattr(problem, "max_memory", None)
    size = getattr(problem, "volume_bytes", None)
    if budget is None or size is None:
        return True, trajectory
    volume = size()
    left = budget - _held(problem) - volume          # the reconstruction is always built
    d, frames = problem.image_domain.ndim, problem.num_steps + 1
    keep_deformation = d * volume <= left
    if keep_deformation:
        left -= d * volume
    else:
        log.info("the deformation phi_(1,0) is not kept in the result: it needs %.3g GiB (%d volumes) and "
                 "max_memory=%.3g GiB leaves %.3g GiB after the problem's own arrays and the reconstruction; "
                 "result.problem.deformation_field(result.velocity) computes it", d * volume / GIB, d, budget / GIB,
                 max(left, 0) / GIB)
    keep_trajectory = trajectory and frames * volume <= left
    if trajectory and not keep_trajectory:
        log.info("the trajectory is not kept in the result: it needs %.3g GiB (%d volumes) and max_memory=%.3g GiB "
                 "leaves %.3g GiB; result.problem.image_frames((result.momentum,)) gives its frames one at a time",
                 frames * volume / GIB, frames, budget / GIB, max(left, 0) / GIB)
    return keep_deformation, keep_trajectory
