"""Other tools' conventions for 2D images and parallel-beam sinograms, converted to indreg's (``convention=``).

indreg's convention (``"indreg"``): an image ``f`` is ``(nx, ny)`` with array axis 0 = x and axis 1 = y on the
centred square ``[-half_width, half_width]^2``; a sinogram is ``(num_angles, det_count)`` of line integrals in the
domain's length unit; the angle ``theta`` is that of the detector direction ``w = (cos theta, sin theta)``; bins run
along ``w``. Each other convention names what differs, and :func:`image_to_indreg`, :func:`sinogram_to_indreg`,
:func:`angles_to_indreg`, :func:`domain_for` and :func:`detector_for` convert (the ``*_from_indreg`` functions
convert back, for export).

Convention:
    - ``image``: how an array file (``.npy``, ``.npz``, ``.h5``, ``.mrc``) holds an image: ``"xy"`` (axis 0 = x,
      indreg's), ``"displayed"`` (rows = y from the top down, columns = x: ``f = np.rot90(a, k=-1)``) or ``"yx"``
      (rows = y from the bottom up, MRC sections as IMOD shows them: ``f = a.T``). Pictures (``.png``, ``.tif``)
      are always read as displayed, whatever the convention.
    - ``sinogram``: ``"angle_bin"`` (rows = angles) or ``"bin_angle"`` (columns = angles: transposed).
    - ``angle_sense`` and ``angle_offset`` (degrees): indreg's angle = ``angle_sense`` x the tool's angle +
      ``angle_offset``. ``angle_sense = -1`` for IMOD: its ``tilt`` projects the point ``(x, z)`` of a section to
      ``x cos b - z sin b`` (docs/file_formats.md, "IMOD's projection convention"), indreg to ``x cos t + z sin t``;
      ``angle_offset`` is 0 for every tool here (kept for other tools).
    - ``pixel_units``: the data are line integrals in pixels, i.e. pixel sums (multiplied by the pixel side ``h`` on
      reading).
    - ``bins``: the detector when ``det_min`` / ``det_max`` are not given: ``"fit"`` (indreg fits it to the
      domain), ``"middle"`` (one pixel a bin, centred on the rotation axis) or ``"index"`` (one pixel a bin, bin
      ``D // 2`` on the rotation axis, which is the image's pixel ``n // 2`` in rows and columns: the domain is
      shifted by half a pixel for even ``n``, scikit-image's centre).
    - Arrays handed to ``indreg.load`` follow the same ``image`` and ``sinogram`` layouts as array files. Angles
      are radians here (``angle_unit`` is converted before).
    - The orientation check (:func:`orientation_scores`, :func:`orientation_hint`, :func:`flip_hint`) projects the
      template as each convention reads it (or mirrored) on a copy of at most 64^2 pixels and 18 angles and
      correlates the projection with the data; a reading better by :data:`MARGIN` is named in a warning.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..domain import ImageDomain

__all__ = ["Convention", "CONVENTIONS", "INTEGER_SCALES", "get_convention", "image_to_indreg", "image_from_indreg",
           "sinogram_layout", "sinogram_units", "sinogram_to_indreg", "sinogram_from_indreg", "angles_to_indreg",
           "angles_from_indreg", "domain_for", "detector_for", "describe_image", "describe_sinogram",
           "orientation_scores", "orientation_hint", "flip_hint"]

#: How 8- and 16-bit pictures are read: ``fraction`` of the full scale (value / 255, / 65535) or ``raw`` values.
INTEGER_SCALES = ("fraction", "raw")


@dataclass(frozen=True)
class Convention:
    """One tool's layout, angles, units and detector centre (module docstring); ``source``: where it comes from."""
    name: str
    image: str = "xy"
    sinogram: str = "angle_bin"
    angle_sense: float = 1.0
    angle_offset: float = 0.0
    pixel_units: bool = False
    bins: str = "fit"
    source: str = ""


