"""Figures of merit of a result against the ground truth: SSIM (scikit-image), PSNR and relative error.

Notes
-----
- Every function takes ``(x, gt)``: the result first, the ground truth second, each a 2D image
  ``(nx, ny)`` or a 3D volume ``(nx, ny, nz)`` as a torch tensor (any device, real dtype) or numpy array;
  compared in float64; returns a float. Both must have the same shape, finite real values (complex and
  boolean inputs are refused, not cast), and for SSIM at least 7 cells per axis.
- ``ssim`` / ``psnr``: today's honest convention, ``data_range = gt.max() - gt.min()``.
- ``ssim_paper`` / ``psnr_paper``: the 2017 scikit-image defaults (``compare_ssim`` / ``compare_psnr``) that
  the paper's numbers use: SSIM with data range 2 (the float dtype range -1..1); PSNR with data range 2 if
  an image has negative values, else 1. (The 2017 ``compare_psnr`` looked at its first argument only; the
  authors passed the result first and the ground truths are nonnegative, so "either image" is the same.)
  Other SSIM settings are the defaults then and now: 7 x 7 uniform window, sample covariance.
- 3D SSIM is the same statistic with a 7 x 7 x 7 window (scikit-image's n-dimensional SSIM), averaged over
  the volume. Volumes are read in float64 chunks of :data:`CHUNK` slices along axis 0 (SSIM's with a halo of
  3 slices), never as whole float64 copies: the same numbers as whole volumes to float rounding (the sums'
  order).
"""
from __future__ import annotations

import math

import numpy as np
import torch

#: Side of scikit-image's default SSIM window (cells).
SSIM_WINDOW = 7
#: Slices along axis 0 of a volume read at once (in float64) by the figures of merit.
CHUNK = 16


def _real_array(a, name: str) -> np.ndarray:
    """``a`` (torch tensor or numpy array) as a float64 numpy array; complex, boolean and non-numeric refused."""
    if isinstance(a, torch.Tensor):
        if a.is_complex() or a.dtype == torch.bool:
            raise TypeError(f"{name} must have real numeric values, got dtype {a.dtype}")
        return a.detach().cpu().to(torch.float64).numpy()
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(a).__name__}")
    if a.dtype.kind not in "iuf":
        raise TypeError(f"{name} must have real numeric values, got dtype {a.dtype}")
    return a.astype(np.float64)


def _pair(x, gt) -> tuple:
    """``(x, gt)`` checked: images as float64 arrays; volumes as given (read in float64 chunks, :func:`_rows`)."""
    arrays = []
    for a, name in ((x, "x"), (gt, "gt")):
        volume = getattr(a, "ndim", None) == 3
        head = _real_array(a[:1] if volume else a, name)   # the type and dtype checked
        if not volume and (head.ndim != 2 or head.size == 0) or volume and 0 in a.shape:
            raise ValueError(f"{name} must be a non-empty 2D image (nx, ny) or 3D volume (nx, ny, nz), "
                             f"got shape {tuple(getattr(a, 'shape', head.shape))}")
        finite = bool(torch.isfinite(a).all()) if isinstance(a, torch.Tensor) else np.isfinite(a).all()
        if not finite:
            raise ValueError(f"{name} contains non-finite values (nan or inf)")
        arrays.append(a if volume else head)
    if tuple(arrays[0].shape) != tuple(arrays[1].shape):
        raise ValueError(f"x and gt must have the same shape, got {tuple(arrays[0].shape)} and "
                         f"{tuple(arrays[1].shape)}")
    return tuple(arrays)


def _rows(a, start: int, stop: int) -> np.ndarray:
    """Slices ``start:stop`` (axis 0) of a volume as a float64 array."""
    return _real_array(a[start:stop], "x")


def _chunks(start: int, stop: int):
    """``(a, b)`` ranges of at most :data:`CHUNK` slices covering ``start:stop``."""
    return ((a, min(a + CHUNK, stop)) for a in range(start, stop, CHUNK))


def _gt_range(gt) -> float:
    r = float(gt.max()) - float(gt.min())
    if r <= 0:
        raise ValueError("gt is constant: data_range = gt.max() - gt.min() is 0")
    return r


def _psnr(x, gt, data_range: float) -> float:
    """``10 log10(R^2 / MSE)``: an image's as scikit-image's ``peak_signal_noise_ratio(gt, x)`` computes it (the same
    float64 operations, without importing its ``scipy.stats``), a volume's from float64 chunks."""
    if x.ndim == 2:
        if np.array_equal(x, gt):
            return math.inf
        return float(10 * np.log10(data_range ** 2 / np.mean((gt - x) ** 2, dtype=np.float64)))
    squares, equal = 0.0, True
    for a, b in _chunks(0, x.shape[0]):   # a volume: the mean square error in float64 chunks
        xs, gs = _rows(x, a, b), _rows(gt, a, b)
        equal = equal and np.array_equal(xs, gs)
        squares += float(np.sum((gs - xs) ** 2, dtype=np.float64))
    return math.inf if equal else float(10 * np.log10(data_range ** 2 / (squares / math.prod(x.shape))))


