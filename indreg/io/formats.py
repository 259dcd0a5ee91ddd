"""File formats as a registry: a file's suffix names its :class:`FileFormat` (its reader, its writer and how its
arrays are laid out), for every reader and writer of :mod:`indreg.io` and the app's checks of its files.

Built in, registered in this order (the order of the suffixes in messages):

    NumPy      ``.npy``                      read, written (float64); no pickled objects
    NumPy zip  ``.npz``                      read; a container (``file.npz:key``)
    HDF5       ``.h5``, ``.hdf5``, ``.hspy``   read; a container (``file.h5:/group/dataset``); data in the file only
    MRC        ``.mrc``, ``.st``, ``.ali``     read, written (float32); volumes stored ``(z, y, x)``, a stack of
                                             sections (tilt series), the voxel size in its header
    PNG        ``.png``                      read; a picture (as displayed, 8/16-bit as fractions, RGB to grey)
    TIFF       ``.tif``, ``.tiff``           read; a picture

A format of your own is one :class:`FileFormat` and one :func:`register_format` call in your module
(docs/extending.md); from then on ``indreg.load``, the readers and writers and the app (``plugins=[your_module]``)
take its suffix, and the messages that list the known suffixes list it.
"""
from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ._files import _as_path, _fail, _one_line, _Problem, mrc_header_problem

__all__ = ["FileFormat", "FILE_FORMATS", "register_format", "get_format", "suffixes", "split_path", "check_file"]

#: The registered formats by name (:func:`register_format`): the built-ins, then plug-ins.
FILE_FORMATS: dict = {}
_SUFFIX = re.compile(r"\.[a-z0-9_+-]+")
_ORDERS = ("xyz", "zyx")


@dataclass(frozen=True)
class FileFormat:
    """A file format: what reads and writes it and how indreg lays out its arrays.

    Parameters
    ----------
    name : str
        The format's name in messages (``"MRC"``); registering another format of the same name replaces it.
    suffixes : tuple of str
        Its file name suffixes, ``".ext"`` (one dot; matched case-insensitively; a str is one suffix).
    read : callable, optional
        ``read(path) -> array`` (a ``container``'s: ``read(path, key)``, ``key`` None where the path names none; a
        ``picture``'s returns ``(pixels, rgb)``). Any exception it raises becomes one line naming the file.
        None: a format that is written only.
    write : callable, optional
        ``write(path, array)``: stores a finite real numpy array as it is (the caller has put it in the file's
        order; the writer chooses the stored dtype). A format with ``read_voxel_size`` is also given
        ``voxel_size=`` and ``origin=`` (``(x, y, z)``, None where unknown). None: a format that is read only.
    signature : bytes, optional
        The file's leading bytes, checked before reading (the app checks them before its run directory exists).
    container : bool, optional
        The file holds several arrays, one named by ``file.ext:key``.
    picture : bool, optional
        A picture read as displayed: turned upright for indreg (``np.rot90(displayed, k=-1)``), 8- and 16-bit
        grey levels as fractions of their full scale, RGB(A) to grey; not a volume.
    volume_order : {"xyz", "zyx"}, optional
        How a volume is stored: ``"xyz"`` as indreg's ``(nx, ny, nz)``, ``"zyx"`` as sections ``(z, y, x)``
        (MRC's), transposed by ``read_volume`` and ``write_volume``.
    sections : bool, optional
        A stack of 2D sections (MRC): a 2D image may be one section ``(1, nx, ny)``, a sinogram a stack of one-row
        projections whose angles may be the ``.tlt`` beside it, and ``write_tilt_series`` writes it.
    read_voxel_size : callable, optional
        ``read_voxel_size(path) -> (hx, hy, hz)``: the voxel size in the file's header (``indreg.io.read_voxel_size``).
    doc : str, optional
        A few words on the format.

    Raises
    ------
    TypeError
        A field of the wrong type (a reader or writer that is not callable, a signature that is not bytes).
    ValueError
        No suffix, a suffix not of the form ``".ext"``, an unknown ``volume_order``, or neither reader nor writer.
    """
    name: str
    suffixes: tuple
    read: Optional[Callable] = None
    write: Optional[Callable] = None
    signature: bytes = b""
    container: bool = False
    picture: bool = False
    volume_order: str = "xyz"
    sections: bool = False
    read_voxel_size: Optional[Callable] = None
    doc: str = ""

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"FileFormat name must be a non-empty str, got {self.name!r}")
        given = (self.suffixes,) if isinstance(self.suffixes, str) else tuple(self.suffixes)
        found = tuple(s.lower() for s in given if isinstance(s, str))
        if not found or len(found) != len(given) or not all(_SUFFIX.fullmatch(s) for s in found):
            raise ValueError(f"FileFormat {self.name!r}: suffixes must be like '.ext' (one dot, letters and digits), "
                             f"got {self.suffixes!r}")
        object.__setattr__(self, "suffixes", tuple(dict.fromkeys(found)))
        for field_name in ("read", "write", "read_voxel_size"):
            value = getattr(self, field_name)
            if value is not None and not callable(value):
                raise TypeError(f"FileFormat {self.name!r}: {field_name} must be callable or None, got "
                                f"{type(value).__name__}")
        if self.read is None and self.write is None:
            raise ValueError(f"FileFormat {self.name!r} needs a read or a write function")
        if not isinstance(self.signature, bytes):
            raise TypeError(f"FileFormat {self.name!r}: signature must be bytes, got {type(self.signature).__name__}")
        if self.volume_order not in _ORDERS:
            raise ValueError(f"FileFormat {self.name!r}: volume_order must be one of {', '.join(_ORDERS)}, got "
                             f"{self.volume_order!r}")


