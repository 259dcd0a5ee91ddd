"""The orientation probe before a run: does the template's projection fit the data better under another reading of
them (detector reversed, angles in the opposite sense, a tilt series turned by 180 or 90 degrees)?

A layout mistake ends ``completed`` with a plausible residual: the registration deforms the template until it
fits the mis-read data as well as it can (a flipped detector: SSIM 0.02 instead of 0.78, docs/reliability.md).
The data alone cannot tell most readings apart (every reading is the data of some object); the template can: each
reading is scored by the correlation of the gradients (along the detector, and along the angles or the tilt axis)
of the template's projection and of the data read so, both first blurred along the detector (:data:`BLUR` bins):
the gradients see the edges that tell the readings apart, where the smooth envelope of the projections fits every
reading (raw correlations: 0.86 and 0.92 for a 3D stack turned by 180 degrees and turned back), and the blur keeps
a deformed template ranking the readings right. A reading better than the
data as given by :data:`WARN` gets a warning naming the fix, by :data:`REFUSE` an error (``orientation="warn"``
lets the run go on; ``"off"`` skips the probe). One forward projection of each mirrored or turned template (less
than one iteration: 0.68 and 0.85 of one on docs/reliability.md's 2D and 3D cases), on at most :data:`SLICES`
slices of a tilt series.

Readings (:func:`readings`): an operator with a ``geometry`` (indreg's ray transforms) is probed for a reversed
detector (the data's last axis flipped); a 2D
parallel-beam ``RayTransform`` and a ``TiltSeriesTransform`` also for the opposite sense of the angles (``theta ->
-theta`` is the template mirrored along the second axis of the plane of rotation: exact on a domain centred in
it), a 2D one (square) for its template turned by 90 degrees either way or transposed (an array stored as
displayed, or as an MRC section, read as indreg's), and a tilt series for its stack turned by 180 degrees (rows and
columns reversed) and, with square projections, by 90 degrees. A fan beam: the detector alone; other operators
(composed, user-defined): not probed.

Notes
-----
``template`` ``operator.domain.shape``, ``data`` ``operator.range_shape`` (the prepared inputs of
``indreg.registration.run.setup``); the angles on the first data axis, detector columns on the last.

Longer than 450 lines: the one home of orientation probing: the readings, the probe and the load's check share the
correlation.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from .conventions import (CONVENTIONS, angles_to_indreg, detector_for, domain_for, get_convention, image_from_indreg,
                          image_to_indreg, sinogram_layout)

__all__ = ["WARN", "REFUSE", "MIN_FIT", "RELATIVE", "TIE", "BLUR", "SLICES", "MODES", "MARGIN", "CONVENTION_TIE",
           "CHECK_PIXELS", "CHECK_ANGLES", "Reading", "Table", "readings", "scores", "margin_needed", "verdict", "check",
           "correlation", "orientation_scores", "orientation_hint", "flip_hint", "target_hint"]

log = logging.getLogger("indreg")

#: A reading whose fit exceeds the data-as-given's by this much is named in a warning ...
WARN = 0.05
#: ... and by this much refused (measured, scripts/orientation_probes.py: the right reading of every probe case and
#: every preset scores within 0.005 of the best reading; the wrong ones lose 0.13 (a 3D stack turned by 180 degrees:
#: a warning) to 0.25 (a 2D detector reversed, angles in the opposite sense: refused); docs/reliability.md).
REFUSE = 0.2
#: A reading is named only when its fit is at least this (a template that fits no reading says nothing).
MIN_FIT = 0.3
#: ... and only when it removes at least this fraction of the misfit ``1 - r`` the data as given leave: a template
#: that fits its data poorly in every reading (J against V at 48^2: 0.37 as given) gains a few hundredths in a wrong
#: one by chance (0.42: three false warnings in 260 runs of indreg's own data, ``scripts/orientation_probes.py
#: --false-rate``); the wrong readings named remove 0.28 (ASTRA's layout) to 0.9 of it.
RELATIVE = 0.2
#: Readings within this of the best are named with it (they cannot be told apart on these data).
TIE = 0.02
#: The blurs before the gradients, in bins (a Gaussian's standard deviation along the detector): the one whose best
#: reading fits best is taken (noise-free data: 1 bin; the paper's noisy suites: 4).
BLUR = (1.0, 4.0)
#: A tilt series is probed on at most this many slices along its tilt axis (evenly spaced).
SLICES = 32
#: ``orientation=``: ``check`` (warn, refuse a large margin), ``warn`` (warn only), ``off``.
MODES = ("check", "warn", "off")


@dataclass(frozen=True)
class Reading:
    """One reading of the inputs: ``template`` and ``data`` map the given ones to it; ``fix`` names what makes the
    given inputs this reading."""
    name: str
    template: Callable
    data: Callable
    fix: str


def _same(x):
    return x


def _plane(operator) -> Optional[tuple]:
    """The array axes ``(u, v, t)`` of the plane of rotation (``t``: the tilt axis, None in 2D) of a parallel-beam
    ``RayTransform`` or a ``TiltSeriesTransform``, None for any other operator."""
    from ..forward import ParallelBeamGeometry, RayTransform, TiltSeriesTransform

    if isinstance(operator, TiltSeriesTransform):
        t = operator.geometry.axis
        u, v = (a for a in range(3) if a != t)
        return u, v, t
    if isinstance(operator, RayTransform) and type(operator.geometry) is ParallelBeamGeometry:
        return 0, 1, None
    return None


def readings(operator, data_shape: tuple) -> list:
    """The readings probed for ``operator`` (module docstring); the first is the data as given.

    Parameters
    ----------
    operator : LinearOperator
        The forward operator (a ray transform or tilt series has readings beyond the data as given).
    data_shape : tuple of int
        The data's shape.

    Returns
    -------
    list of Reading
        The readings, the data as given first.
    """
    out = [Reading("as given", _same, _same, "")]
    if getattr(operator, "geometry", None) is None or len(data_shape) < 2:   # not a ray transform: no detector
        return out
    out.append(Reading("the detector reversed", _same, lambda g: g.flip(-1),
                       "reverse the detector bins (np.flip(data, -1))"))
    plane = _plane(operator)
    if plane is None:
        return out
    u, v, t = plane
    k = len(operator.domain.shape)
    mirror = lambda f: f.flip(f.dim() - k + v)   # noqa: E731   (theta -> -theta)
    negate = ("negate the angles (IMOD's .tlt / tilt.f90 sense: data.convention=imod, or convention='imod' in "
              "indreg.load)")
    out.append(Reading("the angles in the opposite sense", mirror, _same, negate))
    if t is None:
        out.append(Reading("the angles in the opposite sense and the detector reversed", mirror,
                           lambda g: g.flip(-1), f"{negate} and reverse the detector bins"))
        return out + (_turns() if operator.domain.shape[0] == operator.domain.shape[1] else [])
    out.append(Reading("the stack turned by 180 degrees", _same, lambda g: g.flip(-1, -2),
                       "turn the stack by 180 degrees: add 180 to the tilt-axis angle (geometry.tilt_axis_angle / "
                       "tilt_axis_angle)"))
    if data_shape[-1] == data_shape[-2]:
        for sign in (1, -1):
            out.append(Reading(f"the stack turned by {90 * sign:+d} degrees",
                               _same, lambda g, s=sign: g.rot90(s, (-2, -1)),
                               f"turn the stack: add {90 * sign:+d} degrees to the tilt-axis angle "
                               "(geometry.tilt_axis_angle / tilt_axis_angle)"))
    return out


def _turns() -> list:
    """The 2D template turned or transposed: an array stored as displayed, or as an MRC section, read as indreg's."""
    return [Reading("the template turned by -90 degrees", lambda f: f.rot90(-1, (-2, -1)), _same,
                    "the template is probably stored as displayed (rows = y top-down, as ASTRA, scikit-image and "
                    "TomoPy hold images): data.convention=astra / skimage / tomopy (convention= in indreg.load), or "
                    "np.rot90(template, -1)"),
            Reading("the template turned by +90 degrees", lambda f: f.rot90(1, (-2, -1)), _same,
                    "turn the template: np.rot90(template)"),
            Reading("the template transposed", lambda f: f.transpose(-2, -1), _same,
                    "the template is probably an MRC section (rows = y bottom-up): data.convention=imod (convention= "
                    "in indreg.load), or template.T")]


