"""Ellipse phantoms for the forward-model tests: supersampled rasterisation and the closed-form Radon transform."""
import math

import pytest
import torch

# Modified Shepp-Logan (Toft): value, semi-axis a, semi-axis b, centre x, centre y, rotation (degrees),
# in the normalised frame [-1, 1]^2.
MODIFIED_SHEPP_LOGAN = (
    (1.0, 0.69, 0.92, 0.0, 0.0, 0.0),
    (-0.8, 0.6624, 0.874, 0.0, -0.0184, 0.0),
    (-0.2, 0.11, 0.31, 0.22, 0.0, -18.0),
    (-0.2, 0.16, 0.41, -0.22, 0.0, 18.0),
    (0.1, 0.21, 0.25, 0.0, 0.35, 0.0),
    (0.1, 0.046, 0.046, 0.0, 0.1, 0.0),
    (0.1, 0.046, 0.046, 0.0, -0.1, 0.0),
    (0.1, 0.046, 0.023, -0.08, -0.605, 0.0),
    (0.1, 0.023, 0.023, 0.0, -0.606, 0.0),
    (0.1, 0.023, 0.046, 0.06, -0.605, 0.0),
)


def _physical(ellipses, scale):
    """Ellipse table in physical units: (value, a, b, cx, cy, phi in radians)."""
    return [(v, a * scale, b * scale, cx * scale, cy * scale, math.radians(phi)) for v, a, b, cx, cy, phi in ellipses]


def rasterise(ellipses, domain, scale=16.0, supersample=4):
    """Pixel averages (supersample^2 points per cell) of a sum of ellipses, float64 (nx, ny)."""
    (hx, hy), k = domain.cell_sides, supersample
    sub = (torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5
    x, y = domain.axes()
    xs = (x[:, None] + sub[None, :] * hx).reshape(-1)
    ys = (y[:, None] + sub[None, :] * hy).reshape(-1)
    X, Y = torch.meshgrid(xs, ys, indexing="ij")
    img = torch.zeros_like(X)
    for v, a, b, cx, cy, phi in _physical(ellipses, scale):
        c, s = math.cos(phi), math.sin(phi)
        u, w = (X - cx) * c + (Y - cy) * s, -(X - cx) * s + (Y - cy) * c
        img += v * ((u / a) ** 2 + (w / b) ** 2 <= 1)
    nx, ny = domain.shape
    return img.reshape(nx, k, ny, k).mean(dim=(1, 3))


def radon_ellipses(ellipses, geometry, scale=16.0):
    """Closed-form line integrals p(theta, s) = 2 v a b sqrt(r^2 - t^2) / r^2, t = s - c.w, float64."""
    return line_integrals(ellipses, geometry.angles[:, None], geometry.det_points[None, :], scale)


def fan_radon_ellipses(ellipses, geometry, scale=16.0):
    """Closed-form fan-beam data: ray (beta, u) is the parallel line (beta - gamma, src_radius sin gamma),
    gamma = atan(u / (src_radius + det_radius))."""
    gamma = torch.atan(geometry.det_points[None, :] / (geometry.src_radius + geometry.det_radius))
    return line_integrals(ellipses, geometry.angles[:, None] - gamma, geometry.src_radius * torch.sin(gamma), scale)


def line_integrals(ellipses, theta, s, scale=16.0):
    """Integrals of the ellipses over the lines {s w + t w_perp}, w = (cos theta, sin theta) (broadcast)."""
    theta, s = torch.broadcast_tensors(theta, s)
    p = torch.zeros(theta.shape, dtype=torch.float64)
    for v, a, b, cx, cy, phi in _physical(ellipses, scale):
        r2 = (a * torch.cos(theta - phi)) ** 2 + (b * torch.sin(theta - phi)) ** 2
        t = s - (cx * torch.cos(theta) + cy * torch.sin(theta))
        p += 2 * v * a * b * torch.sqrt((r2 - t ** 2).clamp(min=0)) / r2
    return p


@pytest.fixture
def ellipses():
    """Namespace with the modified Shepp-Logan table and the two ellipse helpers."""
    class Ellipses:
        shepp_logan = MODIFIED_SHEPP_LOGAN
    Ellipses.rasterise = staticmethod(rasterise)
    Ellipses.radon = staticmethod(radon_ellipses)
    Ellipses.fan_radon = staticmethod(fan_radon_ellipses)
    return Ellipses
