"""Reading templates, sinograms and tilt angles from files; writing result images (``indreg.io.writers``; angle
files: ``indreg.io.angle_files``; both re-exported here).

Convention:
    - Images come back as float64 numpy arrays ``(nx, ny)`` in indreg's layout (axis 0 = x, axis 1 = y),
      volumes as ``(nx, ny, nz)`` (``read_volume``); sinograms as float64 ``(num_angles, det_count)``, tilt
      series as ``(num_tilts, det_rows, det_cols)`` (``read_tilt_series``); angles as float64 radians, 1D.
    - 3D MRC volumes are stored in MRC's order, sections ``(z, y, x)``, and transposed on reading and writing
      (``read_volume``, ``write_volume``); 2D MRC images and tilt-series stacks are taken as stored.
    - Array formats (``.npy``, ``.npz``, ``.h5``/``.hdf5``, ``.mrc``/``.st``/``.ali``) hold indreg's arrays
      as they are: images ``(x, y)``, sinograms ``(angle, bin)``; another tool's layout is converted with
      ``convention=`` (``indreg.io.conventions``: ``skimage``, ``astra``, ``tomopy``, ``imod``, ``odl``).
    - Picture formats (``.png``, ``.tif``/``.tiff``) are read as displayed (rows top to bottom, columns
      left to right). An image is turned upright for indreg, ``f = np.rot90(displayed, k=-1)``, so that
      ``np.rot90(f)`` (how indreg shows images) is the displayed picture: x to the right, y up.
      A sinogram stored as a picture is taken as displayed: rows = angles, columns = bins (no rotation), or
      columns = angles where the convention says so.
    - 8- and 16-bit pictures are read as fractions of their full scale (value / 255, / 65535, as skimage's
      ``img_as_float``; ``integer_scale="raw"`` keeps the values); other dtypes and array formats keep their values
      (counts are physical). RGB(A) pictures
      become grey by luminance ``0.2125 R + 0.7154 G + 0.0721 B`` (ITU-R BT.709, as ``skimage.color.rgb2gray``);
      an alpha channel is ignored.
    - Path syntax: ``file.npz`` (one array) or ``file.npz:key``; ``file.h5:/group/dataset`` (also ``.hdf5``, and
      HyperSpy's ``.hspy``, HDF5 with the signal at ``file.hspy:/Experiments/__unnamed__/data``), the dataset may
      be omitted when the file holds exactly one.
    - Every problem with a file raises :class:`DataFileError`, one line naming the file and the problem.
      Problems with inline values (angle lists, ``angle_unit``) raise ``ValueError``.

See ``docs/file_formats.md`` for the table of formats and how to export data from other packages.
"""
from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path

import numpy as np

from . import conventions
from ._files import (DataFileError, _as_path, _fail, _one_line, _Problem, check_mrc_header, mrc_header_problem,
                     split_path)
from .angle_files import (ANGLE_UNITS, RADIAN_SPAN, mdoc_for, read_angles, read_tilt_axis_angle,  # noqa: F401
                          tilt_angles_for)
from .writers import WRITE_FORMATS, write_image, write_tilt_series, write_volume  # noqa: F401

__all__ = ["DataFileError", "FORMATS", "PICTURE", "MRC", "CONTAINER", "ANGLE_UNITS", "WRITE_FORMATS", "split_path",
           "check_file", "read_image", "read_sinogram", "read_volume", "read_voxel_size", "read_stack",
           "read_tilt_series", "read_angles", "tilt_angles_for", "mdoc_for", "read_tilt_axis_angle", "write_image",
           "write_volume", "write_tilt_series"]

PICTURE = (".png", ".tif", ".tiff")
MRC = (".mrc", ".st", ".ali")
CONTAINER = (".npz", ".h5", ".hdf5", ".hspy")
FORMATS = (".npy",) + CONTAINER + MRC + PICTURE
#: Full scale of the unsigned integer pictures read as fractions (``integer_scale="fraction"``), by bytes a pixel.
FULL_SCALE = {1: 255.0, 2: 65535.0}

log = logging.getLogger("indreg")
#: ITU-R BT.709 luminance weights of R, G, B (``skimage.color.rgb2gray``).
LUMINANCE = (0.2125, 0.7154, 0.0721)
#: Leading bytes of the formats whose readers give confusing messages on other files.
_SIGNATURE = {".npy": b"\x93NUMPY", ".npz": b"PK", ".png": b"\x89PNG\r\n\x1a\n"}


