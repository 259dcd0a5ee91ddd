"""Coarse alignment of a tilt series by cross-correlation with cosine stretching, as IMOD's ``tiltxcorr`` does it:
every view correlated with its neighbour towards the zero tilt, stretched across the tilt axis by the ratio of the
cosines, tapered at the edges and band-passed, the shifts accumulated outward from the zero tilt.

It needs no reconstruction and no object inside the field of view, so it starts the alignment of a slab specimen
(``indreg.alignment.slab``), and its correlation peaks measure how well a trial tilt-axis angle fits
(``indreg.alignment.axis_search``).

Notes
-----
- The axis frame: images ``(K, rows, columns)`` resampled so that the tilt axis runs along the rows (Y), the
  columns across it; pixel ``(i, j)`` at ``q = (j - (nx - 1) / 2, i - (ny - 1) / 2)`` (x across, y along).
- A view's shift ``v_k = (across, along)`` in pixels of the axis frame: its content lies at ``q + v_k``, so the
  raw stack holds it at ``p = R(alpha) (q + v_k)`` (:func:`axis_frame`; ``R`` counter-clockwise, ``alpha`` the
  tilt axis' angle from Y, IMOD's). In ``indreg.alignment.files``' terms: the map ``M = R(alpha)`` and the shift
  ``d = R(alpha) v``.
- Stretching: a point of the mid-plane at ``x`` across the axis projects to ``x cos(theta)``; the view at the
  larger tilt is stretched by ``cos(theta_near) / cos(theta_far)`` about the axis before it is correlated
  with its neighbour, so the measured shift ``r = v_far / c - v_near`` (``c`` the ratio) across the axis.
- Filter (IMOD's defaults for ``tiltxcorr``, in cycles per pixel): a Gaussian high-pass ``1 - exp(-f^2 /
  2 sigma1^2)``, ``sigma1 = 0.03``, and a Gaussian fall-off above ``radius2 = 0.25`` with ``sigma2 = 0.05``;
  a cosine taper over ``taper`` of each image side; the correlation padded (no wrap-around).
- Bound: ``|v| <= bound`` pixels per component (the peak searched within twice that between neighbours); a
  shift that ends at its bound is counted in ``at_bound``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BAND", "TAPER", "CoarseAlignment", "axis_frame", "band_pass", "coarse_alignment", "correlate",
           "stretch", "taper_window"]

#: IMOD ``tiltxcorr``'s default filter: ``(sigma1, radius2, sigma2)`` in cycles per pixel.
BAND = (0.03, 0.25, 0.05)
#: Fraction of each image side over which the images are tapered to 0.
TAPER = 0.1


def _rotation(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s], [s, c]])


def axis_frame(stack: np.ndarray, alpha_deg: float, shifts: np.ndarray | None = None, order: int = 1) -> np.ndarray:
    """The raw ``stack`` resampled into the axis frame (module Notes): ``frame_k(q) = stack_k(R(alpha) (q +
    v_k))``, the nearest edge pixel beyond the image.

    Parameters
    ----------
    stack : numpy.ndarray
        ``(K, ny, nx)`` views as stored.
    alpha_deg : float
        The tilt axis' angle from Y, counter-clockwise (degrees).
    shifts : numpy.ndarray, optional
        ``v``, ``(K, 2)`` px (across, along); zeros when None.
    order : int
        The spline order (1: bilinear).

    Returns
    -------
    numpy.ndarray
        ``(K, ny, nx)`` float64, the tilt axis along the rows.
    """
    from scipy.ndimage import affine_transform

    K, ny, nx = stack.shape
    v = np.zeros((K, 2)) if shifts is None else np.asarray(shifts, dtype=np.float64)
    centre = np.array([(ny - 1) / 2, (nx - 1) / 2])
    R = _rotation(alpha_deg)
    m = np.array([[R[1, 1], R[1, 0]], [R[0, 1], R[0, 0]]])          # (row, column) order
    out = np.empty(stack.shape, dtype=np.float64)
    for k in range(K):
        d = R @ v[k]
        out[k] = affine_transform(np.asarray(stack[k], dtype=np.float64), m, np.array([d[1], d[0]]) + centre
                                  - m @ centre, order=order, mode="nearest")
    return out


def taper_window(rows: int, columns: int, fraction: float = TAPER, half_width: float | None = None) -> np.ndarray:
    """A ``(rows, columns)`` window: 1 inside, a raised cosine to 0 over ``fraction`` of each side at the edges;
    with ``half_width`` (px) the columns beyond ``half_width`` from the middle are 0 too (their taper inside)."""
    def ramp(n: int, half: float) -> np.ndarray:
        x = np.abs(np.arange(n) - (n - 1) / 2)
        m = max(fraction * n, 1.0)
        return 0.5 - 0.5 * np.cos(np.pi * np.clip((half - x) / m, 0.0, 1.0))
    return ramp(rows, rows / 2)[:, None] * ramp(columns, columns / 2 if half_width is None else half_width)[None]


def band_pass(shape: tuple, band: tuple = BAND) -> np.ndarray:
    """The real-FFT filter (module Notes) of images ``shape`` (the padded size), frequencies in cycles per
    pixel."""
    sigma1, radius2, sigma2 = band
    f = np.hypot(np.fft.fftfreq(shape[0])[:, None], np.fft.rfftfreq(shape[1])[None, :])
    high = 1 - np.exp(-f ** 2 / (2 * sigma1 ** 2)) if sigma1 > 0 else np.ones_like(f)
    low = np.where(f <= radius2, 1.0, np.exp(-(f - radius2) ** 2 / (2 * sigma2 ** 2)))
    return high * low


def _subpixel(lo: float, mid: float, hi: float) -> float:
    """The vertex of the parabola through three samples about a maximum (0 when it is not one), within half a px."""
    curvature = lo - 2 * mid + hi
    return 0.0 if curvature >= 0 else float(np.clip(0.5 * (lo - hi) / curvature, -0.5, 0.5))


def correlate(reference: np.ndarray, moving: np.ndarray, limit: tuple, band: tuple = BAND) -> tuple:
    """The shift ``(x, y)`` px of ``moving`` against ``reference`` (``moving(q) ~ reference(q - shift)``) at the
    peak of their band-passed, zero-padded cross-correlation within ``|x| <= limit[0]``, ``|y| <= limit[1]``
    (a parabola through the peak's neighbours for the fraction), and the peak's correlation coefficient of the
    band-passed images. Both images should be tapered already (:func:`taper_window`)."""
    ny, nx = reference.shape
    size = (2 * ny, 2 * nx)
    h = band_pass(size, band) ** 2                                       # the filter on both images
    A, B = np.fft.rfft2(reference, size), np.fft.rfft2(moving, size)
    c = np.fft.irfft2(B * A.conj() * h, size)
    ly = np.fft.fftfreq(size[0], 1 / size[0]).round()
    lx = np.fft.fftfreq(size[1], 1 / size[1]).round()
    allowed = (np.abs(ly)[:, None] <= limit[1]) & (np.abs(lx)[None, :] <= limit[0])
    i, j = np.unravel_index(np.argmax(np.where(allowed, c, -np.inf)), c.shape)
    dy = _subpixel(c[(i - 1) % size[0], j], c[i, j], c[(i + 1) % size[0], j])
    dx = _subpixel(c[i, (j - 1) % size[1]], c[i, j], c[i, (j + 1) % size[1]])
    energy = [float(np.fft.irfft2(np.abs(F) ** 2 * h, size)[0, 0]) for F in (A, B)]   # the filtered images' sums
    norm = math.sqrt(max(energy[0] * energy[1], 0.0))
    return np.array([lx[j] + dx, ly[i] + dy]), float(c[i, j] / norm) if norm > 0 else 0.0


def stretch(image: np.ndarray, factor: float) -> np.ndarray:
    """``image`` stretched across the tilt axis (along the columns) by ``factor`` about its middle: ``out(x, y) =
    image(x / factor, y)`` (bilinear, the nearest edge pixel beyond)."""
    from scipy.ndimage import affine_transform

    ny, nx = image.shape
    centre = np.array([(ny - 1) / 2, (nx - 1) / 2])
    m = np.diag([1.0, 1.0 / factor])
    return affine_transform(image, m, centre - m @ centre, order=1, mode="nearest")


def _prepared(image: np.ndarray, window: np.ndarray) -> np.ndarray:
    """``image`` less its windowed mean, times the window."""
    return (image - (image * window).sum() / window.sum()) * window


@dataclass(frozen=True)
class CoarseAlignment:
    """:func:`coarse_alignment`'s result.

    Attributes
    ----------
    shifts : numpy.ndarray
        ``(K, 2)`` px (across, along; module Notes).
    peaks : numpy.ndarray
        ``(K,)`` the correlation coefficient of each view with its neighbour (1 at the zero tilt).
    at_bound : numpy.ndarray
        ``(K, 2)`` whether a shift ended at its bound.
    bound : tuple
        ``(across, along)`` px.
    zero : int
        The zero tilt's index.
    """
    shifts: np.ndarray
    peaks: np.ndarray
    at_bound: np.ndarray
    bound: tuple
    zero: int


def coarse_alignment(frames: np.ndarray, angles_rad: np.ndarray, bound: tuple | None = None,
                     band: tuple = BAND, taper: float = TAPER) -> CoarseAlignment:
    """Shifts of ``frames`` (``(K, rows, columns)`` in the axis frame, line integrals or any contrast of one
    sign) by stretched cross-correlation of neighbours, outward from the tilt nearest 0 (module Notes).

    Parameters
    ----------
    frames : numpy.ndarray
        The views in the axis frame (:func:`axis_frame`).
    angles_rad : numpy.ndarray
        Their tilt angles (radians; the sign does not matter here).
    bound : tuple, optional
        ``(across, along)`` largest shift in px (default a quarter of the image's columns and rows).
    band, taper
        The filter (:data:`BAND`) and the taper's fraction (:data:`TAPER`).

    Returns
    -------
    CoarseAlignment
        The shifts (the zero tilt's is 0), the peaks' correlation coefficients, which shifts are at their bound.
    """
    K, ny, nx = frames.shape
    theta = np.asarray(angles_rad, dtype=np.float64)
    bound = (0.25 * nx, 0.25 * ny) if bound is None else tuple(float(b) for b in bound)
    limit = (min(2 * bound[0], nx / 2), min(2 * bound[1], ny / 2))
    window = taper_window(ny, nx, taper)
    zero = int(np.argmin(np.abs(theta)))
    v, peaks = np.zeros((K, 2)), np.ones(K)
    for order in (range(zero + 1, K), range(zero - 1, -1, -1)):
        for k in order:
            near = k - 1 if k > zero else k + 1
            ratio = math.cos(theta[k]) / math.cos(theta[near])
            far = _prepared(stretch(frames[k], 1 / ratio), window)
            r, peaks[k] = correlate(_prepared(frames[near], window), far, limit, band)
            v[k] = np.clip([ratio * (r[0] + v[near, 0]), r[1] + v[near, 1]], -np.array(bound), np.array(bound))
    at = np.abs(v) >= np.array(bound) - 1e-9
    return CoarseAlignment(v, peaks, at, bound, zero)
