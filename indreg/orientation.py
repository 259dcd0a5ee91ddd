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

Convention: ``template`` ``operator.domain.shape``, ``data`` ``operator.range_shape`` (the prepared inputs of
``indreg.run.setup``); the angles on the first data axis, detector columns on the last.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Optional

import torch

__all__ = ["WARN", "REFUSE", "MIN_FIT", "TIE", "BLUR", "SLICES", "MODES", "Reading", "readings", "scores", "verdict",
           "check"]

log = logging.getLogger("indreg")

#: A reading whose fit exceeds the data-as-given's by this much is named in a warning ...
WARN = 0.05
#: ... and by this much refused (measured, scripts/orientation_probes.py: the right reading of every probe case and
#: every preset scores within 0.005 of the best reading; the wrong ones lose 0.13 (a 3D stack turned by 180 degrees:
#: a warning) to 0.25 (a 2D detector reversed, angles in the opposite sense: refused); docs/reliability.md).
REFUSE = 0.2
#: A reading is named only when its fit is at least this (a template that fits no reading says nothing).
MIN_FIT = 0.3
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
    from .forward import ParallelBeamGeometry, RayTransform, TiltSeriesTransform

    if isinstance(operator, TiltSeriesTransform):
        t = operator.geometry.axis
        u, v = (a for a in range(3) if a != t)
        return u, v, t
    if isinstance(operator, RayTransform) and type(operator.geometry) is ParallelBeamGeometry:
        return 0, 1, None
    return None


def readings(operator, data_shape: tuple) -> list:
    """The readings probed for ``operator`` (module docstring); the first is the data as given."""
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
    flat = g.reshape(-1, 1, g.shape[-1])
    return torch.nn.functional.conv1d(flat, (w / w.sum()).view(1, 1, -1), padding=r).reshape(g.shape)


def _gradients(g: torch.Tensor, width: float) -> torch.Tensor:
    """The differences of the blurred data along the detector and along the axis before it, as one vector."""
    g = _blur(g.double(), width)
    return torch.cat([g.diff(dim=-1).flatten(), g.diff(dim=-2).flatten()])


def _correlation(a: torch.Tensor, b: torch.Tensor, width: float = BLUR[0]) -> float:
    a, b = _gradients(a, width), _gradients(b, width)
    a, b = a - a.mean(), b - b.mean()
    norm = float(a.norm() * b.norm())
    return float(a @ b) / norm if norm > 0 else 0.0


def _fewer_slices(template: torch.Tensor, data: torch.Tensor, operator) -> tuple:
    """A tilt series of more than :data:`SLICES` slices along its tilt axis probed on that many, evenly spaced and
    symmetric about the middle (so that a turned stack's rows are among them): ``(template, data, operator)``; other
    problems as they are."""
    from .domain import ImageDomain
    from .forward import TiltSeriesGeometry, TiltSeriesTransform

    if not isinstance(operator, TiltSeriesTransform):
        return template, data, operator
    t, n = operator.geometry.axis, operator.domain.shape[operator.geometry.axis]
    if n <= SLICES:
        return template, data, operator
    half = [round(j * (n - 1) / (SLICES - 1)) for j in range(SLICES // 2)]
    rows = torch.as_tensor(half + [n - 1 - i for i in reversed(half)], device=data.device)
    d, g = operator.domain, operator.geometry
    h = d.cell_sides[t]
    shape = tuple(SLICES if a == t else m for a, m in enumerate(d.shape))
    lo = tuple(-h * SLICES / 2 if a == t else x for a, x in enumerate(d.min_pt))
    hi = tuple(h * SLICES / 2 if a == t else x for a, x in enumerate(d.max_pt))
    s = g.slice_geometry
    small = TiltSeriesTransform(ImageDomain(shape, lo, hi), TiltSeriesGeometry(
        s.angles, s.det_count, s.det_min, s.det_max, g.tilt_axis, angle_unit="rad", angle_weights=s.angle_weights))
    k = template.dim() - 3 + t
    return template.index_select(k, rows.to(template.device)), data.index_select(data.dim() - 2, rows), small


def scores(template: torch.Tensor, data: torch.Tensor, operator) -> dict:
    """``{reading name: (correlation, Reading)}`` of the template's projection with the data under each reading, at
    the blur of :data:`BLUR` whose best reading fits best (noisy data: the wider one)."""
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
        for width in BLUR:
            tables.append({r.name: (_correlation(p, g, width), r) for r, p, g in pairs})
    return max(tables, key=lambda t: max(v for v, _ in t.values()))


def verdict(table: dict) -> tuple:
    """``(level, message)``: ``("", "")`` when the data as given fit within :data:`WARN` of the best reading (or no
    reading fits :data:`MIN_FIT`), else ``"warn"`` or ``"refuse"`` (a margin above :data:`REFUSE`) with a one-line
    message naming the fix (of every reading within :data:`TIE` of the best)."""
    own = table["as given"][0]
    best = max(v for v, _ in table.values())
    if best - own <= WARN or best < MIN_FIT:
        return "", ""
    tied = [(k, r) for k, (v, r) in sorted(table.items(), key=lambda kv: -kv[1][0]) if v >= best - TIE]
    listed = ", ".join(f"{k} {v:.2f}" for k, (v, _) in sorted(table.items(), key=lambda kv: -kv[1][0]))
    names = " or ".join(k for k, _ in tied)
    fixes = "; or ".join(r.fix for _, r in tied)
    message = (f"the template's projection fits the data as given at {own:.2f} and read as {names} at {best:.2f} "
               f"(gradient correlations: {listed}): the data were probably read wrongly; {fixes}")
    return ("refuse" if best - own > REFUSE else "warn"), message


def check(template, data, operator, mode: str = "check", key: str = "orientation") -> str:
    """Probe (``mode`` in :data:`MODES`): log a warning, or raise ``ValueError`` (``mode="check"`` and a margin above
    :data:`REFUSE`) naming ``key`` to override; returns the warning (``""``: none, ``mode="off"``, no template, a
    time series), which the run's poor-fit report repeats (``indreg.run.poor_fit``)."""
    from .forward import TimeSeriesOperator

    if mode == "off" or template is None or isinstance(operator, TimeSeriesOperator) \
            or len(readings(operator, tuple(data.shape))) == 1:
        return ""
    level, message = verdict(scores(template, data, operator))
    if level == "refuse" and mode == "check":
        raise ValueError(f"{message} (or {key}='warn' to run anyway)")
    if level:
        log.warning("%s", message)
    return message
