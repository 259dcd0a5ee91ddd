"""The width ``sigma`` of the kernel of V when the user gives none (``register(sigma=None)``, the default, and the
app's ``data=files``), or chooses it from held-out angles (``sigma="auto"``).

``sigma`` is a length in the domain's units, and the domain's box is the template's extent: a user who never
chose that box has no length to start from. The default is a fixed fraction of the box's largest side,

    sigma = SIGMA_FRACTION * max_i (max_pt_i - min_pt_i)          (1/8: 4 on the box [-16, 16]^2)

the same physical width on any grid of the same box (as ``solver="fast"``'s coarse levels assume). Measured
(docs/own_data.md, ``python scripts/own_data_defaults.py``): the width within 0.01 SSIM of the best found on the
scikit-image Shepp-Logan case (128^2) and on the shipped own-data example (64^2); on the paper's suite 1 (J -> V,
a larger deformation) it reaches 0.941 where sigma 6 and 8 reach 0.966 and 0.968: ``sigma="auto"`` finds those.

``sigma="auto"``: each width of :func:`candidates` (``AUTO_FRACTIONS`` of the box's side) registers the data with
every ``AUTO_HOLDOUT``-th angle held out (or the run's own ``holdout``), with the run's other options; the one
whose reconstruction predicts the held-out angles best (least held-out residual on the curve,
``indreg.evaluation.validation``) is used for the run. Its cost: ``len(AUTO_FRACTIONS)`` registrations before the run.
"""
from __future__ import annotations

import logging
from typing import Callable

__all__ = ["SIGMA_FRACTION", "AUTO_FRACTIONS", "AUTO_HOLDOUT", "box_side", "default_sigma", "candidates",
           "choose_sigma"]

log = logging.getLogger("indreg")

#: The default sigma as a fraction of the box's largest side.
SIGMA_FRACTION = 1 / 8
#: ``sigma="auto"``'s candidate widths, as fractions of the box's largest side.
AUTO_FRACTIONS = (1 / 16, 1 / 8, 1 / 4)
#: ``sigma="auto"`` without ``holdout``: every this-many-th angle is held out for the choice.
AUTO_HOLDOUT = 5


def box_side(domain) -> float:
    """The largest side of the domain's box (physical units)."""
    return float(max(domain.extent))


def default_sigma(domain) -> float:
    """``SIGMA_FRACTION`` times the box's largest side."""
    return SIGMA_FRACTION * box_side(domain)


def candidates(domain) -> tuple:
    """``sigma="auto"``'s widths: ``AUTO_FRACTIONS`` of the box's largest side, smallest first."""
    return tuple(f * box_side(domain) for f in AUTO_FRACTIONS)


def choose_sigma(score: Callable[[float], float], widths: tuple, say: Callable[[str], None] = None) -> tuple:
    """The width of ``widths`` with the least ``score(width)`` (a held-out residual; the first of equal ones).

    Parameters
    ----------
    score : callable
        ``score(width) -> float``, e.g. the held-out residual of a registration with that width.
    widths : tuple of float
        The candidates, in the order they are tried.
    say : callable, optional
        ``say(line)`` for each width's score as it comes, then the choice (default: logged at INFO).

    Returns
    -------
    tuple
        ``(sigma, scores)``: the chosen width and ``{width: score}``.
    """
    say = say or (lambda line: log.info("%s", line))
    scores = {}
    for k, w in enumerate(widths, 1):
        scores[w] = score(w)
        say(f"sigma='auto' {k}/{len(widths)}: sigma {w:.4g} gives held-out residual {scores[w]:.4f}")
    best = min(widths, key=lambda w: scores[w])
    say(f"sigma='auto': chose sigma {best:.4g} of {', '.join(f'{w:.4g}' for w in widths)}")
    return best, scores