CONVENTIONS = {c.name: c for c in (
    Convention("indreg", source="indreg's own (docs/geometry.md)"),
    Convention("odl", source="ODL's Parallel2dGeometry defaults on uniform_discr: indreg's (docs/geometry.md)"),
    Convention("skimage", image="displayed", sinogram="bin_angle", pixel_units=True, bins="index",
               source="skimage.transform.radon: picture in, (bins, angles) out, pixel sums, centre n // 2"),
    Convention("astra", image="displayed", pixel_units=True, bins="middle",
               source="ASTRA 'parallel' on its default volume (one unit a pixel), detector centred"),
    Convention("tomopy", image="displayed", pixel_units=True, bins="middle",
               source="tomopy.project / recon: ASTRA's (libtomo calc_coords: rays along (cos, sin) of the slice's "
                      "(row, column) axes, bins along (-sin, cos), centre = det_count / 2)"),
    Convention("imod", image="yx", angle_sense=-1.0, pixel_units=True, bins="middle",
               source="IMOD / MRC: sections (Y, X) with Y up, one row of a tilt series, tilt axis centred; tilt's "
                      "projection x cos b - z sin b (flib/tilt/tilt.f90: sinBeta = -sin), pixel sums"),
)}


def get_convention(name, key: str = "convention") -> Convention:
    """The :class:`Convention` called ``name``; anything else is a one-line ``ValueError`` naming ``key``."""
    if isinstance(name, Convention):
        return name
    if name not in CONVENTIONS:
        raise ValueError(f"{key} must be one of {', '.join(CONVENTIONS)}, got {name!r}")
    return CONVENTIONS[name]


# --- arrays ---------------------------------------------------------------------------------------------------

def image_to_indreg(a: np.ndarray, convention, picture: bool = False) -> np.ndarray:
    """An image array as read from a file, ``(nx, ny)`` in indreg's layout (pictures: always as displayed)."""
    layout = "displayed" if picture else get_convention(convention).image
    if layout == "displayed":
        return np.ascontiguousarray(np.rot90(a, k=-1))
    return np.ascontiguousarray(a.T) if layout == "yx" else a


def image_from_indreg(f: np.ndarray, convention) -> np.ndarray:
    """The array the tool holds for indreg's image ``f`` (the inverse of :func:`image_to_indreg` on arrays)."""
    layout = get_convention(convention).image
    if layout == "displayed":
        return np.ascontiguousarray(np.rot90(f))
    return np.ascontiguousarray(f.T) if layout == "yx" else f


def sinogram_layout(g: np.ndarray, convention) -> np.ndarray:
    """The tool's sinogram array as ``(num_angles, det_count)`` (transposed for ``bin_angle``)."""
    return np.ascontiguousarray(g.T) if get_convention(convention).sinogram == "bin_angle" else g


def sinogram_units(g: np.ndarray, convention, h: float) -> np.ndarray:
    """Line integrals in the domain's length unit: pixel sums times the pixel side ``h`` (``pixel_units``)."""
    return g * h if get_convention(convention).pixel_units else g


def sinogram_to_indreg(g: np.ndarray, convention, h: float = 1.0) -> np.ndarray:
    """The tool's sinogram as indreg's ``(num_angles, det_count)`` in the domain's length unit (pixel side ``h``)."""
    return sinogram_units(sinogram_layout(g, convention), convention, h)


def sinogram_from_indreg(g: np.ndarray, convention, h: float = 1.0) -> np.ndarray:
    """The inverse of :func:`sinogram_to_indreg`."""
    c = get_convention(convention)
    out = g / h if c.pixel_units else g
    return np.ascontiguousarray(out.T if c.sinogram == "bin_angle" else out)


def angles_to_indreg(radians: np.ndarray, convention) -> np.ndarray:
    """The tool's angles (radians) as indreg's: ``angle_sense * angle + angle_offset``."""
    c = get_convention(convention)
    return c.angle_sense * np.asarray(radians, dtype=np.float64) + math.radians(c.angle_offset)


def angles_from_indreg(radians: np.ndarray, convention) -> np.ndarray:
    """The inverse of :func:`angles_to_indreg`."""
    c = get_convention(convention)
    return (np.asarray(radians, dtype=np.float64) - math.radians(c.angle_offset)) / c.angle_sense


# --- domain and detector ----------------------------------------------------------------------------------------