# --- reading raw arrays -------------------------------------------------------------------------------

def _read_npy(path: Path, key) -> np.ndarray:
    return np.load(path, allow_pickle=False)


def _read_npz(path: Path, key) -> np.ndarray:
    with np.load(path, allow_pickle=False) as archive:
        keys = list(archive.files)
        if key is None:
            if len(keys) != 1:
                raise _Problem(f"holds {len(keys)} arrays {keys}; name one as {path.name}:KEY")
            key = keys[0]
        if key not in keys:
            raise _Problem(f"has no array {key!r} (keys: {keys})")
        return archive[key]


def _read_h5(path: Path, key) -> np.ndarray:
    import h5py

    with h5py.File(path, "r") as f:
        if key is None:
            found = []
            f.visititems(lambda n, obj: found.append("/" + n) if isinstance(obj, h5py.Dataset) else None)
            if len(found) != 1:
                raise _Problem(f"holds {len(found)} datasets {found[:10]}; name one as {path.name}:/DATASET")
            key = found[0]
        obj = f.get(key)
        if not isinstance(obj, h5py.Dataset):
            what = "a group, not a dataset" if obj is not None else "missing"
            raise _Problem(f"dataset {key!r} is {what}")
        if obj.dtype.kind not in "biufc":
            raise _Problem(f"dataset {key!r} has non-numeric dtype {obj.dtype}")
        elsewhere = _h5_elsewhere(obj, f)
        if elsewhere:
            raise _Problem(f"dataset {key!r} {elsewhere}; indreg reads only data stored in the file itself")
        return obj[()]


def _h5_elsewhere(obj, f) -> str:
    """Why the dataset's values lie outside the file ``f`` (an external link, a virtual dataset, external raw
    storage: a crafted file could make any file's bytes the image), or ``""``."""
    if obj.file.filename != f.filename:
        return f"is an external link to {obj.file.filename}"
    if obj.is_virtual:
        return "is a virtual dataset (its values lie in other files)"
    if obj.external:
        return f"has external storage ({obj.external[0][0]!r})"
    return ""


def _read_mrc(path: Path, key) -> np.ndarray:
    import mrcfile

    problem = mrc_header_problem(*_head(path))
    if problem:
        raise _Problem(problem)
    try:
        with mrcfile.open(path, mode="r", permissive=False) as mrc:
            return np.array(mrc.data)
    except ValueError as strict_error:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                with mrcfile.open(path, mode="r", permissive=True) as mrc:
                    data = None if mrc.data is None else np.array(mrc.data)
            except (ValueError, OSError):
                data = None
        if data is None:
            raise _Problem(f"not a readable MRC file ({strict_error})") from None
        warnings.warn(_one_line(f"{path}: invalid MRC header ({strict_error}); data read in permissive mode"),
                      stacklevel=4)
        return data


def _head(path: Path) -> tuple:
    with open(path, "rb") as f:
        return f.read(1024), os.fstat(f.fileno()).st_size


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


def _read_png(path: Path, key) -> tuple:
    import imageio.v3 as iio

    pixels = np.asarray(iio.imread(path, plugin="pillow"))
    return pixels, pixels.ndim == 3 and pixels.shape[-1] in (3, 4)


def _read_tif(path: Path, key) -> tuple:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        pixels = tif.asarray()
        rgb = tif.pages[0].photometric == tifffile.PHOTOMETRIC.RGB
    return pixels, rgb


def _check_signature(path: Path, suffix: str) -> None:
    signature = _SIGNATURE.get(suffix, b"")
    with open(path, "rb") as f:
        if f.read(len(signature)) != signature:
            raise _Problem(f"unreadable as {suffix} (not a {suffix} file: wrong leading bytes)")


_READERS = {".npy": _read_npy, ".npz": _read_npz, ".h5": _read_h5, ".hdf5": _read_h5, ".hspy": _read_h5,
            ".png": _read_png, ".tif": _read_tif, ".tiff": _read_tif,
            **{ext: _read_mrc for ext in MRC}}


