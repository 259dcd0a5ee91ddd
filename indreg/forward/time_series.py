"""Data at several time points: one forward operator per frame (spatiotemporal imaging, ``docs/spatiotemporal.md``).

A *time series* of ``K`` frames measures the image ``f_{t_k}`` at time ``t_k`` with its own operator ``T_k`` (a
handful of angles per time point, different at every time point). :class:`TimeSeriesOperator` is their stack (a
``StackedOperator`` of ``indreg.forward.stacking``) and keeps ``T`` and ``g`` single objects for the run loop:

- ``frames(F)`` / ``frames_adjoint(G)``: the block-diagonal operator ``(f_1, ..., f_K) -> (T_1 f_1, ..., T_K f_K)``
  on a stack of frames, and its adjoint (what the spatiotemporal model uses);
- ``__call__(f)`` / ``adjoint(g)``: the same operator on a *static* image, ``f -> (T_1 f, ..., T_K f)``, adjoint
  ``g -> sum_k T_k^* g_k``. This is the linear-operator protocol of ``indreg.forward.operator`` (domain = one
  frame's grid), so every tool that takes an operator works on all the data at once as if nothing moved: the
  static TV baseline is ``tv_reconstruction(T, g, mu)``, ``operator_norm(T)`` is ``||sum_k T_k^* T_k||^(1/2)``,
  and ``indreg.register`` with ``model="lddmm"`` registers one image to all the data.

The data inner product is the sum of the frames' own (``sum_k <y_k, z_k>_k``), so both adjoints are L2 adjoints.
"""
from __future__ import annotations

import torch

from .stacking import StackedOperator


class TimeSeriesOperator(StackedOperator):
    """The forward operators ``T_1 .. T_K`` of the frames of a time series: their ``StackedOperator``
    (``indreg.forward.stacking``), one part per time point (module docstring).

    Parameters
    ----------
    operators : list or tuple of LinearOperator
        ``T_1 .. T_K`` (K >= 1) on one ``domain`` with one ``range_shape`` ``R`` (e.g.
        ``(num_angles, det_count)``: the same number of angles per time point, at different angles).

    Raises
    ------
    ValueError, TypeError
        As ``StackedOperator``.

    Notes
    -----
    - ``range_shape`` ``(K, *R)``: the frames' data stacked on axis ``-len(R) - 1`` (frame ``k`` = ``T_k``'s).
    - ``frames``: ``(..., K, *domain.shape) -> (..., K, *R)``; ``frames_adjoint``: back; ``__call__``:
      ``(..., *domain.shape) -> (..., K, *R)``; ``adjoint``: ``(..., K, *R) -> (..., *domain.shape)``.
    - ``inner_data`` sums the frames' ``T_k.inner_data`` (batch dims kept); ``frame_inner`` keeps the frames.

    Examples
    --------
    >>> import indreg, math
    >>> dom = indreg.ImageDomain.paper(16)
    >>> ops = [indreg.RayTransform(dom, indreg.ParallelBeamGeometry(angles=[(k + 4 * j) * math.pi / 12
    ...        for j in range(3)], det_count=24, det_min=-24, det_max=24)) for k in range(4)]
    >>> T = TimeSeriesOperator(ops)
    >>> T.range_shape, T.adjointness_test() < 1e-12, T.frames_adjointness_test() < 1e-12
    ((4, 3, 24), True, True)
    """


def as_time_series(operator, data) -> tuple:
    """A sequence of operators becomes a :class:`TimeSeriesOperator` and a sequence of data one stacked tensor
    ``(K, *R)`` (arrays / tensors in their common dtype, integers as float64; ``indreg.registration.run.setup`` casts it);
    anything else is returned as given."""
    import functools

    import numpy as np

    if isinstance(operator, (list, tuple)):
        operator = TimeSeriesOperator(operator)
    if isinstance(data, (list, tuple)):
        if isinstance(operator, TimeSeriesOperator) and len(data) != len(operator):
            raise ValueError(f"data has {len(data)} frames but the operators {len(operator)}: give one data set per "
                             "operator (time point)")
        items = [d.detach() if isinstance(d, torch.Tensor) else torch.from_numpy(np.asarray(d)) for d in data]
        for k, d in enumerate(items):
            if isinstance(operator, TimeSeriesOperator) and tuple(d.shape) != operator.frame_shape:
                raise ValueError(f"data[{k}] has shape {tuple(d.shape)}, expected {operator.frame_shape} "
                                 f"(operators[{k}].range_shape)")
        if len({tuple(d.shape) for d in items}) > 1:
            raise ValueError(f"the data sets have different shapes {[tuple(d.shape) for d in items]}")
        common = functools.reduce(torch.promote_types, [d.dtype for d in items])   # an integer frame truncates none
        data = torch.stack([d.to(common if common.is_floating_point or common.is_complex else torch.float64)
                            for d in items])
    return operator, data
