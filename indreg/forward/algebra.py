"""Operator algebra: compositions, sums, multiples, stacks and row restrictions of linear forward operators.

Each operator here follows the protocol of ``indreg.forward.operator`` and is built from operators that follow it:
indreg's own (which also write ``A * B``, ``c * A``, ``A + B``, ``A - B``: ``OperatorAlgebra``) or foreign ones
(through the functions). As ODL's ``OperatorComp`` / ``OperatorSum`` / ``ScalingOperator`` and deepinv's
``Physics.__mul__`` / ``stack``:

    compose(A, B)  = A * B     f -> A(B f); adjoint B^* A^*; A's data space (B: a blur, or any operator into
                               A's domain)
    add(A, B)      = A + B     f -> A f + B f; adjoint A^* + B^*; one domain, one data space
    scale(c, A)    = c * A     f -> c A f; adjoint c A^*
    stack(T_1, .., T_K)        f -> (T_1 f, ..., T_K f); adjoint g -> sum_k T_k^* g_k; and the block-diagonal
                               frames(F) = (T_1 f_1, ..., T_K f_K) on a stack of frames (a time series)
    restrict(T, rows)          f -> (T f)[rows] along the first data axis (e.g. held-out angles)
    ImageOperator(domain, forward, adjoint)   an operator of image space (a blur) from two functions

Convention:
    - Images ``(..., *domain.shape)`` and data ``(..., *range_shape)`` with any leading batch dims, 2D or 3D, in the
      dtypes and on the devices the parts accept; everything is differentiable (autograd through the parts).
    - An operator whose range is an image space has ``range_domain`` (an ``ImageDomain``; its ``inner_data`` is
      ``range_domain.inner``): ``ImageOperator`` and what is built on its left.
    - Adjoints are the weighted L2 adjoints of the parts' inner products. The data inner product of a composition,
      sum or multiple is its (outer, first) part's; of a stack the sum of the parts'; of a restriction the part's
      reweighted (``RestrictedOperator``).
    - Parts that do not fit (domains, range shapes, data inner products, compared by ``<1, 1>`` in float64 on the
      CPU) are refused by a one-line ``ValueError`` naming both; an argument that is no operator by a
      ``TypeError`` naming what it lacks.
    - ``on_domain(domain)`` (coarse-to-fine solvers) where every part has it, else ``on_domain`` is None.
"""
from __future__ import annotations

import functools
import math
from typing import Callable, Optional, Sequence

import torch

from .._checks import check_number, check_tensor
from ..domain import ImageDomain
from .operator import OperatorAlgebra, check_data_pair, check_operator

__all__ = ["ImageOperator", "ComposedOperator", "SumOperator", "ScaledOperator", "StackedOperator",
           "RestrictedOperator", "compose", "add", "scale", "stack", "restrict"]


def _name(op) -> str:
    return type(op).__name__


def _unit_inner(inner, shape: tuple) -> float:
    """``<1, 1>`` of a data inner product (float64, CPU): the total weight of its space."""
    one = torch.ones(shape, dtype=torch.float64)
    return float(inner(one, one))


def _check_same_inner(inner_a, inner_b, shape: tuple, what: str) -> None:
    a, b = _unit_inner(inner_a, shape), _unit_inner(inner_b, shape)
    if not math.isclose(a, b, rel_tol=1e-9):
        raise ValueError(f"{what} have different inner products (<1, 1> = {a:.6g} and {b:.6g})")


def _check_alike(first, op, a: str, b: str) -> None:
    """``op`` has ``first``'s domain and range shape (a sum's terms, a stack's parts)."""
    if op.domain != first.domain:
        raise ValueError(f"{b}.domain {op.domain} differs from {a}.domain {first.domain}")
    if tuple(op.range_shape) != tuple(first.range_shape):
        raise ValueError(f"{b}.range_shape {tuple(op.range_shape)} differs from {a}'s {tuple(first.range_shape)}")


def _on_domain(build: Callable, *parts) -> Optional[Callable]:
    """``domain -> build(*[p.on_domain(domain) for p in parts])`` when every part has ``on_domain``, else None."""
    rebuilds = [getattr(p, "on_domain", None) for p in parts]
    if not all(callable(r) for r in rebuilds):
        return None
    return lambda domain: build(*[r(domain) for r in rebuilds])


