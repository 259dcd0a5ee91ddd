"""Reading templates, sinograms and tilt angles from files; writing result images.

Convention:
    - Images come back as float64 numpy arrays ``(nx, ny)`` in indreg's layout (axis 0 = x, axis 1 = y),
      volumes as ``(nx, ny, nz)`` (``read_volume``); sinograms as float64 ``(num_angles, det_count)``, tilt
      series as ``(num_tilts, det_rows, det_cols)`` (``read_tilt_series``); angles as float64 radians, 1D.
    - 3D MRC volumes are stored in MRC's order, sections ``(z, y, x)``, and transposed on reading and writing
      (``read_volume``, ``write_volume``); 2D MRC images and tilt-series stacks are taken as stored.
    - Array formats (``.npy``, ``.npz``, ``.h5``/``.hdf5``, ``.mrc``/``.st``/``.ali``) hold indreg's arrays
      as they are: images ``(x, y)``, sinograms ``(angle, bin)``.
    - Picture formats (``.png``, ``.tif``/``.tiff``) are read as displayed (rows top to bottom, columns
      left to right). An image is turned upright for indreg, ``f = np.rot90(displayed, k=-1)``, so that
      ``np.rot90(f)`` (how indreg shows images) is the displayed picture: x to the right, y up.
      A sinogram stored as a picture is taken as displayed: rows = angles, columns = bins (no rotation).
    - Grey levels are kept as numbers (uint8 / uint16 values become floats, no rescaling). RGB(A) pictures
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
import math
import os
import re
import warnings
from pathlib import Path

import numpy as np

from ._checks import check_positive
from .domain import ImageDomain

PICTURE = (".png", ".tif", ".tiff")
MRC = (".mrc", ".st", ".ali")
CONTAINER = (".npz", ".h5", ".hdf5", ".hspy")
FORMATS = (".npy",) + CONTAINER + MRC + PICTURE
WRITE_FORMATS = (".npy", ".mrc")
ANGLE_UNITS = ("deg", "rad")
#: Angles in degrees spanning at most this many (a little over pi) are probably radians: a warning says so.
RADIAN_SPAN = 3.2

log = logging.getLogger("indreg")
#: ITU-R BT.709 luminance weights of R, G, B (``skimage.color.rgb2gray``).
LUMINANCE = (0.2125, 0.7154, 0.0721)
_KEYED = re.compile(r"^(.*\.(?:npy|npz|h5|hdf5|hspy|mrc|st|ali|png|tif|tiff)):(.*)$", re.IGNORECASE)
#: Leading bytes of the formats whose readers give confusing messages on other files.
_SIGNATURE = {".npy": b"\x93NUMPY", ".npz": b"PK", ".png": b"\x89PNG\r\n\x1a\n"}


class DataFileError(ValueError):
    """A file that cannot be used: the message is one line naming the file and the problem."""


class _Problem(Exception):
    """Internal: a problem found while reading, turned into a ``DataFileError`` naming the file."""


def _one_line(text) -> str:
    return re.sub(r"\s*[\r\n]+\s*", " ", str(text)).strip()


def _fail(name: str, spec, problem) -> DataFileError:
    return DataFileError(_one_line(f"{name} file {spec}: {problem}"))


def _as_path(spec, name: str) -> Path:
    """``spec`` as a ``Path``; anything but a str / ``os.PathLike`` is a ``DataFileError`` naming ``name``."""
    if not isinstance(spec, (str, os.PathLike)):
        raise DataFileError(f"{name} path must be a str or os.PathLike, got {type(spec).__name__}")
    return Path(spec)


def split_path(spec, name: str = "data") -> tuple:
    """``(path, key)`` of a path ``file.npz:key`` / ``file.h5:/group/dataset`` (key ``None`` if not given)."""
    text = str(_as_path(spec, name))
    match = _KEYED.match(text)
    if match and not Path(text).exists():
        return Path(match.group(1)), (match.group(2) or None)
    return Path(text), None


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
        return obj[()]


def _read_mrc(path: Path, key) -> np.ndarray:
    import mrcfile

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


def _grey(pixels: np.ndarray, rgb: bool) -> np.ndarray:
    """Grey values of a picture ``(rows, cols[, channels])``: luminance for RGB(A), alpha dropped."""
    if pixels.ndim == 3 and rgb and pixels.shape[-1] in (3, 4):
        return pixels[..., :3].astype(np.float64) @ np.asarray(LUMINANCE)
    if pixels.ndim == 3 and not rgb and pixels.shape[-1] == 2:   # grey + alpha
        return pixels[..., 0]
    return pixels


def _read_png(path: Path, key) -> np.ndarray:
    import imageio.v3 as iio

    pixels = np.asarray(iio.imread(path, plugin="pillow"))
    return _grey(pixels, rgb=pixels.ndim == 3 and pixels.shape[-1] in (3, 4))


def _read_tif(path: Path, key) -> np.ndarray:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        pixels = tif.asarray()
        rgb = tif.pages[0].photometric == tifffile.PHOTOMETRIC.RGB
    return _grey(pixels, rgb)


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


def _load(spec, name: str) -> tuple:
    """``(raw array, suffix)`` of the file named by ``spec``; every failure is a ``DataFileError``."""
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
    return np.asarray(raw), suffix


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

def read_image(path, *, name: str = "template", ndim: int = 2) -> np.ndarray:
    """Read a 2D image as float64 ``(nx, ny)``, axis 0 = x, axis 1 = y (``ndim=3``: ``read_volume``).

    Convention:
        - ``.npy``/``.npz``/``.h5``/``.mrc`` arrays are taken as they are (already ``(x, y)``); an MRC file
          may also hold one section ``(1, nx, ny)``.
        - ``.png``/``.tif`` pictures are read as displayed and rotated, ``f = np.rot90(displayed, k=-1)``,
          so that ``np.rot90(f)`` shows the picture upright (x to the right, y up).
        - Grey levels are not rescaled; RGB(A) is turned to grey by BT.709 luminance, alpha ignored.

    Raises:
        DataFileError: one line ``"{name} file {path}: {problem}"``.
    """
    if ndim == 3:
        return read_volume(path, name=name)
    if ndim != 2:
        raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")
    raw, suffix = _load(path, name)
    if suffix in MRC and raw.ndim == 3 and raw.shape[0] == 1:
        raw = raw[0]
    image = _numeric(raw, name, path)
    if suffix in PICTURE:
        image = np.ascontiguousarray(np.rot90(image, k=-1))
    return image


def read_sinogram(path, *, name: str = "sinogram") -> np.ndarray:
    """Read 2D parallel-beam data as float64 ``(num_angles, det_count)``.

    Convention:
        - Arrays are ``(angle, bin)`` as they are; pictures are taken as displayed (rows = angles,
          columns = bins, no rotation).
        - An MRC tilt series may be a stack of one-row projections, ``(num_tilts, 1, det_count)`` or
          ``(num_tilts, det_count, 1)``, or a 2D image ``(num_tilts, det_count)``.
        - Values are line integrals in the image domain's physical units (see ``RayTransform``).

    Raises:
        DataFileError: one line ``"{name} file {path}: {problem}"``.
    """
    raw, suffix = _load(path, name)
    if suffix in MRC and raw.ndim == 3 and 1 in raw.shape[1:]:
        raw = raw[:, 0, :] if raw.shape[1] == 1 else raw[:, :, 0]
    return _numeric(raw, name, path)


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
    raw, suffix = _load(path, name)
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
    raw, _ = _load(path, name)
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


def _angle_file(path: Path, name: str) -> list:
    """Angles of a text file, one per line (IMOD ``.tlt``/``.rawtlt``); blank lines and ``#`` comments skipped."""
    if not path.exists():
        raise _fail(name, path, "no such file")
    if not path.is_file():
        raise _fail(name, path, "is not a file")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (UnicodeDecodeError, OSError) as err:
        raise _fail(name, path, f"not a readable text file ({type(err).__name__}: {err})") from None
    angles = []
    for number, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        try:
            value = float(text)
        except ValueError:
            raise _fail(name, path, f"line {number} is not one angle: {text[:40]!r}") from None
        if not math.isfinite(value):
            raise _fail(name, path, f"line {number} is not a finite angle: {text!r}")
        angles.append(value)
    if not angles:
        raise _fail(name, path, "holds no angles")
    return angles


