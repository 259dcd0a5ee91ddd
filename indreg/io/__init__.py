"""Reading templates, sinograms, volumes, tilt series and tilt angles from files; writing results
(``indreg.io.writers``; angle files: ``indreg.io.angle_files``; both re-exported here). Which suffix is which format,
with its reader and writer, is the registry of ``indreg.io.formats`` (``register_format`` adds one of yours).

Notes
-----
- Images come back as float64 numpy arrays ``(nx, ny)`` in indreg's layout (axis 0 = x, axis 1 = y),
  volumes as ``(nx, ny, nz)`` (``read_volume``); sinograms as float64 ``(num_angles, det_count)``, tilt
  series as ``(num_tilts, det_rows, det_cols)`` (``read_tilt_series``); angles as float64 radians, 1D.
- 3D MRC volumes are stored in MRC's order, sections ``(z, y, x)``, and transposed on reading and writing
  (``read_volume``, ``write_volume``; a format's ``volume_order``); 2D MRC images and tilt-series stacks are
  taken as stored.
- Array formats (``.npy``, ``.npz``, ``.h5``/``.hdf5``, ``.mrc``/``.st``/``.ali``) hold indreg's arrays
  as they are: images ``(x, y)``, sinograms ``(angle, bin)``; another tool's layout is converted with
  ``convention=`` (``indreg.io.conventions``: ``skimage``, ``astra``, ``tomopy``, ``imod``, ``odl``).
- Picture formats (``.png``, ``.tif``/``.tiff``; a format's ``picture``) are read as displayed (rows top to
  bottom, columns left to right). An image is turned upright for indreg, ``f = np.rot90(displayed, k=-1)``, so
  that ``np.rot90(f)`` (how indreg shows images) is the displayed picture: x to the right, y up.
  A sinogram stored as a picture is taken as displayed: rows = angles, columns = bins (no rotation), or
  columns = angles where the convention says so.
- 8- and 16-bit pictures are read as fractions of their full scale (value / 255, / 65535, as skimage's
  ``img_as_float``; ``integer_scale="raw"`` keeps the values); other dtypes and array formats keep their values
  (counts are physical). RGB(A) pictures
  become grey by luminance ``0.2125 R + 0.7154 G + 0.0721 B`` (ITU-R BT.709, as ``skimage.color.rgb2gray``);
  an alpha channel is ignored.
- Path syntax: ``file.npz`` (one array) or ``file.npz:key``; ``file.h5:/group/dataset`` (also ``.hdf5``, and
  HyperSpy's ``.hspy``, HDF5 with the signal at ``file.hspy:/Experiments/__unnamed__/data``), the dataset may
  be omitted when the file holds exactly one (a format's ``container``).
- Every problem with a file raises :class:`DataFileError`, one line naming the file and the problem.
  Problems with inline values (angle lists, ``angle_unit``) raise ``ValueError``.

See ``docs/file_formats.md`` for the table of formats and how to export data from other packages.
"""
from __future__ import annotations

import logging
import os
import warnings

import numpy as np

from .._lazy import REMOVED_IN
from . import conventions
from ._files import DataFileError, _as_path, _fail, _Problem, check_mrc_header
from .angle_files import (ANGLE_UNITS, RADIAN_SPAN, mdoc_for, read_angles, read_tilt_axis_angle,  # noqa: F401
                          tilt_angles_for)
from .formats import FILE_FORMATS, FileFormat, check_file, get_format, register_format, split_path, suffixes
from .writers import write_image, write_tilt_series, write_volume  # noqa: F401

__all__ = ["DataFileError", "FileFormat", "register_format", "ANGLE_UNITS", "split_path", "check_file",
           "read_image", "read_sinogram", "read_volume", "read_voxel_size", "read_stack", "read_tilt_series",
           "read_angles", "tilt_angles_for", "mdoc_for", "read_tilt_axis_angle", "write_image", "write_volume",
           "write_tilt_series"]

