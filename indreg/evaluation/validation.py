"""Held-out validation: some angles (or tilts) are left out of the fit and their relative residual measures how
well the reconstruction predicts data it was not fitted to, without a ground truth.

``holdout`` (``indreg.register(holdout=...)``, the app's ``validation.holdout``) is an integer ``k``: every
``k``-th angle, indices ``k // 2, k // 2 + k, ...`` (``k = 5`` on 30 angles: 2, 7, 12, 17, 22, 27), or an explicit
list of indices. The fit uses the operator restricted to the other angles
(``indreg.forward.restrict``, which works for any operator of the protocol: the angles are the first axis of its
range), the held-out angles are compared with the same reconstruction every ``every``
iterations (the loop's log period): ``||T_H f - g_H|| / ||g_H||``. With ``patience`` the run stops
(``early_stopped``) after ``patience`` such evaluations without a new minimum.

Notes
-----
Indices along the data's first axis (``operator.range_shape[0]``: angles of a sinogram, tilts of a tilt series);
the residual uses the operator's data inner product.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import torch

from ..forward.stacking import restrict
from ..options import OptionError


def holdout_rows(spec, count: int, name: str = "holdout") -> tuple:
    """The kept and held-out angles of ``count`` for ``spec``.

    Parameters
    ----------
    spec : int or list of int
        An integer ``k >= 2`` (every ``k``-th angle from ``k // 2``) or a list of indices, as
        ``indreg.options.holdout`` normalises it.
    count : int
        The number of angles.
    name : str
        The option's name in messages.

    Returns
    -------
    kept, held : list of int
        The indices fitted and the indices held out, increasing.

    Raises
    ------
    OptionError
        A ``ValueError`` naming ``name``: an index out of range, a holdout that holds out no angle or leaves none
        to fit.
    """
    if isinstance(spec, int):
        held = list(range(spec // 2, count, spec))
        if not held:
            raise OptionError(name, spec, f"an integer k with k // 2 < {count} (the data have {count} angles)")
    else:
        held = sorted(spec)
        if not 0 <= held[0] <= held[-1] < count:
            raise OptionError(name, spec, f"indices in 0..{count - 1} (the data have {count} angles)")
    kept = [i for i in range(count) if i not in set(held)]
    if not kept:
        raise OptionError(name, spec, f"a selection that leaves at least one of the {count} angles to fit")
    return kept, held


@dataclass
class Validation:
    """The held-out data and the early-stopping record of a run.

    Parameters
    ----------
    operator : LinearOperator
        ``T_H``: ``T`` restricted to the held-out rows.
    data : torch.Tensor
        ``g_H``: the data of the held-out rows.
    held : list of int
        The held-out rows.
    patience : int, optional
        Stop after this many evaluations without a new minimum (None: never).
    curve : list of tuple
        ``[(iteration, residual), ...]`` so far.
    """
    operator: object
    data: torch.Tensor
    held: list
    patience: Optional[int] = None
    curve: list = field(default_factory=list)

    def residual(self, image: torch.Tensor) -> float:
        """``||T_H f - g_H|| / ||g_H||``."""
        with torch.no_grad():
            r = self.operator(image) - self.data
            norm = float(self.operator.inner_data(self.data, self.data).sum())
            return math.sqrt(float(self.operator.inner_data(r, r).sum()) / norm) if norm > 0 else math.nan

    def record(self, iteration: int, image: torch.Tensor) -> float:
        """Evaluate at ``iteration`` and keep the value on the curve."""
        value = self.residual(image)
        self.curve.append((iteration, value))
        return value

    def restore(self, history: list) -> None:
        """The curve of a resumed run, from its history (entries with ``holdout_residual``)."""
        self.curve = [(h["iteration"], h["holdout_residual"]) for h in history if "holdout_residual" in h]

    @property
    def best(self) -> tuple:
        """``(iteration, residual)`` of the least residual so far (the first one on ties), ``(None, nan)``
        before any evaluation."""
        finite = [c for c in self.curve if math.isfinite(c[1])]
        return min(finite, key=lambda c: c[1]) if finite else (None, math.nan)

    def exhausted(self) -> bool:
        """Whether the last ``patience`` evaluations came after the minimum (early stopping)."""
        if self.patience is None or not self.curve:
            return False
        best = self.best[0]
        after = sum(1 for it, _ in self.curve if best is None or it > best)
        return after >= self.patience

    def summary(self, image: torch.Tensor) -> dict:
        """``holdout_residual`` of ``image``, the minimum on the curve and its iteration, the held-out indices."""
        it, value = self.best
        return {"holdout_residual": self.residual(image), "holdout_best_residual": value,
                "holdout_best_iteration": it, "holdout_indices": list(self.held)}


def split(operator, data: torch.Tensor, spec, patience: Optional[int] = None, name: str = "holdout") -> tuple:
    """The operator and data restricted to the kept angles, and the :class:`Validation` of the held-out ones.

    Parameters
    ----------
    operator : LinearOperator
        ``T``; its first data axis holds the angles.
    data : torch.Tensor
        ``g``, ``(..., *operator.range_shape)``.
    spec : int or list of int
        The holdout (:func:`holdout_rows`).
    patience : int, optional
        Early stopping (:class:`Validation`).
    name : str
        The option's name in messages.

    Returns
    -------
    fit_operator : RestrictedOperator
        ``T`` on the kept rows.
    fit_data : torch.Tensor
        Their data.
    validation : Validation
        The held-out rows' operator, data and record.

    Raises
    ------
    OptionError
        As :func:`holdout_rows`.
    """
    kept, held = holdout_rows(spec, int(operator.range_shape[0]), name)
    k = len(operator.range_shape)
    axis = data.dim() - k
    rows = lambda idx: torch.as_tensor(idx, dtype=torch.long, device=data.device)   # noqa: E731
    fit, check = restrict(operator, kept), restrict(operator, held)
    return (fit, data.index_select(axis, rows(kept)),
            Validation(check, data.index_select(axis, rows(held)), held, patience))

