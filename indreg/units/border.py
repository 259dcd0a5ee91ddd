"""Vacuum or specimen at the detector's border, the slab law, and the background that projections of either have.

Projections (line integrals) of an object inside the field of view are about 0 outside its shadow: the detector's
outermost columns see vacuum, their level is the data's offset (``background='auto'`` subtracts it). A specimen
wider than the field of view (a slab of ice, a lamella, tissue in region-of-interest CT) covers the border: its
level is material, and subtracting it makes much of the data negative (measured on a cryo-ET stack: 45 % of all
values, 84 % at 0 degrees). :func:`check_border` tells the two apart from the data alone, three ways:

- **position**: vacuum is the bottom of every projection's range; the fraction of values more than ``3 sigma`` below
  their projection's border level (``sigma``: the noise, ``indreg.units.noise_std``) is then near 0 (each projection
  against its own: an exposure that drifts with the tilt moves the whole frame). Above ``BELOW`` the border
  is not the bottom: specimen.
- **texture**: vacuum is flat; the border's variation within a projection beyond the noise, relative to the data's
  range, above ``TEXTURE`` is structure: specimen.
- **tilt law** (a tilt series, angles known): through a slab the path length is ``t / cos theta``, so the border's
  level follows ``a / cos(theta - theta0) + b`` with ``a > 0`` (:func:`slab_law`); a law whose swing over the tilts
  exceeds ``LAW_SWING`` times both its residual and the levels' noise, and explains most of their variance, is a
  slab. Vacuum does not follow it (its level is the offset, or changes with the exposure, which decreases it).

None of them: vacuum when the border is flat (its texture below ``TEXTURE / 2``), else unclear (a few values below
the vacuum are no specimen: etspy's aligned HAADF stack has 4 % of them, the fill beside its shifted frames).
:func:`background_level` is what ``background='auto'`` subtracts: the vacuum's level; for a slab tilt series the slab
law's intercept ``b`` fitted to the projections' means (a slab's line integrals have none: ``b`` is the offset); else
0. It never returns a level that would make most of the data negative (:func:`negative_fraction`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from . import noise_std

__all__ = ["BELOW", "TEXTURE", "LAW_SWING", "MOST", "SlabLaw", "BorderCheck", "slab_law", "check_border",
           "background_level", "slab_offset", "negative_fraction", "projection_angles", "border_columns"]

#: Fraction of values more than 3 sigma below the border's level above which the border is not vacuum.
BELOW = 0.10
#: The border's variation beyond the noise, relative to the data's range, above which it is structure.
TEXTURE = 0.05
#: A slab law counts when its swing over the tilts is this many times its residual and the levels' noise.
LAW_SWING = 4.0
#: A background that makes more than this fraction of the data negative (beyond the noise) is refused.
MOST = 0.5
_OFFSETS = np.radians(np.arange(-15.0, 15.01, 0.25))   # theta0 searched (the specimen's own tilt)


@dataclass
class SlabLaw:
    """``level(theta) = a / cos(theta - theta0) + b [+ c extra(theta)]`` fitted by least squares (:func:`slab_law`).

    Attributes
    ----------
    a, b : float
        The law's slope (a slab: its attenuation times its thickness) and intercept (the data's offset).
    theta0 : float
        The specimen's own tilt (radians).
    rms, r2 : float
        The residual's root mean square and the fraction of the levels' variance explained.
    swing : float
        ``a (max - min) 1 / cos(theta - theta0)`` over the fitted tilts.
    c, c_se : float
        The coefficient of an ``extra`` regressor and its standard error (0 without).
    """
    a: float
    b: float
    theta0: float
    rms: float
    r2: float
    swing: float
    c: float = 0.0
    c_se: float = 0.0

    def predict(self, angles) -> np.ndarray:
        """The law without its extra term.

        Parameters
        ----------
        angles : array_like
            Radians.

        Returns
        -------
        numpy.ndarray
            ``a / cos(angles - theta0) + b``.
        """
        return self.a / np.cos(np.asarray(angles, dtype=np.float64) - self.theta0) + self.b


def slab_law(levels, angles, extra=None) -> Optional[SlabLaw]:
    """Fit ``levels_k = a / cos(theta_k - theta0) + b [+ c extra_k]``: linear least squares for every ``theta0``
    within 15 degrees on a 0.25 degree grid, the best kept.

    Parameters
    ----------
    levels : array_like
        K values, one per tilt.
    angles : array_like
        K tilt angles (radians).
    extra : array_like, optional
        K values of a further regressor (e.g. ``ln cos theta`` for an exposure ``cos^-n theta``).

    Returns
    -------
    SlabLaw or None
        None with fewer than 4 tilts (5 with ``extra``), tilts within 20 degrees of 90 (the law diverges), or no
        spread in ``1 / cos``.
    """
    y = np.asarray(levels, dtype=np.float64).reshape(-1)
    th = np.asarray(angles, dtype=np.float64).reshape(-1)
    columns = [] if extra is None else [np.asarray(extra, dtype=np.float64).reshape(-1)]
    if y.size != th.size or y.size < 4 + len(columns) or not np.isfinite(y).all():
        return None
    best = None
    for t0 in _OFFSETS:
        c = np.cos(th - t0)
        if c.min() < math.cos(math.radians(70.0)):
            continue
        x = 1.0 / c
        if np.ptp(x) < 1e-3:
            continue
        design = np.stack([x, np.ones_like(x), *columns], 1)
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)
        rss = float(((design @ coef - y) ** 2).sum())
        if best is None or rss < best[0]:
            best = (rss, coef, t0, np.ptp(x), design)
    if best is None:
        return None
    rss, coef, t0, spread, design = best
    tss = float(((y - y.mean()) ** 2).sum())
    law = SlabLaw(float(coef[0]), float(coef[1]), float(t0), math.sqrt(rss / y.size),
                  1.0 - rss / tss if tss > 0 else 0.0, float(coef[0] * spread))
    if columns:
        cov = np.linalg.pinv(design.T @ design) * rss / max(y.size - design.shape[1], 1)
        law.c, law.c_se = float(coef[2]), math.sqrt(max(float(cov[2, 2]), 0.0))
    return law


@dataclass
class BorderCheck:
    """What :func:`check_border` found.

    Attributes
    ----------
    kind : str
        ``"vacuum"``, ``"specimen"`` or ``"unclear"``.
    level : float
        The border's median (``indreg.units.border_level``).
    below : float
        The fraction of values more than 3 sigma below their projection's border level.
    texture : float
        The border's variation beyond the noise over the data's range.
    sigma : float
        The data's noise (``indreg.units.noise_std``).
    law : SlabLaw or None
        The slab law of the border's levels over the tilts (None without angles).
    reasons : list of str
        Why, in words.
    """
    kind: str
    level: float
    below: float
    texture: float
    sigma: float
    law: Optional[SlabLaw] = None
    reasons: list = field(default_factory=list)

    def describe(self) -> str:
        """The decision in one phrase.

        Returns
        -------
        str
            The kind and why.
        """
        why = "; ".join(self.reasons) if self.reasons else "no sign of either"
        return f"the detector's outermost columns look like {self.kind} ({why})"

    def as_dict(self) -> dict:
        """The decision's numbers for a run's metrics.

        Returns
        -------
        dict
            ``border``, ``border_level``, ``border_below``, ``border_texture``, ``border_reasons`` and the law's.
        """
        return {"border": self.kind, "border_level": self.level, "border_below": self.below,
                "border_texture": self.texture, "border_reasons": "; ".join(self.reasons),
                **({} if self.law is None else {"border_law_a": self.law.a, "border_law_b": self.law.b,
                                                "border_law_theta0_deg": math.degrees(self.law.theta0),
                                                "border_law_r2": self.law.r2})}


def projection_angles(operator) -> Optional[np.ndarray]:
    """The angles of an operator's projections, the first axis of its data.

    Parameters
    ----------
    operator : LinearOperator
        A ray transform, a tilt series, an aligned one around them, or another.

    Returns
    -------
    numpy.ndarray or None
        Radians; None for an operator without a geometry's angles.
    """
    inner = getattr(operator, "operator", operator)
    angles = getattr(getattr(inner, "geometry", None), "angles", None)
    return None if angles is None else np.asarray(angles, dtype=np.float64)


def _frames(data: torch.Tensor, angles) -> Optional[torch.Tensor]:
    """``(K, rows, columns)`` float64 views of the K projections when ``angles`` matches the data's first axis."""
    g = data.detach().double()
    if angles is None or g.dim() not in (2, 3) or g.shape[0] != len(angles):
        return None
    return g.reshape(g.shape[0], -1, g.shape[-1])


