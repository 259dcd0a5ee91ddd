"""Data at several time points: one forward operator per frame (spatiotemporal imaging, ``docs/spatiotemporal.md``).

A *time series* of ``K`` frames measures the image ``f_{t_k}`` at time ``t_k`` with its own operator ``T_k`` (a
handful of angles per time point, different at every time point). :class:`TimeSeriesOperator` holds the ``T_k``
and keeps ``T`` and ``g`` single objects for the run loop:

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

from .._checks import check_tensor
from .operator import adjointness, check_data_pair, check_operator, operator_norm


class TimeSeriesOperator:
    """The forward operators ``T_1 .. T_K`` of the frames of a time series (module docstring).

    Convention:
        - ``operators``: a non-empty sequence of linear operators (``indreg.forward.LinearOperator``) on one
          ``domain`` with one ``range_shape`` ``R`` (e.g. ``(num_angles, det_count)``: the same number of angles
          per time point, at different angles).
        - ``range_shape`` ``(K, *R)``: the frames' data stacked on axis ``-len(R) - 1`` (frame ``k`` = ``T_k``'s).
        - ``frames``: ``(..., K, *domain.shape) -> (..., K, *R)``; ``frames_adjoint``: back; ``__call__``:
          ``(..., *domain.shape) -> (..., K, *R)``; ``adjoint``: ``(..., K, *R) -> (..., *domain.shape)``.
        - ``inner_data`` sums the frames' ``T_k.inner_data`` (batch dims kept); ``frame_inner`` keeps the frames.

    Example:
        >>> import indreg, math
        >>> dom = indreg.ImageDomain.paper(16)
        >>> ops = [indreg.RayTransform(dom, indreg.ParallelBeamGeometry(angles=[(k + 4 * j) * math.pi / 12
        ...        for j in range(3)], det_count=24, det_min=-24, det_max=24)) for k in range(4)]
        >>> T = TimeSeriesOperator(ops)
        >>> T.range_shape, T.adjointness_test() < 1e-12, T.frames_adjointness_test() < 1e-12
        ((4, 3, 24), True, True)
    """

    def __init__(self, operators):
        ops = list(operators) if isinstance(operators, (list, tuple)) else None
        if not ops:
            raise ValueError(f"operators must be a non-empty list of operators (one per time point), got "
                             f"{type(operators).__name__}{'' if ops is None else ' of length 0'}")
        for k, op in enumerate(ops):
            check_operator(op, f"operators[{k}]")
            if op.domain != ops[0].domain:
                raise ValueError(f"operators[{k}].domain {op.domain} differs from operators[0].domain {ops[0].domain}")
            if tuple(op.range_shape) != tuple(ops[0].range_shape):
                raise ValueError(f"operators[{k}].range_shape {tuple(op.range_shape)} differs from operators[0]'s "
                                 f"{tuple(ops[0].range_shape)} (every time point needs data of one shape)")
        self.operators = ops
        self.domain = ops[0].domain
        self.frame_shape = tuple(ops[0].range_shape)
        self.range_shape = (len(ops), *self.frame_shape)

    def __len__(self) -> int:
        return len(self.operators)

    def __repr__(self) -> str:
        return f"TimeSeriesOperator({len(self)} frames of {self.operators[0]!r})"

    @property
    def _image_axis(self) -> int:
        return -self.domain.ndim - 1

    @property
    def _data_axis(self) -> int:
        return -len(self.frame_shape) - 1

    def frames(self, f: torch.Tensor) -> torch.Tensor:
        """``(T_1 f_1, ..., T_K f_K)``: frames ``(..., K, *domain.shape)`` -> data ``(..., K, *R)`` (differentiable)."""
        check_tensor(f, "frames", (len(self), *self.domain.shape), finite=False)
        a = self._image_axis
        return torch.stack([T(f.select(a, k)) for k, T in enumerate(self.operators)], dim=self._data_axis)

    def frames_adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``(T_1^* y_1, ..., T_K^* y_K)``: data ``(..., K, *R)`` -> frames ``(..., K, *domain.shape)``."""
        check_tensor(y, "data", self.range_shape, finite=False)
        a = self._data_axis
        return torch.stack([T.adjoint(y.select(a, k)) for k, T in enumerate(self.operators)], dim=self._image_axis)

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        """``(T_1 f, ..., T_K f)`` of one (static) image: ``(..., *domain.shape)`` -> ``(..., K, *R)``."""
        check_tensor(f, "f", self.domain.shape, finite=False)
        return torch.stack([T(f) for T in self.operators], dim=self._data_axis)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``sum_k T_k^* y_k``: ``(..., K, *R)`` -> ``(..., *domain.shape)`` (the adjoint of ``__call__``)."""
        return self.frames_adjoint(y).sum(dim=self._image_axis)

    def frame_inner(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``<y1_k, y2_k>_k`` per frame, ``(..., K)``."""
        check_data_pair(y1, y2, self.range_shape)
        a = self._data_axis
        return torch.stack([T.inner_data(y1.select(a, k), y2.select(a, k)) for k, T in enumerate(self.operators)],
                           dim=-1)

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``sum_k <y1_k, y2_k>_k``: the frames' data inner products summed, batch dims kept."""
        return self.frame_inner(y1, y2).sum(dim=-1)

    def norm_data(self, y: torch.Tensor) -> torch.Tensor:
        return self.inner_data(y, y).sqrt()

    @property
    def on_domain(self):
        """``domain -> TimeSeriesOperator([T_k.on_domain(domain)])`` when every ``T_k`` has ``on_domain``, else None."""
        rebuilds = [getattr(T, "on_domain", None) for T in self.operators]
        if not all(callable(r) for r in rebuilds):
            return None
        return lambda domain: TimeSeriesOperator([r(domain) for r in rebuilds])

    def adjointness_test(self, dtype: torch.dtype = torch.float64, device=None, seed: int = 0) -> float:
        """``|<T f, y> - <f, T^* y>| / (||T f|| ||y||)`` of the static operator (``indreg.forward.adjointness``)."""
        return adjointness(self, dtype, device, seed)

    def frames_adjointness_test(self, dtype: torch.dtype = torch.float64, device=None, seed: int = 0) -> float:
        """The same for ``frames`` / ``frames_adjoint`` on random frames ``(K, *shape)`` and data ``(K, *R)``."""
        gen = torch.Generator().manual_seed(int(seed))
        f = torch.randn((len(self), *self.domain.shape), generator=gen, dtype=dtype).to(device)
        y = torch.randn(self.range_shape, generator=gen, dtype=dtype).to(device)
        with torch.no_grad():
            tf = self.frames(f)
            lhs = self.inner_data(tf, y)
            rhs = self.domain.inner(f, self.frames_adjoint(y)).sum()
            return float((lhs - rhs).abs() / (self.norm_data(tf) * self.norm_data(y)))

    def operator_norm(self, num_iter: int = 100, dtype: torch.dtype = torch.float64, device=None,
                      seed: int = 0) -> float:
        """``||T||`` of the static operator: ``||sum_k T_k^* T_k||^(1/2)`` (power iteration)."""
        return operator_norm(self, num_iter, dtype, device, seed)


def as_time_series(operator, data) -> tuple:
    """A sequence of operators becomes a :class:`TimeSeriesOperator` and a sequence of data one stacked tensor
    ``(K, *R)`` (arrays / tensors; the data's dtype is kept, ``indreg.run.setup`` casts it); anything else is
    returned as given."""
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
        data = torch.stack([d.to(items[0].dtype) for d in items])
    return operator, data
