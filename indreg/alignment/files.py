"""Alignment files of other tools, in and out: IMOD's ``.xf`` (with ``.tlt`` / ``.xtilt``) and AreTomo's ``.aln``,
applied in the operator (``AlignedOperator``), not by resampling the stack (docs/file_formats.md, Alignment files).

An :class:`Alignment` holds, per tilt ``k`` of the raw stack, the map from the aligned (ideal) image to the raw one
in centred pixel coordinates: a point ``q`` of the aligned image is seen at ``p = M_k q + d_k`` in the raw one.

Notes
-----
- Pixel coordinates ``(x, y)``: x along the columns (MRC's X, the detector columns ``s``), y along the rows
  (MRC's Y, along the tilt axis, ``t``), in pixels of the stack as stored, centred on the image's middle:
  pixel index ``i`` sits at ``i - (n - 1) / 2``. IMOD's own coordinates run from 0 at the left edge of the
  first pixel to ``n`` at the right edge of the last, with the centre at ``n / 2`` (cubinterp since 2007): the
  same centre.
- IMOD ``.xf``: one line ``A11 A12 A21 A22 DX DY`` per view of the raw stack; newstack makes the aligned
  image by ``u' = A u + D`` (``u`` raw, ``u'`` aligned, both centred), so ``M = A^-1`` and ``d = -A^-1 D``.
  Angles: the ``.tlt`` next to it (degrees, one a line), ``.xtilt`` (a tilt about X) is read and must be 0
  (it is not modelled).
- AreTomo ``.aln`` (AreTomo2's ``CCorrTomoStack`` / ``GCorrPatchShift``): the aligned image at ``q`` takes the
  raw one at ``R(ROT) q + (TX, TY)``, so ``M = R(ROT)`` (``R`` counter-clockwise, degrees) and ``d = (TX, TY)``;
  ``GMAG`` is not applied by AreTomo's correction and is not here (a warning when it is not 1); rows are the
  stack's sections ``SEC`` (0-based; 1-based files are recognised by their range), ``# DarkFrame`` lines
  name the sections left out, ``TILT`` gives the angle. Local (patch) alignments are not read.
- In the operator (:func:`to_operator`): ``AlignedOperator(T, shifts, 0, matrices=B)`` with ``B_k`` the map
  ``M_k`` in the detector's physical units and the shifts in pixels (the tilt-axis angle ``alpha`` starts at
  0 and is refined on top: ``p = R(alpha) B_k q + shift``); :func:`from_operator` goes back.

Longer than 450 lines: the readers and writers of IMOD's and AreTomo's files share the maps' conventions and one-
line checks.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..io._files import _as_path, _fail, read_text
from .operator import AlignedOperator

__all__ = ["Alignment", "ALIGNMENT_FORMATS", "read_alignment", "read_xf", "read_aln", "write_xf", "write_aln",
           "write_alignment", "to_operator", "from_operator", "xf_of", "rotation_of", "check_shifts", "app_conventions"]

log = logging.getLogger("indreg")

ALIGNMENT_FORMATS = (".xf", ".aln")
#: An ``.xtilt`` angle (degrees) above this is an error: the single-axis model has no tilt about X.
MAX_XTILT_DEG = 0.05


@dataclass
class Alignment:
    """Per-tilt maps from the aligned image to the raw one (module Notes): ``p = M_k q + d_k``.

    Parameters
    ----------
    matrices : numpy.ndarray
        ``M_k``, ``(K, 2, 2)``.
    shifts : numpy.ndarray
        ``d_k``, ``(K, 2)`` pixels (x, y).
    tilt_angles_deg : numpy.ndarray
        ``(K,)`` degrees.
    frames : numpy.ndarray
        The raw stack's sections they belong to (dark frames left out).
    raw_size : tuple, optional
        ``(nx, ny, sections)`` when the file says it.
    source : str
        Where it came from (e.g. ``"IMOD name.xf"``).
    notes : list of str
        Remarks made while reading it.
    """
    matrices: np.ndarray
    shifts: np.ndarray
    tilt_angles_deg: np.ndarray
    frames: np.ndarray
    raw_size: Optional[tuple] = None
    source: str = ""
    notes: list = field(default_factory=list)

    @property
    def axis_angle_deg(self) -> float:
        """The mean in-plane rotation of the maps (degrees, counter-clockwise): the tilt axis' angle from Y."""
        return float(np.degrees(np.angle(np.exp(1j * np.radians(rotation_of(self.matrices))).mean())))


