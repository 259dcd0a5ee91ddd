"""Intensities in, line integrals out: bright-field / transmission images as ``p = -ln(I / I0)``.

A bright-field electron micrograph or an X-ray radiograph records the transmitted intensity
``I = I0 exp(-integral mu)`` (Beer-Lambert); the ray transform's data are the line integrals ``p = -ln(I / I0)``.
``I0``, the intensity without a specimen, is found from the data (:func:`line_integrals`):

- **vacuum**: where the detector's border sees none of the specimen (``indreg.units.border.check_border`` on ``-ln I``),
  ``I0`` of projection k is its border's level, ``exp(-median(-ln I))`` there: a per-tilt exposure is then measured
  by every frame's own vacuum.
- **slab law**: a specimen wider than the field of view (no vacuum in the frame) has a mean transmission that follows
  ``-ln<I_k> = a / cos(theta_k - theta0) + b`` over the tilts (the path length through a slab; measured on a cryo-ET
  stack to 1.3 %): ``I0 = exp(-b)``. Where the exposure changes with the tilt as ``cos^-n theta`` (SerialEM's exposure
  scaled with the tilt), ``-ln<I_k>`` gains ``n ln cos theta_k``; ``exposure="auto"`` fits ``n`` too and keeps it where
  the data say so: the plain law fails (its ``a <= 0``: the means fall with the tilt) or its residual at least halves,
  and ``|n|`` exceeds 3 standard errors and ``MIN_POWER``. The two terms are nearly collinear over +-60 degrees, so
  ``I0`` is then rough (``n = 1.07`` and ``I0`` 5 % off for ``n = 1`` on the structured synthetic slab of
  tests/units/test_transmission.py, noise-free). A per-tilt exposure known from
  the acquisition (the ``.mdoc``'s ``ExposureTime`` / dose) is given as ``exposure=[...]`` (relative values).

Neither (a full-angle scan of an object wider than the detector): ``I0`` cannot be told from the data; give it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from .border import border_columns, check_border, slab_law
from . import noise_std

__all__ = ["Transmission", "line_integrals", "NONPOSITIVE", "MIN_POWER"]

#: Intensities must be positive; up to this fraction of values <= 0 (a counted, low-dose frame's empty pixels) are
#: raised to half the smallest positive value, more is an error (the data are not intensities).
NONPOSITIVE = 0.01


#: An exposure ``cos^-n theta`` is kept from the data only for ``|n|`` at least this (acquisitions use n = 0.5 to 1; the
#: law's ``1 / cos`` and ``ln cos`` are nearly collinear over +-60 degrees, so a structured slab's deviations from the
#: law fit a small ``n`` by themselves: 0.07 on the synthetic stack of tests/units/test_transmission.py).
MIN_POWER = 0.25


@dataclass
class Transmission:
    """What :func:`line_integrals` did.

    Attributes
    ----------
    i0 : numpy.ndarray
        ``(K,)``: the intensity without specimen, per projection.
    how : str
        How it was found, in words.
    law : SlabLaw or None
        The slab law fitted to the mean transmission (None for vacuum or a given ``I0``).
    exposure_power : float or None
        The ``n`` of an exposure ``cos^-n theta`` kept from the data (None: none).
    raised : int
        The count of values <= 0 raised to ``floor``.
    floor : float
        Half the smallest positive value (0 when none was raised).
    """
    i0: np.ndarray
    how: str
    law: Optional[object] = None
    exposure_power: Optional[float] = None
    raised: int = 0
    floor: float = 0.0

    def as_dict(self) -> dict:
        """The numbers for a run's metrics.

        Returns
        -------
        dict
            ``i0`` (the median), ``i0_min``, ``i0_max``, ``i0_how``, ``exposure_power``, ``raised_values``,
            ``raised_to``.
        """
        i0 = np.atleast_1d(self.i0)
        return {"i0": float(np.median(i0)), "i0_min": float(i0.min()), "i0_max": float(i0.max()),
                "i0_how": self.how, "exposure_power": self.exposure_power, "raised_values": self.raised,
                "raised_to": self.floor}


def _positive(data: torch.Tensor, label: str) -> tuple:
    """``(data, count, floor)``: ``data`` as float64 with values <= 0 raised to ``floor``, half the smallest positive
    one (at most ``NONPOSITIVE`` of them, else a ValueError naming ``label``), and their count."""
    g = data.detach().double()
    bad = g <= 0
    count = int(bad.sum())
    if count == 0:
        return g, 0, 0.0
    if count > NONPOSITIVE * g.numel() or count == g.numel():
        raise ValueError(f"{label}: {100 * count / g.numel():.1f} % of the data are <= 0, which intensities cannot "
                         f"be (-ln(I / I0) needs I > 0): are they line integrals already? Then leave {label} unset")
    floor = float(g[~bad].min()) / 2
    return torch.where(bad, torch.full_like(g, floor), g), count, floor


def _exposure(given, count: int, label: str) -> Optional[np.ndarray]:
    """A given per-projection exposure (relative, positive), or None for ``"auto"`` / None."""
    if given is None or isinstance(given, str):
        return None
    e = np.asarray(given, dtype=np.float64).reshape(-1)
    if e.size != count or not np.isfinite(e).all() or not (e > 0).all():
        raise ValueError(f"{label} exposure must be {count} positive numbers (one per projection), got {given!r}")
    return e / np.median(e)


def _frame_levels(intensities: torch.Tensor, k: int) -> tuple:
    """Per projection, the level the slab law is fitted to, and which: the mean of ``-ln I`` where the noise of
    ``-ln I`` is below the projections' own variation (its bias ``sigma^2 / 2`` is then the smaller), else ``-ln<I>``
    (no noise bias, but Jensen's ``var(p) / 2``)."""
    q = -torch.log(intensities.reshape(k, -1, intensities.shape[-1]))
    sigma = noise_std(q)
    signal = float(q.reshape(k, -1).var(dim=1).median()) - (sigma ** 2 if math.isfinite(sigma) else 0.0)
    if math.isfinite(sigma) and sigma ** 2 < signal:
        return q.reshape(k, -1).mean(1).numpy(), "<-ln I>"
    return -np.log(intensities.reshape(k, -1).mean(1).numpy()), "-ln<I>"


def _slab_i0(intensities: torch.Tensor, angles: np.ndarray, exposure, label: str) -> Transmission:
    """``I0`` from the slab law on the projections' mean transmission (module docstring)."""
    k = len(angles)
    means, which = _frame_levels(intensities, k)
    given = _exposure(exposure, k, label)
    if given is not None:
        means = means + np.log(given)     # the law of the frames at one exposure
    law = slab_law(means, angles)
    power = None
    if given is None and exposure == "auto":   # an exposure cos^-n theta, where the data say so
        scaled = slab_law(means, angles, np.log(np.cos(angles)))
        plain_fails = law is None or not law.a > 0
        if scaled is not None and scaled.a > 0 and abs(scaled.c) > max(3 * scaled.c_se, MIN_POWER) and \
                (plain_fails or scaled.rms <= 0.5 * law.rms):
            law, power = scaled, scaled.c
    if law is None or not law.a > 0:
        raise ValueError(f"{label}='auto': the frames show no vacuum at the detector's border and their mean "
                         f"transmission does not follow the slab law -ln<I> = a / cos(theta - theta0) + b over the "
                         f"tilts; give {label}=<I0> (the intensity without specimen)")
    how = (f"the slab law of the mean transmission: {which} = {law.a:.4g} / cos(theta - "
           f"{math.degrees(law.theta0):.1f} deg) + {law.b:.4g}" + ("" if power is None else
                                                               f" + {power:.3g} ln cos theta (an exposure cos^-n)")
           + f", rms {law.rms:.2g}")
    i0 = np.exp(-(law.b + (np.zeros(k) if power is None else power * np.log(np.cos(angles)))))
    if given is not None:
        i0, how = i0 * given, how + ", with the given exposure per tilt"
    return Transmission(i0, how, law, power)


def line_integrals(intensities, angles=None, i0="auto", exposure="auto", label: str = "transmission") -> tuple:
    """``(p, Transmission)``: ``p = -ln(I / I0_k)``, float64, the shape of ``intensities`` (projections first).

    Parameters
    ----------
    intensities : tensor ``(K, columns)`` or ``(K, rows, columns)``
        Bright-field / transmission intensities (counts or normalised), positive.
    angles : array of K radians, optional
        The projections' angles (for the slab law); None: vacuum or a given ``i0`` only.
    i0 : ``"auto"`` or a positive number
        The intensity without specimen; ``"auto"``: the frames' vacuum, else the slab law (module docstring).
    exposure : ``"auto"``, None or K positive numbers
        The exposure per projection: ``"auto"`` fits a ``cos^-n theta`` exposure where the data say so, None keeps
        one ``I0``, numbers are relative exposures (applied to the slab law's ``I0``, or to a given one).
    label : str
        How errors name the option.

    Returns
    -------
    tuple
        ``(p, Transmission)``.

    Raises
    ------
    ValueError
        Data with more than ``NONPOSITIVE`` of values <= 0; ``i0`` not positive; ``"auto"`` with neither vacuum nor
        a slab law (naming ``label``).
    """
    g, raised, floor = _positive(torch.as_tensor(intensities), label)
    q = -torch.log(g)
    k = g.shape[0]
    angles = None if angles is None else np.asarray(angles, dtype=np.float64).reshape(-1)
    if angles is not None and len(angles) != k:
        angles = None
    if i0 != "auto":
        value = float(i0) if isinstance(i0, (int, float)) and not isinstance(i0, bool) else math.nan
        if not (value > 0 and math.isfinite(value)):
            raise ValueError(f"{label} must be None, 'auto' or a positive number (I0), got {i0!r}")
        given = _exposure(exposure, k, label)
        t = Transmission(np.full(k, value) * (1.0 if given is None else given),
                         f"given: {value:.6g}" + ("" if given is None else " with the given exposure per tilt"))
    else:
        check = check_border(q, angles)
        if check.kind == "vacuum":
            border = border_columns(q.reshape(k, -1, q.shape[-1])).reshape(k, -1)
            t = Transmission(torch.exp(-border.median(dim=1).values).numpy(),
                             "the vacuum at the detector's border, frame by frame")
        elif angles is not None:
            t = _slab_i0(g, angles, exposure, label)
        else:
            raise ValueError(f"{label}='auto' needs vacuum at the detector's border or the tilt angles (for the "
                             f"slab law); {check.describe()}: give {label}=<I0>")
    t.raised, t.floor = raised, floor
    shape = (k,) + (1,) * (q.dim() - 1)
    p = q + torch.log(torch.as_tensor(np.atleast_1d(t.i0), dtype=q.dtype)).reshape(shape)
    return p, t