def check_file(spec, name: str = "data") -> tuple:
    """``(path, key, suffix)`` of a data file that exists, in a known format, with the right leading bytes,
    without reading it (the app checks its files before creating a run directory). Raises ``DataFileError``."""
    path, key = split_path(spec, name)
    suffix = path.suffix.lower()
    if suffix not in _READERS:
        raise _fail(name, spec, f"unknown format {suffix or '(no extension)'!r}; supported: {', '.join(FORMATS)}")
    if key is not None and suffix not in CONTAINER:
        raise _fail(name, spec, f"a ':KEY' suffix is only for {', '.join(CONTAINER)} files")
    if not path.exists():
        raise _fail(name, spec, "no such file")
    if not path.is_file():
        raise _fail(name, spec, "is not a file")
    try:
        _check_signature(path, suffix)
    except _Problem as problem:
        raise _fail(name, spec, problem) from None
    return path, key, suffix


def _load(spec, name: str, integer_scale: str = "raw") -> tuple:
    """``(raw array, suffix, note)`` of the file named by ``spec`` (a picture's grey levels per ``integer_scale``, the
    note says how); every failure is a ``DataFileError``."""
    if integer_scale not in conventions.INTEGER_SCALES:
        raise ValueError(f"integer_scale must be one of {', '.join(conventions.INTEGER_SCALES)}, got {integer_scale!r}")
    path, key, suffix = check_file(spec, name)
    try:
        raw = _READERS[suffix](path, key)
    except _Problem as problem:
        raise _fail(name, spec, problem) from None
    except ValueError as err:
        if "allow_pickle" in str(err):   # numpy refusing an object array
            raise _fail(name, spec, "holds Python objects (pickled data), not numbers") from None
        raise _fail(name, spec, f"unreadable as {suffix} (ValueError: {err})") from None
    except Exception as err:   # any library's complaint about a broken file, as one line
        raise _fail(name, spec, f"unreadable as {suffix} ({type(err).__name__}: {err})") from None
    if suffix not in PICTURE:
        return np.asarray(raw), suffix, "values as stored"
    pixels, rgb = raw
    if pixels.dtype.kind in "biu":   # scale before luminance, which turns integers into floats
        pixels, note = _scaled(pixels, integer_scale)
    else:
        note = f"{pixels.dtype} values as stored"
    return np.asarray(_grey(pixels, rgb)), suffix, note


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
    """Read a 2D image as float64 ``(nx, ny)``, axis 0 = x, axis 1 = y (``ndim=3``: ``read_volume``).

    Convention:
        - ``.npy``/``.npz``/``.h5``/``.mrc`` arrays are in ``convention``'s layout (``indreg``: already
          ``(x, y)``; ``indreg.io.conventions``); an MRC file may also hold one section ``(1, nx, ny)``.
        - ``.png``/``.tif`` pictures are read as displayed and rotated, ``f = np.rot90(displayed, k=-1)``,
          so that ``np.rot90(f)`` shows the picture upright (x to the right, y up), whatever the convention.
        - 8- / 16-bit pictures: fractions of 255 / 65535 (``integer_scale="fraction"``) or their values (``"raw"``);
          RGB(A) is turned to grey by BT.709 luminance, alpha ignored. The log says how the file was read.

    Raises:
        DataFileError: one line ``"{name} file {path}: {problem}"``.
        ValueError: a bad ``convention`` or ``integer_scale``.
    """
    if ndim == 3:
        return read_volume(path, name=name)
    if ndim != 2:
        raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")
    convention = conventions.get_convention(convention)
    raw, suffix, note = _load(path, name, integer_scale)
    if suffix in MRC and raw.ndim == 3 and raw.shape[0] == 1:
        raw = raw[0]
    image = conventions.image_to_indreg(_numeric(raw, name, path), convention, picture=suffix in PICTURE)
    log.info("%s file %s: %s; %s", name, path, conventions.describe_image(suffix, convention, suffix in PICTURE),
             note)
    return image


def read_sinogram(path, *, name: str = "sinogram", convention="indreg", integer_scale: str = "fraction") -> np.ndarray:
    """Read 2D parallel-beam data as float64 ``(num_angles, det_count)``, in the file's units.

    Convention:
        - Arrays and pictures (as displayed) are ``(angle, bin)``, or ``(bin, angle)`` (transposed) where
          ``convention`` says so (``skimage``); units and angles are converted by ``indreg.load``.
        - An MRC tilt series may be a stack of one-row projections, ``(num_tilts, 1, det_count)`` or
          ``(num_tilts, det_count, 1)``, or a 2D image ``(num_tilts, det_count)``.
        - 8- / 16-bit pictures: as :func:`read_image`'s ``integer_scale``.

    Raises:
        DataFileError: one line ``"{name} file {path}: {problem}"``.
        ValueError: a bad ``convention`` or ``integer_scale``.
    """
    convention = conventions.get_convention(convention)
    raw, suffix, note = _load(path, name, integer_scale)
    if suffix in MRC and raw.ndim == 3 and 1 in raw.shape[1:]:
        raw = raw[:, 0, :] if raw.shape[1] == 1 else raw[:, :, 0]
    g = conventions.sinogram_layout(_numeric(raw, name, path), convention)
    log.info("%s file %s: %s %s; %s", name, path, suffix, conventions.describe_sinogram(convention), note)
    return g