def rotation_of(matrices: np.ndarray) -> np.ndarray:
    """The rotation angle (degrees) of each ``2 x 2`` matrix's closest rotation (polar decomposition)."""
    m = np.asarray(matrices, dtype=np.float64)
    return np.degrees(np.arctan2(m[..., 1, 0] - m[..., 0, 1], m[..., 0, 0] + m[..., 1, 1]))


def _rotation(deg: np.ndarray) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


# ---------------------------------------------------------------------------------------------------- IMOD .xf
def _numbers(path: Path, name: str, width: Optional[int] = None) -> list:
    """Rows of numbers of a text file (blank lines skipped), each ``width`` long when given; the file read as small
    UTF-8 text (``indreg.io._files.read_text``: a FIFO, a file of millions of lines or other bytes refused first)."""
    rows = []
    for i, line in enumerate(read_text(path, name).splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = [float(v) for v in line.split()]
        except ValueError:
            raise _fail(name, path, f"line {i} is not numbers: {line.strip()[:60]!r}") from None
        if width is not None and len(row) != width:
            raise _fail(name, path, f"line {i} has {len(row)} numbers, an {path.suffix} line has {width}")
        if not all(math.isfinite(v) for v in row):
            raise _fail(name, path, f"line {i} has a non-finite number")
        rows.append(row)
    if not rows:
        raise _fail(name, path, "holds no lines")
    return rows


def xf_of(alignment: Alignment) -> np.ndarray:
    """IMOD's ``(K, 6)`` ``A11 A12 A21 A22 DX DY`` of ``alignment`` (module Notes)."""
    A = np.linalg.inv(alignment.matrices)
    D = -np.einsum("kij,kj->ki", A, alignment.shifts)
    return np.concatenate([A.reshape(-1, 4), D], axis=1)


def read_xf(path, angles=None, *, name: str = "alignment") -> Alignment:
    """IMOD's ``.xf`` with its angles: ``angles`` (degrees, a list or a ``.tlt`` path) or the ``stem.tlt`` next to
    it; a ``stem.xtilt`` next to it must be zero. One-line errors name the file and the line."""
    path = _as_path(path, name)
    rows = np.asarray(_numbers(path, name, 6))
    A, D = rows[:, :4].reshape(-1, 2, 2), rows[:, 4:]
    det = np.linalg.det(A)
    if np.any(np.abs(det) < 1e-6):
        raise _fail(name, path, f"line {int(np.argmin(np.abs(det))) + 1} has a singular matrix")
    degrees = _xf_angles(path, angles, len(rows), name)
    xtilt = path.with_suffix(".xtilt")
    if xtilt.is_file():
        values = np.asarray(_numbers(xtilt, name, 1))[:, 0]
        if np.abs(values).max() > MAX_XTILT_DEG:
            raise _fail(name, xtilt, f"X-axis tilts up to {np.abs(values).max():.3g} degrees: a tilt about X is "
                                     "not modelled (single-axis tilt series); realign without it")
    M = np.linalg.inv(A)
    return Alignment(M, -np.einsum("kij,kj->ki", M, D), degrees, np.arange(len(rows)), None, f"IMOD {path.name}")


def _xf_angles(path: Path, angles, count: int, name: str) -> np.ndarray:
    from ..io.angle_files import read_angles

    if angles is None:
        tlt = path.with_suffix(".tlt")
        if not tlt.is_file():
            raise _fail(name, path, f"no tilt angles: put {tlt.name} (degrees, one a line) next to it or give them")
        angles = tlt
    degrees = np.degrees(read_angles(angles, "deg", name=str(angles) if isinstance(angles, Path) else "angles"))
    if degrees.size != count:
        raise _fail(name, path, f"{count} transforms but {degrees.size} tilt angles")
    return degrees


def write_xf(path, alignment: Alignment) -> Path:
    """``alignment`` as IMOD's ``.xf`` plus ``stem.tlt`` (degrees) next to it."""
    path = _as_path(path, "output")
    lines = ["".join(f"{v:12.7f}" for v in row[:4]) + "".join(f"{v:12.4f}" for v in row[4:])
             for row in xf_of(alignment) + 0.0]   # + 0.0: no "-0.0000000"
    _write_text(path, "\n".join(lines) + "\n")
    _write_text(path.with_suffix(".tlt"), "\n".join(f"{a:.4f}" for a in alignment.tilt_angles_deg) + "\n")
    return path


def _write_text(path: Path, text: str) -> None:
    """``text`` into ``path`` through ``indreg._outfiles`` (a fresh file renamed over it: no link followed)."""
    from .._outfiles import open_replacing

    try:
        with open_replacing(path, "w") as f:
            f.write(text)
    except OSError as err:
        raise _fail("output", path, f"cannot be written ({type(err).__name__}: {err})") from None


# ---------------------------------------------------------------------------------------------------- AreTomo .aln
ALN_COLUMNS = ("SEC", "ROT", "GMAG", "TX", "TY", "SMEAN", "SFIT", "SCALE", "BASE", "TILT")


def read_aln(path, *, name: str = "alignment") -> Alignment:
    """AreTomo's ``.aln`` (module Notes): the global alignment rows, ``RawSize`` and the dark frames."""
    path = _as_path(path, name)
    raw_size, darks, rows, local = None, [], [], False
    for i, line in enumerate(read_text(path, name).splitlines(), 1):
        text = line.strip()
        if not text:
            continue
        if text.startswith("#"):
            key, _, value = text.lstrip("#").partition("=")
            key = key.strip()
            if key == "RawSize":
                raw_size = _raw_size(value, i, path, name)
            elif key == "DarkFrame":
                darks.append(_finite_row(value, i, path, name, "DarkFrame"))
            elif "Local" in key:
                local = True
            continue
        if local:
            continue
        row = _finite_row(text, i, path, name, "the row")
        if len(row) != len(ALN_COLUMNS):
            raise _fail(name, path, f"line {i} has {len(row)} numbers, an alignment row has {len(ALN_COLUMNS)} "
                                    f"({' '.join(ALN_COLUMNS)})")
        rows.append(row)
    if not rows:
        raise _fail(name, path, "holds no alignment rows")
    a = np.asarray(rows)
    frames = _sections(a[:, 0].astype(int), darks, raw_size, path, name)
    notes = []
    if np.abs(a[:, 2] - 1).max() > 1e-4:
        notes.append(f"GMAG {a[:, 2].min():.4f}..{a[:, 2].max():.4f} not applied (AreTomo's correction ignores it)")
        log.warning("%s: %s", path, notes[-1])
    if local:
        notes.append("local (patch) alignment not read")
        log.warning("%s: %s", path, notes[-1])
    return Alignment(_rotation(a[:, 1]), a[:, 3:5].copy(), a[:, 9].copy(), frames, raw_size, f"AreTomo {path.name}",
                     notes)


def _finite_row(text: str, line: int, path: Path, name: str, what: str) -> list:
    """The numbers of ``text`` (line ``line``), all finite; else a one-line error naming the line."""
    try:
        row = [float(v) for v in text.split()]
    except ValueError:
        raise _fail(name, path, f"line {line}: {what} is not numbers: {text.strip()[:60]!r}") from None
    if not all(math.isfinite(v) for v in row):
        raise _fail(name, path, f"line {line}: {what} has a non-finite number: {text.strip()[:60]!r}")
    return row


def _raw_size(value: str, line: int, path: Path, name: str) -> tuple:
    """``# RawSize = nx ny sections``: three integers >= 1."""
    parts = value.split()
    if len(parts) != 3 or not all(p.isdigit() and int(p) >= 1 for p in parts):
        raise _fail(name, path, f"line {line}: RawSize must be three integers >= 1 (nx ny sections), got "
                                f"{value.strip()[:60]!r}")
    return tuple(int(p) for p in parts)


def check_shifts(alignment: Alignment, nx: int, ny: int, path, name: str = "alignment") -> None:
    """Every shift within the raw images ``nx x ny`` (pixels): a larger one moves the whole image out of view (a
    damaged file, or another stack's), and ``1e300`` would overflow the operator's indices. One-line error."""
    limit = np.array([nx, ny], dtype=np.float64)
    over = np.abs(alignment.shifts) > limit
    if over.any():
        k = int(np.argmax(over.any(axis=1)))
        raise _fail(name, path, f"tilt {k}'s shift ({alignment.shifts[k, 0]:.4g}, {alignment.shifts[k, 1]:.4g}) px "
                                f"is beyond the stack's {nx} x {ny} px images")


def _sections(sec: np.ndarray, darks: list, raw_size, path: Path, name: str) -> np.ndarray:
    """0-based sections of the rows: ``SEC`` as it is, or minus 1 when the file counts from 1 (its smallest
    section, dark frames included, is 1 and its largest the number of sections)."""
    total = raw_size[2] if raw_size and len(raw_size) == 3 else len(sec) + len(darks)
    every = np.concatenate([sec, [int(d[1]) for d in darks if len(d) >= 2]]).astype(int)
    base = 1 if every.min() >= 1 and every.max() == total else 0
    frames = sec - base
    if frames.min() < 0 or frames.max() >= total or len(set(frames.tolist())) != len(frames):
        raise _fail(name, path, f"sections {sec.min()}..{sec.max()} do not fit a stack of {total} (RawSize)")
    return frames


def write_aln(path, alignment: Alignment) -> Path:
    """``alignment`` as AreTomo's ``.aln`` (global alignment, no patches); a map that is not a rotation (a
    magnification or stretch) cannot be written there: a one-line error."""
    path = _as_path(path, "output")
    M = alignment.matrices
    rot = rotation_of(M)
    off = np.abs(M - _rotation(rot)).max()
    if off > 1e-4:
        raise _fail("output", path, f"the maps are not rotations (off by {off:.3g}): AreTomo's .aln holds a rotation "
                                    "and a shift per tilt; write .xf instead")
    nx, ny, n = alignment.raw_size or (0, 0, int(alignment.frames.max()) + 1)
    kept = set(alignment.frames.tolist())
    lines = ["# AreTomo Alignment / Priims bprmMn", f"# RawSize = {nx} {ny} {n}", "# NumPatches = 0"]
    lines += [f"# DarkFrame = {i:5d} {i:5d} {0.0:8.2f}" for i in range(n) if i not in kept]
    lines.append("# SEC     ROT         GMAG       TX          TY      SMEAN     SFIT    SCALE     BASE     TILT")
    for k in range(len(rot)):
        lines.append(f"{int(alignment.frames[k]):5d} {rot[k]:11.4f} {1.0:10.5f} {alignment.shifts[k, 0]:10.4f} "
                     f"{alignment.shifts[k, 1]:10.4f} {1.0:8.2f} {1.0:8.2f} {1.0:8.2f} {0.0:8.2f} "
                     f"{alignment.tilt_angles_deg[k]:8.2f}")
    _write_text(path, "\n".join(lines) + "\n")
    return path


def read_alignment(path, angles=None, *, name: str = "alignment") -> Alignment:
    """An ``.xf`` (:func:`read_xf`) or ``.aln`` (:func:`read_aln`) file.

    Parameters
    ----------
    path : str or os.PathLike
        The file; its suffix names the format.
    angles : str or os.PathLike or sequence of float, optional
        ``.xf``: its tilt angles (degrees, a list or a ``.tlt`` path); None: the ``stem.tlt`` next to it.
    name : str
        How messages call the file.

    Returns
    -------
    Alignment
        The per-tilt maps.

    Raises
    ------
    DataFileError
        One line naming the file (and the line): an unknown suffix, a missing or malformed file, a singular map,
        a tilt about X.
    """
    path = _as_path(path, name)
    suffix = path.suffix.lower()
    if suffix == ".xf":
        return read_xf(path, angles, name=name)
    if suffix == ".aln":
        return read_aln(path, name=name)
    raise _fail(name, path, f"unknown alignment format {suffix or '(no extension)'!r}; use {ALIGNMENT_FORMATS}")


# ---------------------------------------------------------------------------------------------------- the operator
def _frame(T) -> tuple:
    """``D = diag(det_cell, row_cell)`` and the detector's middle ``c = (s_mid, 0)`` (physical) of a tilt series."""
    from ..forward.tilt_series import TiltSeriesTransform

    if not isinstance(T, TiltSeriesTransform):
        raise TypeError(f"alignment files describe a tilt series (TiltSeriesTransform), got {type(T).__name__}")
    g = T.geometry
    return np.diag([g.det_cell, g.row_cell]), np.array([(g.det_min + g.det_max) / 2, 0.0])


def to_operator(T, alignment: Alignment, **options) -> AlignedOperator:
    """``T`` (a ``TiltSeriesTransform`` of the raw stack's frames ``alignment.frames``) with ``alignment`` as its
    own: ``AlignedOperator(T, shifts, 0, matrices=B)`` (module Notes).

    Parameters
    ----------
    T : TiltSeriesTransform
        The raw stack's frames' operator.
    alignment : Alignment
        The maps, one per tilt of ``T``.
    **options
        ``interpolation``, ``edge`` of the ``AlignedOperator``.

    Returns
    -------
    AlignedOperator
        ``T`` with the alignment's shifts and matrices (angle 0).

    Raises
    ------
    TypeError
        ``T`` is no ``TiltSeriesTransform``.
    ValueError
        A count of maps other than the tilts'.
    """
    D, c = _frame(T)
    K = T.geometry.num_tilts
    if len(alignment.shifts) != K:
        raise ValueError(f"the alignment has {len(alignment.shifts)} tilts, the operator {K}")
    Dinv = np.linalg.inv(D)
    B = D @ alignment.matrices @ Dinv
    shifts = alignment.shifts + np.einsum("ij,kj->ki", Dinv, c - np.einsum("kij,j->ki", B, c))
    return AlignedOperator(T, torch.from_numpy(shifts), 0.0, matrices=torch.from_numpy(B), **options)


def from_operator(op: AlignedOperator, frames=None, raw_size=None, source: str = "indreg") -> Alignment:
    """The alignment of ``op`` (its shifts, tilt-axis angle and matrices) in pixels of the stack: what
    :func:`to_operator` turns back into ``op``'s model.

    Parameters
    ----------
    op : AlignedOperator
        A tilt series' aligned operator.
    frames : array_like, optional
        The raw stack's sections of its tilts (default ``0 .. K-1``).
    raw_size : tuple, optional
        ``(nx, ny, sections)`` of the raw stack (default: ``op``'s images, columns by rows, and the sections up to
        the last of ``frames``).
    source : str
        Recorded as ``Alignment.source``.

    Returns
    -------
    Alignment
        The maps.

    Raises
    ------
    TypeError
        ``op``'s operator is no ``TiltSeriesTransform``.
    """
    D, c = _frame(op.operator)
    Dinv = np.linalg.inv(D)
    K = op.num_projections
    B = np.broadcast_to(np.eye(2), (K, 2, 2)) if op.matrices is None else op.matrices.detach().cpu().numpy()
    M_phys = _rotation(np.full(K, math.degrees(float(op.angle)))) @ B
    shifts = op.shifts.detach().cpu().numpy() - np.einsum("ij,kj->ki", Dinv, c - np.einsum("kij,j->ki", M_phys, c))
    angles = np.degrees(op.operator.geometry.angles.detach().cpu().numpy())
    frames = np.arange(K) if frames is None else np.asarray(frames)
    if raw_size is None:
        rows, cols = op.range_shape[-2:]
        raw_size = (int(cols), int(rows), int(frames.max()) + 1)
    return Alignment(Dinv @ M_phys @ D, shifts, angles, frames, raw_size, source)


CONVENTIONS = {
    "coordinates": "pixels of the raw stack as stored; x along the columns (MRC X), y along the rows (MRC Y, the "
                   "tilt axis after alignment); origin at the image's middle: pixel index i at i - (n - 1) / 2 "
                   "(IMOD's n / 2 with pixel edges at integers)",
    "map": "a point q of the aligned image is seen at p = matrix q + shift in the raw image",
    "xf": "IMOD: A = inverse(matrix), D = -A shift; newstack -xf makes the aligned stack (u' = A u + D)",
    "aln": "AreTomo: ROT = rotation angle of matrix (degrees, counter-clockwise), (TX, TY) = shift; SEC 0-based",
    "tilt_angles": "degrees, in the sign of the writer's convention (indreg-align: --convention, IMOD's by "
                   "default; indreg's angle is minus IMOD's: docs/file_formats.md, IMOD's projection convention)",
    "axis_angle": "the maps' mean rotation, degrees from Y counter-clockwise (IMOD's rotation angle)",
}


def app_conventions(alignment_files: dict, pixel: float, voxel: float, convention: str = "indreg") -> dict:
    """The conventions of each of ``indreg-align``'s output files for its record (``indreg.io.provenance``): the
    alignment files (``alignment_files``), the aligned stack (``pixel`` Angstrom) and the reconstruction (``voxel``)."""

    volume = {"axis_order": "indreg's (nx, ny, nz) stored as (z, y, x): x along the aligned images' columns, "
                            "y along the tilt axis, z the beam at tilt 0", "voxel_size_A": [voxel] * 3,
              "origin": "the centre of voxel (0, 0, 0), Angstrom, the volume centred on the tilt axis"}
    out = {name: {"units": {"shifts": "pixel of the raw stack", "angles": "degree"}, "conventions": CONVENTIONS}
           for name in alignment_files.values()}
    sense = "IMOD's sign (--convention imod)" if convention == "imod" else "indreg's sign (--convention indreg)"
    out[alignment_files["tlt"]] = {"units": "degree", "contents": f"the tilt angles, one a line ({sense})"}
    out["alignment.json"] = {"contents": "the alignment's numbers, units and conventions"}
    out["aligned.mrc"] = {"axis_order": "sections = tilts, (Y, X) images with the tilt axis along Y (rows)",
                          "pixel_size_A": pixel, "made_by": "the raw stack resampled through the alignment "
                                                            "(scipy.ndimage.affine_transform, bilinear)"}
    out["aligned.tlt"] = {"units": "degree", "contents": f"the aligned stack's tilt angles, one a line ({sense})"}
    out["reconstruction.mrc"] = out["reconstruction.zarr"] = volume
    return out


def write_alignment(directory, alignment, stem: str = "alignment", pixel_size: Optional[float] = None,
                    extra: Optional[dict] = None) -> dict:
    """``stem.xf`` + ``stem.tlt``, ``stem.aln`` (when the maps are rotations) and ``stem.json`` (the numbers,
    units and conventions) of ``alignment`` into ``directory``.

    Parameters
    ----------
    directory : str or os.PathLike
        Where the files go (it must exist).
    alignment : Alignment or AlignedOperator
        The maps (an operator through :func:`from_operator`).
    stem : str
        The files' name before the suffix.
    pixel_size : float, optional
        Angstrom per pixel, recorded in the JSON.
    extra : dict, optional
        More entries of the JSON record.

    Returns
    -------
    dict
        The JSON record (files written, conventions, units, the numbers).
    """
    directory = Path(directory)
    if isinstance(alignment, AlignedOperator):
        alignment = from_operator(alignment)
    raw_size = alignment.raw_size
    written = {"xf": write_xf(directory / f"{stem}.xf", alignment).name, "tlt": f"{stem}.tlt"}
    try:
        written["aln"] = write_aln(directory / f"{stem}.aln", alignment).name
    except ValueError as err:
        log.warning("%s", err)
    record = {"files": written, "writer": "indreg.alignment.files", "conventions": CONVENTIONS,
              "units": {"shifts": "pixel", "angles": "degree", "pixel_size": "Angstrom" if pixel_size else None},
              "pixel_size": pixel_size, "raw_size": list(raw_size) if raw_size else None,
              "frames": alignment.frames.tolist(), "tilt_angles_deg": alignment.tilt_angles_deg.tolist(),
              "matrices": alignment.matrices.tolist(), "shifts_px": alignment.shifts.tolist(),
              "axis_angle_deg": alignment.axis_angle_deg, **(extra or {})}
    _write_text(directory / f"{stem}.json", json.dumps(record, indent=1) + "\n")
    return record