def _ssim(x, gt, data_range: float) -> float:
    """scikit-image's SSIM; a volume's by chunks of slices with a halo of the window's half width ``p``, each
    chunk's SSIM map kept where its window lies inside the chunk (scikit-image averages the cells ``p`` or more
    from every edge)."""
    from skimage.metrics import structural_similarity   # here: importing indreg.metrics costs no scikit-image

    if x.ndim == 2:
        return float(structural_similarity(x, gt, data_range=data_range))
    p, n = (SSIM_WINDOW - 1) // 2, x.shape[0]
    total, count = 0.0, 0
    for a, b in _chunks(p, n - p):
        _, s = structural_similarity(_rows(x, a - p, b + p), _rows(gt, a - p, b + p), data_range=data_range,
                                     full=True)
        inner = s[p:p + b - a, p:-p, p:-p]
        total, count = total + float(inner.sum(dtype=np.float64)), count + inner.size
    return total / count


def _ssim_pair(x, gt) -> tuple:
    """``_pair`` for SSIM, whose 7-pixel window needs every side >= 7."""
    x, gt = _pair(x, gt)
    if min(x.shape) < SSIM_WINDOW:
        raise ValueError(f"x and gt must be at least {SSIM_WINDOW} cells along every axis for SSIM (its "
                         f"{SSIM_WINDOW}-cell window), got shape {tuple(x.shape)}")
    return x, gt


def ssim(x, gt) -> float:
    """Structural similarity, ``data_range = gt.max() - gt.min()``.

    Parameters
    ----------
    x : torch.Tensor or numpy.ndarray
        The result, a 2D image or 3D volume (at least 7 cells per axis).
    gt : torch.Tensor or numpy.ndarray
        The ground truth, ``x``'s shape.

    Returns
    -------
    float
        SSIM; 1 for identical images.

    Raises
    ------
    TypeError
        An input that is no tensor / array, or complex, boolean or non-numeric.
    ValueError
        Empty, not 2D / 3D, non-finite, shapes that differ, fewer than 7 cells on an axis, a constant ``gt``.
    """
    x, gt = _ssim_pair(x, gt)
    return _ssim(x, gt, _gt_range(gt))


def psnr(x, gt) -> float:
    """``10 log10(R^2 / MSE)`` in dB with ``R = gt.max() - gt.min()``.

    Parameters
    ----------
    x : torch.Tensor or numpy.ndarray
        The result, a 2D image or 3D volume.
    gt : torch.Tensor or numpy.ndarray
        The ground truth, ``x``'s shape.

    Returns
    -------
    float
        PSNR in dB; ``inf`` for identical images.

    Raises
    ------
    TypeError
        An input that is no tensor / array, or complex, boolean or non-numeric.
    ValueError
        Empty, not 2D / 3D, non-finite, shapes that differ, a constant ``gt``.
    """
    x, gt = _pair(x, gt)
    return _psnr(x, gt, _gt_range(gt))


def ssim_paper(x, gt) -> float:
    """Structural similarity as the paper computed it (2017 ``compare_ssim`` on floats: data range 2).

    Parameters
    ----------
    x : torch.Tensor or numpy.ndarray
        The result, a 2D image or 3D volume (at least 7 cells per axis).
    gt : torch.Tensor or numpy.ndarray
        The ground truth, ``x``'s shape.

    Returns
    -------
    float
        SSIM; 1 for identical images.

    Raises
    ------
    TypeError
        An input that is no tensor / array, or complex, boolean or non-numeric.
    ValueError
        Empty, not 2D / 3D, non-finite, shapes that differ, fewer than 7 cells on an axis.
    """
    x, gt = _ssim_pair(x, gt)
    return _ssim(x, gt, 2.0)


def psnr_paper(x, gt) -> float:
    """PSNR as the paper computed it (2017 ``compare_psnr`` on floats): data range 2 if ``x`` or ``gt`` has
    negative values, else 1.

    Parameters
    ----------
    x : torch.Tensor or numpy.ndarray
        The result, a 2D image or 3D volume.
    gt : torch.Tensor or numpy.ndarray
        The ground truth, ``x``'s shape.

    Returns
    -------
    float
        PSNR in dB; ``inf`` for identical images.

    Raises
    ------
    TypeError
        An input that is no tensor / array, or complex, boolean or non-numeric.
    ValueError
        Empty, not 2D / 3D, non-finite, shapes that differ.
    """
    x, gt = _pair(x, gt)
    return _psnr(x, gt, 2.0 if min(float(x.min()), float(gt.min())) < 0 else 1.0)


def relative_error(x, gt) -> float:
    """``||x - gt|| / ||gt||`` (Frobenius norms; a cell-volume weight cancels).

    Parameters
    ----------
    x : torch.Tensor or numpy.ndarray
        The result, a 2D image or 3D volume.
    gt : torch.Tensor or numpy.ndarray
        The ground truth, ``x``'s shape.

    Returns
    -------
    float
        The relative error.

    Raises
    ------
    TypeError
        An input that is no tensor / array, or complex, boolean or non-numeric.
    ValueError
        Empty, not 2D / 3D, non-finite, shapes that differ, a zero ``gt``.
    """
    x, gt = _pair(x, gt)
    if x.ndim == 2:
        error, ref = float(np.linalg.norm(x - gt)), float(np.linalg.norm(gt))
    else:   # a volume: the sums of squares in float64 chunks
        parts = [(np.sum((_rows(x, a, b) - _rows(gt, a, b)) ** 2), np.sum(_rows(gt, a, b) ** 2))
                 for a, b in _chunks(0, x.shape[0])]
        error, ref = (math.sqrt(sum(float(v[i]) for v in parts)) for i in (0, 1))
    if ref == 0:
        raise ValueError("gt is zero: the relative error is undefined")
    return error / ref