def _blur(g: torch.Tensor, width: float) -> torch.Tensor:
    """A Gaussian blur of ``width`` bins along the last axis (zero padding)."""
    r = max(1, math.ceil(3 * width))
    x = torch.arange(-r, r + 1, dtype=g.dtype, device=g.device)
    w = torch.exp(-x ** 2 / (2 * width ** 2))
    w = (w / w.sum()).tolist()
    padded = torch.nn.functional.pad(g, (r, r))
    n = g.shape[-1]
    out = padded[..., :n] * w[0]   # a sum of shifted copies: two arrays of the data's size (conv1d's unfolding
    for k in range(1, 2 * r + 1):  # held 25 of them: 400 MB for 32 slices of a 1024-column stack)
        out.add_(padded[..., k:k + n], alpha=w[k])
    return out


def _gradients(g: torch.Tensor, width: float) -> torch.Tensor:
    """The differences of the blurred data along the detector and along the axis before it, as one vector."""
    g = _blur(g.double(), width)
    return torch.cat([g.diff(dim=-1).flatten(), g.diff(dim=-2).flatten()])


def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    """The correlation coefficient of ``a`` and ``b`` as vectors (float64); 0 where either is constant."""
    a, b = a.double().flatten(), b.double().flatten()
    a, b = a - a.mean(), b - b.mean()
    norm = float(a.norm() * b.norm())
    return float(a @ b) / norm if norm > 0 else 0.0