def _inline_angles(values, name: str) -> list:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(_one_line(f"{name} must be a list of numbers, got {values!r}"[:200])) from None
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1D list of numbers, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(_one_line(f"{name} must be finite, got {arr.tolist()}"))
    return arr.tolist()


def read_angles(spec, unit: str = "deg", *, name: str = "angles") -> np.ndarray:
    """Projection angles as float64 radians, 1D.

    Convention:
        - ``spec`` is a path to a text file (one angle per line, IMOD ``.tlt``/``.rawtlt`` style; blank
          lines and ``#`` comments allowed) or an inline list/tuple/array of numbers.
        - ``unit`` is ``"deg"`` or ``"rad"``: the unit of the given numbers. The angle ``theta`` is that of
          the detector direction ``w = (cos theta, sin theta)`` (see ``ParallelBeamGeometry``). Degrees that
          span at most about pi (:data:`RADIAN_SPAN`) log a warning that they may be radians.

    Raises:
        DataFileError: a problem with the file (missing, junk line N, no angles, non-finite angle).
        ValueError: bad inline values, or ``angle_unit`` not ``"deg"``/``"rad"``.
    """
    if unit not in ANGLE_UNITS:
        raise ValueError(f"angle_unit must be 'deg' or 'rad', got {unit!r}")
    if isinstance(spec, (str, os.PathLike)):
        values = _angle_file(Path(spec), name)
    else:
        values = _inline_angles(spec, name)
    angles = np.asarray(values, dtype=np.float64)
    if unit == "deg":
        _check_degrees(angles, name)
        return np.deg2rad(angles)
    return angles


