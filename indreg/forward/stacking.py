"""Stacks and row restrictions of operators (deepinv's ``stack``): one image to the data of several operators, the
block-diagonal form on a stack of frames, and an operator restricted to some rows (angles, tilts) of its range.

Notes
-----
As :mod:`indreg.forward.algebra` (the protocol of :mod:`indreg.forward.operator`; adjoints in the weighted data
inner products, by construction).
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np
import torch

from .._checks import check_tensor
from .algebra import OperatorAlgebra, _check_alike, _on_domain
from .operator import check_data_pair, check_operator

__all__ = ["StackedOperator", "RestrictedOperator", "stack", "restrict"]


class StackedOperator(OperatorAlgebra):
    """The operators ``T_1 .. T_K`` of one domain and one range shape ``R``, stacked (deepinv's ``stack``).

    Parameters
    ----------
    operators : list or tuple of LinearOperator
        ``T_1 .. T_K`` (K >= 1), one domain and one range shape.

    Raises
    ------
    ValueError
        An empty or non-list argument, or parts that differ in domain or range shape.
    TypeError
        A part that is no operator.

    Notes
    -----
    - ``range_shape`` ``(K, *R)``: part ``k``'s data on axis ``-len(R) - 1``.
    - ``__call__``: ``(..., *domain.shape) -> (..., K, *R)``, ``f -> (T_1 f, ..., T_K f)``; ``adjoint``: back,
      ``g -> sum_k T_k^* g_k``.
    - ``frames`` / ``frames_adjoint``: the block-diagonal operator ``(f_1, .., f_K) -> (T_1 f_1, .., T_K f_K)``,
      ``(..., K, *domain.shape) <-> (..., K, *R)`` (a frame per part, e.g. per time point).
    - ``inner_data`` sums the parts' ``T_k.inner_data`` (batch dims kept); ``frame_inner`` keeps the parts.
    """

    def __init__(self, operators: Sequence):
        ops = list(operators) if isinstance(operators, (list, tuple)) else None
        if not ops:
            raise ValueError(f"operators must be a non-empty list of operators, got "
                             f"{type(operators).__name__}{'' if ops is None else ' of length 0'}")
        for k, op in enumerate(ops):
            check_operator(op, f"operators[{k}]")
            _check_alike(ops[0], op, "operators[0]", f"operators[{k}]")
        self.operators = ops
        self.domain = ops[0].domain
        self.frame_shape = tuple(ops[0].range_shape)
        self.range_shape = (len(ops), *self.frame_shape)

    def __len__(self) -> int:
        return len(self.operators)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({len(self)} x {self.operators[0]!r})"

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
        """``(T_1 f, ..., T_K f)`` of one image: ``(..., *domain.shape)`` -> ``(..., K, *R)``."""
        check_tensor(f, "f", self.domain.shape, finite=False)
        return torch.stack([T(f) for T in self.operators], dim=self._data_axis)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``sum_k T_k^* y_k``: ``(..., K, *R)`` -> ``(..., *domain.shape)`` (the adjoint of ``__call__``)."""
        return self.frames_adjoint(y).sum(dim=self._image_axis)

    def frame_inner(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``<y1_k, y2_k>_k`` per part, ``(..., K)``."""
        check_data_pair(y1, y2, self.range_shape)
        a = self._data_axis
        return torch.stack([T.inner_data(y1.select(a, k), y2.select(a, k)) for k, T in enumerate(self.operators)],
                           dim=-1)

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``sum_k <y1_k, y2_k>_k``: the parts' data inner products summed, batch dims kept."""
        return self.frame_inner(y1, y2).sum(dim=-1)

    @property
    def on_domain(self) -> Optional[Callable]:
        """``domain -> type(self)([T_k.on_domain(domain)])`` when every ``T_k`` has ``on_domain``, else None."""
        return _on_domain(lambda *ops: type(self)(list(ops)), *self.operators)

    def frames_adjointness_test(self, dtype: torch.dtype = torch.float64, device=None, seed: int = 0) -> float:
        """``adjointness_test`` of ``frames`` / ``frames_adjoint`` on random frames ``(K, *shape)`` and data
        ``(K, *R)``."""
        gen = torch.Generator().manual_seed(int(seed))
        f = torch.randn((len(self), *self.domain.shape), generator=gen, dtype=dtype).to(device)
        y = torch.randn(self.range_shape, generator=gen, dtype=dtype).to(device)
        with torch.no_grad():
            tf = self.frames(f)
            lhs = self.inner_data(tf, y)
            rhs = self.domain.inner(f, self.frames_adjoint(y)).sum()
            return float((lhs - rhs).abs() / (self.norm_data(tf) * self.norm_data(y)))


class RestrictedOperator(OperatorAlgebra):
    """``T`` restricted to some rows of its range: ``T_S f = (T f)[rows]`` along the first data axis (the angles of
    a ray transform, the tilts of a tilt series, the parts of a stack); it computes ``T f`` and selects.

    Parameters
    ----------
    operator : LinearOperator
        ``T``.
    rows : int or array_like of int
        The rows kept: strictly increasing indices in ``[0, T.range_shape[0])`` (integer-valued floats
        accepted).

    Raises
    ------
    TypeError
        ``operator`` is no operator, or ``rows`` is not integer indices (None, a string, booleans).
    ValueError
        ``rows`` empty, not 1D, not strictly increasing, out of range or not integer-valued.

    Notes
    -----
    - ``range_shape`` ``(len(rows), *T.range_shape[1:])``; ``rows`` strictly increasing indices in
      ``[0, T.range_shape[0])``.
    - ``inner_data(y1, y2) = c * T.inner_data(E y1, E y2)`` with ``E`` the zero fill into ``T``'s range and
      ``c = T.range_shape[0] / len(rows)``: the weight per datum is that of ``T`` with only these rows (a ray
      transform's ``angle_cell = pi / num_angles`` becomes ``pi / len(rows)``), so a data term keeps its scale
      per datum whatever is left out. ``adjoint(y) = c * T.adjoint(E y)`` is then the L2 adjoint, for any ``T``
      whose data inner product is a weighted sum over data entries (every indreg operator).
    """

    def __init__(self, operator, rows):
        check_operator(operator, "operator")
        count = int(operator.range_shape[0])
        self.rows = _indices(rows, count)
        if self.rows.numel() == 0 or bool((self.rows < 0).any()) or bool((self.rows >= count).any()) \
                or bool((self.rows[1:] <= self.rows[:-1]).any()):
            raise ValueError(f"rows must be strictly increasing indices in [0, {count}), got {self.rows.tolist()}")
        self.operator = operator
        self.domain = operator.domain
        self.range_shape = (self.rows.numel(), *tuple(operator.range_shape)[1:])
        self.scale = count / self.rows.numel()

    @property
    def _axis(self) -> int:
        return -len(self.range_shape)

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        """``(T f)[..., rows, ...]``: images ``(..., *domain.shape)`` -> data ``(..., *range_shape)``."""
        y = self.operator(f)
        return y.index_select(y.dim() + self._axis, self.rows.to(y.device))

    def embed(self, y: torch.Tensor) -> torch.Tensor:
        """``E y``: data of this operator zero-filled into ``T``'s range (differentiable)."""
        y = check_tensor(y, "data", self.range_shape, finite=False)
        full = y.new_zeros((*y.shape[:y.dim() + self._axis], *self.operator.range_shape))
        return full.index_copy(y.dim() + self._axis, self.rows.to(y.device), y)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """L2 adjoint ``c T^*(E y)``."""
        return self.scale * self.operator.adjoint(self.embed(y))

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``c <E y1, E y2>`` in ``T``'s data inner product, batch dims kept."""
        check_data_pair(y1, y2, self.range_shape)
        return self.scale * self.operator.inner_data(self.embed(y1), self.embed(y2))

    @property
    def on_domain(self) -> Optional[Callable]:
        """``domain -> RestrictedOperator(T.on_domain(domain), rows)``, or None when ``T`` has no ``on_domain``."""
        return _on_domain(lambda op: RestrictedOperator(op, self.rows), self.operator)

    def __repr__(self) -> str:
        return f"RestrictedOperator({self.operator!r}, {len(self.rows)} of {self.operator.range_shape[0]} rows)"


def _indices(rows, count: int) -> torch.Tensor:
    """``rows`` (an int, or a 1D sequence / array / tensor of integers, integer-valued floats included) as a long
    tensor; anything else (a string, None, booleans, fractions, nested lists) is a one-line error."""
    what = f"rows must be a 1D sequence of integer indices in [0, {count})"
    if rows is None or isinstance(rows, (str, bytes)):
        raise TypeError(f"{what}, got {rows!r}")
    try:
        a = np.asarray(rows.detach().cpu() if isinstance(rows, torch.Tensor) else rows)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{what}, got {rows!r} ({e})") from None
    if a.ndim > 1:
        raise ValueError(f"{what}, got an array of shape {a.shape}")
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise TypeError(f"{what}, got {rows!r} (dtype {a.dtype})")
    if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a) & (a == np.round(a))):
        raise ValueError(f"{what}, got {a.tolist()} (not integers)")
    return torch.as_tensor(a.astype(np.int64).reshape(-1))


def stack(*operators) -> StackedOperator:
    """``f -> (T_1 f, ..., T_K f)`` (``StackedOperator``, as deepinv's ``stack``).

    Parameters
    ----------
    *operators : LinearOperator
        ``T_1 .. T_K`` (K >= 1) of one domain and one range shape.

    Returns
    -------
    StackedOperator
        The stack, range shape ``(K, *T_1.range_shape)``.

    Raises
    ------
    ValueError, TypeError
        As ``StackedOperator``.
    """
    return StackedOperator(list(operators))


def restrict(operator, rows) -> RestrictedOperator:
    """``f -> (T f)[rows]`` along the first data axis (``RestrictedOperator``).

    Parameters
    ----------
    operator : LinearOperator
        ``T``.
    rows : int or array_like of int
        Strictly increasing indices in ``[0, T.range_shape[0])``.

    Returns
    -------
    RestrictedOperator
        ``T`` restricted, range shape ``(len(rows), *T.range_shape[1:])``.

    Raises
    ------
    ValueError, TypeError
        As ``RestrictedOperator``.
    """
    return RestrictedOperator(operator, rows)