def register_format(fmt: FileFormat) -> FileFormat:
    """Add a format to the registry, under its name (a format of that name already there is replaced).

    Parameters
    ----------
    fmt : FileFormat
        The format.

    Returns
    -------
    FileFormat
        ``fmt`` (so that ``MY_FORMAT = register_format(FileFormat(...))`` names it).

    Raises
    ------
    TypeError
        ``fmt`` is not a :class:`FileFormat`.
    ValueError
        One of its suffixes belongs to another registered format (replace that format by its name instead).
    """
    if not isinstance(fmt, FileFormat):
        raise TypeError(f"register_format takes an indreg.io.formats.FileFormat, got {type(fmt).__name__}")
    for suffix in fmt.suffixes:
        holder = get_format(suffix)
        if holder is not None and holder.name != fmt.name:
            raise ValueError(f"register_format: suffix {suffix} is format {holder.name!r}'s; register a FileFormat "
                             f"named {holder.name!r} to replace it")
    FILE_FORMATS[fmt.name] = fmt
    return fmt


def get_format(suffix: str) -> Optional[FileFormat]:
    """The registered format of a suffix.

    Parameters
    ----------
    suffix : str
        ``".ext"``, any case (``Path.suffix``).

    Returns
    -------
    FileFormat or None
        The format, or None where no registered format has the suffix.
    """
    suffix = suffix.lower()
    return next((f for f in FILE_FORMATS.values() if suffix in f.suffixes), None)


def suffixes(having=None) -> tuple:
    """The registered suffixes, in the order of registration.

    Parameters
    ----------
    having : str or callable, optional
        A field of :class:`FileFormat` that must be set (``"read"``, ``"write"``, ``"container"``, ``"picture"``,
        ``"sections"``, ``"read_voxel_size"``), or a test ``fn(fmt) -> bool``; None: every suffix.

    Returns
    -------
    tuple of str
        The suffixes of the formats that pass.
    """
    test = having if callable(having) else (lambda f: True) if having is None else (lambda f: bool(getattr(f, having)))
    return tuple(s for f in FILE_FORMATS.values() if test(f) for s in f.suffixes)


def split_path(spec, name: str = "data") -> tuple:
    """Split the path syntax ``file.npz:key`` / ``file.h5:/group/dataset``.

    Parameters
    ----------
    spec : str or os.PathLike
        A path, optionally followed by ``:key`` after a registered suffix.
    name : str, optional
        What the file is, for the message.

    Returns
    -------
    tuple
        ``(path, key)``: a ``Path`` and the key (None if not given, or where a file of the whole name exists).

    Raises
    ------
    DataFileError
        ``spec`` is not a str or ``os.PathLike``.
    """
    text = str(_as_path(spec, name))
    known = "|".join(re.escape(s[1:]) for s in suffixes())
    match = re.match(rf"^(.*\.(?:{known})):(.*)$", text, re.IGNORECASE) if known else None
    if match and not Path(text).exists():
        return Path(match.group(1)), (match.group(2) or None)
    return Path(text), None