def border_columns(g: torch.Tensor) -> torch.Tensor:
    """The detector's border.

    Parameters
    ----------
    g : torch.Tensor
        ``(..., n)``, the last axis the detector's columns.

    Returns
    -------
    torch.Tensor
        ``(..., 2 k)``: the outermost ``k = max(1, n // 16)`` columns on each side.
    """
    n = g.shape[-1]
    k = max(1, n // 16)
    return torch.cat([g[..., :k], g[..., n - k:]], -1) if n > 1 else g


def _spread(g: torch.Tensor) -> float:
    """The data's range between the 0.5 and 99.5 percentiles (a subsample of at most 10^6 values)."""
    flat = g.reshape(-1)
    if flat.numel() > 10 ** 6:
        flat = flat[torch.linspace(0, flat.numel() - 1, 10 ** 6, dtype=torch.float64).long()]
    lo, hi = torch.quantile(flat, torch.tensor([0.005, 0.995], dtype=flat.dtype))
    return float(hi - lo)


def negative_fraction(data: torch.Tensor, level: float, sigma: Optional[float] = None) -> float:
    """The values that subtracting ``level`` makes negative beyond what the noise explains.

    Parameters
    ----------
    data : torch.Tensor
        Any shape.
    level : float
        The level subtracted.
    sigma : float, optional
        The noise; None: :func:`indreg.units.noise_std` (at least 1e-6 of the data's range either way).

    Returns
    -------
    float
        The fraction of ``data - level`` below ``-3 sigma``.
    """
    g = data.detach().double()
    if sigma is None:
        sigma = noise_std(g)
    sigma = max(sigma if math.isfinite(sigma) else 0.0, 1e-6 * _spread(g))
    return float((g < level - 3.0 * sigma).double().mean())


def check_border(data: torch.Tensor, angles=None) -> BorderCheck:
    """Vacuum, specimen or unclear at the detector's border (module docstring).

    Parameters
    ----------
    data : torch.Tensor
        ``(..., columns)``, the last axis the detector's columns; projections along the first.
    angles : array_like, optional
        Radians, one per projection, for the tilt law (None: none).

    Returns
    -------
    BorderCheck
        The decision, its numbers and reasons.
    """
    g = data.detach().double()
    sigma = noise_std(g)
    sigma = sigma if math.isfinite(sigma) else 0.0
    spread = _spread(g)
    level = float(border_columns(g).median())
    frames = _frames(g, angles)
    rows = (frames if frames is not None else g.reshape(-1, 1, g.shape[-1]))
    per_frame = border_columns(rows).reshape(rows.shape[0], -1)
    floor = 3.0 * max(sigma, 1e-6 * spread)   # each projection against its own border (an exposure may drift)
    below = float((rows < per_frame.median(dim=1).values[:, None, None] - floor).double().mean())
    within = float(per_frame.var(dim=1).median()) if per_frame.shape[1] > 1 else 0.0
    texture = math.sqrt(max(within - sigma ** 2, 0.0)) / spread if spread > 0 else 0.0
    law = None if frames is None else slab_law(per_frame.median(dim=1).values.numpy(), angles)
    reasons = []
    if below > BELOW:
        reasons.append(f"{100 * below:.0f} % of the values lie below the border's level {level:.4g} by more than "
                       "3x the noise: it is not the bottom of the projections")
    if texture > TEXTURE:
        reasons.append(f"the border varies by {100 * texture:.0f} % of the data's range beyond its noise: structure")
    if law is not None:
        noise = 1.2533 * sigma / math.sqrt(per_frame.shape[1])   # a median's standard error
        if law.a > 0 and law.r2 > 0.5 and law.swing > LAW_SWING * max(law.rms, noise, 1e-9 * spread):
            reasons.append(f"its level follows a / cos(theta - theta0) + b over the tilts (a = {law.a:.4g}, "
                           f"theta0 = {math.degrees(law.theta0):.1f} deg, {100 * law.r2:.0f} % of the variance), "
                           "as a slab's path length")
    if reasons:
        return BorderCheck("specimen", level, below, texture, sigma, law, reasons)
    if texture < TEXTURE / 2:   # below BELOW too: a frame's fill beside a shifted image is no specimen
        return BorderCheck("vacuum", level, below, texture, sigma, law,
                           ["flat, at the bottom of the projections" + ("" if law is None else
                                                                       ", its level not following 1 / cos")])
    return BorderCheck("unclear", level, below, texture, sigma, law, [])


def slab_offset(data: torch.Tensor, angles) -> Optional[SlabLaw]:
    """The slab law of the projections' means over the tilts (its ``b``: the data's offset, since a slab's line
    integrals have none).

    Parameters
    ----------
    data : torch.Tensor
        ``(K, columns)`` or ``(K, rows, columns)``.
    angles : array_like or None
        K radians.

    Returns
    -------
    SlabLaw or None
        None where the angles do not match the data's first axis or the law has no ``a > 0``.
    """
    frames = _frames(data, angles)
    law = None if frames is None else slab_law(frames.mean(dim=(1, 2)).numpy(), angles)
    return law if law is not None and law.a > 0 else None


def background_level(data: torch.Tensor, angles=None, check: Optional[BorderCheck] = None) -> tuple:
    """What ``background='auto'`` subtracts (module docstring), and why.

    Vacuum: the border's level; a slab tilt series: the slab law's intercept over the projections' means; else 0.
    A level that would make more than ``MOST`` of the values negative is not taken (0, and ``how`` says so).

    Parameters
    ----------
    data : torch.Tensor
        Line integrals ``(..., columns)``, projections along the first axis.
    angles : array_like, optional
        Radians, one per projection.
    check : BorderCheck, optional
        :func:`check_border`'s decision, if made already.

    Returns
    -------
    tuple
        ``(level, check, how)``: the level, the decision, and why in words.
    """
    check = check_border(data, angles) if check is None else check
    law = slab_offset(data, angles) if check.kind == "specimen" else None
    if check.kind == "vacuum":
        level, how = check.level, "the level of the vacuum at the detector's border"
    elif law is not None:
        level, how = law.b, (f"the slab law's intercept: the projections' means follow {law.a:.4g} / cos(theta - "
                             f"{math.degrees(law.theta0):.1f} deg) + {law.b:.4g}, and a slab's line integrals have "
                             "no offset")
    else:
        return 0.0, check, f"none: {check.describe()}, so no vacuum level and no slab law to read an offset from"
    if negative_fraction(data, level, check.sigma) > MOST:
        return 0.0, check, (f"none: {how} is {level:.4g}, which would make more than {100 * MOST:.0f} % of the data "
                            "negative")
    return level, check, how