def domain_for(convention, n: int, half_width: float) -> ImageDomain:
    """``n x n`` cells of side ``h = 2 half_width / n``: centred, or (``bins="index"``) with the centre of the
    displayed pixel ``(n // 2, n // 2)`` at the origin (x index ``n // 2``, y index ``n - 1 - n // 2``)."""
    if get_convention(convention).bins != "index":
        return ImageDomain((n, n), (-half_width,) * 2, (half_width,) * 2)
    h, c = 2.0 * half_width / n, n // 2
    return ImageDomain((n, n), (-(c + 0.5) * h, -(n - c - 0.5) * h), ((n - c - 0.5) * h, (c + 0.5) * h))


def detector_for(convention, det_count: int, h: float, det_min=None, det_max=None) -> tuple:
    """``(det_min, det_max)``: the given ones, else the convention's (``(None, None)``: fitted by indreg)."""
    bins = get_convention(convention).bins
    if det_min is not None or det_max is not None or bins == "fit":
        return det_min, det_max
    if bins == "middle":
        return -det_count * h / 2, det_count * h / 2
    c = det_count // 2
    return -(c + 0.5) * h, (det_count - c - 0.5) * h


# --- what the loader says ------------------------------------------------------------------------------------------

def describe_image(suffix: str, convention, picture: bool) -> str:
    """How an image file was read, for the loader's message."""
    c = get_convention(convention)
    layout = "displayed" if picture else c.image
    if layout == "displayed":
        how = "as displayed (rows = y top-down, columns = x), converted to axis 0 = x"
    elif layout == "yx":
        how = "as MRC sections (rows = y bottom-up, columns = x), transposed to axis 0 = x"
    else:
        how = "as stored: axis 0 = x, axis 1 = y"
    return f"{suffix} read {how} (convention {c.name})"


def describe_sinogram(convention) -> str:
    """How a sinogram was read, for the loader's message."""
    c = get_convention(convention)
    parts = ["(bins, angles), transposed" if c.sinogram == "bin_angle" else "rows = angles, columns = bins"]
    if c.angle_sense < 0:
        parts.append("angles negated (the opposite sense of rotation)")
    if c.angle_offset:
        parts.append(f"angles + {c.angle_offset:g} degrees")
    if c.pixel_units:
        parts.append("pixel units times the pixel side")
    if c.bins != "fit":
        parts.append("one pixel a bin, " + ("bin det_count // 2 on the axis" if c.bins == "index" else "centred"))
    return f"read as {'; '.join(parts)} (convention {c.name})"


# --- orientation check ------------------------------------------------------------------------------------------

#: A convention whose reading fits the data better by this much correlation is named in a warning.
MARGIN = 0.1
#: Readings within this correlation of the best are named with it (ASTRA's picture and IMOD's section with its
#: angles are one reading: the displayed picture is the section mirrored, and the mirror negates the angles).
TIE = 0.01
#: The check runs on at most this many pixels a side and angles (block means, evenly chosen rows): milliseconds.
CHECK_PIXELS, CHECK_ANGLES = 64, 18


def _correlation(a, b) -> float:
    a, b = (np.asarray(v, dtype=np.float64).ravel() for v in (a, b))
    a, b = a - a.mean(), b - b.mean()
    norm = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float(a @ b) / norm if norm > 0 else 0.0


def _distinct() -> dict:
    """One convention per distinct reading (``odl`` reads as ``indreg``, ``tomopy`` as ``astra``): ``{first: names}``."""
    groups: dict = {}
    for c in CONVENTIONS.values():
        key = (c.image, c.sinogram, c.angle_sense, c.angle_offset, c.pixel_units, c.bins)
        groups.setdefault(key, []).append(c.name)
    return {names[0]: names for names in groups.values()}


