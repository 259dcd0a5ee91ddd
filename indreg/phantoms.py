"""Targets and templates of the paper's test suites, sampled on any :class:`~indreg.domain.ImageDomain`.

Convention:
    - Every phantom is a function ``f(domain) -> float64 tensor (nx, ny)`` on the CPU: axis 0 is x,
      axis 1 is y, values at the domain's cell centres. Show a phantom upright with ``np.rot90(a)``.
    - Raster phantoms (J, V, six objects) are functions on the paper's frame ``[-16, 16]^2``: the stored
      pixels are linear-interpolation nodes at their cell centres, the function is zero beyond the frame
      (falling linearly to zero within half a stored pixel of its edge), and it is sampled at the
      requested domain's cell centres (a domain's box may differ from ``[-16, 16]^2``).
    - Ellipse phantoms are analytic, in the normalised frame ``[-1, 1]^2`` that maps affinely onto the
      domain's box ``[min_pt, max_pt]``; each pixel is the mean of ``supersample x supersample`` point
      values inside it (anti-aliasing). Ellipse rows are
      ``(value, semi-axis x, semi-axis y, centre x, centre y, rotation in degrees)``, y pointing up, and a
      point ``p`` is inside when ``|R(rotation) (p - centre) / axes| <= 1`` with
      ``R(t) = [[cos t, sin t], [-sin t, cos t]]`` (ODL's ellipsoid phantom).

Names for :func:`get`: ``"j"``, ``"v"`` (suite 1), ``"six_objects_target"``, ``"six_objects_template"``
(suite 2), ``"shepp_logan"``, ``"shepp_logan_template"`` (suite 3), ``"shepp_logan_template_missing"``,
``"shepp_logan_template_extra"`` (suite 4), ``"shepp_logan_template_contrast"`` (metamorphosis).
"""
from __future__ import annotations

import math
from functools import lru_cache
from importlib import resources

import numpy as np
import torch
from scipy import ndimage

from ._checks import check_int
from .domain import ImageDomain

#: The frame ``[-16, 16]^2`` on which the raster phantoms are defined (the paper's image domain).
RASTER_FRAME = ((-16.0, -16.0), (16.0, 16.0))

#: Modified Shepp-Logan (Toft's intensities): the standard 10 ellipses, y up, rotation in degrees.
SHEPP_LOGAN_ELLIPSES = (
    (1.00, .6900, .9200, 0.0000, 0.0000, 0.0),
    (-.80, .6624, .8740, 0.0000, -.0184, 0.0),
    (-.20, .1100, .3100, 0.2200, 0.0000, -18.0),
    (-.20, .1600, .4100, -.2200, 0.0000, 18.0),
    (0.10, .2100, .2500, 0.0000, 0.3500, 0.0),
    (0.10, .0460, .0460, 0.0000, 0.1000, 0.0),
    (0.10, .0460, .0460, 0.0000, -.1000, 0.0),
    (0.10, .0460, .0230, -.0800, -.6050, 0.0),
    (0.10, .0230, .0230, 0.0000, -.6060, 0.0),
    (0.10, .0230, .0460, 0.0600, -.6050, 0.0),
)

#: Suite-3 template: the authors' "compressed" ellipse list with the modified intensities (docs/paper_notes.md).
SHEPP_LOGAN_TEMPLATE_ELLIPSES = (
    (1.00, .6000, .6000, 0.0000, 0.1200, 0.0),
    (-.80, .5624, .5640, 0.0000, 0.1016, 0.0),
    (-.20, .1100, .1100, 0.2600, 0.1500, -18.0),
    (-.20, .1300, .1300, -.2500, 0.2000, 18.0),
    (0.10, .1650, .1650, 0.0000, 0.3000, 0.0),
    (0.10, .0300, .0300, 0.0000, 0.1400, 0.0),
    (0.10, .0300, .0300, -.1400, 0.1000, 0.0),
    (0.10, .0360, .0230, -.0770, -.2050, 0.0),
    (0.10, .0230, .0230, 0.0000, -.2060, 0.0),
    (0.10, .0230, .0360, 0.0600, -.2050, 0.0),
)

