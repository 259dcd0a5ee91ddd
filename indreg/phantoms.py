"""Targets and templates of the paper's test suites, sampled on any :class:`~indreg.domain.ImageDomain`.

Notes
-----
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
``"shepp_logan_template_extra"`` (suite 4), ``"shepp_logan_template_contrast"`` (metamorphosis); 3D (on a
3D domain, ``(nx, ny, nz)``): ``"shepp_logan_3d"`` (template) and ``"shepp_logan_3d_swirl"`` (target) of the
electron-tomography suite ET-3D.

3D phantoms: ellipsoids in the normalised frame ``[-1, 1]^3`` mapped affinely onto the domain's box, cell
means of ``supersample^3`` points (default 2), rows ``(value, a, b, c, cx, cy, cz, phi, theta, psi)`` with
ZXZ Euler angles in degrees (``ellipsoid_rotation``); exact line integrals ``ellipsoid_line_integrals``.
The ET-3D target is the template deformed by the analytic volume-preserving swirl-and-bend ``swirl_bend``.

Longer than 450 lines: the catalogue of the paper's phantoms (its four suites, the 3D extensions), one short
function each, kept in the one module whose names ``phantoms.get`` looks up; most lines are their numbers.
"""
from __future__ import annotations

import math
from functools import lru_cache
from importlib import resources
from typing import TYPE_CHECKING

import numpy as np

from ._checks import broadcast_shapes, check_int
from .domain import ImageDomain

if TYPE_CHECKING:   # torch and scipy are imported where used: the app's preflight reads the names without them
    import torch

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

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain.
    ellipses : sequence of tuple
        Rows ``(value, a, b, cx, cy, rotation_deg)`` (Notes).
    supersample : int
        Sub-samples per pixel and axis (>= 1).

    Returns
    -------
    torch.Tensor
        Float64 ``(nx, ny)``.

    Raises
    ------
    ValueError
        A row without 6 entries, a semi-axis <= 0, ``supersample < 1``.

    Notes
    -----
    ``ellipses`` rows are ``(value, a, b, cx, cy, rotation_deg)`` in the normalised frame ``[-1, 1]^2``
    mapped onto ``[min_pt, max_pt]`` (module docstring); returns float64 ``(nx, ny)``. The integral of one
    ellipse over the domain is ``value * pi * a * b * extent_x * extent_y / 4`` up to the sub-sampling error.
    """
    import torch

    s = check_int(supersample, "supersample", 1)
    nx, ny = domain.shape
    # sub-sample positions in normalised coordinates: cell (i, k) of the fine grid of (s nx) x (s ny) cells
    u = (torch.arange(s * nx, dtype=torch.float64) + 0.5) * (2.0 / (s * nx)) - 1.0
    v = (torch.arange(s * ny, dtype=torch.float64) + 0.5) * (2.0 / (s * ny)) - 1.0
    X, Y = torch.meshgrid(u, v, indexing="ij")
    return ellipse_values(ellipses, X, Y).reshape(nx, s, ny, s).mean(dim=(1, 3))


def ellipse_values(ellipses, X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """The sum of the ellipses' values at the normalised points ``(X, Y)`` (``ellipse_phantom``'s rows).

    Parameters
    ----------
    ellipses : sequence of tuple
        Rows ``(value, a, b, cx, cy, rotation_deg)``.
    X, Y : torch.Tensor
        The points' normalised coordinates (one shape).

    Returns
    -------
    torch.Tensor
        ``X``'s shape.

    Raises
    ------
    ValueError
        A row without 6 entries, a semi-axis <= 0.
    """
    import torch

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
    return fine


def shepp_logan(domain: ImageDomain) -> torch.Tensor:
    """Suite-3 target: the modified Shepp-Logan phantom (intensities 1.0, -0.8, -0.2, -0.2, 0.1 x 6).

    Upright under ``np.rot90``: the three small ellipses are at the bottom (negative y). Values: 1.0 on the
    skull rim, 0.2 in the brain, 0.0 in the ventricles, 0.3 in the small ellipses.

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    return ellipse_phantom(domain, SHEPP_LOGAN_ELLIPSES)


