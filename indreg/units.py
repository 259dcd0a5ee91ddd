"""Units: how template and data are brought to one unit before a run, and the scale that makes weights and steps
relative to the data term.

Two things depend on the units of the inputs. (1) The template and the data must agree: ``T I`` should be
comparable with ``g`` (:func:`compare_units`: the ratio of norms and the least-squares factor ``c``; the options
``template_scale`` and ``background`` act on them through :meth:`Units.apply`, the one place that scales the
template and subtracts the data's offset). (2) The objective ``(gamma / 2) ||nu||_V^2 + (1/2) ||T W(nu, I) - g||^2``
scales with the data's intensity unit squared and its length unit, so an absolute ``gamma`` or Algorithm 1 step
means different things for data in counts and nanometres and for data in the paper's 0..1 and [-16, 16]^2. The
*relative* options remove that: with the data-term scale ``S = ||g||^2_data / L^2`` (``L`` the largest side of the
box, physical units; :func:`data_term_scale`)

    gamma = gamma_rel * S        step_size = step_rel / S

Scaling template and data by ``s`` scales ``S``, the data term and its gradient by ``s^2``: the iterates
``nu`` are unchanged, and so are the step halvings. A length unit ``lambda`` (nanometres for the paper's units)
scales ``||nu||_V^2`` by ``lambda^2`` (``nu`` is a displacement per unit time) and ``L^2`` likewise. The paper's
absolute numbers convert both ways with the ``S`` of the data (``indreg.register``'s result reports it:
``result.units.data_scale``); the defaults ``gamma_rel`` and ``step_rel`` (``indreg.options``) are the paper's
suite-1 ``gamma = 1e-6`` and ``step = 0.02`` converted with its ``S``.

Convention: ``template`` ``operator.domain.shape``, ``data`` ``operator.range_shape`` (torch tensors of one dtype
and device); norms in the weighted data inner product ``operator.inner_data``.
"""
from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:   # imported where used: the app's preflight loads this module without torch
    import torch

__all__ = ["GAMMA_REL", "STEP_REL", "UNIT_RANGE", "OFFSET_FRACTION", "UNIT_FACTORS", "UNIT_SNAP", "Units",
           "apply_units", "border_level", "check_offset", "compare_units", "data_term_scale", "measure", "noise_residual",
           "noise_sigma", "prepare", "unit_factor"]

log = logging.getLogger("indreg")

#: The relative defaults of ``indreg.options`` (``gamma_rel``, ``step_rel``): the paper's suite-1 ``gamma = 1e-6`` and
#: step 0.02 at its data-term scale ``S = ||g||^2 / L^2 = 5.95`` (10 angles x 92 bins, 4.87 dB, the box
#: [-16, 16]^2).
GAMMA_REL, STEP_REL = 1.7e-7, 0.12

#: Template and data agree in units when ``||T I|| / ||g||`` and ``c = <T I, g> / <T I, T I>`` lie in
#: ``[1 / UNIT_RANGE, UNIT_RANGE]`` (the paper's suites: 0.68-1.3); outside, a warning names both.
UNIT_RANGE = 3.0
#: Data look offset when the median of the detector's outermost columns (``border_level``) is away from zero, or
#: the median of all the data is below zero, by more than this fraction of the data's range.
OFFSET_FRACTION = 0.05
#: The factors by which file formats change units: the full scales of 8- to 16-bit integers (``2^b - 1``: images
#: are normalised by their type's maximum), the metric prefixes' 1e3 and 1e6, their reciprocals, and 1.
#: ``template_scale="auto"`` takes the nearest one when the fitted ``c`` lies within ``UNIT_SNAP`` of it
#: (relative), since the fit is biased low by the shapes' mismatch (the paper's suite 1: ``c = 0.9735`` for a
#: template in the data's units; the own-data example: 0.990). Factors of 10 are left out: a physical factor (one
#: over a voxel side of 10.5 nm: 0.095) lies near them as often as a unit change does.
UNIT_FACTORS = tuple(sorted({f ** e for f in [1e3, 1e6] + [float(2 ** b - 1) for b in (8, 10, 12, 14, 16)]
                             for e in (1, -1)} | {1.0}))
UNIT_SNAP = 0.05