def _check_degrees(angles: np.ndarray, name: str) -> None:
    """Warn when angles read as degrees span at most :data:`RADIAN_SPAN` (e.g. 0..3.1 or -1.05..1.05): they are
    probably radians (``ParallelBeamGeometry`` refuses the reverse, radians beyond 2 pi)."""
    span = float(angles.max() - angles.min()) if angles.size > 1 else 0.0
    if 0 < span <= RADIAN_SPAN:
        log.warning("%s span only %.4g degrees (%.4g .. %.4g): they may be radians; if so, give the unit 'rad' "
                    "(angle_unit='rad', geometry.angle_unit=rad)", name, span, angles.min(), angles.max())


def tilt_angles_for(sinogram_path) -> Path | None:
    """The sibling angle file of a sinogram: ``stem.tlt``, else ``stem.rawtlt``, else ``None``.

    A ``:key`` suffix (``data.h5:/sino``) is ignored: the sibling of ``data.h5`` is ``data.tlt``.
    """
    path, _ = split_path(sinogram_path, "sinogram")
    for suffix in (".tlt", ".rawtlt"):
        candidate = path.with_suffix(suffix)
        if candidate.is_file():
            return candidate
    return None


_TILT_AXIS = re.compile(r"tilt\s*axis\s*angle\s*=\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)", re.IGNORECASE)


def mdoc_for(stack_path) -> Path | None:
    """The SerialEM / IMOD metadata file of a stack: ``name.mrc.mdoc`` (SerialEM: the file name plus ``.mdoc``),
    else ``name.mdoc``, else ``None``. A ``:key`` suffix is ignored."""
    path, _ = split_path(stack_path, "tilt series")
    for candidate in (path.with_name(path.name + ".mdoc"), path.with_suffix(".mdoc")):
        if candidate.is_file():
            return candidate
    return None


def read_tilt_axis_angle(mdoc, *, name: str = "mdoc") -> float | None:
    """The tilt axis angle (degrees) of an ``.mdoc`` file: the first ``TiltAxisAngle = a`` or ``Tilt axis angle =
    a`` (also inside a ``[T = ...]`` title line), ``None`` when the file has none. The angle is IMOD's and
    SerialEM's: from the image's Y axis to the tilt axis, counterclockwise positive (``indreg.tilt_axis``).

    Raises:
        DataFileError: the file cannot be read.
    """
    path = Path(mdoc)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise _fail(name, path, f"not a readable text file ({type(err).__name__}: {err})") from None
    match = _TILT_AXIS.search(text)
    if match is None:
        return None
    value = float(match.group(1))
    if not math.isfinite(value):
        raise _fail(name, path, f"tilt axis angle is not finite: {match.group(0)!r}")
    return value


# --- writing ------------------------------------------------------------------------------------------

def write_image(path, array) -> Path:
    """Write a result array (numpy or torch, any shape for ``.npy``; 2D/3D for ``.mrc``) as it is.

    Convention:
        - No reorientation: an image ``(nx, ny)`` is stored ``(x, y)``, so :func:`read_image` gives it back.
        - ``.npy`` keeps float64; ``.mrc`` stores float32 (MRC mode 2), overwriting an existing file.

    Raises:
        DataFileError: unknown extension, non-numeric or non-finite data, or the file cannot be written.
    """
    path = _as_path(path, "output")
    suffix = path.suffix.lower()
    if suffix not in WRITE_FORMATS:
        raise _fail("output", path, f"cannot write format {suffix or '(no extension)'!r}; use {WRITE_FORMATS}")
    if hasattr(array, "detach"):   # torch tensor
        array = array.detach().cpu().numpy()
    data = np.asarray(array)
    if data.dtype.kind not in "biuf" or data.size == 0:
        raise _fail("output", path, f"needs a non-empty real numeric array, got dtype {data.dtype}, shape {data.shape}")
    if not np.isfinite(data).all():
        raise _fail("output", path, "array has non-finite values (NaN or Inf)")
    try:
        if suffix == ".npy":
            np.save(path, np.asarray(data, dtype=np.float64))
        else:
            if data.ndim not in (2, 3):
                raise _Problem(f"MRC needs a 2D or 3D array, got shape {data.shape}")
            import mrcfile

            with mrcfile.new(path, overwrite=True) as mrc:
                mrc.set_data(np.asarray(data, dtype=np.float32))
    except _Problem as problem:
        raise _fail("output", path, problem) from None
    except OSError as err:
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None
    return path


