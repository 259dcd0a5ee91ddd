"""Figures of merit of a result against the ground truth: SSIM, PSNR (scikit-image) and relative error.

Convention:
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
      the volume.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

#: Side of scikit-image's default SSIM window (cells).
SSIM_WINDOW = 7


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
    arrays = []
    for a, name in ((x, "x"), (gt, "gt")):
        a = _real_array(a, name)
        if a.ndim not in (2, 3) or a.size == 0:
            raise ValueError(f"{name} must be a non-empty 2D image (nx, ny) or 3D volume (nx, ny, nz), "
                             f"got shape {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{name} contains non-finite values (nan or inf)")
        arrays.append(a)
    if arrays[0].shape != arrays[1].shape:
        raise ValueError(f"x and gt must have the same shape, got {arrays[0].shape} and {arrays[1].shape}")
    return tuple(arrays)


def _gt_range(gt: np.ndarray) -> float:
    r = float(gt.max() - gt.min())
    if r <= 0:
        raise ValueError("gt is constant: data_range = gt.max() - gt.min() is 0")
    return r


def _psnr(x: np.ndarray, gt: np.ndarray, data_range: float) -> float:
    if np.array_equal(x, gt):
        return math.inf
    return float(peak_signal_noise_ratio(gt, x, data_range=data_range))


def _ssim_pair(x, gt) -> tuple:
    """``_pair`` for SSIM, whose 7-pixel window needs every side >= 7."""
    x, gt = _pair(x, gt)
    if min(x.shape) < SSIM_WINDOW:
        raise ValueError(f"x and gt must be at least {SSIM_WINDOW} cells along every axis for SSIM (its "
                         f"{SSIM_WINDOW}-cell window), got shape {x.shape}")
    return x, gt


def ssim(x, gt) -> float:
    """Structural similarity, ``data_range = gt.max() - gt.min()`` (1 for identical images)."""
    x, gt = _ssim_pair(x, gt)
    return float(structural_similarity(x, gt, data_range=_gt_range(gt)))


def psnr(x, gt) -> float:
    """``10 log10(R^2 / MSE)`` in dB with ``R = gt.max() - gt.min()``; ``inf`` for identical images."""
    x, gt = _pair(x, gt)
    return _psnr(x, gt, _gt_range(gt))


def ssim_paper(x, gt) -> float:
    """Structural similarity as the paper computed it (2017 ``compare_ssim`` on floats: data range 2)."""
    x, gt = _ssim_pair(x, gt)
    return float(structural_similarity(x, gt, data_range=2.0))


def psnr_paper(x, gt) -> float:
    """PSNR as the paper computed it (2017 ``compare_psnr`` on floats): data range 2 if ``x`` or ``gt`` has
    negative values, else 1; ``inf`` for identical images."""
    x, gt = _pair(x, gt)
    return _psnr(x, gt, 2.0 if min(x.min(), gt.min()) < 0 else 1.0)


def relative_error(x, gt) -> float:
    """``||x - gt|| / ||gt||`` (Frobenius norms; a cell-volume weight cancels)."""
    x, gt = _pair(x, gt)
    ref = np.linalg.norm(gt)
    if ref == 0:
        raise ValueError("gt is zero: the relative error is undefined")
    return float(np.linalg.norm(x - gt) / ref)
