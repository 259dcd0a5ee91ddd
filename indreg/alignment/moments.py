"""The tilt-axis angle from the stack alone: the Helgason-Ludwig consistency conditions of every detector row
(docs/alignment.md, "The angle from the stack: moment conditions").

With the tilt axis right, detector row ``v`` across the tilts is the parallel-beam sinogram of one slice of the
specimen, so its moments across the axis, ``m_n(v, theta) = int u^n p_theta(u, v) du``, are homogeneous
polynomials of degree ``n`` in ``(cos theta, sin theta)``:

    m_0 = M(v),   m_1 = a(v) cos + b(v) sin,   m_2 = A(v) cos^2 + 2 B(v) cos sin + C(v) sin^2.

A trial angle off by ``delta`` mixes the rows: to first order ``m_1`` gains ``delta`` times terms of ``m_2``, not of
the form ``a cos + b sin`` wherever a slice is not round, centred on the axis or not. The estimator scans the trial
angle ``alpha`` and, at each, fits these conditions to the stack.

Notes
-----
- ``stack`` ``(tilts, rows, columns)``: rows along the tilt axis, columns across it (indreg's layout), square
  pixels, ``alpha`` indreg's tilt-axis angle (``indreg.alignment.operator``: a feature at the ideal point ``q``
  appears at ``R(alpha) q + shift``). A pixel at ``(s, t)`` (columns, rows, from the image's centre) lies at
  ``u = cos(alpha) s + sin(alpha) t - c_k`` across the axis and ``v = -sin(alpha) s + cos(alpha) t - d_k``
  along it; ``(c_k, d_k)`` are tilt ``k``'s shifts across / along (px).
- No interpolation of the data: per tilt, exact sums over the pixels, ``G_{n,k}(rho) = sum_p I_k(p) u_p^n
  w(v_p) exp(-2 pi i rho v_p)``, ``w`` a Tukey window along the axis that keeps the rows near the detector's
  top and bottom out (what leaves the detector along the axis), ``rho`` at a spacing of one over the window's
  length up to ``band`` cycles per pixel. The conditions hold for every ``rho`` (a weighting along the axis
  keeps them), so each is a linear model per ``rho`` (real and imaginary parts apart).
- Noise: ``sigma`` from the data (:func:`noise_level`: each pixel less its four neighbours' mean, a robust
  spread); every ``G`` is divided by its standard deviation, so the criterion ``chi2(alpha)`` (the shifts and
  the linear model fitted) is a chi-square; the angle's standard error is ``sqrt(2 / chi2''(alpha))``, times
  ``sqrt(chi2 / dof)`` where the conditions fit worse than the noise, combined with the spread of the slope of
  pure noise's criterion over the curvature (the rows, and the noise summed into them, move with the trial
  angle: :func:`_noise_slopes`).
- Shifts: ``c_k`` keeps the axis' offset (orthogonal to ``cos theta_k, sin theta_k`` only, which a translation
  of the specimen explains), ``d_k`` mean zero.
- Scales (``scales=True``, the default): tilt ``k``'s ``G`` is ``a_k`` times the conditions (an exposure or a
  signal that changes with the path length), ``a_k`` fitted by least squares against them, mean 1.

Longer than 450 lines: one method (the moment conditions) with its scan, binning and standard error.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["MAX_PIXELS", "MAX_SE_DEG", "MIN_TILTS", "SCAN_DEG", "AxisEstimate", "binned", "binned_within",
           "condition_misfit", "estimate_axis_angle", "noise_level", "support_columns"]


#: Above this standard error (deg) the angle is reported as not determined by the data.
MAX_SE_DEG = 0.2
#: The scan: trial angles from ``-SCAN_DEG`` to ``SCAN_DEG`` every degree, then every quarter around the least.
SCAN_DEG = 10.0
#: Columns whose mean over the rows is below this fraction of the largest count as beyond the specimen.
FLOOR = 0.01
#: Pure-noise scans whose slopes measure how the criterion's noise moves with the trial angle.
NOISE_REPLICAS = 4
#: Fewest tilts whose specimen stays inside the detector.
MIN_TILTS = 6
#: Alternations of the shifts' Gauss-Newton step and the linear model's fit per trial angle.
SHIFT_ROUNDS = 8
#: A larger stack is binned (block means) to at most this many pixels along each image axis before the estimate:
#: its cost grows as the pixels times the rows (41 tilts, one thread: 14 s at 64^2, 78 s at 128^2).
MAX_PIXELS = 128


@dataclass(frozen=True)
class AxisEstimate:
    """The tilt-axis angle from the stack (:func:`estimate_axis_angle`).

    Attributes
    ----------
    angle_deg : float
        The estimate (indreg's convention).
    se_deg : float
        Its standard error (``inf``: the criterion is flat or has no interior minimum).
    determined : bool
        ``se_deg <= MAX_SE_DEG``.
    chi2_per_dof : float
        The criterion at the minimum over its degrees of freedom (about 1 when the conditions fit to the noise).
    shifts_px : numpy.ndarray
        ``(tilts, 2)``, across / along, in the stack's own pixels.
    tilts_used : numpy.ndarray
        Which tilts entered (bool): those whose specimen stays inside the detector across the axis
        (:func:`support_columns`).
    scan : tuple
        The trial angles and their ``chi2``.
    reason : str
        Why the stack could not be used, where it could not (:meth:`refused`: no angle, not determined).
    scales : numpy.ndarray or None
        ``(tilts,)``: every tilt's fitted intensity scale (mean 1 over the tilts used; None: not fitted).
    binning : int
        The stack was binned by this factor for the estimate (:data:`MAX_PIXELS`).
    """
    angle_deg: float
    se_deg: float
    determined: bool
    chi2_per_dof: float
    shifts_px: np.ndarray
    tilts_used: np.ndarray
    scan: tuple = field(repr=False)
    reason: str = ""
    scales: np.ndarray | None = field(default=None, repr=False)
    binning: int = 1

    @classmethod
    def refused(cls, reason: str, tilts: int) -> "AxisEstimate":
        """No estimate: the stack cannot tell the angle (``reason``, e.g. too few tilts on the detector)."""
        return cls(math.nan, math.inf, False, math.nan, np.full((tilts, 2), np.nan), np.zeros(tilts, bool),
                   (np.zeros(0), np.zeros(0)), reason)

    def describe(self) -> str:
        """One line for the log."""
        if self.reason:
            return f"tilt-axis angle from the stack's moment conditions: not estimated ({self.reason})"
        se = f"{self.se_deg:.3f}" if math.isfinite(self.se_deg) else "inf"
        state = "" if self.determined else " (not determined by the data)"
        binned = f", binned by {self.binning}" if self.binning > 1 else ""
        return (f"tilt-axis angle from the stack's moment conditions: {self.angle_deg:.3f} deg, s.e. {se} deg"
                f"{state}; chi2 per degree of freedom {self.chi2_per_dof:.2f}, {int(self.tilts_used.sum())} tilts"
                f"{binned}")


# ---------------------------------------------------------------------------------------------------- the data
def noise_level(stack: np.ndarray) -> float:
    """The noise's standard deviation: the robust spread (1.4826 times the median absolute deviation) of every
    interior pixel less its four neighbours' mean, divided by ``sqrt(1 + 1/4)`` (that difference's gain on white
    noise)."""
    a = np.asarray(stack, dtype=np.float64)
    e = a[:, 1:-1, 1:-1] - 0.25 * (a[:, :-2, 1:-1] + a[:, 2:, 1:-1] + a[:, 1:-1, :-2] + a[:, 1:-1, 2:])
    mad = np.median(np.abs(e - np.median(e)))
    return float(1.4826 * mad / math.sqrt(1.25))


def support_columns(stack: np.ndarray, sigma: float, margin: int = 2, level: float = 3.0,
                    floor: float = FLOOR) -> tuple:
    """Every tilt's specimen across the axis: the first and last columns whose mean over the rows exceeds
    ``level`` times its noise (``sigma / sqrt(rows)``) and ``floor`` times the image's largest column mean,
    widened by ``margin`` columns, ``(first, last)`` ``(tilts,)`` each; and which tilts' specimen runs off the
    detector's sides (it reaches the outermost column): a row's moments need the whole row, so those are left
    out. The columns
    beyond the specimen carry noise only: leaving them out of the sums keeps the conditions and drops their
    noise."""
    a = np.asarray(stack, dtype=np.float64)
    rows, cols = a.shape[1:]
    means = a.mean(axis=1)                                                       # (tilts, columns)
    bar = np.maximum(level * sigma / math.sqrt(rows), floor * means.max(1))
    above = means > bar[:, None]
    any_above = above.any(1)
    first = np.where(any_above, above.argmax(1), 0)
    last = np.where(any_above, cols - 1 - above[:, ::-1].argmax(1), cols - 1)
    outside = (first <= 0) | (last >= cols - 1) | ~any_above
    return np.maximum(first - margin, 0), np.minimum(last + margin, cols - 1), outside


def _frame(shape: tuple) -> tuple:
    """Every pixel's ``(s, t)`` (columns, rows) from the image's centre, flattened."""
    rows, cols = shape
    t, s = np.meshgrid(np.arange(rows) - (rows - 1) / 2, np.arange(cols) - (cols - 1) / 2, indexing="ij")
    return s.reshape(-1), t.reshape(-1)


def _window(x: np.ndarray, half: float, taper: float) -> tuple:
    """The Tukey window (1 within ``half - taper``, a cos^2 taper to 0 at ``half``) at ``x`` and its derivative."""
    r = (np.abs(x) - (half - taper)) / taper
    inside = (r > 0) & (r < 1)
    w = np.where(r <= 0, 1.0, np.where(inside, np.cos(0.5 * np.pi * r) ** 2, 0.0))
    dw = np.where(inside, -0.5 * np.pi / taper * np.sin(np.pi * r) * np.sign(x), 0.0)
    return w, dw


# ---------------------------------------------------------------------------------------------------- the conditions
@dataclass
class _Setup:
    images: np.ndarray          # (tilts, pixels), zero beyond the specimen's columns
    mask: np.ndarray            # (tilts, pixels): 1 within the specimen's columns (:func:`support_columns`)
    s: np.ndarray
    t: np.ndarray
    theta: np.ndarray           # tilt angles (rad)
    freqs: np.ndarray           # cycles per pixel
    half: float                 # window half-length (px)
    taper: float
    sigma: float
    orders: int = 2
    scales: np.ndarray | None = None    # (tilts,) per-tilt intensity scales (exposure), mean 1; None: not fitted


def _design(theta: np.ndarray, orders: int) -> list:
    """The conditions' designs over the tilts, orders ``0 .. orders``: order ``n`` is spanned by ``cos^(n-j)
    sin^j``, ``j = 0 .. n``."""
    c, s = np.cos(theta), np.sin(theta)
    return [np.stack([c ** (n - j) * s ** j for j in range(n + 1)], 1) for n in range(orders + 1)]


def _transforms(S: _Setup, alpha: float, c: np.ndarray, d: np.ndarray, derivatives: bool = False) -> tuple:
    """``G (tilts, 3, freqs)`` (module Notes), the standard deviations of their real and imaginary parts
    ``(2, tilts, 3, freqs)`` and, with ``derivatives``, ``dG/dc`` and ``dG/dd`` ``(tilts, 3, freqs)`` each.

    A tilt's shift along the axis ``d_k`` enters the phase as a factor of its own, ``exp(-2 pi i rho v) = exp(-2 pi
    i rho v0) exp(2 pi i rho d_k)`` (``v0`` the pixel's coordinate along the trial axis), so the pixel sums are
    matrix products with one ``(pixels, freqs)`` phase for every tilt; the variances use ``cos^2 = (1 + cos 2x) /
    2`` and ``sin^2 = (1 - cos 2x) / 2`` the same way."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    u = (ca * S.s + sa * S.t)[None, :] - c[:, None]                       # (tilts, pixels)
    v0 = -sa * S.s + ca * S.t                                             # (pixels,)
    w, dw = _window(v0[None, :] - d[:, None], S.half, S.taper)
    phase = np.exp(-2j * np.pi * np.outer(v0, S.freqs))                   # (pixels, freqs)
    along = np.exp(2j * np.pi * np.outer(d, S.freqs))[:, None, :]         # (tilts, 1, freqs)
    powers = np.stack([u ** n for n in range(S.orders + 1)], 1)           # (tilts, orders + 1, pixels)
    G = ((powers * (S.images * w)[:, None]) @ phase) * along
    basis2 = (powers * (w * S.mask)[:, None]) ** 2
    total = basis2.sum(-1)[..., None]
    cos2 = ((basis2 @ phase ** 2) * along ** 2).real                      # sum of basis2 cos(2 x), x the phase
    var = np.maximum(np.stack([total + cos2, total - cos2]), 0.0) / 2
    var[1][..., S.freqs == 0] = 0.0                                       # the imaginary part at rho = 0: none
    sd = S.sigma * np.sqrt(var)
    if not derivatives:
        return G, sd
    lower = np.stack([n * u ** max(n - 1, 0) for n in range(S.orders + 1)], 1) * (S.images * w)[:, None]
    dG_dc = -(lower @ phase) * along
    dG_dd = -((powers * (S.images * dw)[:, None]) @ phase) * along + 2j * np.pi * S.freqs * G
    return G, sd, dG_dc, dG_dd


def _parts(z: np.ndarray) -> np.ndarray:
    """Real and imaginary parts stacked first: ``(2, ...)``."""
    return np.stack([z.real, z.imag])


def _model_fit(S: _Setup, G: np.ndarray, sd: np.ndarray, model: bool = False) -> tuple:
    """The weighted least-squares fit of the conditions per order, ``rho`` and part, each tilt's ``G`` scaled by its
    intensity scale (``S.scales``: ``G_k = a_k x model``): the whitened residual ``(2, tilts, 3, freqs)``, the number
    of fitted coefficients and, with ``model``, the fitted conditions (unscaled, ``(2, tilts, 3, freqs)``). Parts
    with no variance (the imaginary part at ``rho = 0``) are left out (residual 0)."""
    a = np.ones(len(S.theta)) if S.scales is None else S.scales
    y, residual, fitted = _parts(G), np.zeros((2,) + G.shape), 0
    values = np.zeros((2,) + G.shape)
    ok = sd > 1e-300
    for n, X in enumerate(_design(S.theta, S.orders)):
        for part in range(2):
            for f in range(G.shape[2]):
                keep = ok[part, :, n, f]
                if keep.sum() <= X.shape[1]:
                    continue
                wgt = 1.0 / sd[part, keep, n, f]
                A, b = X[keep] * (a[keep] * wgt)[:, None], y[part, keep, n, f] * wgt
                coef = np.linalg.lstsq(A, b, rcond=None)[0]
                residual[part, keep, n, f] = b - A @ coef
                values[part, keep, n, f] = X[keep] @ coef
                fitted += X.shape[1]
    return (residual, fitted, values) if model else (residual, fitted)


def _scale_step(S: _Setup, G: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Every tilt's intensity scale by weighted least squares against the fitted conditions (the model held),
    normalised to mean 1 (the overall scale is the model's)."""
    _, _, m = _model_fit(S, G, sd, model=True)
    ok = sd > 1e-300
    w = np.where(ok, 1.0 / np.where(ok, sd, 1.0) ** 2, 0.0)
    y = _parts(G)
    num, den = (w * y * m).sum(axis=(0, 2, 3)), (w * m * m).sum(axis=(0, 2, 3))
    a = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
    a = np.clip(a, 1e-3, None)
    return a / a.mean()


def _gauge(S: _Setup, c: np.ndarray, d: np.ndarray) -> tuple:
    """``c`` less its least-squares ``cos theta, sin theta`` part (a translation of the specimen), ``d`` less its
    mean."""
    X = _design(S.theta, 1)[1]
    return c - X @ np.linalg.lstsq(X, c, rcond=None)[0], d - d.mean()


def _shift_step(S: _Setup, alpha: float, c: np.ndarray, d: np.ndarray) -> tuple:
    """One Gauss-Newton step of every tilt's ``(c_k, d_k)`` with the linear model held (at most 1 px), gauged."""
    G, sd, dG_dc, dG_dd = _transforms(S, alpha, c, d, derivatives=True)
    residual, _ = _model_fit(S, G, sd)
    scale = np.where(sd > 1e-300, 1.0 / np.maximum(sd, 1e-300), 0.0)
    J = np.stack([_parts(dG_dc) * scale, _parts(dG_dd) * scale], -1)      # (2, tilts, 3, freqs, 2)
    J = np.moveaxis(J, 1, 0).reshape(len(c), -1, 2)
    r = np.moveaxis(residual, 1, 0).reshape(len(c), -1)
    H = np.einsum("kpi,kpj->kij", J, J) + 1e-9 * np.eye(2)
    step = -np.linalg.solve(H, np.einsum("kpi,kp->ki", J, r)[..., None])[..., 0]
    step = np.clip(step, -1.0, 1.0)
    return _gauge(S, c + step[:, 0], d + step[:, 1])


def _conditions(S: _Setup, alpha_deg: float, c: np.ndarray, d: np.ndarray, rounds: int = SHIFT_ROUNDS) -> tuple:
    """``chi2`` of the conditions at the trial angle with the shifts fitted from ``(c, d)`` (``rounds`` Gauss-Newton
    steps, each with the linear model re-fitted), the number of degrees of freedom, and the shifts."""
    alpha = math.radians(alpha_deg)
    if S.scales is not None:
        S.scales = np.ones(len(c))
    for _ in range(rounds):
        c_new, d_new = _shift_step(S, alpha, c, d)
        moved = max(np.abs(c_new - c).max(), np.abs(d_new - d).max())
        c, d = c_new, d_new
        if S.scales is not None:
            G, sd = _transforms(S, alpha, c, d)
            scales = _scale_step(S, G, sd)
            moved = max(moved, np.abs(scales - S.scales).max())
            S.scales = scales
        if moved < 1e-3:
            break
    G, sd = _transforms(S, alpha, c, d)
    residual, fitted = _model_fit(S, G, sd)
    data = int((sd > 1e-300).sum())
    scales = 0 if S.scales is None else len(c) - 1
    return float((residual ** 2).sum()), data - fitted - 2 * len(c) - scales, c, d


def _start(S: _Setup, alpha: float) -> tuple:
    """The shifts' start: each image's centre of mass across the trial axis (its ``cos, sin`` part removed) and
    along it (less the mean), which the order-0 and 1 conditions give at ``rho = 0`` without noise."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    u, v = ca * S.s + sa * S.t, -sa * S.s + ca * S.t
    mass = S.images.sum(1)
    mass = np.where(np.abs(mass) > 0, mass, 1.0)
    c, d = S.images @ u / mass, S.images @ v / mass
    limit = 0.25 * math.sqrt(len(S.s))
    return _gauge(S, np.clip(c, -limit, limit), np.clip(d, -limit, limit))


# ---------------------------------------------------------------------------------------------------- the estimate
def _quadratic_minimum(x: np.ndarray, y: np.ndarray) -> tuple:
    """The least-squares parabola through ``(x, y)``: its minimum and its curvature ``y''`` (``nan`` if not
    convex)."""
    a2, a1, _ = np.polyfit(x, y, 2)
    if a2 <= 0:
        return float(x[np.argmin(y)]), float("nan")
    return float(-a1 / (2 * a2)), float(2 * a2)


def _prepare(stack, tilt_angles, band: float, margin: float, scan_deg: float, sigma, orders: int,
             support: bool = True) -> tuple:
    """The checked stack's :class:`_Setup` (the specimen's columns, or with ``support=False`` every tilt and
    column; the window along the axis; the frequencies) and which tilts it uses; one-line errors for a bad
    stack."""
    a = np.asarray(stack, dtype=np.float64)
    theta = np.asarray(tilt_angles, dtype=np.float64).reshape(-1)
    if a.ndim != 3:
        raise ValueError(f"stack must be (tilts, rows, columns), got shape {a.shape}")
    if len(theta) != len(a):
        raise ValueError(f"tilt_angles has {len(theta)} angles, the stack {len(a)} tilts")
    if not np.isfinite(a).all():
        raise ValueError("stack has non-finite values")
    sigma = noise_level(a) if sigma is None else float(sigma)
    sigma = max(sigma, 1e-9 * float(np.abs(a).max()), 1e-300)
    first, last, outside = support_columns(a, sigma)
    if not support:
        first, last, outside = 0 * first, 0 * last + a.shape[2] - 1, np.zeros_like(outside)
    used = ~outside
    if used.sum() < MIN_TILTS:
        raise ValueError(f"the tilt-axis angle needs at least {MIN_TILTS} tilts whose specimen stays inside the "
                         f"detector across the axis, {int(used.sum())} of {len(a)} do")
    rows, cols = a.shape[1:]
    s, t = _frame((rows, cols))
    columns = np.arange(cols)[None, :]
    mask = np.broadcast_to(((columns >= first[:, None]) & (columns <= last[:, None]))[:, None, :], a.shape)
    masked = (a * mask)[used].reshape(int(used.sum()), -1)
    S = _Setup(masked, mask[used].reshape(len(masked), -1).astype(np.float64), s, t, theta[used], np.zeros(1), 1.0,
               1.0, sigma, orders)
    _, d0 = _start(S, 0.0)
    half = rows / 2 - np.abs(d0).max() - 0.5 * cols * math.sin(math.radians(scan_deg)) - margin
    if half < 4:
        raise ValueError(f"the stack has too few rows ({rows}) for the window along the tilt axis")
    S.half, S.taper = half, max(2.0, 0.25 * half)
    S.freqs = np.arange(0.0, band + 1e-12, 1.0 / (2 * half))
    return S, used


def condition_misfit(stack, tilt_angles, alpha_deg: float, shifts_px, band: float = 0.25, margin: float = 1.0,
                     orders: int = 2) -> float:
    """The conditions' relative misfit ``||G - fit|| / ||G||`` (each ``G`` weighted alike) at the trial angle
    ``alpha_deg`` with the shifts ``shifts_px`` ``(tilts, 2)`` (across, along the trial axis, px) held, over every
    tilt and the whole rows: 0 to rounding for an exact, noise-free series at its true angle and shifts whose
    specimen lies within the detector."""
    S, used = _prepare(stack, tilt_angles, band, margin, SCAN_DEG, None, orders, support=False)
    shifts = np.asarray(shifts_px, dtype=np.float64)[used]
    G, sd = _transforms(S, math.radians(alpha_deg), shifts[:, 0], shifts[:, 1])
    residual, _ = _model_fit(S, G, sd)
    return float(np.sqrt((residual ** 2).sum() / ((_parts(G) / np.where(sd > 0, sd, np.inf)) ** 2).sum()))


def binned(stack: np.ndarray, factor: int) -> np.ndarray:
    """``stack`` ``(tilts, rows, columns)`` averaged over ``factor x factor`` blocks about the images' centres (the
    rows and columns that do not fill a block left out at both ends alike): the angle is the same, a shift is
    ``1 / factor`` as many pixels."""
    if factor == 1:
        return stack
    K, R, C = stack.shape
    r0, c0 = (R % factor) // 2, (C % factor) // 2
    a = stack[:, r0:r0 + R // factor * factor, c0:c0 + C // factor * factor]
    return a.reshape(K, R // factor, factor, C // factor, factor).mean(axis=(2, 4))


def estimate_axis_angle(stack, tilt_angles, band: float = 0.25, margin: float = 1.0, scan_deg: float = SCAN_DEG,
                        sigma: float | None = None, orders: int = 2, scales: bool = True,
                        max_pixels: int | None = MAX_PIXELS) -> AxisEstimate:
    """The tilt-axis angle of ``stack`` (module Notes) from the Helgason-Ludwig conditions of orders
    ``0 .. orders``, with per-tilt shifts across and along the axis. Tilts whose specimen runs off the detector
    across the axis are left out (:func:`support_columns`).

    Parameters
    ----------
    stack : array_like
        ``(tilts, rows, columns)``, finite.
    tilt_angles : array_like
        One angle per tilt, radians.
    band : float
        The highest frequency along the axis (cycles per pixel).
    margin : float
        Rows kept from the window's ends beyond the shifts and the trial turn (px).
    scan_deg : float
        The trial angles' range (every degree, then every quarter within one degree of the least, a parabola
        fitted there).
    sigma : float, optional
        The noise's standard deviation (default :func:`noise_level`).
    orders : int
        The highest order of the conditions.
    scales : bool
        Fit an intensity scale per tilt too (exposure, a signal that changes with the path length), alternating
        with the shifts; False: every tilt's scale 1.
    max_pixels : int, optional
        A stack larger along either image axis is binned first (:func:`binned`, the smallest factor that brings
        it within; None: never).

    Returns
    -------
    AxisEstimate
        The angle, its standard error and whether the data determine it.

    Raises
    ------
    ValueError
        A stack that is not 3D or has non-finite values, a count of angles other than the tilts', too few tilts
        whose specimen stays on the detector, too few rows.
    """
    a, sigma, factor = _within(np.asarray(stack), max_pixels, sigma)
    S, used = _prepare(a, tilt_angles, band, margin, scan_deg, sigma, orders)
    S.scales = np.ones(len(S.theta)) if scales else None
    coarse = np.arange(-scan_deg, scan_deg + 1e-9, 1.0)
    chi2, _ = _scan(S, coarse)
    best = int(np.argmin(chi2))
    fine = coarse[best] + np.arange(-1.0, 1.0 + 1e-9, 0.25)
    fine_chi2, fine_shifts = _scan(S, fine)
    angle, curvature = _quadratic_minimum(fine, fine_chi2)
    chi2_min, dof, c, d = _conditions(S, angle, *fine_shifts[int(np.argmin(fine_chi2))])
    interior = abs(angle) < scan_deg and abs(angle - coarse[best]) <= 1.0
    inflation = max(1.0, chi2_min / max(dof, 1))
    se = math.inf
    if interior and curvature > 0:
        wander = _noise_slopes(S, fine, fine_shifts, angle).std(ddof=1) / curvature
        se = math.sqrt(2 / curvature * inflation + wander ** 2)
    x, y = np.concatenate([coarse, fine]), np.concatenate([chi2, fine_chi2])
    order = np.argsort(x)
    return AxisEstimate(angle, se, se <= MAX_SE_DEG, chi2_min / max(dof, 1),
                        _every_tilt(factor * np.stack([c, d], 1), used), used, (x[order], y[order]),
                        scales=None if S.scales is None else _every_tilt(S.scales, used), binning=factor)


def binned_within(stack: np.ndarray, max_pixels: int = MAX_PIXELS) -> tuple:
    """``stack`` ``(tilts, rows, columns)`` binned by the smallest factor that brings it within ``max_pixels``
    along each image axis (:func:`binned`), and the factor."""
    factor = max(1, -(-max(stack.shape[1:]) // int(max_pixels)))
    return binned(stack, factor), factor


def _within(stack: np.ndarray, max_pixels: int | None, sigma: float | None) -> tuple:
    """:func:`binned_within` (``max_pixels=None``: as it is), the noise's ``sigma`` with it (a block mean of
    ``f^2`` pixels), the factor."""
    if max_pixels is None or stack.ndim != 3:
        return stack, sigma, 1
    stack, factor = binned_within(stack, max_pixels)
    return stack, None if sigma is None else sigma / factor, factor


def _every_tilt(values: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Per-tilt ``values`` of the tilts ``used`` placed among all tilts, ``nan`` at the others."""
    out = np.full((len(used),) + values.shape[1:], np.nan)
    out[used] = values
    return out


