"""SIRT (simultaneous iterative reconstruction technique) for any ``LinearOperator`` with a nonnegative matrix.

Iteration (Gregor & Benson 2008; ASTRA's ``SIRT``), for ``T = A`` as a matrix with nonnegative entries:

    x_{k+1} = P( x_k + C A^T R (y - A x_k) ),   R = diag(1 / A 1),  C = diag(1 / A^T 1),

``P`` the projection on ``x >= 0`` (``nonneg``) or the identity. Only the protocol is used: ``A 1 = T(1)``
and ``C A^T = diag(1 / T^*(1)) T^*`` (the weight of the L2 adjoint cancels), so it works for the ray
transforms in 2D and 3D and for any user operator whose matrix is nonnegative. Rays or cells with a zero sum
get a zero weight. It is gradient descent on ``(1/2) ||A x - y||_R^2`` in the metric ``C^{-1}`` with step 1,
and ``||R^{1/2} A C^{1/2}|| <= 1`` for a nonnegative ``A`` (Schur's test), so the weighted residual
``||A x_k - y||_R^2`` decreases monotonically, with or without ``nonneg``.

Over ranks (``indreg.forward.split``): ``T`` a ``SlabTransform``, ``y`` its rows. For a tilt series ``A 1`` and
``A^T 1`` are per slice, so the iteration is exact slab by slab; the one global quantity, the largest sum (the
threshold of a zero sum), and the residuals are reduced over the ranks.
"""
from __future__ import annotations

import torch

from .._checks import check_bool, check_int, check_tensor
from .operator import check_operator
from .split import maximum, total


def _inverse_sums(sums: torch.Tensor, what: str, domain) -> torch.Tensor:
    """``1 / sums`` where ``sums > 0``, 0 where ``sums == 0``; error if a sum is negative. The threshold is relative
    to the largest sum (over the ranks of a ``SlabDomain``)."""
    scale = float(maximum(sums.abs().max(), domain)) if sums.numel() else 0.0
    if bool((sums < -1e-12 * scale).any()):
        raise ValueError(f"sirt needs an operator with a nonnegative matrix, but {what} has negative entries")
    positive = sums > 1e-12 * scale
    return torch.where(positive, 1.0 / torch.where(positive, sums, torch.ones_like(sums)), torch.zeros_like(sums))


def start_image(x0, batch: tuple, domain, y: torch.Tensor) -> torch.Tensor:
    """A copy of the start image ``x0``, shape exactly ``(*batch, *domain.shape)`` (the data's batch), in the
    dtype and device of the data ``y`` (shared by ``sirt`` and ``tv_reconstruction``)."""
    shape = (*batch, *domain.shape)
    check_tensor(x0, "x0", tuple(domain.shape))
    if tuple(x0.shape) != shape:
        raise ValueError(f"x0 must have shape {shape} (the data's batch dims, then the domain's), "
                         f"got {tuple(x0.shape)}")
    return x0.to(dtype=y.dtype, device=y.device).clone()


@torch.no_grad()
def sirt(T, y: torch.Tensor, num_iter: int = 100, x0: torch.Tensor | None = None, nonneg: bool = False,
         callback=None) -> tuple:
    """``num_iter`` SIRT iterations for ``T x = y`` (module docstring).

    Parameters
    ----------
    T : LinearOperator
        The forward operator, with a nonnegative matrix (ray sums ``T 1`` and cell sums ``T^* 1`` >= 0).
    y : torch.Tensor
        Data ``(..., *T.range_shape)``, any leading batch dims; the images' dtype and device follow it.
    num_iter : int
        Iterations (>= 1).
    x0 : torch.Tensor, optional
        Start image ``(*batch, *T.domain.shape)`` (default zeros).
    nonneg : bool
        Clip to ``x >= 0`` after every step.
    callback : callable, optional
        ``callback(i, x)`` after iteration ``i`` (0-based).

    Returns
    -------
    x : torch.Tensor
        The reconstruction ``(..., *T.domain.shape)`` (2D or 3D).
    history : dict
        ``history["residual"]`` float64 CPU ``(num_iter, ...)``, the weighted residual ``sum R (T x_k - y)^2``
        after iteration ``k`` (non-increasing), and ``history["data_residual"]`` the data-space norm
        ``||T x_k - y||`` (``T.inner_data``).

    Raises
    ------
    TypeError
        ``T`` is no operator, or a wrong type of argument.
    ValueError
        Data or ``x0`` of the wrong shape, non-finite values, ``num_iter < 1``, an operator with negative
        entries.
    """
    check_operator(T, "T")
    y = check_tensor(y, "y", tuple(T.range_shape))
    num_iter = check_int(num_iter, "num_iter", 1)
    nonneg = check_bool(nonneg, "nonneg")
    dom = T.domain
    batch = y.shape[:y.dim() - len(T.range_shape)]
    x = dom.zeros(*batch, dtype=y.dtype, device=y.device) if x0 is None else start_image(x0, batch, dom, y)
    row = _inverse_sums(T(dom.zeros(dtype=y.dtype, device=y.device) + 1.0), "T(1) (ray sums)", dom)
    col = _inverse_sums(T.adjoint(torch.ones(T.range_shape, dtype=y.dtype, device=y.device)),
                        "T^*(1) (cell sums)", dom)
    data_dims = tuple(range(-len(T.range_shape), 0))
    residual = torch.empty((num_iter,) + tuple(batch), dtype=torch.float64)
    data_residual = torch.empty_like(residual)
    r = y - T(x)
    for i in range(num_iter):
        x = x + col * T.adjoint(row * r)
        if nonneg:
            x = x.clamp(min=0.0)
        r = y - T(x)
        residual[i] = total((row * r * r).sum(dim=data_dims), dom).cpu()
        data_residual[i] = T.inner_data(r, r).sqrt().cpu()
        if callback is not None:
            callback(i, x)
    return x, {"residual": residual, "data_residual": data_residual}
