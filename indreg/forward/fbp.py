"""Filtered backprojection (FBP) for the parallel-beam ``RayTransform``.

Derivation (angles on ``[0, pi)``). With ``P(theta, rho) = integral p(theta, s) exp(-2 pi i rho s) ds`` the
Fourier slice theorem gives ``P(theta, rho) = F(rho w)``, and writing Fourier inversion in polar
coordinates over half a turn,

    f(x) = integral_0^pi q(theta, x . w) dtheta,   q(theta, .) = IFT( |rho| P(theta, rho) ),

i.e. ``f = B q`` with the ramp-filtered data ``q`` and the backprojection ``B``. The operator's L2 adjoint
``T^* = (data_weight / cell_volume) A^T`` is the discrete ``B`` (each angle weighted by ``pi / num_angles``,
since a pixel's Joseph weights summed over the detector bins are ``cell_volume / det_cell``), so
``fbp(T, y) = T.adjoint(q)`` with no further constant.

The ramp filter is the band-limited one (Ram-Lak; Kak & Slaney, ch. 3): the kernel samples
``h(0) = 1 / (4 tau^2)``, ``h(n tau) = -1 / (pi n tau)^2`` for odd ``n``, 0 for even ``n`` (``tau = det_cell``)
are Fourier transformed, so the DC term is right (no negative offset, unlike a sampled ``|rho|``), and
the convolution ``q(s_k) = tau sum_n h(n tau) p(s_k - n tau)`` is done by FFT along the detector axis.
Windows follow ODL's ``fbp_filter_op`` semantics: ``norm_freq = rho / rho_Nyquist`` in ``[0, 1]``, the window
is evaluated at ``norm_freq / frequency_scaling`` and frequencies with ``norm_freq > frequency_scaling``
are set to 0.
"""
from __future__ import annotations

import math

import torch

from .._checks import check_positive, check_tensor

FILTERS = ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")


def _window(norm_freq: torch.Tensor, name: str, scaling: float) -> torch.Tensor:
    """Apodisation window on normalised frequencies (1 at DC), zero above ``scaling``."""
    u = norm_freq / scaling
    if name == "ram-lak":
        w = torch.ones_like(u)
    elif name == "shepp-logan":
        w = torch.sinc(u / 2)
    elif name == "cosine":
        w = torch.cos(u * math.pi / 2)
    elif name == "hamming":
        w = 0.54 + 0.46 * torch.cos(u * math.pi)
    else:  # hann
        w = torch.cos(u * math.pi / 2) ** 2
    return w * (norm_freq <= scaling)


def fbp_filter(det_count: int, det_cell: float, filter: str = "ram-lak", frequency_scaling: float = 1.0,
               padding: bool = True, dtype=torch.float64, device=None) -> torch.Tensor:
    """Real frequency response (length ``n_fft // 2 + 1``, for ``torch.fft.rfft`` of size ``n_fft``).

    ``n_fft = 2 * det_count`` with padding (linear convolution), ``det_count`` without (circular).
    Units: ``1 / length`` (the response approximates ``|rho|``, ``rho`` in cycles per unit length).
    """
    name = str(filter).lower()
    if name not in FILTERS:
        raise ValueError(f"filter must be one of {FILTERS}, got {filter!r}")
    scaling = check_positive(frequency_scaling, "frequency_scaling")
    if scaling > 1:
        raise ValueError(f"frequency_scaling must be in (0, 1], got {frequency_scaling!r}")
    n_fft = 2 * det_count if padding else det_count
    offset = torch.fft.fftfreq(n_fft, 1.0 / n_fft, dtype=torch.float64)   # integer offsets n, fft order
    kernel = torch.where(offset.remainder(2) == 1, -1.0 / (math.pi * offset * det_cell) ** 2,
                         torch.zeros_like(offset))
    kernel[0] = 1.0 / (4 * det_cell ** 2)
    response = det_cell * torch.fft.rfft(kernel).real
    norm_freq = torch.arange(response.numel(), dtype=torch.float64) / max(n_fft // 2, 1)
    return (response * _window(norm_freq, name, scaling)).to(device=device, dtype=dtype)


def fbp(T, y: torch.Tensor, filter: str = "hamming", frequency_scaling: float = 0.4,
        padding: bool = True) -> torch.Tensor:
    """Filtered backprojection ``T^*( h * y )`` of data ``y`` for the ray transform ``T``.

    Convention:
        - ``y``: ``(..., num_angles, det_count)`` line integrals (physical units) as produced by ``T``;
          returns images ``(..., nx, ny)`` on ``T.domain`` in the units of the original ``f``
          (e.g. a unit disk reconstructs to about 1 inside with ``ram-lak``, ``frequency_scaling=1``).
        - Assumes angles spread over ``[0, pi)`` (each weighted ``pi / num_angles``).
        - Differentiable (FFT, multiplication and ``T.adjoint`` are all differentiable).

    Args:
        filter: one of ``ram-lak``, ``shepp-logan``, ``cosine``, ``hamming``, ``hann``.
        frequency_scaling: relative cut-off in (0, 1]; frequencies above ``scaling * Nyquist`` are zeroed.
        padding: zero-pad the detector axis to ``2 * det_count`` before the FFT (no wrap-around).

    The paper's FBP baseline is ``filter="hamming", frequency_scaling=0.4, padding=True``.
    """
    y = check_tensor(y, "data", T.range_shape)
    m = y.shape[-1]
    response = fbp_filter(m, T.geometry.det_cell, filter, frequency_scaling, padding, y.dtype, y.device)
    n_fft = 2 * m if padding else m
    q = torch.fft.irfft(torch.fft.rfft(y, n=n_fft, dim=-1) * response, n=n_fft, dim=-1)[..., :m]
    return T.adjoint(q.contiguous())