def _fit(stored_f, stored_g, radians, convention, half_width: float, det_min, det_max, picture: bool):
    """``(correlation, transposed)`` of the parallel-beam projection of the template, read in ``convention``, with
    the data read so, on a coarse copy of the problem; the data are taken transposed (``transposed=True``) if their
    rows are then not one per angle, and ``None`` is returned if neither way fits."""
    import torch
    import torch.nn.functional as F

    from ..forward import ParallelBeamGeometry, RayTransform

    c = get_convention(convention)
    g, transposed = sinogram_layout(stored_g, c), False
    if g.shape[0] != radians.size:
        g, transposed = np.ascontiguousarray(g.T), True
    if g.shape[0] != radians.size:
        return None
    rows = np.unique(np.linspace(0, radians.size - 1, min(radians.size, CHECK_ANGLES)).round().astype(int))
    f = torch.as_tensor(image_to_indreg(stored_f, c, picture))
    n = f.shape[0]
    m = min(n, CHECK_PIXELS)
    small = F.interpolate(f[None, None], size=(m, m), mode="area")[0, 0] if m < n else f
    lo, hi = detector_for(c, g.shape[1], 2.0 * half_width / n, det_min, det_max)
    geometry = ParallelBeamGeometry(angles=torch.as_tensor(angles_to_indreg(radians[rows], c)),
                                    det_count=g.shape[1], det_min=lo, det_max=hi)
    projection = RayTransform(domain_for(c, m, half_width), geometry)(small.contiguous())
    return _correlation(projection.numpy(), g[rows]), transposed


def orientation_scores(stored_f, stored_g, radians, half_width: float, det_min=None, det_max=None,
                       picture: bool = False) -> dict:
    """``{convention: (correlation, transposed)}`` of the template's projection with the data, each read in that
    convention (``transposed``: the sinogram only fits transposed from that convention's layout).

    ``stored_f``, ``stored_g``: the arrays as stored (a picture's as displayed, with ``picture=True``),
    ``radians``: the angles as given; ``det_min`` / ``det_max``: the user's, if any."""
    scores = {}
    for name in _distinct():
        if picture and CONVENTIONS[name].angle_sense < 0:   # no tool of the other sense writes pictures: a picture
            continue                                         # upside down is flip_hint's
        score = _fit(stored_f, stored_g, np.asarray(radians), name, half_width, det_min, det_max, picture)
        if score is not None:
            scores[name] = score
    return scores


def orientation_hint(scores: dict, current) -> str | None:
    """A one-line hint naming the convention whose reading fits the data clearly better than ``current``'s."""
    c = get_convention(current)
    own = next(name for name, names in _distinct().items() if c.name in names)
    best = max(scores, key=lambda name: scores[name][0], default=own)
    if own not in scores or best == own or scores[best][0] < scores[own][0] + MARGIN:
        return None
    tied = [name for name in scores if scores[name][0] >= scores[best][0] - TIE]   # no telling them apart here
    names = " or ".join(n for name in sorted(tied, key=lambda k: -scores[k][0]) for n in _distinct()[name])
    listed = ", ".join(f"{name} {value:.2f}" for name, (value, _) in sorted(scores.items(), key=lambda kv: -kv[1][0]))
    layout = "(bins, angles)" if CONVENTIONS[best].sinogram == "bin_angle" else "(angles, bins)"
    swapped = f", with the sinogram's axes swapped ({best}'s is {layout})" if scores[best][1] else ""
    return (f"read as convention {c.name}, the template's projection correlates {scores[own][0]:.2f} with the "
            f"data; read as {names}, {scores[best][0]:.2f} ({listed}): the files probably follow {names}{swapped}")


#: Mirror images no convention makes: a picture saved upside down, an array saved transposed.
_FLIPS = {"flipped along y (np.flip(f, 1): a picture upside down?)": lambda f: f[:, ::-1],
          "flipped along x (np.flip(f, 0))": lambda f: f[::-1],
          "transposed (f.T)": lambda f: f.T}


def flip_hint(f, g, radians, convention, half_width: float, det_min=None, det_max=None) -> str | None:
    """A one-line hint when the template ``f`` (indreg's layout, as read in ``convention``) fits the data ``g``
    clearly better mirrored (:data:`_FLIPS`); ``radians``: the angles as given; ``None`` otherwise."""
    c = get_convention(convention)
    stored_g = g.T if c.sinogram == "bin_angle" else g

    def score(image):
        stored = image_from_indreg(np.ascontiguousarray(image), c)
        return _fit(stored, stored_g, np.asarray(radians), c, half_width, det_min, det_max, False)

    own = score(f)
    scores = {name: score(flip(f)) for name, flip in _FLIPS.items()}
    best = max(scores, key=lambda name: scores[name][0])
    if own is None or scores[best][0] < own[0] + MARGIN:
        return None
    return (f"the template's projection correlates {own[0]:.2f} with the data, {scores[best][0]:.2f} with the "
            f"template {best}: check the template's orientation")