class ImageOperator(OperatorAlgebra):
    """A linear operator of image space ``B: L2(domain) -> L2(domain)`` from its action (e.g. a blur), to compose
    with a projector: ``T = R * ImageOperator(domain, blur)``.

    Convention:
        - ``forward(f)`` / ``adjoint(f)``: tensors ``(..., *domain.shape)`` -> the same shape, batched and
          differentiable (torch operations); ``adjoint=None``: ``B`` is self-adjoint. Both sides carry
          ``domain.inner``, so the L2 adjoint is the plain transpose.
        - ``range_shape = domain.shape``, ``range_domain = domain``, ``inner_data = domain.inner``.
        - ``on_domain(d)``: the same functions on the grid ``d`` (they must accept any grid shape; a stencil in
          cells keeps its width in cells, not in physical units).

    Example:
        >>> import indreg
        >>> dom = indreg.ImageDomain.paper(16)
        >>> B = ImageOperator(dom, lambda f: 0.5 * f + 0.25 * (f.roll(1, -1) + f.roll(-1, -1)))  # periodic blur
        >>> T = indreg.RayTransform(dom, indreg.ParallelBeamGeometry.paper(6, 24)) * B
        >>> T.range_shape, T.adjointness_test() < 1e-12
        ((6, 24), True)
    """

    def __init__(self, domain: ImageDomain, forward: Callable, adjoint: Optional[Callable] = None):
        if not isinstance(domain, ImageDomain):
            raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
        for fn, name in ((forward, "forward"), (adjoint, "adjoint")):
            if not (callable(fn) or (fn is None and name == "adjoint")):
                raise TypeError(f"{name} must be a function of an image tensor, got {type(fn).__name__}")
        self.domain = self.range_domain = domain
        self.function, self.adjoint_function = forward, adjoint

    @property
    def range_shape(self) -> tuple:
        return self.domain.shape

    def _apply(self, fn: Callable, f: torch.Tensor, name: str) -> torch.Tensor:
        f = check_tensor(f, name, self.domain.shape, finite=False)   # values: checked by the projector it feeds
        out = fn(f)
        if not isinstance(out, torch.Tensor) or out.shape != f.shape:
            got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ValueError(f"the image operator's function returned {got} for an image of shape "
                             f"{tuple(f.shape)}: it must return a tensor of the same shape")
        return out

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        """``B f``: ``(..., *domain.shape)`` -> the same shape."""
        return self._apply(self.function, f, "image")

    def adjoint(self, f: torch.Tensor) -> torch.Tensor:
        """``B^* f`` (``forward`` when no adjoint was given)."""
        return self._apply(self.adjoint_function or self.function, f, "image")

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``domain.inner``: the range is the image space."""
        check_data_pair(y1, y2, self.range_shape)
        return self.domain.inner(y1, y2)

    def on_domain(self, domain: ImageDomain) -> "ImageOperator":
        """The same functions on another grid (class docstring)."""
        return ImageOperator(domain, self.function, self.adjoint_function)

    def __repr__(self) -> str:
        return f"ImageOperator({getattr(self.function, '__name__', 'forward')} on {self.domain.shape})"


class ComposedOperator(OperatorAlgebra):
    """``A B: f -> A(B f)`` for ``B``'s range = ``A``'s domain; ``adjoint = B^* A^*``, ``inner_data`` = ``A``'s,
    ``domain`` = ``B``'s (module docstring). ``B``'s range is ``A``'s domain when ``B.range_domain == A.domain``,
    or, for an operator without ``range_domain``, when its ``range_shape`` and data inner product are those of
    ``A.domain``."""

    def __init__(self, outer, inner):
        self.outer, self.inner = check_operator(outer, "A (of A * B)"), check_operator(inner, "B (of A * B)")
        what = f"cannot compose A * B (A: {_name(outer)}, B: {_name(inner)})"
        where = getattr(inner, "range_domain", None)
        if where is not None and where != outer.domain:
            raise ValueError(f"{what}: B maps to {where}, A acts on {outer.domain}")
        if where is None:
            if tuple(inner.range_shape) != tuple(outer.domain.shape):
                raise ValueError(f"{what}: B's range_shape {tuple(inner.range_shape)} is not A's domain shape "
                                 f"{outer.domain.shape}")
            _check_same_inner(inner.inner_data, outer.domain.inner, outer.domain.shape,
                              f"{what}: B's data and A's images")
        self.domain, self.range_shape = inner.domain, tuple(outer.range_shape)
        self.range_domain = getattr(outer, "range_domain", None)

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        """``A(B f)``."""
        return self.outer(self.inner(f))

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``B^*(A^* y)``."""
        return self.inner.adjoint(self.outer.adjoint(y))

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """``A``'s data inner product."""
        return self.outer.inner_data(y1, y2)

    @property
    def on_domain(self) -> Optional[Callable]:
        """``domain -> A.on_domain(domain) * B.on_domain(domain)`` when both have it, else None."""
        return _on_domain(ComposedOperator, self.outer, self.inner)

    def __repr__(self) -> str:
        return f"({self.outer!r} * {self.inner!r})"


