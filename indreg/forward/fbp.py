"""Filtered backprojection (FBP) for the ``RayTransform`` (parallel beam; fan beam by rebinning) and, slice by
slice, for the ``TiltSeriesTransform`` (weighted backprojection of a tilt series).

Derivation (angles on ``[0, pi)``). With ``P(theta, rho) = integral p(theta, s) exp(-2 pi i rho s) ds`` the
Fourier slice theorem gives ``P(theta, rho) = F(rho w)``, and writing Fourier inversion in polar
coordinates over half a turn,

    f(x) = integral_0^pi q(theta, x . w) dtheta,   q(theta, .) = IFT( |rho| P(theta, rho) ),

i.e. ``f = B q`` with the ramp-filtered data ``q`` and the backprojection ``B``. The operator's L2 adjoint
``T^* = (data_weight / cell_volume) A^T`` is the discrete ``B`` (each angle weighted by ``pi / num_angles``,
since a pixel's Joseph weights summed over the detector bins are ``cell_volume / det_cell``), so
``fbp(T, y) = T.adjoint(q)`` with no further constant. For other angle sets (non-uniform, limited, a tilt
series) the integral over ``theta`` is the midpoint rule: angle ``k`` is weighted by its quadrature cell
``geometry.angle_weights[k]``, i.e. ``q_k`` is scaled by ``angle_weights[k] / angle_cell`` before ``T.adjoint``
(a factor of exactly 1 for uniform angles on ``[0, pi)`` and the paper's presets, which stay bit-identical).
A limited angular range then reconstructs with the scale of the angles it has (a centred disk's centre
value is ``covered range / pi`` of the true value), not inflated by ``pi / num_angles``.

Fan beam (flat detector, full turn): the data are rebinned to parallel beam, ray ``(beta, u)`` being the
parallel ray ``(beta - gamma, src_radius sin gamma)``, ``gamma = atan(u / (src_radius + det_radius))``: for
``num_angles`` parallel angles uniform on ``[0, 2 pi)`` and ``det_count`` uniform bins spanning the fan at
the origin, the fan data are interpolated bilinearly (periodic in ``beta``, zero beyond the detector), and
the parallel FBP above is applied with a parallel ``RayTransform`` on the same domain (built once, cached
on ``T``).

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

import numpy as np
import torch

from .._checks import check_bool, check_int, check_nonempty, check_positive, check_tensor
from .geometry import FanBeamGeometry, ParallelBeamGeometry

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
    name = filter.lower() if isinstance(filter, str) else filter
    if name not in FILTERS:
        raise ValueError(f"filter must be one of {FILTERS}, got {filter!r}")
    scaling = check_positive(frequency_scaling, "frequency_scaling")
    if scaling > 1:
        raise ValueError(f"frequency_scaling must be in (0, 1], got {frequency_scaling!r}")
    det_count, det_cell = check_int(det_count, "det_count", 1), check_positive(det_cell, "det_cell")
    n_fft = 2 * det_count if check_bool(padding, "padding") else det_count
    offset = torch.fft.fftfreq(n_fft, 1.0 / n_fft, dtype=torch.float64)   # integer offsets n, fft order
    kernel = torch.where(offset.remainder(2) == 1, -1.0 / (math.pi * offset * det_cell) ** 2,
                         torch.zeros_like(offset))
    kernel[0] = 1.0 / (4 * det_cell ** 2)
    response = det_cell * torch.fft.rfft(kernel).real
    norm_freq = torch.arange(response.numel(), dtype=torch.float64) / max(n_fft // 2, 1)
    return (response * _window(norm_freq, name, scaling)).to(device=device, dtype=dtype)


def fbp(T, y: torch.Tensor, filter: str = "hamming", frequency_scaling: float = 0.4,
        padding: bool = True) -> torch.Tensor:
    """Filtered backprojection ``T^*( w h * y )`` of data ``y`` for the ray transform ``T``.

    The paper's FBP baseline is ``filter="hamming", frequency_scaling=0.4, padding=True``.

    Parameters
    ----------
    T : RayTransform or TiltSeriesTransform
        The operator of the data (parallel or fan beam; a tilt series).
    y : torch.Tensor
        Data ``(..., num_angles, det_count)`` (a tilt series: ``(..., num_tilts, det_rows, det_cols)``), line
        integrals in physical units as produced by ``T``.
    filter : {"hamming", "ram-lak", "shepp-logan", "cosine", "hann"}
        The apodisation window of the ramp filter.
    frequency_scaling : float
        Relative cut-off in (0, 1]; frequencies above ``frequency_scaling * Nyquist`` are zeroed.
    padding : bool
        Zero-pad the detector axis to ``2 * det_count`` before the FFT (no wrap-around).

    Returns
    -------
    torch.Tensor
        Images ``(..., nx, ny)`` on ``T.domain`` (volumes ``(..., nx, ny, nz)`` for a tilt series), in the units
        of the original ``f`` (a unit disk reconstructs to about 1 inside with ``ram-lak``,
        ``frequency_scaling=1``).

    Raises
    ------
    TypeError
        ``T`` is not a ray transform of a parallel- or fan-beam geometry or a tilt series.
    ValueError
        Data of another shape, an unknown filter, ``frequency_scaling`` outside (0, 1], fan-beam angles that do
        not cover a full turn.

    Notes
    -----
    - Parallel beam: any angle set; angle ``k`` is weighted by its quadrature cell
      ``T.geometry.angle_weights[k]`` (module docstring). Fan beam: angles over a full turn, rebinned.
    - Tilt series: the 2D FBP of ``T.slice_transform`` applied to every detector row at once (the weighted
      backprojection of electron tomography, each tilt weighted by its quadrature cell).
    - Differentiable (FFT, multiplication, the rebinning and ``T.adjoint`` are all differentiable).
    """
    if hasattr(T, "slice_transform"):
        return _fbp_tilt_series(T, y, filter, frequency_scaling, padding)
    geometry = getattr(T, "geometry", None)
    if not isinstance(geometry, (ParallelBeamGeometry, FanBeamGeometry)):
        raise TypeError(f"fbp needs a RayTransform with a parallel- or fan-beam geometry, got {type(T).__name__}")
    y = check_tensor(y, "data", T.range_shape)
    check_nonempty(y, "data", len(T.range_shape))
    if isinstance(geometry, FanBeamGeometry):
        T, y = _rebin_to_parallel(T, y)
        geometry = T.geometry
    m = y.shape[-1]
    response = fbp_filter(m, geometry.det_cell, filter, frequency_scaling, padding, y.dtype, y.device)
    n_fft = 2 * m if padding else m
    q = torch.fft.irfft(torch.fft.rfft(y, n=n_fft, dim=-1) * response, n=n_fft, dim=-1)[..., :m]
    ratio = geometry.angle_weights / geometry.angle_cell     # quadrature cell / the adjoint's weight
    if not bool((ratio == 1.0).all()):
        q = q * ratio.to(dtype=q.dtype, device=q.device)[:, None]
    return T.adjoint(q.contiguous())


def _fbp_tilt_series(T, y: torch.Tensor, filter: str, frequency_scaling: float, padding: bool) -> torch.Tensor:
    """Slice-wise FBP of a tilt series: rows (along the tilt axis) into the batch, 2D FBP, rows back."""
    y = check_tensor(y, "data", T.range_shape)
    rows = fbp(T.slice_transform, y.movedim(-2, -3), filter, frequency_scaling, padding)   # (..., n_t, n_u, n_v)
    return rows.movedim(-3, rows.dim() - 3 + T.geometry.axis)


def _rebin_to_parallel(T, y: torch.Tensor) -> tuple:
    """Fan data ``(..., num_angles, det_count)`` -> ``(T_parallel, parallel data)`` (module docstring)."""
    cache = T.__dict__.setdefault("_fbp_rebinning", {})
    if "plan" not in cache:
        cache["plan"] = _rebinning_plan(T)
    T_par, index, weight = cache["plan"]
    flat = y.reshape(*y.shape[:-2], -1)
    out = (flat[..., index.to(y.device)] * weight.to(dtype=y.dtype, device=y.device)).sum(-1)
    return T_par, out


def _rebinning_plan(T) -> tuple:
    """Parallel ``RayTransform`` and bilinear gather indices/weights ``(n_theta, n_s, 4)`` into the fan data."""
    from .ray_transform import RayTransform   # fbp is imported by ray_transform's package; avoid a cycle

    g = T.geometry
    beta = np.mod(g.angles.numpy(), 2 * np.pi)
    order = np.argsort(beta)
    beta_sorted = beta[order]
    gaps = np.diff(np.concatenate([beta_sorted, beta_sorted[:1] + 2 * np.pi]))
    if gaps.max() > 3 * 2 * np.pi / g.num_angles:
        raise ValueError(f"fan-beam fbp needs angles over a full turn; the largest gap between angles is "
                         f"{np.degrees(gaps.max()):.1f} degrees for {g.num_angles} angles")
    radius, length = g.src_radius, g.src_radius + g.det_radius
    s_lo, s_hi = (radius * math.sin(math.atan(u / length)) for u in (g.det_min, g.det_max))
    par = ParallelBeamGeometry(g.num_angles, g.det_count, s_lo, s_hi,
                               angles=np.arange(g.num_angles) * (2 * np.pi / g.num_angles), angle_unit="rad")
    gamma = np.arcsin(par.det_points.numpy() / radius)[None, :]
    b = np.mod(par.angles.numpy()[:, None] + gamma, 2 * np.pi)                 # fan angle of each parallel ray
    u = (length * np.tan(gamma) - g.det_min) / g.det_cell - 0.5                # fractional bin index
    u = np.broadcast_to(u, b.shape)
    ext = np.concatenate([beta_sorted[-1:] - 2 * np.pi, beta_sorted, beta_sorted[:1] + 2 * np.pi])
    idx_ext = np.concatenate([order[-1:], order, order[:1]])
    j = np.clip(np.searchsorted(ext, b, side="right") - 1, 0, len(ext) - 2)
    wb = (b - ext[j]) / (ext[j + 1] - ext[j])
    k0 = np.floor(u).astype(np.int64)
    wu = u - k0
    index, weight = [], []
    for ka, wa in ((idx_ext[j], 1 - wb), (idx_ext[j + 1], wb)):
        for kd, wd in ((k0, 1 - wu), (k0 + 1, wu)):
            inside = (kd >= 0) & (kd < g.det_count)
            index.append(ka * g.det_count + np.clip(kd, 0, g.det_count - 1))
            weight.append(wa * wd * inside)
    return (RayTransform(T.domain, par), torch.from_numpy(np.stack(index, -1)),
            torch.from_numpy(np.stack(weight, -1)))