#: Suite 4, first case: the suite-3 template without its larger dark ventricle (row 3, centre (-0.25, 0.2)).
SHEPP_LOGAN_TEMPLATE_MISSING_ELLIPSES = SHEPP_LOGAN_TEMPLATE_ELLIPSES[:3] + SHEPP_LOGAN_TEMPLATE_ELLIPSES[4:]

#: Suite 4, second case: the suite-3 template plus a bright disc (value +0.3, radius 0.08, centre
#: (-0.25, -0.15)) in the lower left of the brain, clear of every other ellipse; the target has nothing there.
SHEPP_LOGAN_TEMPLATE_EXTRA_ELLIPSES = SHEPP_LOGAN_TEMPLATE_ELLIPSES + ((0.30, .0800, .0800, -.2500, -.1500, 0.0),)


def ellipse_phantom(domain: ImageDomain, ellipses, supersample: int = 4) -> torch.Tensor:
    """Sum of constant-valued ellipses, averaged over ``supersample^2`` points per pixel.

    Convention:
        ``ellipses`` rows are ``(value, a, b, cx, cy, rotation_deg)`` in the normalised frame ``[-1, 1]^2``
        mapped onto ``[min_pt, max_pt]`` (module docstring); returns float64 ``(nx, ny)``. The integral of one
        ellipse over the domain is ``value * pi * a * b * extent_x * extent_y / 4`` up to the sub-sampling error.
    """
    s = check_int(supersample, "supersample", 1)
    nx, ny = domain.shape
    # sub-sample positions in normalised coordinates: cell (i, k) of the fine grid of (s nx) x (s ny) cells
    u = (torch.arange(s * nx, dtype=torch.float64) + 0.5) * (2.0 / (s * nx)) - 1.0
    v = (torch.arange(s * ny, dtype=torch.float64) + 0.5) * (2.0 / (s * ny)) - 1.0
    X, Y = torch.meshgrid(u, v, indexing="ij")
    fine = torch.zeros_like(X)
    for row in ellipses:
        if len(row) != 6:
            raise ValueError(f"each ellipse must have 6 entries (value, a, b, cx, cy, rotation_deg), got {row!r}")
        value, a, b, cx, cy, rot = (float(r) for r in row)
        if not (a > 0 and b > 0):
            raise ValueError(f"ellipse semi-axes must be > 0, got a={a}, b={b}")
        c, sn = math.cos(math.radians(rot)), math.sin(math.radians(rot))
        dx, dy = X - cx, Y - cy
        inside = ((c * dx + sn * dy) / a) ** 2 + ((-sn * dx + c * dy) / b) ** 2 <= 1.0
        fine = fine + value * inside.to(fine.dtype)
    return fine.reshape(nx, s, ny, s).mean(dim=(1, 3))


def shepp_logan(domain: ImageDomain) -> torch.Tensor:
    """Suite-3 target: the modified Shepp-Logan phantom (intensities 1.0, -0.8, -0.2, -0.2, 0.1 x 6).

    Upright under ``np.rot90``: the three small ellipses are at the bottom (negative y). Values: 1.0 on the
    skull rim, 0.2 in the brain, 0.0 in the ventricles, 0.3 in the small ellipses.
    """
    return ellipse_phantom(domain, SHEPP_LOGAN_ELLIPSES)


def shepp_logan_template(domain: ImageDomain) -> torch.Tensor:
    """Suite-3 template: the authors' "compressed" ellipse list, modified Shepp-Logan intensities."""
    return ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_ELLIPSES)


def shepp_logan_template_missing(domain: ImageDomain) -> torch.Tensor:
    """Suite-4 template lacking an object of the target: the suite-3 template without its larger dark
    ventricle (radius 0.13, centre (-0.25, 0.2), left half). The paper's image is not public; this is our choice.
    """
    return ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_MISSING_ELLIPSES)


def shepp_logan_template_extra(domain: ImageDomain) -> torch.Tensor:
    """Suite-4 template with an object the target lacks: the suite-3 template plus a bright disc of
    value +0.3 (0.5 on the 0.2 brain), radius 0.08, centre (-0.25, -0.15), lower left of the brain, touching
    no other ellipse. The paper's image is not public; this is our choice.
    """
    return ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_EXTRA_ELLIPSES)