def check_file(spec, name: str = "data") -> tuple:
    """Check a data file without reading it: it exists, its format is registered and readable, its leading bytes
    are the format's (the app checks its files so before it creates a run directory).

    Parameters
    ----------
    spec : str or os.PathLike
        The file, with ``:key`` for a container.
    name : str, optional
        What the file is (``"template"``, ``"data.sinogram"``), for the message.

    Returns
    -------
    tuple
        ``(path, key, suffix)``: the ``Path``, the key (None if not given) and the lower-case suffix.

    Raises
    ------
    DataFileError
        One line ``"{name} file {spec}: {problem}"``: an unknown suffix (the message lists the registered ones), a
        key for a format that is no container, no such file, not a file, or the wrong leading bytes.
    """
    path, key = split_path(spec, name)
    suffix = path.suffix.lower()
    fmt = get_format(suffix)
    if fmt is None or fmt.read is None:
        what = "unknown format" if fmt is None else f"format {fmt.name} is written only, not read:"
        raise _fail(name, spec, f"{what} {suffix or '(no extension)'!r}; supported: {', '.join(suffixes('read'))}")
    if key is not None and not fmt.container:
        raise _fail(name, spec, f"a ':KEY' suffix is only for {', '.join(suffixes('container'))} files")
    if not path.exists():
        raise _fail(name, spec, "no such file")
    if not path.is_file():
        raise _fail(name, spec, "is not a file")
    with open(path, "rb") as f:
        if f.read(len(fmt.signature)) != fmt.signature:
            raise _fail(name, spec, f"unreadable as {suffix} (not a {suffix} file: wrong leading bytes)")
    return path, key, suffix


# --- the built-in formats' readers and writers ---------------------------------------------------------------

def _read_npy(path: Path) -> np.ndarray:
    return np.load(path, allow_pickle=False)


def _write_npy(path: Path, array: np.ndarray) -> None:
    with open(path, "wb") as f:   # np.save(path) would add ".npy" to a name ending in ".NPY"
        np.save(f, np.asarray(array, dtype=np.float64))


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


def _read_mrc(path: Path) -> np.ndarray:
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


def _write_mrc(path: Path, array: np.ndarray, voxel_size=None, origin=None) -> None:
    """float32 (MRC mode 2), overwriting an existing file; the voxel size and origin in the header where given."""
    import mrcfile

    if array.ndim not in (2, 3):
        raise _Problem(f"MRC needs a 2D or 3D array, got shape {array.shape}")
    with mrcfile.new(path, overwrite=True) as mrc:
        mrc.set_data(np.ascontiguousarray(array, dtype=np.float32))
        if voxel_size is not None:
            mrc.voxel_size = tuple(float(h) for h in voxel_size)
        if origin is not None:
            mrc.header.origin = tuple(float(o) for o in origin)


def _mrc_voxel_size(path: Path) -> tuple:
    import mrcfile

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with mrcfile.open(path, mode="r", permissive=True, header_only=True) as mrc:
            size = mrc.voxel_size
    return float(size.x), float(size.y), float(size.z)


def _read_png(path: Path) -> tuple:
    import imageio.v3 as iio

    pixels = np.asarray(iio.imread(path, plugin="pillow"))
    return pixels, pixels.ndim == 3 and pixels.shape[-1] in (3, 4)


def _read_tif(path: Path) -> tuple:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        pixels = tif.asarray()
        rgb = tif.pages[0].photometric == tifffile.PHOTOMETRIC.RGB
    return pixels, rgb


register_format(FileFormat("NumPy", ".npy", _read_npy, _write_npy, signature=b"\x93NUMPY", doc="numpy's .npy"))
register_format(FileFormat("NumPy zip", ".npz", _read_npz, signature=b"PK", container=True,
                           doc="numpy's .npz archive: file.npz:key"))
register_format(FileFormat("HDF5", (".h5", ".hdf5", ".hspy"), _read_h5, container=True,
                           doc="HDF5 (h5py), HyperSpy's .hspy: file.h5:/group/dataset"))
register_format(FileFormat("MRC", (".mrc", ".st", ".ali"), _read_mrc, _write_mrc, volume_order="zyx", sections=True,
                           read_voxel_size=_mrc_voxel_size, doc="MRC2014 (mrcfile); IMOD's stacks"))
register_format(FileFormat("PNG", ".png", _read_png, signature=b"\x89PNG\r\n\x1a\n", picture=True,
                           doc="PNG pictures (imageio, Pillow)"))
register_format(FileFormat("TIFF", (".tif", ".tiff"), _read_tif, picture=True, doc="TIFF pictures (tifffile)"))