def read_volume(path, *, name: str = "template") -> np.ndarray:
    """Read a 3D volume as float64 ``(nx, ny, nz)``, axis 0 = x, axis 1 = y, axis 2 = z.

    Convention:
        - ``.npy``/``.npz``/``.h5`` arrays are taken as they are (already ``(x, y, z)``, as ``write_volume``
          writes them).
        - ``.mrc``/``.st``/``.ali``: MRC stores sections ``(z, y, x)`` (x fastest, the standard
          ``mapc, mapr, maps = 1, 2, 3``); the array is transposed to ``(x, y, z)``. The voxel size is
          ``read_voxel_size``.
        - Pictures (``.png``/``.tif``) are not volumes.

    Raises:
        DataFileError: one line ``"{name} file {path}: {problem}"``.
    """
    if split_path(path, name)[0].suffix.lower() in PICTURE:
        raise _fail(name, path, f"a volume must be {', '.join(('.npy',) + CONTAINER + MRC)}, not a picture")
    raw, suffix, _ = _load(path, name)
    volume = _numeric(raw, name, path, ndim=3)
    return np.ascontiguousarray(volume.transpose(2, 1, 0)) if suffix in MRC else volume


def read_voxel_size(path, *, name: str = "volume") -> tuple:
    """Voxel (cell) size ``(hx, hy, hz)`` from an MRC header, as floats (MRC's unit, Angstrom by convention)."""
    import mrcfile

    path = _as_path(path, name)
    if path.suffix.lower() not in MRC:
        raise _fail(name, path, f"only MRC files ({', '.join(MRC)}) carry a voxel size")
    if not path.is_file():
        raise _fail(name, path, "no such file")
    check_mrc_header(path, name)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with mrcfile.open(path, mode="r", permissive=True, header_only=True) as mrc:
                size = mrc.voxel_size
    except (ValueError, OSError) as err:
        raise _fail(name, path, f"not a readable MRC file ({type(err).__name__}: {err})") from None
    return float(size.x), float(size.y), float(size.z)


def read_stack(path, *, name: str = "tilt series") -> np.ndarray:
    """Read a stack of projections as stored: float64 ``(num_tilts, det_rows, det_cols)`` (MRC sections = tilts,
    no transposition; ``.npy``/``.npz``/``.h5`` the same ``(tilt, row, column)`` array). ``read_tilt_series``
    adds the angles.

    Raises:
        DataFileError: one line ``"{name} file {path}: {problem}"``.
    """
    raw, _, _ = _load(path, name)
    return _numeric(raw, name, path, ndim=3)


def read_tilt_series(path, angles=None, unit: str = "deg", *, name: str = "tilt series") -> tuple:
    """Read a tilt series and its angles: ``(data, angles)``, float64 ``(num_tilts, det_rows, det_cols)`` and
    radians ``(num_tilts,)``.

    Convention (``TiltSeriesGeometry`` with ``tilt_axis="y"``, docs/tilt_series.md):
        - An MRC stack ``.mrc``/``.st``/``.ali`` is taken as stored: sections = tilts, rows = the image's Y
          (along the tilt axis: detector rows), columns = X (detector columns), so IMOD's aligned stack (tilt
          axis along Y) is indreg's data with no transposition. ``.npy``/``.npz``/``.h5`` hold the same
          ``(tilt, row, column)`` array.
        - ``angles``: a ``.tlt``/``.rawtlt`` path or a list in ``unit`` (``"deg"`` default, or ``"rad"``);
          ``None``: the sibling ``stem.tlt``, else ``stem.rawtlt`` (``tilt_angles_for``); one angle per tilt.

    Raises:
        DataFileError: a problem with a file, no angle file next to the stack, or a count mismatch.
        ValueError: bad inline angles or ``unit``.
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