@dataclass
class Units:
    """What :func:`prepare` found and did, for the result (``result.units``) and metrics.json.

    ``template_scale``: the factor applied to the template (1.0: none), ``template_offset`` the offset added to it
    (``template_scale="fit"``, ``indreg.registration.intensity``: both fitted with the deformation); ``background``: the offset
    subtracted from the data (0.0: none); ``projection_ratio`` = ``||T I|| / ||g||`` and ``scale_fit`` = the least-squares
    ``c = <T I, g> / <T I, T I>`` of the template as given and the data after the background (data inner product
    ``T.inner_data``), with ``align`` and a fitted ``template_scale`` the fit through the shifts that align the
    template's projection to the data (:meth:`fit_through_alignment`) and ``scale_fit_unaligned`` the plain one
    (NaN when there was none); ``data_scale``: ``S = ||g||^2_data / L^2`` of the fitted data (:func:`data_term_scale`),
    the scale of the relative options (``gamma = gamma_rel S``, ``step_size = step_rel / S``); ``noise_residual``:
    the relative residual ``||n|| / ||g||`` that the data's noise alone explains (:func:`noise_residual`);
    ``target_units``: ``"data"`` or ``"template"`` (as given), the units of a ground truth, where SSIM / PSNR
    score the reconstruction (:meth:`locate_target`, :meth:`to_target_units`)."""
    template_scale: float = 1.0
    template_offset: float = 0.0
    background: float = 0.0
    projection_ratio: float = math.nan
    scale_fit: float = math.nan
    scale_fit_unaligned: float = math.nan
    data_scale: float = math.nan
    noise_residual: float = math.nan
    target_units: str = "data"

    def apply(self, template, data) -> tuple:
        """``(template * template_scale + template_offset, data - background)``: the only place the inputs are
        transformed (the run's tensors and the app's float64 copies alike); a template None (unknown) stays None."""
        if template is not None and (self.template_scale != 1.0 or self.template_offset != 0.0):
            template = template * self.template_scale + self.template_offset
        return template, (data - self.background if self.background != 0.0 else data)

    def locate_target(self, template, target) -> None:
        """Decide the units of a ground truth (``target_units``): the template's as given (a picture read like the
        template) when its mean magnitude is nearer (in ratio) to the given template's than to the prepared
        ``template``'s, else the data's."""
        if self.template_scale == 1.0 and self.template_offset == 0.0:
            return
        r = float(target.double().abs().mean()) / max(float(template.double().abs().mean()), 1e-300)
        if r > 0 and abs(math.log(r * self.template_scale)) < abs(math.log(r)):
            self.target_units = "template"

    def to_target_units(self, image):
        """An image of the run (the data's units) in the target's (:meth:`locate_target`), where SSIM / PSNR score
        it: ``(image - template_offset) / template_scale`` for a target in the template's units as given (the
        inverse of :meth:`apply` on the template), else the image."""
        if self.target_units != "template":
            return image
        return (image - self.template_offset) / self.template_scale

    def fit_through_alignment(self, c: float) -> None:
        """Take ``c``, the template's scale fitted through the alignment of its projection to the data
        (``indreg.alignment.fit.fit_scale``), as ``scale_fit``; the plain fit becomes ``scale_fit_unaligned``."""
        self.scale_fit_unaligned, self.scale_fit = self.scale_fit, c
        log.info("the template's scale fitted through the alignment of its projection to the data: c = %.6g "
                 "(%.6g without it)", c, self.scale_fit_unaligned)

    def as_dict(self) -> dict:
        return asdict(self)