def shepp_logan_template(domain: ImageDomain) -> torch.Tensor:
    """Suite-3 template: the authors' "compressed" ellipse list, modified Shepp-Logan intensities.

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    return ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_ELLIPSES)


def shepp_logan_template_missing(domain: ImageDomain) -> torch.Tensor:
    """Suite-4 template lacking an object of the target: the suite-3 template without its larger dark
    ventricle (radius 0.13, centre (-0.25, 0.2), left half). The paper's image is not public; this is our choice.

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    return ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_MISSING_ELLIPSES)


def missing_ventricle_mask(domain: ImageDomain) -> torch.Tensor:
    """Where the suite-4 "missing" template must gain an object: the pixels at least half covered by the target's
    ventricle that it lacks (row 3 of ``SHEPP_LOGAN_ELLIPSES``, centre (-0.22, 0)), ``(nx, ny)`` bool. The RMS error
    of a result inside it is the ventricle error of docs/metamorphosis.md.

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Bool ``domain.shape``.
    """
    return ellipse_phantom(domain, ((1.0, *SHEPP_LOGAN_ELLIPSES[3][1:]),)) >= 0.5


def shepp_logan_template_extra(domain: ImageDomain) -> torch.Tensor:
    """Suite-4 template with an object the target lacks: the suite-3 template plus a bright disc of
    value +0.3 (0.5 on the 0.2 brain), radius 0.08, centre (-0.25, -0.15), lower left of the brain, touching
    no other ellipse. The paper's image is not public; this is our choice.

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    return ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_EXTRA_ELLIPSES)


def shepp_logan_template_contrast(domain: ImageDomain) -> torch.Tensor:
    """The suite-3 template with other grey values (an atlas or a scan of another contrast): ``0.6 I + 0.1``
    on the head (where the head's outer ellipse covers the pixel), 0 outside. Skull 0.7, brain 0.22,
    ventricles 0.1 where the target has 1.0, 0.2, 0.0: a case for metamorphosis (LDDMM cannot change them).

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    template = shepp_logan_template(domain)
    head = ellipse_phantom(domain, SHEPP_LOGAN_TEMPLATE_ELLIPSES[:1]) / SHEPP_LOGAN_TEMPLATE_ELLIPSES[0][0]
    return 0.6 * template + 0.1 * head


#: 3D modified Shepp-Logan (Kak & Slaney's head ellipsoids as in Schabel's ``phantom3d``, Toft's intensities):
#: rows ``(value, a, b, c, cx, cy, cz, phi, theta, psi)``, semi-axes along x, y, z and the centre in the
#: normalised frame ``[-1, 1]^3``, ZXZ Euler angles in degrees (``ellipsoid_rotation``). The slice z = 0 is
#: the 2D phantom up to the ventricles' rotation (phi + psi = -8 and 28 degrees instead of -18 and 18).
SHEPP_LOGAN_3D_ELLIPSOIDS = (
    (1.00, .6900, .9200, .8100, 0.0000, 0.0000, 0.0000, 0.0, 0.0, 0.0),
    (-.80, .6624, .8740, .7800, 0.0000, -.0184, 0.0000, 0.0, 0.0, 0.0),
    (-.20, .1100, .3100, .2200, 0.2200, 0.0000, 0.0000, -18.0, 0.0, 10.0),
    (-.20, .1600, .4100, .2800, -.2200, 0.0000, 0.0000, 18.0, 0.0, 10.0),
    (0.10, .2100, .2500, .4100, 0.0000, 0.3500, -.1500, 0.0, 0.0, 0.0),
    (0.10, .0460, .0460, .0500, 0.0000, 0.1000, 0.2500, 0.0, 0.0, 0.0),
    (0.10, .0460, .0460, .0500, 0.0000, -.1000, 0.2500, 0.0, 0.0, 0.0),
    (0.10, .0460, .0230, .0500, -.0800, -.6050, 0.0000, 0.0, 0.0, 0.0),
    (0.10, .0230, .0230, .0200, 0.0000, -.6060, 0.0000, 0.0, 0.0, 0.0),
    (0.10, .0230, .0460, .0200, 0.0600, -.6050, 0.0000, 0.0, 0.0, 0.0),
)

#: Parameters of ``swirl_bend`` (normalised frame): swirl angle at the centre (radians), its radial and axial
#: widths, and the bend's amplitude.
SWIRL_ANGLE, SWIRL_RADIUS, SWIRL_HEIGHT, BEND = 0.7, 0.45, 0.5, 0.12


def ellipsoid_rotation(phi: float, theta: float, psi: float) -> torch.Tensor:
    """ZXZ Euler rotation (degrees) ``R`` of an ellipsoid: ``p`` is inside when ``|R (p - c) / axes| <= 1``.
    With ``theta = psi = 0`` it is the 2D ``R(phi) = [[cos, sin], [-sin, cos]]`` about z (module docstring).

    Parameters
    ----------
    phi, theta, psi : float
        The ZXZ Euler angles, degrees.

    Returns
    -------
    torch.Tensor
        ``R``, float64 ``(3, 3)``.
    """
    import torch

    f, t, s = (math.radians(a) for a in (phi, theta, psi))
    cf, sf, ct, st, cs, ss = math.cos(f), math.sin(f), math.cos(t), math.sin(t), math.cos(s), math.sin(s)
    return torch.tensor([[cs * cf - ct * sf * ss, cs * sf + ct * cf * ss, ss * st],
                         [-ss * cf - ct * sf * cs, -ss * sf + ct * cf * cs, cs * st],
                         [st * sf, -st * cf, ct]], dtype=torch.float64)


def _ellipsoids(rows) -> list:
    """Checked rows as ``(value, axes (3,), centre (3,), R (3, 3))``."""
    import torch

    out = []
    for row in rows:
        if len(row) != 10:
            raise ValueError(f"each ellipsoid must have 10 entries (value, a, b, c, cx, cy, cz, phi, theta, psi), "
                             f"got {row!r}")
        r = [float(v) for v in row]
        if not all(math.isfinite(v) for v in r) or min(r[1:4]) <= 0:
            raise ValueError(f"ellipsoid entries must be finite with semi-axes > 0, got {row!r}")
        out.append((r[0], torch.tensor(r[1:4], dtype=torch.float64), torch.tensor(r[4:7], dtype=torch.float64),
                    ellipsoid_rotation(*r[7:10])))
    return out


def ellipsoid_values(ellipsoids, u: torch.Tensor) -> torch.Tensor:
    """Sum of constant-valued ellipsoids at normalised points ``u`` ``(3, ...)`` (rows as
    ``SHEPP_LOGAN_3D_ELLIPSOIDS``); returns ``u.shape[1:]``.

    Parameters
    ----------
    ellipsoids : sequence of tuple
        Rows ``(value, a, b, c, cx, cy, cz, phi, theta, psi)``.
    u : torch.Tensor
        Normalised points ``(3, ...)``.

    Returns
    -------
    torch.Tensor
        Float64 ``u.shape[1:]``.

    Raises
    ------
    ValueError
        A row without 10 entries, non-finite, or with a semi-axis <= 0.
    """
    import torch

    out = torch.zeros(u.shape[1:], dtype=torch.float64)
    for value, axes, centre, rot in _ellipsoids(ellipsoids):
        q = torch.tensordot(rot, u - centre.view(3, *([1] * (u.dim() - 1))), dims=1)
        inside = (q / axes.view(3, *([1] * (u.dim() - 1)))).pow(2).sum(0) <= 1.0
        out += value * inside.to(torch.float64)
    return out


def supersampled(domain: ImageDomain, fn, supersample: int = 2, rows: tuple | None = None) -> torch.Tensor:
    """Cell means of ``fn(u)`` over ``supersample^3`` points per cell of a 3D ``domain``; ``fn`` takes
    normalised points ``u`` ``(3, ...)`` in ``[-1, 1]^3`` (mapped affinely onto the domain's box) and returns
    values ``u.shape[1:]``. Evaluated in slabs along x of at most about 2^18 points, so that every temporary stays
    below glibc's mmap threshold (32 MiB): larger ones are mapped afresh and page-faulted at every operation, which
    made 64^3 take 5.8 s instead of 2.0 s. Returns float64 ``(nx, ny, nz)``; with ``rows = (axis, start, stop)``
    only the cells whose index along ``axis`` is in ``[start, stop)`` (that axis cut to ``stop - start``: those rows
    of the whole volume to rounding, e.g. one process's share of a tilt series' slices).

    Parameters
    ----------
    domain : ImageDomain
        A 3D domain.
    fn : callable
        ``fn(u) -> values``, ``u`` normalised points ``(3, ...)``.
    supersample : int
        Sub-samples per cell and axis (>= 1).
    rows : tuple of int, optional
        ``(axis, start, stop)``: the share of the cells along ``axis``.

    Returns
    -------
    torch.Tensor
        Float64 ``(nx, ny, nz)`` (the ``rows`` axis cut to ``stop - start``).

    Raises
    ------
    ValueError
        A domain that is not 3D, ``rows`` out of range, ``supersample < 1``.
    """
    import torch

    s = check_int(supersample, "supersample", 1)
    if domain.ndim != 3:
        raise ValueError(f"a 3D phantom needs a 3D domain, got shape {domain.shape}")
    fine = [(torch.arange(s * n, dtype=torch.float64) + 0.5) * (2.0 / (s * n)) - 1.0 for n in domain.shape]
    shape = list(domain.shape)
    if rows is not None:
        axis, start, stop = _check_rows(rows, domain.shape)
        fine[axis], shape[axis] = fine[axis][s * start: s * stop], stop - start
    nx, ny, nz = shape
    step = max(1, 2**18 // (s ** 3 * ny * nz))   # cells along x per slab
    slabs = []
    for i in range(0, nx, step):
        k = min(step, nx - i)
        u = torch.stack(torch.meshgrid(fine[0][s * i: s * (i + k)], fine[1], fine[2], indexing="ij"))
        slabs.append(fn(u).reshape(k, s, ny, s, nz, s).mean(dim=(1, 3, 5)))
    return torch.cat(slabs)


def _check_rows(rows, shape: tuple) -> tuple:
    """``rows = (axis, start, stop)`` checked against a volume's ``shape``: ``0 <= start < stop <= shape[axis]``."""
    if not (isinstance(rows, tuple) and len(rows) == 3 and all(isinstance(r, int) and not isinstance(r, bool)
                                                               for r in rows)):
        raise ValueError(f"rows must be a tuple (axis, start, stop) of integers, got {rows!r}")
    axis, start, stop = rows
    if axis not in (0, 1, 2) or not 0 <= start < stop <= shape[axis]:
        raise ValueError(f"rows (axis, start, stop) must have axis 0, 1 or 2 and 0 <= start < stop <= the "
                         f"axis' {shape[axis] if axis in (0, 1, 2) else '?'} cells, got {rows!r}")
    return axis, start, stop


def ellipsoid_phantom(domain: ImageDomain, ellipsoids, supersample: int = 2, rows: tuple | None = None) \
        -> torch.Tensor:
    """Sum of constant-valued ellipsoids on a 3D domain, averaged over ``supersample^3`` points per cell.

    Parameters
    ----------
    domain : ImageDomain
        A 3D domain.
    ellipsoids : sequence of tuple
        Rows ``(value, a, b, c, cx, cy, cz, phi, theta, psi)`` (Notes).
    supersample : int
        Sub-samples per cell and axis.
    rows : tuple of int, optional
        ``(axis, start, stop)``: a share of the cells along one axis, as :func:`supersampled`.

    Returns
    -------
    torch.Tensor
        Float64 ``(nx, ny, nz)``.

    Raises
    ------
    ValueError
        Malformed rows, a domain that is not 3D, ``rows`` out of range.

    Notes
    -----
    rows ``(value, a, b, c, cx, cy, cz, phi, theta, psi)`` in the normalised frame ``[-1, 1]^3``
    mapped affinely onto ``[min_pt, max_pt]`` (as the 2D ``ellipse_phantom``); returns float64 ``(nx, ny, nz)``
    (``rows``: a share of the cells along one axis, as ``supersampled``).
    Analytic line integrals: ``ellipsoid_line_integrals``.
    """
    table = tuple(ellipsoids)
    _ellipsoids(table)
    return supersampled(domain, lambda u: ellipsoid_values(table, u), supersample, rows)


def ellipsoid_line_integrals(ellipsoids, domain: ImageDomain, points: torch.Tensor,
                             directions: torch.Tensor) -> torch.Tensor:
    """Exact integrals of ``ellipsoid_phantom``'s function over the lines ``{p + t d : t in R}``.

    Parameters
    ----------
    ellipsoids : sequence of tuple
        Rows as :func:`ellipsoid_phantom`'s.
    domain : ImageDomain
        The 3D box the normalised frame is mapped onto.
    points : torch.Tensor
        ``p``, ``(..., 3)``, physical units (x, y, z).
    directions : torch.Tensor
        ``d``, ``(..., 3)``, unit length.

    Returns
    -------
    torch.Tensor
        Float64 ``(...)``.

    Raises
    ------
    ValueError
        Malformed rows.

    Notes
    -----
    ``points`` and ``directions`` ``(..., 3)`` in physical units (x, y, z), directions of unit
    length; returns ``(...)``. Each ellipsoid contributes ``value * chord length``: in the normalised frame
    ``u = (x - centre_box) / half_extent`` the line is ``q + t e`` (``q = R (u_p - c) / axes``,
    ``e = R (d / half_extent) / axes``) and the chord is ``2 sqrt(b^2 - |e|^2 (|q|^2 - 1)) / |e|^2``,
    ``b = q . e``, where the root is real (exact for any box, also non-cubic).
    """
    import torch

    lo, hi = (torch.tensor(v, dtype=torch.float64) for v in (domain.min_pt, domain.max_pt))
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    u, e_u = (points.to(torch.float64) - mid) / half, directions.to(torch.float64) / half
    out = torch.zeros(points.shape[:-1], dtype=torch.float64)
    for value, axes, centre, rot in _ellipsoids(ellipsoids):
        q = ((u - centre) @ rot.T) / axes
        e = (e_u @ rot.T) / axes
        a, b, c = (e * e).sum(-1), (q * e).sum(-1), (q * q).sum(-1) - 1.0
        out += value * 2.0 * (b * b - a * c).clamp(min=0).sqrt() / a
    return out


def ellipsoid_tilt_series(ellipsoids, domain: ImageDomain, geometry) -> torch.Tensor:
    """Exact tilt-series data ``(num_tilts, det_rows, det_cols)`` of ``ellipsoid_phantom(domain, ellipsoids)``
    for a resolved ``TiltSeriesGeometry`` (``TiltSeriesTransform(...).geometry``): the line through
    ``s_d w + t_j e_t`` along ``w_perp`` in the slice plane (``TiltSeriesGeometry``).

    Parameters
    ----------
    ellipsoids : sequence of tuple
        Rows as :func:`ellipsoid_phantom`'s.
    domain : ImageDomain
        The 3D domain.
    geometry : TiltSeriesGeometry
        Resolved for ``domain``.

    Returns
    -------
    torch.Tensor
        Float64 ``(num_tilts, det_rows, det_cols)``.
    """
    import torch

    u, v = geometry.slice_axes
    theta = geometry.angles[:, None, None]
    s = geometry.det_points[None, None, :]
    t = domain.axes()[geometry.axis][None, :, None]
    shape = broadcast_shapes(theta.shape, t.shape, s.shape)
    p, d = torch.zeros(*shape, 3, dtype=torch.float64), torch.zeros(*shape, 3, dtype=torch.float64)
    p[..., u], p[..., v], p[..., geometry.axis] = s * torch.cos(theta), s * torch.sin(theta), t
    d[..., u], d[..., v] = -torch.sin(theta).expand(shape), torch.cos(theta).expand(shape)
    return ellipsoid_line_integrals(ellipsoids, domain, p, d)


def swirl_bend(u: torch.Tensor, inverse: bool = False) -> torch.Tensor:
    """The smooth volume-preserving diffeomorphism ``phi = B o S`` of suite ET-3D (normalised points ``(3, ...)``).

    ``S`` swirls about the z axis: ``(r, angle, z) -> (r, angle + alpha(r, z), z)`` in cylindrical coordinates
    with ``alpha = SWIRL_ANGLE exp(-r^2 / (2 SWIRL_RADIUS^2) - z^2 / (2 SWIRL_HEIGHT^2))`` (40 degrees at the
    centre); ``B`` bends along x: ``(x, y, z) -> (x + BEND cos(pi z / 2), y, z)``. Both Jacobian matrices are
    unit-triangular in suitable coordinates, so ``det D phi = 1`` everywhere (positive, volume-preserving), and
    both are inverted in closed form (``r`` and ``z`` are invariant): ``phi^-1 = S^-1 o B^-1`` (``inverse=True``).

    Parameters
    ----------
    u : torch.Tensor
        Normalised points ``(3, ...)``.
    inverse : bool
        ``phi^-1`` instead of ``phi``.

    Returns
    -------
    torch.Tensor
        The mapped points, ``u``'s shape.
    """
    import torch

    def swirl(w, sign):
        alpha = sign * SWIRL_ANGLE * torch.exp(-(w[0] ** 2 + w[1] ** 2) / (2 * SWIRL_RADIUS ** 2)
                                               - w[2] ** 2 / (2 * SWIRL_HEIGHT ** 2))
        c, s = torch.cos(alpha), torch.sin(alpha)
        return torch.stack((c * w[0] - s * w[1], s * w[0] + c * w[1], w[2]))

    def bend(w, sign):
        return torch.stack((w[0] + sign * BEND * torch.cos(math.pi * w[2] / 2), w[1], w[2]))

    return swirl(bend(u, -1.0), -1.0) if inverse else bend(swirl(u, 1.0), 1.0)


def shepp_logan_3d(domain: ImageDomain, rows: tuple | None = None) -> torch.Tensor:
    """3D modified Shepp-Logan (``SHEPP_LOGAN_3D_ELLIPSOIDS``) on a 3D domain: suite ET-3D's template (``rows``:
    only a share of the cells along one axis, ``supersampled``).

    Parameters
    ----------
    domain : ImageDomain
        A 3D domain.
    rows : tuple of int, optional
        ``(axis, start, stop)``: only the cells whose index along ``axis`` is in ``[start, stop)``
        (:func:`supersampled`).

    Returns
    -------
    torch.Tensor
        Float64 ``(nx, ny, nz)`` (the ``rows`` axis cut to ``stop - start``).

    Raises
    ------
    ValueError
        A domain that is not 3D, ``rows`` out of range.
    """
    return ellipsoid_phantom(domain, SHEPP_LOGAN_3D_ELLIPSOIDS, rows=rows)


def shepp_logan_3d_swirl(domain: ImageDomain, rows: tuple | None = None) -> torch.Tensor:
    """Suite ET-3D's target: the 3D Shepp-Logan deformed by ``swirl_bend``, ``I o phi^-1`` evaluated exactly
    (the ellipsoids at ``phi^-1(u)``) at the sub-sample points, so no registration code is involved (``rows``: as
    ``shepp_logan_3d``).

    Parameters
    ----------
    domain : ImageDomain
        A 3D domain.
    rows : tuple of int, optional
        ``(axis, start, stop)``: only the cells whose index along ``axis`` is in ``[start, stop)``
        (:func:`supersampled`).

    Returns
    -------
    torch.Tensor
        Float64 ``(nx, ny, nz)`` (the ``rows`` axis cut to ``stop - start``).

    Raises
    ------
    ValueError
        A domain that is not 3D, ``rows`` out of range.
    """
    return supersampled(domain, lambda u: ellipsoid_values(SHEPP_LOGAN_3D_ELLIPSOIDS, swirl_bend(u, inverse=True)),
                        rows=rows)


@lru_cache(maxsize=None)
def _raster(filename: str) -> np.ndarray:
    """Package data as float64 with axis 0 = x (read-only, cached)."""
    ref = resources.files("indreg").joinpath("data", filename)
    with resources.as_file(ref) as path:
        if filename.endswith(".npy"):
            img = np.load(path).astype(np.float64)
        else:
            import imageio.v3 as iio   # the reader scikit-image's imread calls, without its plug-ins (0.3 s)

            raw = iio.imread(path)     # 8-bit grey
            img = raw.astype(np.float64) / np.iinfo(raw.dtype).max  # integer grey levels -> [0, 1]
            img = np.rot90(img, -1)  # as the authors' code: row-major PNG -> axis 0 = x, axis 1 = y
    img = np.ascontiguousarray(img)
    img.setflags(write=False)
    return img


def sample_raster(img: np.ndarray, domain: ImageDomain) -> torch.Tensor:
    """Sample a raster ``img`` (axis 0 = x, cell centres on ``[-16, 16]^2``) at the domain's cell centres.

    Linear interpolation, zero beyond the frame (``scipy.ndimage.map_coordinates``, ``grid-constant``).
    On the raster's own grid the values are returned unchanged.

    Parameters
    ----------
    img : numpy.ndarray
        The raster ``(n_x, n_y)``.
    domain : ImageDomain
        A 2D domain.

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    import torch
    from scipy import ndimage

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
    """Suite-1 template: the letter J (``data/j.png``, 64 x 64, grey values in [0, 1]).

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    return sample_raster(_raster("j.png"), domain)


def v(domain: ImageDomain) -> torch.Tensor:
    """Suite-1 target: the letter V (``data/v.png``, 64 x 64, grey values in [0, 1]).

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    return sample_raster(_raster("v.png"), domain)


def six_objects_target(domain: ImageDomain) -> torch.Tensor:
    """Suite-2 target: six star-like objects (public 256 x 256 copy of the 438 x 438 original).

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
    return sample_raster(_raster("six_objects_target_256.npy"), domain)


def six_objects_template(domain: ImageDomain) -> torch.Tensor:
    """Suite-2 template: six triangles (public 256 x 256 copy of the 438 x 438 original).

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain (the image is sampled at its cell centres).

    Returns
    -------
    torch.Tensor
        Float64 ``domain.shape``.
    """
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
    "shepp_logan_3d": shepp_logan_3d,
    "shepp_logan_3d_swirl": shepp_logan_3d_swirl,
}

#: Phantoms of volumes (3D domains); all others are 2D.
_3D = ("shepp_logan_3d", "shepp_logan_3d_swirl")


def names() -> list:
    """Names accepted by :func:`get`.

    Returns
    -------
    list of str
        The phantoms' names.
    """
    return list(_REGISTRY)


def ndim(name: str) -> int:
    """The dimension (2 or 3) of the domain the phantom ``name`` is defined on.

    Parameters
    ----------
    name : str
        A name of :func:`names`.

    Returns
    -------
    int
        2 or 3.

    Raises
    ------
    ValueError
        An unknown name (the message lists the valid ones).
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown phantom {name!r}; valid names: {', '.join(names())}")
    return 3 if name in _3D else 2


def get(name: str, domain: ImageDomain, rows: tuple | None = None) -> torch.Tensor:
    """The phantom called ``name`` sampled on ``domain``: float64 ``(nx, ny)`` or, for 3D phantoms,
    ``(nx, ny, nz)``; ``rows = (axis, start, stop)`` (3D phantoms only): the cells whose index along ``axis`` is in
    ``[start, stop)``, those rows of the whole volume to rounding (``supersampled``).

    Parameters
    ----------
    name : str
        A name of :func:`names`.
    domain : ImageDomain
        A domain of the phantom's dimension (:func:`ndim`).
    rows : tuple of int, optional
        ``(axis, start, stop)``, 3D phantoms only: the cells whose index along ``axis`` is in ``[start, stop)``,
        those rows of the whole volume to rounding (:func:`supersampled`).

    Returns
    -------
    torch.Tensor
        Float64 ``(nx, ny)`` or, for 3D phantoms, ``(nx, ny, nz)``.

    Raises
    ------
    ValueError
        An unknown name, a domain of another dimension, ``rows`` for a 2D phantom or out of range.
    TypeError
        ``domain`` is no ``ImageDomain``.
    """
    d = ndim(name)
    if not isinstance(domain, ImageDomain):
        raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
    if domain.ndim != d:
        raise ValueError(f"phantom {name!r} is {d}D but the domain has shape {domain.shape}")
    if rows is None:
        return _REGISTRY[name](domain)
    if d != 3:
        raise ValueError(f"rows: only the 3D phantoms are evaluated by rows, got the 2D phantom {name!r}")
    return _REGISTRY[name](domain, rows=rows)