def _correlation(a: torch.Tensor, b: torch.Tensor, width: float = BLUR[0]) -> float:
    """:func:`correlation` of the blurred gradients (module docstring)."""
    return correlation(_gradients(a, width), _gradients(b, width))


def _fewer_slices(template: torch.Tensor, data: torch.Tensor, operator) -> tuple:
    """A tilt series of more than :data:`SLICES` slices along its tilt axis probed on that many, evenly spaced and
    symmetric about the middle (so that a turned stack's rows are among them): ``(template, data, operator)``; other
    problems as they are."""
    from ..domain import ImageDomain
    from ..forward import TiltSeriesTransform

    if not isinstance(operator, TiltSeriesTransform):
        return template, data, operator
    t, n = operator.geometry.axis, operator.domain.shape[operator.geometry.axis]
    if n <= SLICES:
        return template, data, operator
    half = [round(j * (n - 1) / (SLICES - 1)) for j in range(SLICES // 2)]
    rows = torch.as_tensor(half + [n - 1 - i for i in reversed(half)], device=data.device)
    d = operator.domain
    h = d.cell_sides[t]
    shape = tuple(SLICES if a == t else m for a, m in enumerate(d.shape))
    lo = tuple(-h * SLICES / 2 if a == t else x for a, x in enumerate(d.min_pt))
    hi = tuple(h * SLICES / 2 if a == t else x for a, x in enumerate(d.max_pt))
    small = operator.on_rows(ImageDomain(shape, lo, hi))   # the same slices: its system matrix, not a new one
    k = template.dim() - 3 + t
    return template.index_select(k, rows.to(template.device)), data.index_select(data.dim() - 2, rows), small


class Table(dict):
    """``{reading name: (correlation, Reading)}`` and ``samples``: the gradient values each correlation was taken
    over, divided by ``1 + 2 blur`` (neighbours the blur makes alike): the correlations' sampling error is about
    ``1 / sqrt(samples)``."""

    samples: float = math.inf


def scores(template: torch.Tensor, data: torch.Tensor, operator) -> dict:
    """``{reading name: (correlation, Reading)}`` of the template's projection with the data under each reading, at
    the blur of :data:`BLUR` whose best reading fits best (noisy data: the wider one).

    Parameters
    ----------
    template : torch.Tensor
        The template, ``operator.domain.shape``.
    data : torch.Tensor
        The data, ``operator.range_shape``.
    operator : LinearOperator
        The forward operator (a tilt series is probed on at most :data:`SLICES` slices).

    Returns
    -------
    Table
        ``{reading name: (correlation, Reading)}``.
    """
    tables = []
    template, data, operator = _fewer_slices(template, data, operator)
    with torch.no_grad():
        projections = {}
        pairs = []
        for r in readings(operator, tuple(data.shape)):
            key = r.template if r.template is not _same else None
            if key not in projections:
                projections[key] = operator(r.template(template))
            pairs.append((r, projections[key], r.data(data)))
        count = _gradients(data, BLUR[0]).numel()
        for width in BLUR:
            table = Table({r.name: (_correlation(p, g, width), r) for r, p, g in pairs})
            table.samples = count / (1 + 2 * width)
            tables.append(table)
    return max(tables, key=lambda t: max(v for v, _ in t.values()))


def margin_needed(table: dict) -> float:
    """How much a reading must fit better than the data as given to be named: :data:`WARN`, :data:`RELATIVE` of the
    misfit the data as given leave, and the correlations' sampling error (``1 / sqrt(samples)``, :class:`Table`),
    whichever is largest."""
    own = table["as given"][0]
    return max(WARN, RELATIVE * (1.0 - own), 1.0 / math.sqrt(getattr(table, "samples", math.inf)))


def verdict(table: dict) -> tuple:
    """``(level, message)``: ``("", "")`` when the data as given fit within :func:`margin_needed` of the best reading
    (or no reading fits :data:`MIN_FIT`), else ``"warn"`` or ``"refuse"`` (a margin above :data:`REFUSE`) with a
    one-line message naming the fix (of every reading within :data:`TIE` of the best)."""
    own = table["as given"][0]
    best = max(v for v, _ in table.values())
    if best - own <= margin_needed(table) or best < MIN_FIT:
        return "", ""
    tied = [(k, r) for k, (v, r) in sorted(table.items(), key=lambda kv: -kv[1][0]) if v >= best - TIE]
    listed = ", ".join(f"{k} {v:.2f}" for k, (v, _) in sorted(table.items(), key=lambda kv: -kv[1][0]))
    names = " or ".join(k for k, _ in tied)
    fixes = "; or ".join(r.fix for _, r in tied)
    message = (f"the template's projection fits the data as given at {own:.2f} and read as {names} at {best:.2f} "
               f"(gradient correlations: {listed}): the data were probably read wrongly; {fixes}")
    return ("refuse" if best - own > REFUSE else "warn"), message


#: The readings of a 2D target (the ground truth) tried by :func:`target_hint`: turned, transposed, mirrored.
_TARGET_READINGS = {"turned by -90 degrees": lambda t: t.rot90(-1, (0, 1)),
                    "turned by +90 degrees": lambda t: t.rot90(1, (0, 1)),
                    "transposed": lambda t: t.T, "mirrored along y": lambda t: t.flip(1),
                    "mirrored along x": lambda t: t.flip(0)}


def target_hint(target, data, operator) -> str:
    """Whether a 2D square ``target`` (the ground truth given with the data) projects onto ``data`` clearly better
    (by :data:`WARN`, gradient correlations) turned, transposed or mirrored: a target file in another layout than
    the data (e.g. the example's arrays read in ASTRA's layout while its picture is read as displayed), which would
    score a right reconstruction as a wrong one. One line naming the reading, or ``""``."""
    t = torch.as_tensor(target, dtype=data.dtype, device=data.device)
    if t.dim() != 2 or t.shape[0] != t.shape[1] or tuple(t.shape) != tuple(operator.domain.shape):
        return ""
    with torch.no_grad():
        table = {name: _correlation(operator(read(t).contiguous()), data) for name, read in
                 {"as read": _same, **_TARGET_READINGS}.items()}
    best = max(table, key=table.get)
    if table[best] - table["as read"] <= WARN or table[best] < MIN_FIT:
        return ""
    return (f"the target's projection fits the data at {table['as read']:.2f} as read and at {table[best]:.2f} "
            f"{best}: the target or the data were probably read in another layout (a picture is read as displayed in "
            "every convention, an array in the convention's layout), so the SSIM / PSNR against the target would be "
            "wrong")


def check(template, data, operator, mode: str = "check", key: str = "orientation") -> str:
    """Probe (``mode`` in :data:`MODES`): log a warning, or raise ``ValueError`` (``mode="check"`` and a margin above
    :data:`REFUSE`) naming ``key`` to override; returns the warning (``""``: none, ``mode="off"``, no template, a
    time series), which the run's poor-fit report repeats (``indreg.registration.run.poor_fit``).

    Parameters
    ----------
    template : torch.Tensor or None
        The template (None: no probe).
    data : torch.Tensor
        The data.
    operator : LinearOperator
        The forward operator.
    mode : {"check", "warn", "off"}
        Refuse a large margin, only warn, or skip.
    key : str
        The option's name in messages.

    Returns
    -------
    str
        The warning, ``""`` for none.

    Raises
    ------
    ValueError
        ``mode="check"`` and the data fit another reading better by more than :data:`REFUSE`.
    """
    from ..forward import TimeSeriesOperator

    if mode == "off" or template is None or isinstance(operator, TimeSeriesOperator) \
            or len(readings(operator, tuple(data.shape))) == 1:
        return ""
    level, message = verdict(scores(template, data, operator))
    if level == "refuse" and mode == "check":
        raise ValueError(f"{message} (or {key}='warn' to run anyway)")
    if level:
        log.warning("%s", message)
    return message


# ---------------------------------------------------------------------------------------------------- the files' convention
# At load (``indreg.load``): does the template's projection fit the data better read in another convention, or
# mirrored? Plain correlations of a coarse copy of the problem (milliseconds).

#: A convention whose reading fits the data better by this much correlation is named in a warning.
MARGIN = 0.1
#: Readings within this correlation of the best are named with it (ASTRA's picture and IMOD's section with its
#: angles are one reading: the displayed picture is the section mirrored, and the mirror negates the angles).
CONVENTION_TIE = 0.01
#: The check runs on at most this many pixels a side and angles (block means, evenly chosen rows): milliseconds.
CHECK_PIXELS, CHECK_ANGLES = 64, 18


def _distinct() -> dict:
    """One convention per distinct reading (``odl`` reads as ``indreg``, ``tomopy`` as ``astra``): ``{first: names}``."""
    groups: dict = {}
    for c in CONVENTIONS.values():
        key = (c.image, c.sinogram, c.angle_sense, c.angle_offset, c.pixel_units, c.bins)
        groups.setdefault(key, []).append(c.name)
    return {names[0]: names for names in groups.values()}


def _fit(stored_f, stored_g, radians, convention, half_width: float, det_min, det_max, picture: bool):
    """``(correlation, transposed)`` of the parallel-beam projection of the template, read in ``convention``, with
    the data read so, on a coarse copy of the problem; the data are taken transposed (``transposed=True``) if their
    rows are then not one per angle, and ``None`` is returned if neither way fits."""
    import torch.nn.functional as F

    from ..forward import ParallelBeamGeometry, RayTransform

    c = get_convention(convention)
    g, transposed = sinogram_layout(stored_g, c), False
    if g.shape[0] != radians.size:
        g, transposed = np.ascontiguousarray(g.T), True
    if g.shape[0] != radians.size:
        return None
    rows = np.unique(np.linspace(0, radians.size - 1, min(radians.size, CHECK_ANGLES)).round().astype(int))
    f = torch.as_tensor(image_to_indreg(stored_f, c, picture))
    n = f.shape[0]
    m = min(n, CHECK_PIXELS)
    small = F.interpolate(f[None, None], size=(m, m), mode="area")[0, 0] if m < n else f
    lo, hi = detector_for(c, g.shape[1], 2.0 * half_width / n, det_min, det_max)
    geometry = ParallelBeamGeometry(angles=torch.as_tensor(angles_to_indreg(radians[rows], c)),
                                    det_count=g.shape[1], det_min=lo, det_max=hi)
    projection = RayTransform(domain_for(c, m, half_width), geometry)(small.contiguous())
    return correlation(projection, torch.from_numpy(g[rows])), transposed


def orientation_scores(stored_f, stored_g, radians, half_width: float, det_min=None, det_max=None,
                       picture: bool = False) -> dict:
    """``{convention: (correlation, transposed)}`` of the template's projection with the data, each read in that
    convention (``transposed``: the sinogram only fits transposed from that convention's layout).

    ``stored_f``, ``stored_g``: the arrays as stored (a picture's as displayed, with ``picture=True``),
    ``radians``: the angles as given; ``det_min`` / ``det_max``: the user's, if any.

    Parameters
    ----------
    stored_f, stored_g : numpy.ndarray
        The template and the sinogram as stored (a picture's as displayed, with ``picture=True``).
    radians : array_like
        The angles as given.
    half_width : float
        The domain's half side.
    det_min, det_max : float, optional
        The user's detector extent, if any.
    picture : bool
        The template is a picture.

    Returns
    -------
    dict
        ``{convention: (correlation, transposed)}``, one convention per distinct reading.
    """
    scores = {}
    for name in _distinct():
        if picture and CONVENTIONS[name].angle_sense < 0:   # no tool of the other sense writes pictures: a picture
            continue                                         # upside down is flip_hint's
        score = _fit(stored_f, stored_g, np.asarray(radians), name, half_width, det_min, det_max, picture)
        if score is not None:
            scores[name] = score
    return scores


def orientation_hint(scores: dict, current) -> str | None:
    """A one-line hint naming the convention whose reading fits the data clearly better than ``current``'s.

    Parameters
    ----------
    scores : dict
        :func:`orientation_scores`'s.
    current : str or Convention
        The convention the files were read in.

    Returns
    -------
    str or None
        The hint, None when the current reading fits within :data:`MARGIN` of the best.
    """
    c = get_convention(current)
    own = next(name for name, names in _distinct().items() if c.name in names)
    best = max(scores, key=lambda name: scores[name][0], default=own)
    if own not in scores or best == own or scores[best][0] < scores[own][0] + MARGIN:
        return None
    tied = [name for name in scores if scores[name][0] >= scores[best][0] - CONVENTION_TIE]   # no telling them apart here
    names = " or ".join(n for name in sorted(tied, key=lambda k: -scores[k][0]) for n in _distinct()[name])
    listed = ", ".join(f"{name} {value:.2f}" for name, (value, _) in sorted(scores.items(), key=lambda kv: -kv[1][0]))
    layout = "(bins, angles)" if CONVENTIONS[best].sinogram == "bin_angle" else "(angles, bins)"
    swapped = f", with the sinogram's axes swapped ({best}'s is {layout})" if scores[best][1] else ""
    return (f"read as convention {c.name}, the template's projection correlates {scores[own][0]:.2f} with the "
            f"data; read as {names}, {scores[best][0]:.2f} ({listed}): the files probably follow {names}{swapped}")


#: Mirror images no convention makes: a picture saved upside down, an array saved transposed.
_FLIPS = {"flipped along y (np.flip(f, 1): a picture upside down?)": lambda f: f[:, ::-1],
          "flipped along x (np.flip(f, 0))": lambda f: f[::-1],
          "transposed (f.T)": lambda f: f.T}


def flip_hint(f, g, radians, convention, half_width: float, det_min=None, det_max=None) -> str | None:
    """A one-line hint when the template ``f`` (indreg's layout, as read in ``convention``) fits the data ``g``
    clearly better mirrored (:data:`_FLIPS`); ``radians``: the angles as given; ``None`` otherwise."""
    c = get_convention(convention)
    stored_g = g.T if c.sinogram == "bin_angle" else g

    def score(image):
        stored = image_from_indreg(np.ascontiguousarray(image), c)
        return _fit(stored, stored_g, np.asarray(radians), c, half_width, det_min, det_max, False)

    own = score(f)
    scores = {name: score(flip(f)) for name, flip in _FLIPS.items()}
    best = max(scores, key=lambda name: scores[name][0])
    if own is None or scores[best][0] < own[0] + MARGIN:
        return None
    return (f"the template's projection correlates {own[0]:.2f} with the data, {scores[best][0]:.2f} with the "
            f"template {best}: check the template's orientation")
