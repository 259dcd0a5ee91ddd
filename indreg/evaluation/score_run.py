"""The work of ``indreg-score`` (:mod:`.score_app`, its conventions): read the stack, the alignment and the volumes,
build the operator of each scored set, score every volume (:mod:`.score`)."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import torch

from ..io.formats import suffixes
from .score import NOISE_ROW, fitted_scale, relative_residual, score_table
from .tilt_sets import parse_sets, tilt_set

__all__ = ["run", "read_any_alignment", "read_any_volume", "UNIT_RANGE"]

log = logging.getLogger("indreg.score")

#: ``--scale 1`` refuses a volume whose least-squares scale on the scored tilts lies outside this range.
UNIT_RANGE = (1 / 3, 3.0)
#: Angstrom per length unit.
LENGTH_UNITS = {"A": 1.0, "nm": 10.0}


def read_any_alignment(path: str, degrees: np.ndarray):
    """An ``Alignment`` from an ``.xf`` (the stack's angles), ``.aln`` or indreg's ``.json`` record, and the
    record's interpolation (None for the others)."""
    from ..alignment.files import Alignment, read_alignment

    p = Path(path)
    if p.suffix.lower() != ".json":
        return read_alignment(p, angles=degrees if p.suffix.lower() == ".xf" else None), None
    try:
        r = json.loads(p.read_text())
        a = Alignment(np.asarray(r["matrices"], float), np.asarray(r["shifts_px"], float),
                      np.asarray(r["tilt_angles_deg"], float), np.asarray(r["frames"], int),
                      tuple(r["raw_size"]) if r.get("raw_size") else None, f"indreg {p.name}")
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not an indreg alignment record ({type(e).__name__}: {e})") from None
    return a, r.get("interpolation")


def read_any_volume(path: str, voxel_size) -> tuple:
    """``(volume (x, y, z) float64, voxel sides in Angstrom or None)`` of an MRC, array or OME-Zarr file."""
    from .. import io

    if Path(path).suffix.lower() == ".zarr":
        from ..io.volume_files import ome_zarr_available, read_ome_zarr_scale

        if not ome_zarr_available():
            raise ValueError(f"{path}: OME-Zarr needs the optional package ome-zarr: pip install 'indreg[zarr]'")
        zyx, scale, _, _ = read_ome_zarr_scale(path)
        return np.ascontiguousarray(np.asarray(zyx, float).transpose(2, 1, 0)), tuple(scale[::-1])
    volume = io.read_volume(path, name="volume")
    with_size = Path(path).suffix.lower() in suffixes("read_voxel_size")
    sides = io.read_voxel_size(path, name="volume") if with_size else None
    return volume, (voxel_size,) * 3 if voxel_size is not None else sides


def _stack(args) -> tuple:
    """``(binned stack less its background, radians, pixel (A) or None, level)``."""
    from .. import io
    from ..alignment.tilt_axis import align_tilt_axis
    from ..units import border_level

    angles = args.angles
    if angles is not None and not Path(angles).is_file():
        angles = [float(v) for v in angles.split(",")]
    stack, radians = io.read_tilt_series(args.stack, angles)
    if not args.alignment and args.tilt_axis_angle:
        stack = align_tilt_axis(stack, args.tilt_axis_angle)
    pixel = args.pixel_size
    if pixel is None and Path(args.stack).suffix.lower() in suffixes("read_voxel_size"):
        size = io.read_voxel_size(args.stack)[0]
        pixel = size if size > 0 and size != 1.0 else None   # 1: MRC's "unset"
    b, (t, rows, cols) = args.bin, stack.shape
    if rows % b or cols % b:
        raise ValueError(f"--bin {b} must divide the stack's {rows} x {cols} pixels")
    binned = stack.reshape(t, rows // b, b, cols // b, b).mean(axis=(2, 4))
    if args.background == "auto":
        level = border_level(torch.from_numpy(binned))
    elif args.background == "none":
        level = 0.0
    else:
        try:
            level = float(args.background)
        except ValueError:
            raise ValueError(f"--background must be auto, none or a number, got {args.background!r}") from None
    return binned - level, radians, pixel, level


def _operator(shape: tuple, sides: tuple, radians: np.ndarray, cols: int, det_cell: float, alignment,
              interpolation: str):
    from ..domain import ImageDomain
    from ..forward.tilt_series import TiltSeriesGeometry, TiltSeriesTransform

    domain = ImageDomain(shape, tuple(-n * h / 2 for n, h in zip(shape, sides)),
                         tuple(n * h / 2 for n, h in zip(shape, sides)))
    half = cols * det_cell / 2
    T = TiltSeriesTransform(domain, TiltSeriesGeometry(torch.as_tensor(radians), det_count=cols, det_min=-half,
                                                       det_max=half, angle_unit="rad"))
    if alignment is None:
        return T
    from ..alignment.files import to_operator

    return to_operator(T, alignment, interpolation=interpolation)


def _volume(path: str, args, rows: int, pixel_b) -> tuple:
    """The volume (float64 tensor) and its voxel sides in the length unit, checked against the binned stack."""
    v, sides = read_any_volume(path, args.voxel_size)
    if args.swap_yz:
        v = np.ascontiguousarray(v.transpose(0, 2, 1))
        sides = None if sides is None else (sides[0], sides[2], sides[1])
    if args.flip_z:
        v = np.ascontiguousarray(v[:, :, ::-1])
    if sides is None or min(sides) <= 0:
        if pixel_b is None:
            raise ValueError(f"{path}: no voxel size (give --voxel-size, or --pixel-size for the stack)")
        sides = (pixel_b,) * 3
    if v.shape[1] != rows:
        raise ValueError(f"{path}: volume of shape {v.shape} has {v.shape[1]} slices along y (the tilt axis) but the "
                         f"binned stack has {rows} rows: one slice per detector row (--bin, --swap-yz?)")
    if pixel_b is not None and abs(sides[1] - pixel_b) > 0.01 * pixel_b:
        raise ValueError(f"{path}: voxel side {sides[1]:.6g} A along y but the binned stack's rows are {pixel_b:.6g} A "
                         f"apart (units: --voxel-size, --pixel-size, --bin)")
    unit = LENGTH_UNITS[args.length_unit]
    return torch.from_numpy(np.ascontiguousarray(v, dtype=np.float64)), tuple(s / unit for s in sides)


def run(args) -> tuple:
    """``(Markdown table, scores)``; writes ``--csv`` / ``--markdown`` (module :mod:`.score_app`)."""
    y, radians, pixel, level = _stack(args)
    degrees = np.degrees(radians)
    sets = parse_sets(args.tilts, degrees)
    alignment, interpolation = (None, None)
    frames = np.arange(len(radians))
    if args.alignment:
        alignment, interpolation = read_any_alignment(args.alignment, degrees)
        frames = np.asarray(alignment.frames)
        if frames.size and (frames.min() < 0 or frames.max() >= len(radians)):
            raise ValueError(f"{args.alignment}: sections {frames.min()}-{frames.max()} but the stack has "
                             f"{len(radians)}")
        alignment.shifts = alignment.shifts / args.bin
    position = {int(f): i for i, f in enumerate(frames)}
    for name, idx in sets.items():
        missing = [i for i in idx if i not in position]
        if missing:
            raise ValueError(f"--tilts {name}: sections {missing[:5]} have no alignment in {args.alignment}")
    interpolation = args.interpolation or interpolation or "linear"
    pixel_b = None if pixel is None else pixel * args.bin
    data = torch.from_numpy(np.ascontiguousarray(y[frames]))
    scored = sorted({i for idx in sets.values() for i in idx})
    scale_rows = tilt_set(args.scale_tilts, degrees, "--scale-tilts") if args.scale_tilts else \
        [int(f) for f in frames if int(f) not in set(scored)] or scored
    scores = {}
    for path in args.volumes:
        x, sides = _volume(path, args, y.shape[1], pixel_b)
        det_cell = sides[0] if pixel_b is None else pixel_b / LENGTH_UNITS[args.length_unit]
        T = _operator(tuple(x.shape), sides, radians[frames], y.shape[2], det_cell, alignment, interpolation)
        ops = {k: _restricted(T, [position[i] for i in idx]) for k, idx in sets.items()}
        ys = {k: data[[position[i] for i in idx]] for k, idx in sets.items()}
        c = _scale(args, path, x, T, data, position, scored, scale_rows)
        scores[Path(path).name] = {**{f"{k}_residual": relative_residual(ops[k], x, ys[k], c) for k in sets},
                                   "scale": c}
    from ..units import noise_residual

    scores[NOISE_ROW] = {f"{k}_residual": noise_residual(data[[position[i] for i in idx]]) for k, idx in sets.items()}
    counts = {k: len(v) for k, v in sets.items()}
    table = score_table(scores, list(sets), "markdown", counts)
    log.info("indreg-score: %d volume(s), background %.6g, bin %d, alignment %s (%s)", len(args.volumes), level,
             args.bin, args.alignment or "none", interpolation)
    for fmt, dest in (("csv", args.csv), ("markdown", args.markdown)):
        if dest:
            Path(dest).write_text(score_table(scores, list(sets), fmt, counts))
    return table, scores


def _restricted(T, rows: list):
    from ..forward.stacking import restrict

    return restrict(T, rows)


def _scale(args, path: str, x, T, data, position: dict, scored: list, scale_rows: list) -> float:
    """1 (checked: the least-squares scale on the scored tilts within :data:`UNIT_RANGE`) or the fitted scale."""
    rows = [position[i] for i in (scale_rows if args.scale == "fit" else scored) if i in position]
    c = fitted_scale([_restricted(T, rows)], x, [data[rows]])
    if args.scale == "fit":
        if not math.isfinite(c):
            raise ValueError(f"{path}: the volume projects to zero: no scale can be fitted")
        return c
    if not (math.isfinite(c) and UNIT_RANGE[0] <= c <= UNIT_RANGE[1]):
        raise ValueError(f"{path}: its projections are {1 / c if c else math.inf:.3g} times the data's (least-squares "
                         f"scale {c:.3g}, outside [1/3, 3]): a volume in other units; pass --scale fit, or check "
                         f"--length-unit and --background")
    return 1.0
