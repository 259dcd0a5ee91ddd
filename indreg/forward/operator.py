"""The linear-operator protocol of indreg's forward models, with adjointness and norm checks.

Anything with these members is a forward operator for indreg (``RayTransform`` is one; a blur, a masked
Fourier transform or a wrapped deepinv/ODL/ASTRA operator can be another):

    domain        ImageDomain of the images
    range_shape   tuple, shape of one datum (e.g. ``(num_angles, det_count)``)
    __call__(f)   images ``(..., *domain.shape)`` -> data ``(..., *range_shape)``; batched, differentiable
    adjoint(y)    the L2 adjoint for ``domain.inner`` and ``inner_data``: ``<T f, y>_data = <f, T^* y>``
    inner_data(y1, y2)  weighted data inner product over the last ``len(range_shape)`` axes, batch dims kept

Operators combine into operators (``indreg.forward.algebra``, ``indreg.forward.stacking``): ``R * B``, ``c * A``,
``A + B`` for those that inherit ``OperatorAlgebra`` (indreg's own), ``compose`` / ``add`` / ``scale`` / ``stack`` /
``restrict`` for any.

Notes
-----
inner products are weighted (``domain.inner`` uses the cell volume; ``inner_data`` whatever
weight the data space has, e.g. ``angle_cell * det_cell`` for ray transforms), so ``adjoint`` is the
weighted L2 adjoint, not the matrix transpose, unless both weights are equal.
"""
from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import torch

from .._checks import FLOAT_DTYPES, broadcast_shapes, check_int, check_same, check_tensor
from ..domain import ImageDomain

MEMBERS = ("domain", "range_shape", "__call__", "adjoint", "inner_data")


@runtime_checkable
class LinearOperator(Protocol):
    """Protocol of a linear forward operator ``T: L2(domain) -> data`` (module docstring)."""

    domain: ImageDomain
    range_shape: tuple

    def __call__(self, f: torch.Tensor) -> torch.Tensor: ...

    def adjoint(self, y: torch.Tensor) -> torch.Tensor: ...

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor: ...


def check_operator(op, name: str = "operator"):
    """Check that ``op`` follows ``LinearOperator`` (its members present, ``adjoint`` and ``inner_data`` callable,
    ``domain`` an ``ImageDomain``).

    Parameters
    ----------
    op : object
        The operator to check.
    name : str
        Its name in the message.

    Returns
    -------
    object
        ``op`` itself.

    Raises
    ------
    TypeError
        One line naming what is missing or of the wrong type.
    """
    missing = [m for m in MEMBERS if not hasattr(op, m)]
    missing += [m for m in ("adjoint", "inner_data") if m not in missing and not callable(getattr(op, m))]
    if not callable(op) and "__call__" not in missing:
        missing.append("__call__")
    if missing:
        raise TypeError(f"{name} must be a linear operator with {', '.join(MEMBERS)}; "
                        f"{type(op).__name__} lacks {', '.join(missing)}")
    if not isinstance(op.domain, ImageDomain):
        raise TypeError(f"{name}.domain must be an ImageDomain, got {type(op.domain).__name__}")
    return op


def check_data_pair(y1, y2, range_shape) -> tuple:
    """Check the arguments of ``inner_data``: tensors ``(..., *range_shape)`` of one float dtype and device whose
    batch dims broadcast (values may be non-finite: a residual's nan / inf shows in the sum). Returns the data
    axes ``(-k, ..., -1)``."""
    shape = tuple(range_shape)
    for y, name in ((y1, "y1"), (y2, "y2")):
        check_tensor(y, name, shape, finite=False)
    check_same(y1, y2, "y1", "y2")
    k = len(shape)
    try:
        broadcast_shapes(y1.shape[:y1.dim() - k], y2.shape[:y2.dim() - k])
    except RuntimeError:
        raise ValueError(f"batch dims of y1 {tuple(y1.shape[:y1.dim() - k])} and y2 "
                         f"{tuple(y2.shape[:y2.dim() - k])} do not broadcast") from None
    return tuple(range(-k, 0))


def norm_data(op, y: torch.Tensor) -> torch.Tensor:
    """Weighted data norm ``sqrt(op.inner_data(y, y))``, batch dims kept."""
    return op.inner_data(y, y).sqrt()


def _random_pair(op, dtype, device, seed: int) -> tuple:
    if dtype not in FLOAT_DTYPES:
        raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    gen = torch.Generator().manual_seed(check_int(seed, "seed", 0))
    x = torch.randn(op.domain.shape, generator=gen, dtype=dtype).to(device)
    y = torch.randn(tuple(op.range_shape), generator=gen, dtype=dtype).to(device)
    return x, y


def adjointness(op, dtype: torch.dtype = torch.float64, device=None, seed: int = 0) -> float:
    """Relative adjointness error ``|<T x, y> - <x, T^* y>| / (||T x|| ||y||)`` for random normal ``x``, ``y``
    (weighted inner products; as deepinv's ``adjointness_test`` and ODL's ``OperatorTest``).

    Parameters
    ----------
    op : LinearOperator
        The operator (checked by :func:`check_operator`).
    dtype : torch.dtype
        ``torch.float32`` or ``torch.float64`` (default).
    device : torch.device or str, optional
        Where ``x`` and ``y`` are made (default: the CPU).
    seed : int
        Seed of the random pair (>= 0).

    Returns
    -------
    float
        The relative error: about ``1e-15`` for an exact pair in float64.

    Raises
    ------
    TypeError
        ``op`` is not an operator, or another ``dtype``.
    """
    check_operator(op)
    x, y = _random_pair(op, dtype, device, seed)
    with torch.no_grad():
        tx = op(x)
        lhs, rhs = op.inner_data(tx, y), op.domain.inner(x, op.adjoint(y))
        return float((lhs - rhs).abs() / (norm_data(op, tx) * norm_data(op, y)))


@torch.no_grad()
def operator_norm(op, num_iter: int = 100, dtype: torch.dtype = torch.float64, device=None, seed: int = 0) -> float:
    """``||T||`` (L2 to weighted data L2) by ``num_iter`` power iterations on ``T^* T`` from a random start
    (needs only the protocol)."""
    check_operator(op)
    num_iter = check_int(num_iter, "num_iter", 1)
    dom = op.domain
    x = _random_pair(op, dtype, device, seed)[0]
    x = x / dom.norm(x)
    for _ in range(num_iter):
        x = op.adjoint(op(x))
        x = x / dom.norm(x)
    return float(norm_data(op, op(x)))


def relative_residual(operator, image: torch.Tensor, data: torch.Tensor) -> float:
    """``||T f - g|| / ||g||`` in the data norm (``operator.inner_data``)."""
    with torch.no_grad():
        r = operator(image) - data
        return math.sqrt(float(operator.inner_data(r, r).sum()) / float(operator.inner_data(data, data).sum()))