#: Full scale of the unsigned integer pictures read as fractions (``integer_scale="fraction"``), by bytes a pixel.
FULL_SCALE = {1: 255.0, 2: 65535.0}

log = logging.getLogger("indreg")
#: ITU-R BT.709 luminance weights of R, G, B (``skimage.color.rgb2gray``).
LUMINANCE = (0.2125, 0.7154, 0.0721)
#: The suffix tuples of earlier versions (deprecated, removed in ``indreg._lazy.REMOVED_IN``) -> the field of
#: ``indreg.io.formats.suffixes`` that gives them now, from the registry (plug-ins included).
_OLD_SUFFIX_TUPLES = {"FORMATS": "read", "PICTURE": "picture", "MRC": "sections", "CONTAINER": "container",
                      "WRITE_FORMATS": "write"}


def __getattr__(name: str):
    """The deprecated suffix tuples (``indreg.io.MRC``, ...), with a ``DeprecationWarning`` naming their successor."""
    if name not in _OLD_SUFFIX_TUPLES:
        raise AttributeError(f"module 'indreg.io' has no attribute {name!r}")
    new = f"indreg.io.formats.suffixes({_OLD_SUFFIX_TUPLES[name]!r})"
    warnings.warn(f"indreg.io.{name} is deprecated and will be removed in indreg {REMOVED_IN}: use {new} (the "
                  "registered formats, plug-ins included)", DeprecationWarning, stacklevel=2)
    return suffixes(_OLD_SUFFIX_TUPLES[name])


# --- reading raw arrays -------------------------------------------------------------------------------

def _grey(pixels: np.ndarray, rgb: bool) -> np.ndarray:
    """Grey values of a picture ``(rows, cols[, channels])``: luminance for RGB(A), alpha dropped."""
    if pixels.ndim == 3 and rgb and pixels.shape[-1] in (3, 4):
        return pixels[..., :3].astype(np.float64) @ np.asarray(LUMINANCE)
    if pixels.ndim == 3 and not rgb and pixels.shape[-1] == 2:   # grey + alpha
        return pixels[..., 0]
    return pixels


def _scaled(pixels: np.ndarray, integer_scale: str) -> tuple:
    """``(values, note)``: 8- / 16-bit pixels as fractions of their full scale (``integer_scale="fraction"``)."""
    full = FULL_SCALE.get(pixels.dtype.itemsize) if pixels.dtype.kind == "u" else None   # any byte order
    bits = 8 * pixels.dtype.itemsize
    if full is None:
        return pixels, f"{pixels.dtype} values as stored"
    if integer_scale == "raw":
        return pixels, f"{bits}-bit grey levels as stored (0..{full:g}, integer_scale raw)"
    return pixels / full, f"{bits}-bit grey levels as fractions of {full:g} (integer_scale fraction)"


def _load(spec, name: str, integer_scale: str = "raw") -> tuple:
    """``(raw array, format, suffix, note)`` of the file named by ``spec``, read by its registered format's reader (a
    picture's grey levels per ``integer_scale``, the note says how); every failure is a ``DataFileError``."""
    if integer_scale not in conventions.INTEGER_SCALES:
        raise ValueError(f"integer_scale must be one of {', '.join(conventions.INTEGER_SCALES)}, got {integer_scale!r}")
    path, key, suffix = check_file(spec, name)
    fmt = get_format(suffix)
    try:
        raw = fmt.read(path, key) if fmt.container else fmt.read(path)
    except _Problem as problem:
        raise _fail(name, spec, problem) from None
    except ValueError as err:
        if "allow_pickle" in str(err):   # numpy refusing an object array
            raise _fail(name, spec, "holds Python objects (pickled data), not numbers") from None
        raise _fail(name, spec, f"unreadable as {suffix} (ValueError: {err})") from None
    except Exception as err:   # any library's complaint about a broken file, as one line
        raise _fail(name, spec, f"unreadable as {suffix} ({type(err).__name__}: {err})") from None
    if not fmt.picture:
        return np.asarray(raw), fmt, suffix, "values as stored"
    pixels, rgb = raw
    pixels = np.asarray(pixels)
    if pixels.dtype.kind in "biu":   # scale before luminance, which turns integers into floats
        pixels, note = _scaled(pixels, integer_scale)
    else:
        note = f"{pixels.dtype} values as stored"
    return np.asarray(_grey(pixels, rgb)), fmt, suffix, note


