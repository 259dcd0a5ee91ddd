"""The alignment's choices and bounds, declared once and importable without torch (the option table,
``indreg.options``, and the aligner app's argument checks read them before torch loads).

Notes
-----
See docs/alignment.md.

- ``mode``: what the fit estimates; ``gauge``: what the shifts leave to the deformation (a translation of the
  object moves projection ``k`` by ``a cos(theta_k) + b sin(theta_k)`` across the axis, and every projection
  alike along it; ``indreg.alignment.fit.gauge``); ``interpolation`` / ``edge``: how the data model ``T_s``
  moves a projection image (``indreg.alignment.operator``). The first entry of each is the default.
- Bounds: ``|s| <= MAX_SHIFT_FRACTION`` of the detector's pixels along the component, ``|alpha| <=
  MAX_ANGLE_DEG``; a parameter that ends at its bound is reported (a warning, and ``at_bound`` in the
  summary).
"""
from __future__ import annotations

__all__ = ["ALIGN_MODES", "ALIGN_GAUGES", "INTERPOLATIONS", "EDGES", "ALIGN_EVERY", "MAX_SHIFT_FRACTION",
           "MAX_ANGLE_DEG", "MAX_ANGLE_SE_DEG", "MIN_PROJECTIONS", "check_choice"]

#: What the fit estimates: nothing, per-projection shifts, or shifts and the tilt-axis angle (a tilt series).
ALIGN_MODES = ("none", "shifts", "shifts+axis")
#: What the shifts are kept orthogonal to (module Notes).
ALIGN_GAUGES = ("offset+translation", "translation", "none")
#: How ``T_s`` moves a projection image: bilinear, or Keys' cubic convolution.
INTERPOLATIONS = ("linear", "cubic")
#: What ``T_s`` takes beyond the detector: the nearest edge pixel, or zero.
EDGES = ("nearest", "zero")
#: Iterations between two estimates in the fit (docs/alignment.md: re-estimating more often did not recover the
#: shifts better and costs a Gauss-Newton solve each time).
ALIGN_EVERY = 10
#: Bound on ``|s|`` as a fraction of the detector's pixels along the component.
MAX_SHIFT_FRACTION = 0.25
#: Bound on the tilt-axis angle (degrees).
MAX_ANGLE_DEG = 10.0
#: Above this standard error (degrees) the tilt-axis angle is reported as not determined by the data.
MAX_ANGLE_SE_DEG = 0.2
#: Fewest projections that can be aligned (the gauge removes three shifts across the axis).
MIN_PROJECTIONS = 4


def check_choice(name: str, value, allowed: tuple) -> str:
    """``value`` if it is one of ``allowed``.

    Parameters
    ----------
    name : str
        The option as the user named it (keyword or config key), for the message.
    value : object
        The value given.
    allowed : tuple of str
        The choices, e.g. :data:`ALIGN_MODES`.

    Returns
    -------
    str
        ``value``.

    Raises
    ------
    ValueError
        One line naming the option, the choices and the value, when ``value`` is not among them.
    """
    if value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
    return value
