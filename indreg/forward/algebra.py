"""Operator algebra: compositions, sums and multiples of linear forward operators (stacks and row restrictions:
:mod:`indreg.forward.stacking`), and the mixins that give indreg's operators ``*``, ``+`` and the protocol's checks.

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

Notes
-----
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

Longer than 450 lines: the operator algebra's classes (composition, sum, multiple) and mixins, each short, with
their adjoints in docstrings.
"""
from __future__ import annotations

import functools
import math
import numbers
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from .._checks import check_number, check_tensor
from ..domain import ImageDomain
from .operator import MEMBERS, adjointness, check_data_pair, check_operator, norm_data, operator_norm

__all__ = ["OperatorAlgebra", "WeightedDataMixin", "ImageOperator", "ComposedOperator", "SumOperator",
           "ScaledOperator", "compose", "add", "scale"]


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


class OperatorAlgebra:
    """Operator arithmetic and the protocol's checks on the operator itself, for indreg's operators (the ray
    transform, the tilt series, the deepinv wrapper, the generic operators of ``indreg.forward.algebra``).

    ``A * B`` is the composition ``f -> A(B f)`` (``B`` an image-space operator, e.g. a blur, or any operator whose
    range is ``A``'s domain), ``c * A`` / ``A * c`` a multiple, ``A + B`` / ``A - B`` / ``-A`` sums; ``B`` may be a
    foreign operator of the protocol. Anything else (``A * tensor``) is refused by Python's ``TypeError``: an
    operator is applied by calling it, ``A(f)``.

    A mixin: it takes no parameters of its own."""

    def __mul__(self, other):
        if _is_number(other):
            return scale(other, self)
        return compose(self, other) if _is_operator(other) else NotImplemented

    def __rmul__(self, other):
        if _is_number(other):
            return scale(other, self)
        return compose(other, self) if _is_operator(other) else NotImplemented

    def __add__(self, other):
        return add(self, other) if _is_operator(other) else NotImplemented

    def __radd__(self, other):
        return add(other, self) if _is_operator(other) else NotImplemented

    def __neg__(self):
        return scale(-1.0, self)

    def __sub__(self, other):
        return add(self, scale(-1.0, other)) if _is_operator(other) else NotImplemented

    def __rsub__(self, other):
        return add(other, -self) if _is_operator(other) else NotImplemented

    def norm_data(self, y: torch.Tensor) -> torch.Tensor:
        """Weighted data norm over the data axes (:func:`norm_data`)."""
        return norm_data(self, y)

    def adjointness_test(self, dtype: torch.dtype = torch.float64, device=None, seed: int = 0) -> float:
        """``|<T x, y> - <x, T^* y>| / (||T x|| ||y||)`` for random ``x``, ``y`` (:func:`adjointness`)."""
        return adjointness(self, dtype, device, seed)

    def operator_norm(self, num_iter: int = 100, dtype: torch.dtype = torch.float64, device=None,
                      seed: int = 0) -> float:
        """``||T||`` from L2 to the weighted data L2 by power iteration on ``T^* T`` (:func:`operator_norm`)."""
        return operator_norm(self, num_iter, dtype, device, seed)


def _is_number(x) -> bool:
    return (isinstance(x, numbers.Real) or (isinstance(x, torch.Tensor) and x.dim() == 0)) \
        and not isinstance(x, (bool, np.bool_))


def _is_operator(x) -> bool:
    return all(hasattr(x, m) for m in MEMBERS)


class WeightedDataMixin(OperatorAlgebra):
    """The data-space members of a projector whose data inner product is ``geometry.data_weight * sum`` over
    ``range_shape`` (``RayTransform``, ``TiltSeriesTransform``): ``range_shape``, ``adjoint_scale`` and
    ``inner_data``; the arithmetic and the checks (``adjointness_test``, ``operator_norm``) from
    ``OperatorAlgebra``."""

    @property
    def range_shape(self) -> tuple:
        """Data shape: ``geometry.shape``."""
        return self.geometry.shape

    @property
    def adjoint_scale(self) -> float:
        """``data_weight / cell_volume``: the factor between ``adjoint`` and ``transpose``."""
        return self.geometry.data_weight / self.domain.cell_volume

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """Weighted data inner product ``data_weight * sum(y1 * y2)`` over the data axes; batch dims kept.

        Notes
        -----
        ``y1``, ``y2`` ``(..., *range_shape)``, float32 / float64 alike, batch dims broadcast; values
        are not checked for finiteness (a residual may hold nan / inf, which the sum then reports)."""
        dims = check_data_pair(y1, y2, self.range_shape)
        return self.geometry.data_weight * (y1 * y2).sum(dim=dims)


