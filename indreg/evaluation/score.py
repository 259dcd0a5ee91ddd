"""Any reconstruction scored on tilts it was not fitted to: the score of the walk-throughs (docs/real_data.md,
docs/real_data_walnut.md) and of ``indreg-score``.

The score of a volume ``x`` on a set of tilts (or angles) with operator ``T`` and data ``y`` (background removed) is
the relative residual ``||c T x - y|| / ||y||`` in the operator's data inner product, ``c`` the volume's intensity
scale (1 for a volume in the data's units, or fitted by least squares on other tilts for one in any unit). Beside
it, the noise floor ``||n|| / ||y||`` that white noise in those data explains, estimated from the data alone
(``indreg.units.noise_residual``: an upper estimate): no volume can score much below it, and a difference between two
volumes smaller than it is not a difference the data can show.

Convention: ``volumes`` by name, ``operators`` / ``data`` by set name (``test``, ``validation``, ``fit``, ...);
scores in float64.
"""
from __future__ import annotations

import math

import torch

__all__ = ["relative_residual", "fitted_scale", "score_volumes", "score_table", "NOISE_ROW"]

#: The table's row with each set's noise floor.
NOISE_ROW = "noise floor (estimated)"


@torch.no_grad()
def relative_residual(T, x: torch.Tensor, y: torch.Tensor, scale: float = 1.0) -> float:
    """``||scale T x - y|| / ||y||`` in ``T``'s data inner product (float64; nan for all-zero ``y``).

    Parameters
    ----------
    T : LinearOperator
        The operator of the scored tilts or angles (``T(x)`` and ``T.inner_data``).
    x : torch.Tensor or array_like
        The volume, ``T``'s domain shape.
    y : torch.Tensor or array_like
        The data, ``T``'s range shape (background removed).
    scale : float
        The volume's intensity scale ``c``.

    Returns
    -------
    float
        The relative residual (nan when ``y`` is all zero).
    """
    x = torch.as_tensor(x).to(torch.float64)
    y = torch.as_tensor(y).to(torch.float64)
    r = scale * T(x) - y
    yy = float(T.inner_data(y, y).sum())
    return math.sqrt(float(T.inner_data(r, r).sum()) / yy) if yy > 0 else math.nan


@torch.no_grad()
def fitted_scale(operators: list, volume: torch.Tensor, data: list) -> float:
    """The least-squares intensity scale ``c = sum <T x, y> / sum <T x, T x>`` over the pairs of ``operators`` and
    ``data`` (nan when the volume projects to zero)."""
    x = torch.as_tensor(volume).to(torch.float64)
    num = den = 0.0
    for T, y in zip(operators, data):
        p = T(x)
        num += float(T.inner_data(p, torch.as_tensor(y).to(torch.float64)).sum())
        den += float(T.inner_data(p, p).sum())
    return num / den if den > 0 else math.nan


def score_volumes(volumes: dict, operators: dict, data: dict, scales: dict | None = None) -> dict:
    """``{name: {"<set>_residual": ..., "scale": c}}`` for every volume and set, and the noise floors under
    :data:`NOISE_ROW` (``{"<set>_residual": noise_residual(data[set])}``).

    Parameters
    ----------
    volumes : dict
        ``name -> volume`` (tensor or array, the operators' domain shape).
    operators, data : dict
        ``set name -> operator`` and ``set name -> data`` (background removed).
    scales : dict, optional
        ``name -> c`` (default 1 for every volume).

    Returns
    -------
    dict
        The scores by volume, then the noise floors.

    Raises
    ------
    ValueError
        ``operators`` and ``data`` name different sets.
    """
    from ..units import noise_residual

    if set(operators) != set(data):
        raise ValueError(f"operators and data must name the same sets, got {sorted(operators)} and {sorted(data)}")
    scales = scales or {}
    out = {}
    for name, v in volumes.items():
        c = float(scales.get(name, 1.0))
        x = torch.as_tensor(v).to(torch.float64)
        out[name] = {f"{k}_residual": relative_residual(operators[k], x, data[k], c) for k in operators}
        out[name]["scale"] = c
    out[NOISE_ROW] = {f"{k}_residual": noise_residual(torch.as_tensor(data[k]).to(torch.float64)) for k in data}
    return out


def score_table(scores: dict, sets: list, fmt: str = "markdown", counts: dict | None = None) -> str:
    """The scores as a Markdown table (``| volume | <set> (n) | ... | scale |``) or CSV (``volume,<set>,...,scale``),
    residuals to 4 decimals (``counts``: tilts per set, shown in the Markdown header).

    Parameters
    ----------
    scores : dict
        ``name -> {"<set>_residual": ..., "scale": c}`` (:func:`score_volumes`; a row without ``scale`` leaves the
        cell empty), one row each, in order.
    sets : list
        The set names, the columns in order (each row must have their ``<set>_residual``).
    fmt : {"markdown", "csv"}
        The table's format.
    counts : dict, optional
        ``set name -> number of tilts``, shown in the Markdown header (ignored for CSV).

    Returns
    -------
    str
        The table, ending in a newline.

    Raises
    ------
    ValueError
        ``fmt`` neither ``"markdown"`` nor ``"csv"``.
    """
    if fmt not in ("markdown", "csv"):
        raise ValueError(f"fmt must be 'markdown' or 'csv', got {fmt!r}")
    counts = counts or {}
    rows = []
    for name, s in scores.items():
        cells = [f"{s[f'{k}_residual']:.4f}" for k in sets]
        scale = s.get("scale")
        rows.append((name, cells, "" if scale is None else f"{scale:.4g}"))
    if fmt == "csv":
        def quoted(text: str) -> str:
            return f'"{text}"' if any(ch in text for ch in ',"') else text
        lines = [",".join(["volume", *sets, "scale"])]
        lines += [",".join([quoted(n), *c, sc]) for n, c, sc in rows]
        return "\n".join(lines) + "\n"
    head = [f"{k} ({counts[k]})" if k in counts else k for k in sets]
    lines = ["| volume | " + " | ".join(head) + " | scale |", "|---" * (len(sets) + 2) + "|"]
    lines += [f"| {n} | " + " | ".join(c) + f" | {sc} |" for n, c, sc in rows]
    return "\n".join(lines) + "\n"