def _numeric(raw: np.ndarray, name: str, spec, ndim: int = 2) -> np.ndarray:
    """Float64 copy of an ``ndim``-D array after checking it is non-empty, real, numeric and finite."""
    if raw.dtype.kind == "c":
        raise _fail(name, spec, f"has complex values (dtype {raw.dtype}); give the real data")
    if raw.dtype.kind not in "biuf":
        raise _fail(name, spec, f"has non-numeric dtype {raw.dtype}")
    if raw.size == 0:
        raise _fail(name, spec, f"is empty (shape {raw.shape})")
    if raw.ndim != ndim:
        raise _fail(name, spec, f"must hold a {ndim}D array, got shape {raw.shape}")
    out = np.array(raw, dtype=np.float64, order="C")
    bad = int(np.count_nonzero(~np.isfinite(out)))
    if bad:
        raise _fail(name, spec, f"has {bad} non-finite values (NaN or Inf) of {out.size}")
    return out


# --- public readers -----------------------------------------------------------------------------------

def read_image(path, *, name: str = "template", ndim: int = 2, convention="indreg",
               integer_scale: str = "fraction") -> np.ndarray:
    """Read a 2D image as float64 ``(nx, ny)``, axis 0 = x, axis 1 = y (``ndim=3``: :func:`read_volume`).

    Parameters
    ----------
    path : str or os.PathLike
        The file, in a registered format (``indreg.io.formats``), with ``:key`` for a container.
    name : str, optional
        What the file is, for messages.
    ndim : {2, 3}, optional
        3 reads a volume (:func:`read_volume`; ``convention`` and ``integer_scale`` do not apply).
    convention : str or Convention, optional
        The layout of an array file (``indreg.io.conventions.CONVENTIONS``).
    integer_scale : {"fraction", "raw"}, optional
        8- / 16-bit pictures as fractions of their full scale, or as stored.

    Returns
    -------
    numpy.ndarray
        float64 ``(nx, ny)`` (``(nx, ny, nz)`` for ``ndim=3``).

    Raises
    ------
    DataFileError
        One line ``"{name} file {path}: {problem}"``.
    ValueError
        A bad ``ndim``, ``convention`` or ``integer_scale``.

    Notes
    -----
    - Arrays (``.npy``/``.npz``/``.h5``/``.mrc``, any format that is no picture) are in ``convention``'s layout
      (``indreg``: already ``(x, y)``; ``indreg.io.conventions``); a format of ``sections`` (MRC) may also hold
      one section ``(1, nx, ny)``.
    - Pictures (``.png``/``.tif``) are read as displayed and rotated, ``f = np.rot90(displayed, k=-1)``,
      so that ``np.rot90(f)`` shows the picture upright (x to the right, y up), whatever the convention.
    - 8- / 16-bit pictures: fractions of 255 / 65535 (``integer_scale="fraction"``) or their values (``"raw"``);
      RGB(A) is turned to grey by BT.709 luminance, alpha ignored. The log says how the file was read.
    """
    if ndim == 3:
        return read_volume(path, name=name)
    if ndim != 2:
        raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")
    convention = conventions.get_convention(convention)
    raw, fmt, suffix, note = _load(path, name, integer_scale)
    if fmt.sections and raw.ndim == 3 and raw.shape[0] == 1:
        raw = raw[0]
    image = conventions.image_to_indreg(_numeric(raw, name, path), convention, picture=fmt.picture)
    log.info("%s file %s: %s; %s", name, path, conventions.describe_image(suffix, convention, fmt.picture), note)
    return image