def shepp_logan_template_contrast(domain: ImageDomain) -> torch.Tensor:
    """The suite-3 template with other grey values (an atlas or a scan of another contrast): ``0.6 I + 0.1``
    on the head (where the head's outer ellipse covers the pixel), 0 outside. Skull 0.7, brain 0.22,
    ventricles 0.1 where the target has 1.0, 0.2, 0.0: a case for metamorphosis (LDDMM cannot change them)."""
    template = shepp_logan_template(domain)
    head = ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_ELLIPSES[:1]) / SHEPP_LOGAN_TEMPLATE_ELLIPSES[0][0]
    return 0.6 * template + 0.1 * head


@lru_cache(maxsize=None)
def _raster(filename: str) -> np.ndarray:
    """Package data as float64 with axis 0 = x (read-only, cached)."""
    ref = resources.files("indreg").joinpath("data", filename)
    with resources.as_file(ref) as path:
        if filename.endswith(".npy"):
            img = np.load(path).astype(np.float64)
        else:
            from skimage.io import imread

            raw = imread(path, as_gray=True)
            img = raw.astype(np.float64) / np.iinfo(raw.dtype).max  # integer grey levels -> [0, 1]
            img = np.rot90(img, -1)  # as the authors' code: row-major PNG -> axis 0 = x, axis 1 = y
    img = np.ascontiguousarray(img)
    img.setflags(write=False)
    return img


def sample_raster(img: np.ndarray, domain: ImageDomain) -> torch.Tensor:
    """Sample a raster ``img`` (axis 0 = x, cell centres on ``[-16, 16]^2``) at the domain's cell centres.

    Linear interpolation, zero beyond the frame (``scipy.ndimage.map_coordinates``, ``grid-constant``).
    On the raster's own grid the values are returned unchanged.
    """
    (lo, hi), n = RASTER_FRAME, img.shape
    if domain.shape == n and domain.min_pt == lo and domain.max_pt == hi:
        return torch.from_numpy(img.copy())
    x, y = (a.numpy() for a in domain.axes())
    ix = (x - lo[0]) / ((hi[0] - lo[0]) / n[0]) - 0.5  # fractional index of the raster's cell centres
    iy = (y - lo[1]) / ((hi[1] - lo[1]) / n[1]) - 0.5
    coords = np.stack(np.meshgrid(ix, iy, indexing="ij"))
    out = ndimage.map_coordinates(img, coords, order=1, mode="grid-constant", cval=0.0)
    return torch.from_numpy(out)


def j(domain: ImageDomain) -> torch.Tensor:
    """Suite-1 template: the letter J (``data/j.png``, 64 x 64, grey values in [0, 1])."""
    return sample_raster(_raster("j.png"), domain)


def v(domain: ImageDomain) -> torch.Tensor:
    """Suite-1 target: the letter V (``data/v.png``, 64 x 64, grey values in [0, 1])."""
    return sample_raster(_raster("v.png"), domain)


def six_objects_target(domain: ImageDomain) -> torch.Tensor:
    """Suite-2 target: six star-like objects (public 256 x 256 copy of the 438 x 438 original)."""
    return sample_raster(_raster("six_objects_target_256.npy"), domain)


def six_objects_template(domain: ImageDomain) -> torch.Tensor:
    """Suite-2 template: six triangles (public 256 x 256 copy of the 438 x 438 original)."""
    return sample_raster(_raster("six_objects_template_256.npy"), domain)


_REGISTRY = {
    "j": j,
    "v": v,
    "six_objects_target": six_objects_target,
    "six_objects_template": six_objects_template,
    "shepp_logan": shepp_logan,
    "shepp_logan_template": shepp_logan_template,
    "shepp_logan_template_missing": shepp_logan_template_missing,
    "shepp_logan_template_extra": shepp_logan_template_extra,
    "shepp_logan_template_contrast": shepp_logan_template_contrast,
}


def names() -> list:
    """Names accepted by :func:`get`."""
    return list(_REGISTRY)


def get(name: str, domain: ImageDomain) -> torch.Tensor:
    """The phantom called ``name`` sampled on ``domain``: float64 ``(nx, ny)``."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown phantom {name!r}; valid names: {', '.join(names())}")
    if not isinstance(domain, ImageDomain):
        raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
    return _REGISTRY[name](domain)
