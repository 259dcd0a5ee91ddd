"""A simulated dynamic acquisition: a breathing Shepp-Logan phantom scanned a few angles at a time
(docs/spatiotemporal.md).

Motion: in the phantom's normalised frame ``u in [-1, 1]^2`` the object at time ``t`` is ``f_t(u) = I(y_t(u))``
with the backward map (``phi_{t,0}``)

    y_t(u) = (u_x (1 - a(t) g(u)), u_y (1 - c a(t) g(u))),   g(u) = exp(-|u|^2 / (2 s^2)),   a(t) = A sin(pi t)^2,

a smooth anisotropic expansion about the centre that peaks at ``t = 1/2`` and is back at ``t = 1`` (one breath);
``I`` = the modified Shepp-Logan phantom (``phantoms.shepp_logan``), ``f_0 = I``. For ``A < 1`` the map is a
diffeomorphism. Frames are cell means over ``supersample^2`` points of the exact warped ellipses.

Acquisition: ``K`` frames at ``t_k = k / K`` (``k = 1..K``), frame ``k`` with ``per_frame`` parallel-beam angles
``(k - 1 + K j) pi / (K per_frame)``, ``j = 0..per_frame-1``: the ``K per_frame`` angles of all frames together
are uniform on ``[0, pi)``; white noise at ``snr_db`` per frame (``indreg.noise``, the code's convention).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .domain import ImageDomain
from .phantoms import SHEPP_LOGAN_ELLIPSES, ellipse_values


def breathing(t: float, amplitude: float = 0.4, anisotropy: float = 0.6, width: float = 0.5):
    """``u -> y_t(u)`` (module docstring) on normalised points ``u`` ``(2, ...)``."""
    a = amplitude * math.sin(math.pi * t) ** 2

    def backward(u: torch.Tensor) -> torch.Tensor:
        g = torch.exp(-(u[0] ** 2 + u[1] ** 2) / (2 * width ** 2))
        return torch.stack([u[0] * (1 - a * g), u[1] * (1 - anisotropy * a * g)])
    return backward


def _normalised(domain: ImageDomain, supersample: int) -> torch.Tensor:
    s = supersample
    axes = [(torch.arange(s * n, dtype=torch.float64) + 0.5) * (2.0 / (s * n)) - 1.0 for n in domain.shape]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"))


def frame(domain: ImageDomain, t: float, amplitude: float = 0.4, supersample: int = 4) -> torch.Tensor:
    """``f_t`` ``(nx, ny)`` float64: the phantom warped by ``y_t``, cell means."""
    nx, ny = domain.shape
    y = breathing(t, amplitude)(_normalised(domain, supersample))
    return ellipse_values(SHEPP_LOGAN_ELLIPSES, y[0], y[1]).reshape(nx, supersample, ny, supersample).mean(dim=(1, 3))


def displacement(domain: ImageDomain, t: float, amplitude: float = 0.4) -> torch.Tensor:
    """``phi_{t,0}(x) - x`` at the pixel centres, physical units, ``(2, nx, ny)``."""
    u = _normalised(domain, 1)
    half = torch.tensor([(b - a) / 2 for a, b in zip(domain.min_pt, domain.max_pt)], dtype=torch.float64)
    return (breathing(t, amplitude)(u) - u) * half.reshape(2, 1, 1)


def frame_angles(k: int, frames: int, per_frame: int) -> list:
    """Frame ``k``'s (0-based) angles ``(k + K j) pi / (K per_frame)``."""
    return [(k + frames * j) * math.pi / (frames * per_frame) for j in range(per_frame)]


@dataclass
class DynamicData:
    """A simulated dynamic acquisition (float64, CPU). ``template`` = ``f_0``; ``frames`` ``(K, nx, ny)`` the true
    ``f_{t_k}``; ``motion`` ``(K, 2, nx, ny)`` the true ``phi_{t_k,0} - Id`` (physical units); ``operators`` one
    ``RayTransform`` per frame; ``clean`` / ``data`` ``(K, per_frame, det_count)``."""
    domain: ImageDomain
    times: list
    template: torch.Tensor
    frames: torch.Tensor
    motion: torch.Tensor
    operators: list
    clean: torch.Tensor
    data: torch.Tensor
    snr_db: float


def acquisition(size: int = 64, frames: int = 12, per_frame: int = 5, det_count: int = 92, amplitude: float = 0.4,
                snr_db: float = 15.0, seed: int = 0) -> DynamicData:
    """The breathing phantom on ``ImageDomain.paper(size)`` measured as in the module docstring."""
    from .forward import ParallelBeamGeometry, RayTransform
    from .noise import add_white_noise

    domain = ImageDomain.paper(size)
    times = [(k + 1) / frames for k in range(frames)]
    truth = torch.stack([frame(domain, t, amplitude) for t in times])
    motion = torch.stack([displacement(domain, t, amplitude) for t in times])
    ops = [RayTransform(domain, ParallelBeamGeometry(angles=frame_angles(k, frames, per_frame), det_count=det_count,
                                                     det_min=-24.0, det_max=24.0)) for k in range(frames)]
    clean = torch.stack([T(f) for T, f in zip(ops, truth)])
    noisy = add_white_noise(clean, snr_db=snr_db, seed=seed)[0]
    return DynamicData(domain, times, frame(domain, 0.0, amplitude), truth, motion, ops, clean, noisy, snr_db)