def read_sinogram(path, *, name: str = "sinogram", convention="indreg", integer_scale: str = "fraction") -> np.ndarray:
    """Read 2D parallel-beam data as float64 ``(num_angles, det_count)``, in the file's units.

    Parameters
    ----------
    path : str or os.PathLike
        The file, in a registered format, with ``:key`` for a container.
    name : str, optional
        What the file is, for messages.
    convention : str or Convention, optional
        The file's layout (``indreg.io.conventions.CONVENTIONS``).
    integer_scale : {"fraction", "raw"}, optional
        As :func:`read_image`'s.

    Returns
    -------
    numpy.ndarray
        float64 ``(num_angles, det_count)``.

    Raises
    ------
    DataFileError
        One line ``"{name} file {path}: {problem}"``.
    ValueError
        A bad ``convention`` or ``integer_scale``.

    Notes
    -----
    - Arrays and pictures (as displayed) are ``(angle, bin)``, or ``(bin, angle)`` (transposed) where
      ``convention`` says so (``skimage``); units and angles are converted by ``indreg.load``.
    - A tilt series in a format of ``sections`` (MRC) may be a stack of one-row projections,
      ``(num_tilts, 1, det_count)`` or ``(num_tilts, det_count, 1)``, or a 2D image ``(num_tilts, det_count)``.
    - 8- / 16-bit pictures: as :func:`read_image`'s ``integer_scale``.
    """
    convention = conventions.get_convention(convention)
    raw, fmt, suffix, note = _load(path, name, integer_scale)
    if fmt.sections and raw.ndim == 3 and 1 in raw.shape[1:]:
        raw = raw[:, 0, :] if raw.shape[1] == 1 else raw[:, :, 0]
    g = conventions.sinogram_layout(_numeric(raw, name, path), convention)
    log.info("%s file %s: %s %s; %s", name, path, suffix, conventions.describe_sinogram(convention), note)
    return g


def read_volume(path, *, name: str = "template") -> np.ndarray:
    """Read a 3D volume as float64 ``(nx, ny, nz)``, axis 0 = x, axis 1 = y, axis 2 = z.

    Parameters
    ----------
    path : str or os.PathLike
        The file, in a registered format that is no picture, with ``:key`` for a container.
    name : str, optional
        What the file is, for messages.

    Returns
    -------
    numpy.ndarray
        float64 ``(nx, ny, nz)``.

    Raises
    ------
    DataFileError
        One line ``"{name} file {path}: {problem}"`` (a picture: the message lists the volume formats).

    Notes
    -----
    - ``.npy``/``.npz``/``.h5`` arrays (a format's ``volume_order="xyz"``) are taken as they are (already
      ``(x, y, z)``, as ``write_volume`` writes them).
    - ``.mrc``/``.st``/``.ali`` (``volume_order="zyx"``): MRC stores sections ``(z, y, x)`` (x fastest, the
      standard ``mapc, mapr, maps = 1, 2, 3``); the array is transposed to ``(x, y, z)``. The voxel size is
      :func:`read_voxel_size`.
    - Pictures (``.png``/``.tif``) are not volumes.
    """
    fmt = get_format(split_path(path, name)[0].suffix)
    if fmt is not None and fmt.picture:
        volumes = suffixes(lambda f: f.read is not None and not f.picture)
        raise _fail(name, path, f"a volume must be {', '.join(volumes)}, not a picture")
    raw, fmt, _, _ = _load(path, name)
    volume = _numeric(raw, name, path, ndim=3)
    return np.ascontiguousarray(volume.transpose(2, 1, 0)) if fmt.volume_order == "zyx" else volume


