"""Other tools' conventions for 2D images and parallel-beam sinograms, converted to indreg's (``convention=``).

indreg's convention (``"indreg"``): an image ``f`` is ``(nx, ny)`` with array axis 0 = x and axis 1 = y on the
centred square ``[-half_width, half_width]^2``; a sinogram is ``(num_angles, det_count)`` of line integrals in the
domain's length unit; the angle ``theta`` is that of the detector direction ``w = (cos theta, sin theta)``; bins run
along ``w``. Each other convention names what differs, and :func:`image_to_indreg`, :func:`sinogram_to_indreg`,
:func:`angles_to_indreg`, :func:`domain_for` and :func:`detector_for` convert (the ``*_from_indreg`` functions
convert back, for export).

Notes
-----
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
- What a run gives back goes the other way: the app writes its images and data in the files' convention
  (:func:`images_from_indreg`, :func:`sinogram_from_indreg`); from Python, ``RegistrationInputs.as_given``.
- Which convention the files follow is probed at load by ``indreg.io.orientation`` (``orientation_scores``,
  ``orientation_hint``, ``flip_hint``), the one home of orientation probing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..domain import ImageDomain

__all__ = ["Convention", "CONVENTIONS", "INTEGER_SCALES", "get_convention", "image_to_indreg", "image_from_indreg",
           "images_from_indreg", "describe_layout", "sinogram_layout", "sinogram_units", "sinogram_to_indreg",
           "sinogram_from_indreg", "angles_to_indreg", "angles_from_indreg", "domain_for", "detector_for",
           "describe_image", "describe_sinogram"]

#: How 8- and 16-bit pictures are read: ``fraction`` of the full scale (value / 255, / 65535) or ``raw`` values.
INTEGER_SCALES = ("fraction", "raw")


@dataclass(frozen=True)
class Convention:
    """One tool's layout, angles, units and detector centre (module docstring); ``source``: where it comes from.

    Parameters
    ----------
    name : str
        Its name (``convention=``).
    image : {"xy", "displayed", "yx"}
        An image array's layout: indreg's ``(x, y)``, as displayed, or ``(y, x)``.
    sinogram : {"angle_bin", "bin_angle"}
        A sinogram's axes.
    angle_sense : float
        ``+1`` or ``-1``: the sense of its angles against indreg's.
    angle_offset : float
        Degrees added to its angles.
    pixel_units : bool
        Its line integrals are pixel sums (times the pixel side in indreg's).
    bins : {"fit", "index", "middle"}
        Where its detector's centre lies.
    source : str
        Where it comes from.
    """
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
    """The :class:`Convention` called ``name``; anything else is a one-line ``ValueError`` naming ``key``.

    Parameters
    ----------
    name : str or Convention
        A name of ``CONVENTIONS`` (a ``Convention`` is returned as it is).
    key : str
        The argument's name in messages.

    Returns
    -------
    Convention
        The convention.

    Raises
    ------
    ValueError
        An unknown name.
    """
    if isinstance(name, Convention):
        return name
    if name not in CONVENTIONS:
        raise ValueError(f"{key} must be one of {', '.join(CONVENTIONS)}, got {name!r}")
    return CONVENTIONS[name]


# --- arrays ---------------------------------------------------------------------------------------------------

def image_to_indreg(a: np.ndarray, convention, picture: bool = False) -> np.ndarray:
    """An image array as read from a file, ``(nx, ny)`` in indreg's layout (pictures: always as displayed).

    Parameters
    ----------
    a : numpy.ndarray
        The array as read.
    convention : str or Convention
        The tool whose layout it follows.
    picture : bool
        A picture (``.png`` / ``.tif``): as displayed, whatever the convention.

    Returns
    -------
    numpy.ndarray
        ``(nx, ny)``, axis 0 = x.
    """
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


def images_from_indreg(images, convention):
    """Images in indreg's layout as the tool holds them: :func:`image_from_indreg` on the last two axes.

    Parameters
    ----------
    images : numpy.ndarray or torch.Tensor
        ``(..., nx, ny)``, any leading axes (a stack, a trajectory).
    convention : str or Convention
        The tool.

    Returns
    -------
    numpy.ndarray or torch.Tensor
        The same kind as ``images``, its last two axes turned (``"displayed"``) or swapped (``"yx"``).
    """
    layout = get_convention(convention).image
    if layout == "xy":
        return images
    if hasattr(images, "detach"):   # torch: the same rotation (from the first axis towards the second) / transpose
        return images.rot90(1, (-2, -1)) if layout == "displayed" else images.transpose(-2, -1)
    a = np.asarray(images)
    return np.ascontiguousarray(np.rot90(a, axes=(-2, -1)) if layout == "displayed" else np.swapaxes(a, -2, -1))


def describe_layout(convention) -> str:
    """How a convention's arrays hold an image, for messages and records.

    Parameters
    ----------
    convention : str or Convention
        The tool.

    Returns
    -------
    str
        E.g. ``"as displayed: rows = y from the top down, columns = x (...)"``.
    """
    layout = get_convention(convention).image
    return {"xy": "(nx, ny), axis 0 = x",
            "displayed": "as displayed: rows = y from the top down, columns = x (np.rot90 of indreg's (nx, ny))",
            "yx": "as MRC sections: rows = y from the bottom up, columns = x (the transpose of indreg's (nx, ny))"}[
        layout]


def sinogram_layout(g: np.ndarray, convention) -> np.ndarray:
    """The tool's sinogram array as ``(num_angles, det_count)`` (transposed for ``bin_angle``)."""
    return np.ascontiguousarray(g.T) if get_convention(convention).sinogram == "bin_angle" else g


def sinogram_units(g: np.ndarray, convention, h: float) -> np.ndarray:
    """Line integrals in the domain's length unit: pixel sums times the pixel side ``h`` (``pixel_units``)."""
    return g * h if get_convention(convention).pixel_units else g


def sinogram_to_indreg(g: np.ndarray, convention, h: float = 1.0) -> np.ndarray:
    """The tool's sinogram as indreg's ``(num_angles, det_count)`` in the domain's length unit (pixel side ``h``).

    Parameters
    ----------
    g : numpy.ndarray
        The tool's sinogram array.
    convention : str or Convention
        The tool.
    h : float
        The pixel side (the domain's length unit).

    Returns
    -------
    numpy.ndarray
        ``(num_angles, det_count)``.
    """
    return sinogram_units(sinogram_layout(g, convention), convention, h)


def sinogram_from_indreg(g: np.ndarray, convention, h: float = 1.0) -> np.ndarray:
    """The inverse of :func:`sinogram_to_indreg`."""
    c = get_convention(convention)
    out = g / h if c.pixel_units else g
    return np.ascontiguousarray(out.T if c.sinogram == "bin_angle" else out)


def angles_to_indreg(radians: np.ndarray, convention) -> np.ndarray:
    """The tool's angles (radians) as indreg's: ``angle_sense * angle + angle_offset``.

    Parameters
    ----------
    radians : array_like
        The tool's angles, radians.
    convention : str or Convention
        The tool.

    Returns
    -------
    numpy.ndarray
        indreg's angles, float64 radians.
    """
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