class SumOperator(OperatorAlgebra):
    """``A_1 + ... + A_n`` on one domain into one data space (one ``range_shape`` and data inner product);
    ``adjoint`` the sum of the adjoints, ``inner_data`` the first term's."""

    def __init__(self, terms: Sequence):
        terms = list(terms)
        if len(terms) < 2:
            raise ValueError(f"a sum needs at least 2 operators, got {len(terms)}")
        for k, op in enumerate(terms):
            check_operator(op, f"terms[{k}]")
            _check_alike(terms[0], op, "terms[0]", f"terms[{k}]")
            if k:
                _check_same_inner(terms[0].inner_data, op.inner_data, tuple(op.range_shape),
                                  f"the data spaces of terms[0] ({_name(terms[0])}) and terms[{k}] ({_name(op)})")
        self.terms = terms
        self.domain, self.range_shape = terms[0].domain, tuple(terms[0].range_shape)
        self.range_domain = getattr(terms[0], "range_domain", None)

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        """``sum_i A_i f``."""
        return functools.reduce(torch.add, (A(f) for A in self.terms))

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``sum_i A_i^* y``."""
        return functools.reduce(torch.add, (A.adjoint(y) for A in self.terms))

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        return self.terms[0].inner_data(y1, y2)

    @property
    def on_domain(self) -> Optional[Callable]:
        """``domain -> sum_i A_i.on_domain(domain)`` when every term has it, else None."""
        return _on_domain(lambda *terms: SumOperator(terms), *self.terms)

    def __repr__(self) -> str:
        return "(" + " + ".join(map(repr, self.terms)) + ")"


def _factor(value) -> float:
    c = check_number(value, "factor", "a finite real number")
    if not math.isfinite(c):
        raise ValueError(f"factor must be a finite real number, got {value!r}")
    return c


class ScaledOperator(OperatorAlgebra):
    """``c A`` for a finite real ``c``: ``adjoint = c A^*``, ``inner_data`` = ``A``'s."""

    def __init__(self, factor, operator):
        self.factor = _factor(factor)
        self.operator = check_operator(operator, "operator")
        self.domain, self.range_shape = operator.domain, tuple(operator.range_shape)
        self.range_domain = getattr(operator, "range_domain", None)

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        return self.factor * self.operator(f)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return self.factor * self.operator.adjoint(y)

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        return self.operator.inner_data(y1, y2)

    @property
    def on_domain(self) -> Optional[Callable]:
        return _on_domain(lambda op: ScaledOperator(self.factor, op), self.operator)

    def __repr__(self) -> str:
        return f"{self.factor:g} * {self.operator!r}"


class StackedOperator(OperatorAlgebra):
    """The operators ``T_1 .. T_K`` of one domain and one range shape ``R``, stacked (deepinv's ``stack``).

    Convention:
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

    Convention:
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
        self.rows = torch.as_tensor(rows, dtype=torch.long).flatten()
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


def compose(*operators) -> ComposedOperator:
    """``A_1 A_2 ... A_n``: ``f -> A_1(A_2(... A_n f))`` (``ComposedOperator``; ``A * B`` for indreg's operators)."""
    if len(operators) < 2:
        raise ValueError(f"compose needs at least 2 operators, got {len(operators)}")
    return functools.reduce(ComposedOperator, operators)


def add(*operators) -> SumOperator:
    """``A_1 + ... + A_n`` (``SumOperator``; ``A + B`` for indreg's operators)."""
    return SumOperator(operators)


def scale(factor, operator) -> ScaledOperator:
    """``c A`` (``ScaledOperator``; ``c * A`` for indreg's operators); ``c (d A)`` is ``(c d) A``."""
    if isinstance(operator, ScaledOperator):
        return ScaledOperator(_factor(factor) * operator.factor, operator.operator)
    return ScaledOperator(factor, operator)


def stack(*operators) -> StackedOperator:
    """``f -> (T_1 f, ..., T_K f)`` (``StackedOperator``, as deepinv's ``stack``)."""
    return StackedOperator(list(operators))


def restrict(operator, rows) -> RestrictedOperator:
    """``f -> (T f)[rows]`` along the first data axis (``RestrictedOperator``)."""
    return RestrictedOperator(operator, rows)