def read_voxel_size(path, *, name: str = "volume") -> tuple:
    """The voxel (cell) size in a file's header (MRC's unit, Angstrom by convention).

    Parameters
    ----------
    path : str or os.PathLike
        A file of a format with ``read_voxel_size`` (MRC).
    name : str, optional
        What the file is, for messages.

    Returns
    -------
    tuple of float
        ``(hx, hy, hz)``.

    Raises
    ------
    DataFileError
        A format without a voxel size (the message lists those with one), no such file, or an unreadable header.
    """
    path = _as_path(path, name)
    fmt = get_format(path.suffix)
    if fmt is None or fmt.read_voxel_size is None:
        names = " or ".join(f.name for f in FILE_FORMATS.values() if f.read_voxel_size is not None)
        raise _fail(name, path, f"only {names} files ({', '.join(suffixes('read_voxel_size'))}) carry a voxel size")
    if not path.is_file():
        raise _fail(name, path, "no such file")
    check_mrc_header(path, name)
    try:
        size = fmt.read_voxel_size(path)
    except Exception as err:   # the header reader's complaint, as one line
        raise _fail(name, path, f"not a readable {fmt.name} file ({type(err).__name__}: {err})") from None
    return tuple(float(h) for h in size)


def read_stack(path, *, name: str = "tilt series") -> np.ndarray:
    """Read a stack of projections as stored (MRC sections = tilts, no transposition; ``.npy``/``.npz``/``.h5`` the
    same ``(tilt, row, column)`` array); :func:`read_tilt_series` adds the angles.

    Parameters
    ----------
    path : str or os.PathLike
        The file, in a registered format, with ``:key`` for a container.
    name : str, optional
        What the file is, for messages.

    Returns
    -------
    numpy.ndarray
        float64 ``(num_tilts, det_rows, det_cols)``.

    Raises
    ------
    DataFileError
        One line ``"{name} file {path}: {problem}"``.
    """
    raw, _, _, _ = _load(path, name)
    return _numeric(raw, name, path, ndim=3)


def read_tilt_series(path, angles=None, unit: str = "deg", *, name: str = "tilt series") -> tuple:
    """Read a tilt series and its angles.

    Parameters
    ----------
    path : str or os.PathLike
        The stack, in a registered format, with ``:key`` for a container.
    angles : str, os.PathLike or sequence of float, optional
        The angle file or the angles; None: the angle file beside the stack.
    unit : {"deg", "rad"}, optional
        The unit of the angles.
    name : str, optional
        What the file is, for messages.

    Returns
    -------
    tuple
        ``(data, angles)``: float64 ``(num_tilts, det_rows, det_cols)`` and radians ``(num_tilts,)``.

    Raises
    ------
    DataFileError
        A problem with a file, no angle file next to the stack, or a count mismatch.
    ValueError
        Bad inline angles or ``unit``.

    Notes
    -----
    As ``TiltSeriesGeometry`` with ``tilt_axis="y"`` (docs/tilt_series.md):

    - An MRC stack ``.mrc``/``.st``/``.ali`` is taken as stored: sections = tilts, rows = the image's Y
      (along the tilt axis: detector rows), columns = X (detector columns), so IMOD's aligned stack (tilt
      axis along Y) is indreg's data with no transposition. ``.npy``/``.npz``/``.h5`` hold the same
      ``(tilt, row, column)`` array.
    - ``angles``: a ``.tlt``/``.rawtlt`` path or a list in ``unit`` (``"deg"`` default, or ``"rad"``);
      ``None``: the sibling ``stem.tlt``, else ``stem.rawtlt`` (``tilt_angles_for``); one angle per tilt.
    """
    if unit not in ANGLE_UNITS:
        raise ValueError(f"angle_unit must be 'deg' or 'rad', got {unit!r}")
    data = read_stack(path, name=name)
    origin = "angles"
    if angles is None:
        angles = tilt_angles_for(path)
        if angles is None:
            stem = split_path(path)[0].with_suffix("")
            raise _fail(name, path, f"no tilt angles: give angles= or put {stem.name}.tlt (or .rawtlt), one "
                                    "angle a line in degrees, next to it")
    if isinstance(angles, (str, os.PathLike)):
        origin = str(angles)
    radians = read_angles(angles, unit, name=origin)
    if radians.size != data.shape[0]:
        raise _fail(name, path, f"{data.shape[0]} tilts (sections) but {origin} gives {radians.size} angles")
    return data, radians