def _finite_array(array, path: Path, ndim: int, what: str) -> np.ndarray:
    if hasattr(array, "detach"):   # torch tensor
        array = array.detach().cpu().numpy()
    data = np.asarray(array)
    if data.dtype.kind not in "biuf" or data.ndim != ndim or data.size == 0:
        raise _fail("output", path, f"{what} must be a non-empty real {ndim}D array, got dtype {data.dtype}, "
                                    f"shape {data.shape}")
    if not np.isfinite(data).all():
        raise _fail("output", path, "array has non-finite values (NaN or Inf)")
    return data


def _write_mrc(path: Path, sections: np.ndarray, voxel_size) -> None:
    import mrcfile

    try:
        with mrcfile.new(path, overwrite=True) as mrc:
            mrc.set_data(np.ascontiguousarray(sections, dtype=np.float32))
            if voxel_size is not None:
                mrc.voxel_size = tuple(float(h) for h in voxel_size)
    except OSError as err:
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None


def write_volume(path, volume, domain=None) -> Path:
    """Write a volume ``(nx, ny, nz)`` (axis 0 = x) as ``.mrc`` or ``.npy``.

    Convention:
        - ``.mrc``: float32 (mode 2), sections ``(z, y, x)`` (x fastest, MRC's standard axis order), so
          IMOD/ChimeraX show x, y, z as indreg's; the voxel size in the header is the domain's cell sides
          ``(hx, hy, hz)`` in the domain's length unit (MRC readers take it as Angstrom), 1 without a domain.
        - ``.npy``: float64 ``(nx, ny, nz)`` as it is (no voxel size).
        - ``read_volume`` (and ``read_voxel_size``) give both back.

    Raises:
        DataFileError: unknown extension, not a finite real 3D array, a shape other than ``domain.shape``, or
        the file cannot be written.
    """
    path = _as_path(path, "output")
    suffix = path.suffix.lower()
    if suffix not in WRITE_FORMATS:
        raise _fail("output", path, f"cannot write format {suffix or '(no extension)'!r}; use {WRITE_FORMATS}")
    data = _finite_array(volume, path, 3, "volume")
    if domain is not None and not isinstance(domain, ImageDomain):
        raise TypeError(f"domain must be an ImageDomain or None, got {type(domain).__name__}")
    if domain is not None and tuple(data.shape) != tuple(domain.shape):
        raise _fail("output", path, f"volume has shape {data.shape} but the domain has {tuple(domain.shape)}")
    if suffix == ".npy":
        try:
            np.save(path, np.asarray(data, dtype=np.float64))
        except OSError as err:
            raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None
    else:
        _write_mrc(path, data.transpose(2, 1, 0), None if domain is None else domain.cell_sides)
    return path


def write_tilt_series(path, data, angles, pixel_size: float | None = None) -> Path:
    """Write a tilt series ``(num_tilts, det_rows, det_cols)`` as an MRC stack (sections = tilts, as stored)
    and its angles (radians) as ``stem.tlt`` in degrees, one a line: what ``read_tilt_series`` reads.
    ``pixel_size``: the detector cell (x and y of the header; z = 1)."""
    path = _as_path(path, "output")
    if path.suffix.lower() not in MRC:
        raise _fail("output", path, f"a tilt series is written as MRC ({', '.join(MRC)})")
    stack = _finite_array(data, path, 3, "tilt series")
    radians = np.asarray(angles.detach().cpu() if hasattr(angles, "detach") else angles, dtype=np.float64)
    if radians.shape != (stack.shape[0],) or not np.isfinite(radians).all():
        raise _fail("output", path, f"needs {stack.shape[0]} finite angles (one per tilt), got shape {radians.shape}")
    if pixel_size is not None:
        pixel_size = check_positive(pixel_size, "pixel_size")
    _write_mrc(path, stack, None if pixel_size is None else (pixel_size, pixel_size, 1.0))
    tlt = path.with_suffix(".tlt")
    try:
        np.savetxt(tlt, np.rad2deg(radians), fmt="%.6f")
    except OSError as err:
        raise _fail("output", tlt, f"cannot be written ({type(err).__name__}: {err})") from None
    return path