def _noise_slopes(S: _Setup, trials: np.ndarray, shifts: list, angle: float) -> np.ndarray:
    """The slope at ``angle`` of the criterion of pure noise (``sigma`` white, on the specimen's columns; the
    shifts held at the data's), :data:`NOISE_REPLICAS` times (seeded): the part of the criterion that moves with the
    trial angle because the rows, and the noise summed into them, do; its spread over the curvature adds to the
    standard error."""
    gen = np.random.default_rng(0)
    slopes = []
    for _ in range(NOISE_REPLICAS):
        N = replace(S, images=S.sigma * gen.standard_normal(S.images.shape) * S.mask)
        values = [_conditions(N, float(a), c, d, rounds=0)[0] for a, (c, d) in zip(trials, shifts)]
        a2, a1, _ = np.polyfit(trials, values, 2)
        slopes.append(2 * a2 * angle + a1)
    return np.array(slopes)


def _scan(S: _Setup, trials: np.ndarray) -> tuple:
    """``chi2`` at every trial angle, each from the centres of mass at that angle (:func:`_start`); returns the
    values and the fitted shifts."""
    values, shifts = [], []
    for alpha in trials:
        value, _, c, d = _conditions(S, float(alpha), *_start(S, math.radians(alpha)))
        values.append(value)
        shifts.append((c, d))
    return np.array(values), shifts