def border_level(data: torch.Tensor) -> float:
    """The median of the outermost ``max(1, n // 16)`` detector columns on each side (the last axis: bins of a
    sinogram, columns of a tilt series) over all angles (and rows): the level of the detector outside the
    object's shadow, 0 for projections of an object inside the field of view."""
    import torch

    n = data.shape[-1]
    k = max(1, n // 16)
    border = torch.cat([data[..., :k].reshape(-1), data[..., n - k:].reshape(-1)]) if n > 1 else data.reshape(-1)
    return float(border.double().median())


def _ratio(a: float, b: float) -> float:
    return a / b if b != 0 else (math.nan if a == 0 else math.inf)


def check_offset(data: torch.Tensor, label: str) -> None:
    """Warn when the data look offset: their border level or their median is far from zero (a fraction
    ``OFFSET_FRACTION`` of their range) where projections of an object would be about zero outside it and
    mostly positive."""
    spread = float(data.max() - data.min())
    border, median = border_level(data), float(data.double().median())
    if spread > 0 and (abs(border) > OFFSET_FRACTION * spread or median < -OFFSET_FRACTION * spread):
        log.warning("the data look offset: the median of the outermost detector columns is %.4g and of all values "
                    "%.4g, with a range of %.4g (projections are about 0 outside the object); pass %s='auto' to "
                    "subtract the border level, or %s=<number>", border, median, spread, label, label)


def compare_units(template: torch.Tensor, data: torch.Tensor, operator) -> tuple:
    """``(||T I|| / ||g||, c = <T I, g> / <T I, T I>)`` in the data inner product ``operator.inner_data``."""
    import torch

    with torch.no_grad():
        TI = operator(template)
        tt = float(operator.inner_data(TI, TI).sum())
        tg = float(operator.inner_data(TI, data).sum())
        gg = float(operator.inner_data(data, data).sum())
    return math.sqrt(_ratio(tt, gg)), _ratio(tg, tt)


def unit_factor(c: float) -> float:
    """The entry of ``UNIT_FACTORS`` nearest to ``c`` (in ratio) when within ``UNIT_SNAP`` of it, else ``c``."""
    nearest = min(UNIT_FACTORS, key=lambda f: abs(math.log(c / f)))
    return nearest if abs(c / nearest - 1) <= UNIT_SNAP else c


def _template_factor(template_scale, units: Units, key: str) -> float:
    """The template's factor for ``template_scale`` (None: 1 and a warning if the units look different)."""
    if template_scale in ("auto", "fit", "fit+offset"):
        if not (math.isfinite(units.scale_fit) and units.scale_fit > 0):
            raise ValueError(f"{key}={template_scale!r} found no positive scale: c = <T I, g> / <T I, T I> = "
                             f"{units.scale_fit:.4g}; the template's projection does not resemble the data: check "
                             f"both, or give {key}=<number>")
        if template_scale != "auto":   # a start: refitted with the deformation (indreg.registration.intensity)
            return units.scale_fit
        c = unit_factor(units.scale_fit)
        log.info("template scaled by %.6g (%s='auto': the fitted c = %.6g%s; ||T I|| / ||g|| was %.4g)", c, key,
                 units.scale_fit, "" if c == units.scale_fit else ", taken as the nearest unit factor",
                 units.projection_ratio)
        return c
    if template_scale is not None:
        return float(template_scale)
    if not all(1 / UNIT_RANGE <= v <= UNIT_RANGE for v in (units.projection_ratio, units.scale_fit)):
        log.warning("template and data look like different units: ||T I|| / ||g|| = %.4g and the least-squares "
                    "scale c = <T I, g> / <T I, T I> = %.4g (expected in [1/%g, %g]); pass %s='auto' to scale the "
                    "template by c, %s=<number>, or bring the template to the data's units", units.projection_ratio,
                    units.scale_fit, UNIT_RANGE, UNIT_RANGE, key, key)
    return 1.0


def prepare(template: torch.Tensor, data: torch.Tensor, operator, template_scale=None, background=None,
            label=lambda name: name) -> tuple:
    """Bring template and data to one unit before the run: :func:`measure`, then :func:`apply_units`.

    Returns
    -------
    tuple
        ``(template, data, Units)``.
    """
    units = measure(template, data, operator, background, label)
    return apply_units(template, data, units, template_scale, label)


def measure(template: torch.Tensor, data: torch.Tensor, operator, background=None, label=lambda name: name) -> Units:
    """What the inputs' units are, before anything is applied.

    ``background`` (None, ``"auto"``: :func:`border_level`, or a number) is the offset to subtract from the data;
    without it a warning when the data look offset (:func:`check_offset`). Then :func:`compare_units` compares the
    template's projection with the data (a template None, unknown, is not compared).

    Parameters
    ----------
    template, data : torch.Tensor
        The template (``operator.domain.shape``, or None) and the data (``operator.range_shape``).
    operator : LinearOperator
        The forward operator.
    background : None, "auto" or float
        The data's offset.
    label : callable
        ``label(name)`` names an option in messages (the app: its config key).

    Returns
    -------
    Units
        ``background``, ``projection_ratio`` and ``scale_fit`` set.

    Raises
    ------
    ValueError
        All-zero data (after the background).
    """
    units = Units()
    if background is None:
        check_offset(data, label("background"))
    else:
        units.background = border_level(data) if background == "auto" else float(background)
        log.info("subtracted the background %.6g from the data (%s=%r)", units.background, label("background"),
                 background)
    _check_nonzero(operator, units.apply(None, data)[1], "" if background is None else
                   f"; {label('background')}={background!r} subtracted {units.background:.4g} from every value")
    if template is not None:   # None: unknown (reconstructed by the model), no units to compare
        units.projection_ratio, units.scale_fit = compare_units(template, units.apply(None, data)[1], operator)
    return units


def apply_units(template: torch.Tensor, data: torch.Tensor, units: Units, template_scale=None,
                label=lambda name: name) -> tuple:
    """The template's factor for ``template_scale`` (None, ``"auto"``: ``units.scale_fit``, ``"fit"`` /
    ``"fit+offset"``: its start, or a number; without a scale a warning names both of :func:`compare_units`'s
    numbers when either is outside ``[1/UNIT_RANGE, UNIT_RANGE]``), then :meth:`Units.apply`.

    Returns
    -------
    tuple
        ``(template, data, units)``, ``units.template_scale`` set.

    Raises
    ------
    ValueError
        ``"auto"`` finds no positive ``c`` (a template whose projection does not resemble the data), or the
        factor makes the template non-finite.
    """
    import torch

    if template is not None:
        units.template_scale = _template_factor(template_scale, units, label("template_scale"))
    template, data = units.apply(template, data)
    if template is not None and not bool(torch.isfinite(template).all()):
        raise ValueError(f"{label('template_scale')}={template_scale!r} makes the template non-finite in "
                         f"{str(template.dtype).replace('torch.', '')} (scale factor {units.template_scale:.4g})")
    return template, data, units


def data_term_scale(operator, data: torch.Tensor) -> float:
    """``S = ||g||^2_data / L^2``: the data's squared norm in ``operator.inner_data`` over the squared largest side
    ``L`` of the box (physical units), the scale of the relative options (module docstring). Raises ValueError for
    all-zero data (nothing to register to)."""
    return _check_nonzero(operator, data) / max(operator.domain.extent) ** 2


def _check_nonzero(operator, data: torch.Tensor, why: str = "") -> float:
    """``||g||^2`` in ``operator.inner_data``; all-zero (or non-finite) data are a one-line ``ValueError`` (``why``:
    what the background did, appended)."""
    import torch

    with torch.no_grad():
        gg = float(operator.inner_data(data, data).sum())
    if not (gg > 0 and math.isfinite(gg)):
        raise ValueError(f"data must not be all zero (||g||^2 = {gg:.4g}): there is nothing to register to; check the "
                         f"file{why or ', and background (subtracting it may have zeroed the data)'}")
    return gg


def noise_residual(data: torch.Tensor) -> float:
    """The relative residual ``||n|| / ||g||`` that white noise in the data explains, estimated from the data alone:
    the noise's standard deviation from the median absolute second difference along each of the last two axes
    (``sigma = median|d^2 g| / (0.6745 sqrt 6)``; projections are smooth along the detector, so the smoother axis
    shows the noise), the smaller of the two. An upper estimate: the signal's own curvature adds to it (0.24 for
    0.24 on the paper's suite 1, 0.027 for 0.024 at 15 dB, 0.002 for noise-free data)."""
    g = data.detach().double()
    sigma, norm = noise_sigma(g), float(g.norm())
    return sigma * math.sqrt(g.numel()) / norm if norm > 0 and math.isfinite(sigma) else math.nan


def noise_sigma(data: torch.Tensor) -> float:
    """The standard deviation of white noise in ``data`` (per datum), as :func:`noise_residual` estimates it:
    ``median|d^2 g| / (0.6745 sqrt 6)`` along the smoother of the last two axes; nan when no axis has 3 values."""
    g = data.detach().double()
    axes = [a for a in (-1, -2) if g.dim() >= -a and g.shape[a] >= 3]
    if not axes:
        return math.nan
    return min(float(g.diff(n=2, dim=a).abs().median()) for a in axes) / (0.6745 * math.sqrt(6.0))
