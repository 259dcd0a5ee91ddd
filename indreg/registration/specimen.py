"""The wide box of a registration: whether the data call for one, the specimen's size where the data tell it, and the
template padded to it (the options ``wide_box``, ``slab_thickness``, ``slab_extent``, ``template_padding``).

- **whether** (``wide_box="auto"``, the default): when the detector's border sees specimen, not vacuum
  (``indreg.units.border.check_border``, recorded as ``Units.border``): material outside the detector-wide box then adds to
  the data. ``True``: always; ``False``: never.
- **thickness** (``slab_thickness`` None): the template's support along the beam axis at angle 0 (the planes whose mean
  differs from the empty faces', ``indreg.forward.wide_box.slab_thickness``), else the box's own thickness.
- **lateral extent** (``slab_extent`` None): unbounded (a slab); where that would need a box wider than
  ``MAX_WIDTH`` times the given one (a full-angle scan), the extent that the data's mean profile shows: a convex
  specimen's chord ``2 sqrt(R^2 - s^2)`` makes the angle-averaged projection ``P(s)`` satisfy ``P^2 = alpha - beta s^2``
  (a least-squares fit over the detector), ``R = sqrt(alpha / beta)``; else the cap, with a warning naming the option.
- **template** (``template_padding``): ``edge`` (default) repeats the template's outermost cells outwards, the slab's
  profile across its thickness continuing; ``zero`` and ``level`` (the median of its faces) are the alternatives
  (measured in docs/slab.md).
"""
from __future__ import annotations

import logging
import math
from typing import Optional

import numpy as np
import torch

from ..forward.geometry import ParallelBeamGeometry
from ..forward.wide_box import WideBox, slab_thickness, slice_axes, wide_box

log = logging.getLogger("indreg")

__all__ = ["chord_extent", "plan_box"]


def chord_extent(data: torch.Tensor, operator) -> Optional[float]:
    """The specimen's diameter ``2 R`` that a parallel-beam scan over at least 150 degrees shows (the chord law of its
    angle-averaged profile, module docstring).

    Parameters
    ----------
    data : torch.Tensor
        ``operator.range_shape`` (any leading batch axes averaged too).
    operator : RayTransform
        Its operator.

    Returns
    -------
    float or None
        None where the profile does not fall off as a chord's, the angles span less, or the operator is another.
    """
    geometry = getattr(operator, "geometry", None)
    if not isinstance(geometry, ParallelBeamGeometry) or tuple(data.shape[-2:]) != tuple(geometry.shape):
        return None
    if float(geometry.angles.max() - geometry.angles.min()) < math.radians(150):
        return None
    profile = data.detach().double().reshape(-1, *geometry.shape).mean(dim=(0, 1)).numpy()
    s = geometry.det_points.numpy()
    keep = profile > 0
    if keep.sum() < 4:
        return None
    design = np.stack([np.ones(keep.sum()), -s[keep] ** 2], 1)
    (alpha, beta), *_ = np.linalg.lstsq(design, profile[keep] ** 2, rcond=None)
    if not (alpha > 0 and beta > 0):
        return None
    return 2 * math.sqrt(alpha / beta)


def plan_box(template, data: torch.Tensor, operator, o: dict, units, label) -> Optional[WideBox]:
    """The wide box of a run (module docstring); logs what it chose and why, and records it in ``units``.

    Parameters
    ----------
    template : torch.Tensor or None
        On the operator's box (its support along the beam gives the thickness).
    data : torch.Tensor
        The line integrals (background removed).
    operator : LinearOperator
        On the detector-wide box.
    o : dict
        The run's options (``wide_box``, ``slab_thickness``, ``slab_extent``, ``template_padding``).
    units : indreg.units.Units
        What ``indreg.units.measure`` found (its ``border``); ``box_width``, ``slab_thickness`` and ``slab_extent``
        set where a box is made.
    label : callable
        ``label(name)`` names an option in messages.

    Returns
    -------
    WideBox or None
        None where none is called for or nothing would be added.

    Raises
    ------
    TypeError
        ``wide_box=True`` with an operator that has no slice plane.
    """
    mode = o["wide_box"]
    if mode is False or (mode == "auto" and units.border != "specimen"):
        return None
    try:
        u, v = slice_axes(operator)
    except TypeError:
        if mode is True:
            raise TypeError(f"{label('wide_box')}=True needs a RayTransform or a TiltSeriesTransform, got "
                            f"{type(operator).__name__}") from None
        return None
    thickness, how = o["slab_thickness"], "given"
    if thickness is None and template is not None:
        thickness = slab_thickness(template, operator.domain, v)
        how = "the template's support along the beam" if thickness is not None else how
    if thickness is None:
        how = "the box's thickness"
    extent, across = o["slab_extent"], "given" if o["slab_extent"] is not None else "unbounded (a slab)"
    box = wide_box(operator, thickness, extent)
    if box.capped and extent is None:
        found = chord_extent(data, operator)
        if found is not None:
            extent, across = found, "the chord law of the data's mean profile"
            box = wide_box(operator, thickness, extent)
    why = "the data's border is specimen" if mode == "auto" else f"{label('wide_box')}=True"
    if not box.widened:
        log.info("wide box: none needed (%s; thickness %.4g: %s, lateral extent %s): every ray reaching the detector "
                 "crosses the specimen inside the box", why, box.thickness, how,
                 "unbounded" if extent is None else f"{extent:.4g}")
        return None
    units.box_width = box.width_factor
    units.slab_thickness = float(box.thickness)
    units.slab_extent = math.inf if extent is None else float(extent)
    log.info("wide box: %s -> %s cells (%s; thickness %.4g: %s; lateral extent %s: %s); the template padded by "
             "%s=%r; the data term stays on the detector's pixels", tuple(box.field.shape), tuple(box.domain.shape),
             why, box.thickness, how, "unbounded" if extent is None else f"{extent:.4g}", across,
             label("template_padding"), o["template_padding"])
    if box.capped:
        log.warning("wide box: capped at %.3g x the box (a specimen unbounded across the beam at these angles would "
                    "need more): give %s (its lateral extent) or %s", box.width_factor, label("slab_extent"),
                    label("slab_thickness"))
    return box