class ImageOperator(OperatorAlgebra):
    """A linear operator of image space ``B: L2(domain) -> L2(domain)`` from its action (e.g. a blur), to compose
    with a projector: ``T = R * ImageOperator(domain, blur)``.

    Parameters
    ----------
    domain : ImageDomain
        The image space (domain and range).
    forward : callable
        ``f -> B f`` on tensors ``(..., *domain.shape)``.
    adjoint : callable, optional
        ``f -> B^* f``; None: ``B`` is self-adjoint.

    Raises
    ------
    TypeError
        ``domain`` is no ``ImageDomain``, or ``forward`` / ``adjoint`` is not callable.

    Notes
    -----
    - ``forward(f)`` / ``adjoint(f)``: tensors ``(..., *domain.shape)`` -> the same shape, batched and
      differentiable (torch operations); ``adjoint=None``: ``B`` is self-adjoint. Both sides carry
      ``domain.inner``, so the L2 adjoint is the plain transpose.
    - ``range_shape = domain.shape``, ``range_domain = domain``, ``inner_data = domain.inner``.
    - ``on_domain(d)``: the same functions on the grid ``d`` (they must accept any grid shape; a stencil in
      cells keeps its width in cells, not in physical units).
    - A function that returns another shape than it was given is refused when the operator is applied
      (``ValueError``).

    Examples
    --------
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
    ``A.domain``.

    Parameters
    ----------
    outer : LinearOperator
        ``A``, applied second.
    inner : LinearOperator
        ``B``, applied first.

    Raises
    ------
    TypeError
        An argument that is no operator.
    ValueError
        ``B``'s range is not ``A``'s domain (domain, shape or inner product).
    """

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
    ``adjoint`` the sum of the adjoints, ``inner_data`` the first term's.

    Parameters
    ----------
    terms : sequence of LinearOperator
        At least two operators with one domain, range shape and data inner product.

    Raises
    ------
    TypeError
        A term that is no operator.
    ValueError
        Fewer than two terms, or terms that differ in domain, range shape or data inner product.
    """

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
    """``c A`` for a finite real ``c``: ``adjoint = c A^*``, ``inner_data`` = ``A``'s.

    Parameters
    ----------
    factor : float
        ``c``, finite and real.
    operator : LinearOperator
        ``A``.

    Raises
    ------
    TypeError
        A factor that is no real number, or an ``operator`` that is no operator.
    ValueError
        A non-finite factor.
    """

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


def compose(*operators) -> ComposedOperator:
    """``A_1 A_2 ... A_n``: ``f -> A_1(A_2(... A_n f))`` (``ComposedOperator``; ``A * B`` for indreg's operators).

    Parameters
    ----------
    *operators : LinearOperator
        At least two, each one's range the domain of the one before.

    Returns
    -------
    ComposedOperator
        The composition (nested pairwise, ``A_1 (A_2 (... A_n))``).

    Raises
    ------
    ValueError
        Fewer than two operators, or one whose range is not the next one's domain.
    TypeError
        An argument that is no operator.
    """
    if len(operators) < 2:
        raise ValueError(f"compose needs at least 2 operators, got {len(operators)}")
    return functools.reduce(ComposedOperator, operators)


def add(*operators) -> SumOperator:
    """``A_1 + ... + A_n`` (``SumOperator``; ``A + B`` for indreg's operators).

    Parameters
    ----------
    *operators : LinearOperator
        At least two, on one domain into one data space.

    Returns
    -------
    SumOperator
        The sum.

    Raises
    ------
    ValueError, TypeError
        As ``SumOperator``.
    """
    return SumOperator(operators)


def scale(factor, operator) -> ScaledOperator:
    """``c A`` (``ScaledOperator``; ``c * A`` for indreg's operators); ``c (d A)`` is ``(c d) A``.

    Parameters
    ----------
    factor : float
        ``c``, finite and real.
    operator : LinearOperator
        ``A``.

    Returns
    -------
    ScaledOperator
        ``c A`` (one factor where ``A`` is already a multiple).

    Raises
    ------
    ValueError, TypeError
        As ``ScaledOperator``.
    """
    if isinstance(operator, ScaledOperator):
        return ScaledOperator(_factor(factor) * operator.factor, operator.operator)
    return ScaledOperator(factor, operator)
