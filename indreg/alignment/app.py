"""``indreg-align``: a raw tilt series in, its alignment out (IMOD ``.xf`` + ``.tlt``, AreTomo ``.aln``, a JSON record),
with the aligned stack (MRC, pixel size in the header) and a quick reconstruction (SIRT or TV through the alignment;
MRC, and OME-Zarr with ``--zarr``), by projection matching (``indreg.alignment.projection_matching``).

    indreg-align series.mrc [--angles series.tlt] [--tilt-axis-angle 85.3] [--axis-from-stack] [--max-memory 8GiB]

Notes
-----
- The stack is read as stored (``indreg.io.read_tilt_series``: sections = tilts, ``(Y, X)`` images, angles from
  ``--angles`` or the ``.tlt`` / ``.rawtlt`` next to it); the pixel size (Angstrom) from ``--pixel-size`` or the
  MRC header.
- The tilt axis' angle in the images (``--tilt-axis-angle``, degrees from Y counter-clockwise, IMOD's; else the
  ``.mdoc``'s, else 0): its quarter turns are applied to the stack exactly (``np.rot90``), the rest in the
  operator (``AlignedOperator``'s per-tilt maps); ``--axis-from-stack`` replaces that rest by the stack's own
  estimate (``indreg.alignment.moments.estimate_axis_angle``: no reconstruction takes part of it up) where the data
  determine it, and keeps it in the rounds; ``--refine-axis`` refines the angle by projection matching (not
  validated).
- The estimation runs on the stack less its background (``--background``: the images' outer frame by default;
  projections are about 0 outside the object), coarse to fine: ``--rounds`` rounds binned by ``--coarse-bin``
  (``--bin`` times a power of 2, by default the largest that leaves images of at least ``COARSE_SIZE``
  pixels), then ``--fine-rounds`` rounds at each binning halved down to ``--bin`` (default: the least power
  of 2 whose working set fits ``--max-memory``, :func:`working_set`), the shifts carried from level to level
  in the stack's pixels (:func:`levels`). The aligned stack is made at full size tilt by tilt; the
  reconstruction is the finest level's SIRT, or with ``--recon-bin`` a SIRT of the aligned stack binned so,
  slab by slab of rows along the tilt axis (as many as ``--max-memory`` holds, :func:`slab_rows`).
- The alignment files refer to the raw stack as stored (``indreg.alignment.files``).

Longer than 450 lines: the aligner's two paths (a compact specimen's projection matching here, the slab's in
indreg.alignment.slab_app) share this module's binning, operators and resampling helpers; apart, the compact path
imported them back from here.
"""
from __future__ import annotations

import argparse
import logging
import math
import re
import resource
import sys
import time
from pathlib import Path

import numpy as np

from .app_checks import parse_bytes

__all__ = ["main", "working_set", "choose_binning", "parse_bytes", "levels", "slab_rows", "COARSE_SIZE"]

log = logging.getLogger("indreg.align")

#: Bytes a data pixel costs in a Gauss-Newton estimate (measured: 590 per pixel of a 128^2 x 61 series, linear;
#: cubic's 16 taps against 4, scaled), a voxel in SIRT (measured: under 50), the system matrix per nonzero (CSR
#: float64 master + float32 copy of A and A^T), and the process before any array (torch: measured 250-280 MB).
BYTES_PER_PIXEL = {"linear": 600, "cubic": 2000}
BYTES_PER_VOXEL = 48
BYTES_PER_NONZERO = 32
BASE_BYTES = 300 * 2**20
#: The smallest image side (pixels) of the coarsest level by default.
COARSE_SIZE = 128
#: A slab's finest binning by default (``--bin`` overrides): the wide box's leave-one-out volumes at full size
#: take minutes and gigabytes for a 1k stack; the shifts come back in full-size pixels.
SLAB_FINEST = 2


def working_set(nx: int, ny: int, nz: int, tilts: int, interpolation: str = "linear") -> int:
    """Bytes of projection matching on a stack of ``tilts`` images ``ny x nx`` and a volume ``nx x ny x nz``."""
    nonzeros = 2 * tilts * nx * max(nx, nz)
    return (BASE_BYTES + BYTES_PER_PIXEL[interpolation] * tilts * nx * ny + BYTES_PER_VOXEL * nx * ny * nz
            + BYTES_PER_NONZERO * nonzeros)


def choose_binning(nx: int, ny: int, nz: int, tilts: int, budget: int, base: int, interpolation: str) -> int:
    """The least power of 2 whose binned working set plus ``base`` (the full-size stack) fits ``budget``."""
    b = 1
    while base + working_set(nx // b, ny // b, max(nz // b, 1), tilts, interpolation) > budget:
        b *= 2
        if nx // b < 16 or ny // b < 16:
            raise ValueError(f"--max-memory {budget / 2**30:.2f} GiB is too small for this stack even binned by "
                             f"{b // 2} (the stack alone takes {base / 2**30:.2f} GiB)")
    return b


def levels(nx: int, ny: int, fine: int, coarse: int | None = None) -> list:
    """The binnings of the estimation, coarse to fine: ``fine`` times powers of 2, from ``coarse`` (default: the
    largest that keeps ``COARSE_SIZE`` pixels on the images' shorter side, at least ``fine``) down to ``fine``."""
    if coarse is None:
        coarse = fine
        while min(nx, ny) // (2 * coarse) >= COARSE_SIZE:
            coarse *= 2
    ratio = coarse // fine if fine >= 1 and coarse % fine == 0 else 0
    if ratio < 1 or ratio & (ratio - 1):
        raise ValueError(f"--coarse-bin ({coarse}) must be --bin ({fine}) times a power of 2")
    out = [coarse]
    while out[-1] > fine:
        out.append(out[-1] // 2)
    return out


def slab_rows(nx: int, ny: int, nz: int, tilts: int, budget: int) -> int:
    """Rows along the tilt axis of a SIRT slab ``nx x rows x nz`` whose working set (:data:`BYTES_PER_VOXEL` a voxel,
    the data twice in float32, the slice matrix) fits ``budget``; at least 1."""
    fixed = BASE_BYTES + BYTES_PER_NONZERO * 2 * tilts * nx * max(nx, nz)
    per_row = BYTES_PER_VOXEL * nx * nz + 8 * tilts * nx
    return int(min(ny, max(1, (budget - fixed) // per_row)))


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="indreg-align", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stack", help="raw tilt series (.mrc/.st/.ali, .npy, .h5:/dataset): (tilts, Y, X) as stored")
    p.add_argument("--angles", help="tilt angles (a .tlt file or a comma list, degrees); default: the .tlt next to "
                                    "the stack")
    p.add_argument("--out", help="output directory (default: STACK's name + _align)")
    p.add_argument("--convention", default="imod", choices=("imod", "indreg"),
                   help="the tilt angles' sign: imod (the .tlt as IMOD writes it, negated inside; the written "
                        ".tlt / .xf / .aln in IMOD's sign) or indreg's (docs/file_formats.md)")
    p.add_argument("--specimen", default="auto", choices=("auto", "compact", "slab"),
                   help="slab: wider than the detector (cryo-ET, a lamella; stretched cross-correlation, then "
                        "projection matching through the wide box); auto: a slab when the detector's border is "
                        "specimen, not vacuum (default)")
    p.add_argument("--intensities", action="store_true",
                   help="the stack holds bright-field intensities: aligned as -ln(I / I0), I0 from vacuum or the "
                        "slab law (indreg.units.transmission)")
    p.add_argument("--fiducials", choices=("auto", "off"),
                   help="a slab: where the stack holds gold beads, they fix the shifts at full size (and the tilt "
                        "axis with --axis-from-stack; indreg.alignment.fiducials); off: projection matching only "
                        "(default auto)")
    p.add_argument("--max-shift", type=float, default=0.25,
                   help="largest shift as a fraction of the detector's columns / rows (default 0.25); a shift at "
                        "it is warned and recorded (align.json: at_bound)")
    p.add_argument("--tilt-axis-angle", type=float, help="degrees from Y, counter-clockwise (IMOD's); default: the "
                                                         ".mdoc's, else 0")
    p.add_argument("--axis-from-stack", action="store_true",
                   help="estimate the tilt axis' rest (after --tilt-axis-angle's quarter turns, within 9 degrees) "
                        "from the stack's moment conditions and use it where the data determine it (docs/alignment.md)")
    p.add_argument("--refine-axis", action="store_true",
                   help="refine the tilt-axis angle by projection matching (not validated: it stays near its start, "
                        "docs/alignment.md)")
    p.add_argument("--pixel-size", type=float, help="Angstrom per pixel (default: the MRC header's, else 1)")
    p.add_argument("--thickness", type=int, help="volume depth in pixels of the stack (default: X / 2; a slab: "
                                                 "measured from a WBP)")
    p.add_argument("--background", default="auto", help="level subtracted for the estimation: auto (the images' "
                                                         "outer frame), none, or a number (default auto)")
    p.add_argument("--bin", type=int, help="binning of the estimation (default: from --max-memory)")
    p.add_argument("--max-memory", default="8GiB", help="memory budget (default 8GiB)")
    p.add_argument("--coarse-bin", type=int, help="binning of the first rounds: --bin times a power of 2 (default: "
                                                  f"the largest leaving {COARSE_SIZE}-pixel images)")
    p.add_argument("--rounds", type=int, default=4, help="projection-matching rounds at the coarsest level "
                                                         "(default 4)")
    p.add_argument("--fine-rounds", type=int, default=1, help="rounds at each finer level (default 1)")
    p.add_argument("--recon-bin", type=int, help="binning of the reconstruction, made slab-wise from the aligned "
                                                 "stack (default: the finest level's SIRT)")
    p.add_argument("--iters", type=int, default=30, help="SIRT iterations per round (default 30)")
    p.add_argument("--interpolation", default="linear", choices=("linear", "cubic"))
    p.add_argument("--recon", default="sirt", choices=("sirt", "tv"), help="the quick reconstruction")
    p.add_argument("--tv-weight", type=float, default=0.1, help="TV weight relative to the data (default 0.1)")
    p.add_argument("--zarr", action="store_true", help="also write the reconstruction as OME-Zarr (indreg[zarr])")
    p.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    p.add_argument("--invert", action="store_true", help="the object is darker than the background (bright-field "
                                                         "contrast): estimate and reconstruct from the inverted stack")
    return p


def _read(args) -> tuple:
    """The stack (float32), its angles (radians), pixel size (Angstrom) and tilt-axis angle (degrees)."""
    from .. import io

    angles = args.angles
    if angles is not None and not Path(angles).is_file():
        try:
            angles = [float(v) for v in angles.split(",")]
        except ValueError:
            raise ValueError(f"--angles {angles}: no such file, and not a comma list of angles (degrees)") from None
    stack, radians = io.read_tilt_series(args.stack, angles)
    pixel = args.pixel_size
    if pixel is None and Path(args.stack).suffix.lower() in io.formats.suffixes("read_voxel_size"):
        pixel = io.read_voxel_size(args.stack)[0] or None
    axis = args.tilt_axis_angle
    if axis is None:
        mdoc = io.mdoc_for(args.stack)
        axis = (io.read_tilt_axis_angle(mdoc) if mdoc else None) or 0.0
    return stack.astype(np.float32), radians, float(pixel or 1.0), float(axis)


def _bin(stack: np.ndarray, b: int) -> tuple:
    """``stack`` binned by ``b`` (block means; the remainder cropped, its larger half at the end) and the offset
    ``delta`` (x, y) of the binned centred coordinates: ``x = b x_b + delta``."""
    from .moments import binned

    _, ny, nx = stack.shape
    (ry, rx), (ly, lx) = (ny % b, nx % b), (ny % b // 2, nx % b // 2)
    delta = np.array([(2 * lx - rx) / 2, (2 * ly - ry) / 2])
    return np.array(binned(stack, b), dtype=np.float32), delta        # a copy: callers subtract in place


def _background(stack: np.ndarray, spec: str) -> float:
    """The level subtracted before the estimation (projections are ~0 outside the object): ``"auto"`` the median of
    the images' outer frame (``indreg.alignment.tilt_axis.frame_level``), ``"none"`` 0, or a number."""
    from .tilt_axis import frame_level

    if spec == "auto":
        level = frame_level(stack)
        log.info("background: the images' outer frame, %.6g, subtracted for the estimation", level)
        return level
    if spec == "none":
        return 0.0
    try:
        return float(spec)
    except ValueError:
        raise ValueError(f"--background must be auto, none or a number, got {spec!r}") from None


def _rotation(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s], [s, c]])


def _operator(stack_b: np.ndarray, radians: np.ndarray, nz: int, rest_deg: float):
    """The binned series' tilt-series operator (unit voxels, detector as wide as the volume, centred) with the
    tilt axis' remaining angle as its per-tilt maps."""
    import torch

    from ..domain import ImageDomain
    from ..forward import TiltSeriesGeometry, TiltSeriesTransform
    from .operator import AlignedOperator

    K, ny, nx = stack_b.shape
    domain = ImageDomain((nx, ny, nz), (-nx / 2, -ny / 2, -nz / 2), (nx / 2, ny / 2, nz / 2))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry(torch.as_tensor(radians), nx, -nx / 2, nx / 2,
                                                       angle_unit="rad"))
    matrices = None if rest_deg == 0 else torch.from_numpy(np.tile(_rotation(rest_deg), (K, 1, 1)))
    return AlignedOperator(T, matrices=matrices)


def _in_stack_pixels(op, b: int, delta: np.ndarray) -> tuple:
    """The binned operator's maps ``(M, d)`` in pixels of the (quarter-turned) full-size stack."""
    from .files import from_operator

    a = from_operator(op)
    return a.matrices, b * a.shifts + np.einsum("kij,j->ki", np.eye(2) - a.matrices, delta)


def _binned_operator(T, M: np.ndarray, d: np.ndarray, b: int, delta: np.ndarray, radians: np.ndarray):
    """``T`` (a level binned by ``b``) with the maps ``(M, d)`` of the full-size stack as its own."""
    from .files import Alignment, to_operator

    shifts = (d - np.einsum("kij,j->ki", np.eye(2) - M, delta)) / b
    return to_operator(T, Alignment(M, shifts, np.degrees(radians), np.arange(len(M))))


def _raw_alignment(M: np.ndarray, d: np.ndarray, quarter: int, raw_shape: tuple, radians: np.ndarray):
    """The maps of the quarter-turned stack in pixels of the raw stack as stored (module Notes)."""
    from .files import Alignment

    Q = np.round(_rotation(90.0 * quarter))                            # raw = R(90 q) rotated (centred)
    K, ny, nx = raw_shape
    return Alignment(Q @ M, d @ Q.T, np.degrees(radians), np.arange(K), (nx, ny, K), "indreg-align")


def _aligned_stack(rotated: np.ndarray, M: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The aligned images at full size, tilt by tilt: aligned(q) = rotated(M q + d) (bilinear, edge pixels)."""
    from scipy.ndimage import affine_transform

    K, ny, nx = rotated.shape
    c = np.array([(ny - 1) / 2, (nx - 1) / 2])
    out = np.empty_like(rotated)
    for k in range(K):
        m = np.array([[M[k, 1, 1], M[k, 1, 0]], [M[k, 0, 1], M[k, 0, 0]]])   # (row, column) order
        out[k] = affine_transform(rotated[k], m, np.array([d[k, 1], d[k, 0]]) + c - m @ c, order=1, mode="nearest")
    return out


def _reconstruct(op, data, x_sirt, kind: str, iters: int, weight: float):
    """SIRT's (from projection matching) or TV's (``weight`` times ``tv_weight_unit``, nonnegative) volume."""
    if kind == "sirt":
        return x_sirt
    from ..forward.tv import tv_reconstruction, tv_weight_unit

    return tv_reconstruction(op, data, weight * tv_weight_unit(op, data), num_iter=iters, x0=x_sirt,
                             nonneg=True)[0]


def _slab_sirt(stack: np.ndarray, radians: np.ndarray, nz: int, iters: int, rows: int) -> tuple:
    """Nonnegative SIRT of an aligned stack ``(K, ny, nx)`` (tilt axis along Y) slab by slab of ``rows`` rows:
    the volume ``(nx, ny, nz)`` and its relative data residual. Exact: a tilt series' rows are independent."""
    import torch

    from ..forward.sirt import sirt

    K, ny, nx = stack.shape
    volume = torch.empty(nx, ny, nz)
    squares, norm = 0.0, 0.0
    for start in range(0, ny, rows):
        piece = torch.from_numpy(np.ascontiguousarray(stack[:, start:start + rows]))
        op = _operator(piece.numpy(), radians, nz, 0.0).operator
        x, history = sirt(op, piece, num_iter=iters, nonneg=True)
        volume[:, start:start + rows] = x
        squares += float(history["data_residual"][-1]) ** 2
        norm += float(op.inner_data(piece, piece))
        log.info("reconstruction: rows %d-%d of %d", start, min(start + rows, ny) - 1, ny)
    return volume, math.sqrt(squares / norm)


def _residual(op, x, data) -> float:
    r = op(x) - data
    return float(op.inner_data(r, r).sqrt() / op.inner_data(data, data).sqrt())


def _peak_rss() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _stack_rest(stack: np.ndarray, radians: np.ndarray, rest: float) -> tuple:
    """``--axis-from-stack``: the tilt axis' angle in the quarter-turned ``stack`` (less its background) from its
    moment conditions where they determine it, else ``rest`` with a warning; and a record of the estimate."""
    from .moments import MAX_PIXELS, SCAN_DEG, estimate_axis_angle

    if abs(rest) >= SCAN_DEG - 1:
        log.warning("--axis-from-stack: the given angle is %.2f deg from a quarter turn, beyond the estimate's scan "
                    "(+-%g): kept", rest, SCAN_DEG - 1)
        return rest, {"estimated": False, "reason": "beyond the scan"}
    log.info("--axis-from-stack: estimating the angle from the stack's moment conditions (%d tilts of %d x %d px, "
             "binned to at most %d px a side; measured 14 s at 64^2, 78 s at 128^2 on two cores)", *stack.shape,
             MAX_PIXELS)
    try:
        e = estimate_axis_angle(stack, radians)
    except ValueError as err:
        log.warning("--axis-from-stack: not estimated (%s): the given angle kept", err)
        return rest, {"estimated": False, "reason": str(err)}
    log.info("--axis-from-stack: %s", e.describe())
    record = {"estimated": True, "rest_deg": e.angle_deg, "se_deg": e.se_deg if math.isfinite(e.se_deg) else None,
              "determined": e.determined, "given_rest_deg": rest}
    if not e.determined:
        log.warning("--axis-from-stack: the tilt-axis angle is not determined by the data (%s): the given angle "
                    "kept", e.describe())
        return rest, record
    return e.angle_deg, record


def compact_alignment(args, rotated, radians, rest, steps, level, thickness, raw_bytes, budget, start) -> tuple:
    """The compact specimen's estimation (module Convention): ``(M, d, history, from_stack, op, x, data,
    at_bound)``."""
    import torch

    from .fit import bounds, projection_matching

    K, ny, nx = rotated.shape
    from_stack = None
    if args.axis_from_stack:   # binned first (the estimate's bound), so no full-size copy less the background
        from .moments import binned_within

        rest, from_stack = _stack_rest(binned_within(rotated)[0] - level, radians, rest)
    M, d = np.tile(_rotation(rest), (K, 1, 1)), np.zeros((K, 2))
    mode = "shifts+axis" if args.refine_axis else "shifts"
    if args.refine_axis:
        log.warning("--refine-axis: the refined tilt-axis angle is not validated: projection matching's SIRT "
                    "reconstruction takes up a turn of the axis, and the angle stays near its start "
                    "(docs/alignment.md, issue #39); measure it beforehand where it matters")
    history = []
    for i, bl in enumerate(steps):
        binned, delta = _bin(rotated, bl)
        binned -= level
        nz = max(thickness // bl, 4)
        rounds = args.rounds if i == 0 else args.fine_rounds
        log.info("level %d/%d: binned by %d, %d x %d px, volume %d x %d x %d, %d rounds (working set ~%.2f GiB of "
                 "%.2f)", i + 1, len(steps), bl, binned.shape[2], binned.shape[1], binned.shape[2], binned.shape[1],
                 nz, rounds, (3 * raw_bytes + working_set(binned.shape[2], binned.shape[1], nz, K,
                                                          args.interpolation)) / 2**30, budget / 2**30)
        data = torch.from_numpy(binned)
        op0 = _binned_operator(_operator(binned, radians, nz, 0.0).operator, M, d, bl, delta, radians)

        def progress(r, rec, bl=bl, rounds=rounds):
            log.info("bin %d, round %d/%d: SIRT residual %.4f, largest shift update %.3f px (binned), %.0f s", bl,
                     r + 1, rounds, rec[0], rec[1], time.perf_counter() - start)

        op, x, records = projection_matching(op0, data, mode, rounds, args.iters, args.interpolation, progress,
                                             args.max_shift)
        M, d = _in_stack_pixels(op, bl, delta)
        history.append({"bin": bl, "shape": list(binned.shape), "rounds": records})
    at = (op.shifts.abs() >= bounds(op) - 1e-9).any(dim=1)
    return M, d, history, from_stack, op, x, data, [int(k) for k in torch.nonzero(at).flatten()]


def run(args) -> dict:
    """The whole run (module docstring); returns the JSON record written as ``align.json``."""
    # Longer than 80 lines: the aligner's steps in their order (read, check, estimate on the compact or the slab path,
    # write, reconstruct, record), each one call; split, the record's names would be passed through every piece.
    import torch

    from .. import io
    from ..tally import current, warning_kinds
    from .app_checks import check_options, check_sizes, check_stack, output_dir
    from .files import app_conventions, write_alignment
    from .slab_app import line_integrals, slab_alignment, slab_background, specimen_kind, wide_reconstruction
    from .tilt_axis import check_tilt_axis
    from ..io.provenance import write_record
    from ..io.volume_files import write_mrc, write_ome_zarr

    start = time.perf_counter()
    budget = check_options(args)          # every check before anything is written
    out = output_dir(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    raw, radians, pixel, axis = _read(args)
    sign = -1.0 if args.convention == "imod" else 1.0   # IMOD's .tlt: indreg's angle is minus IMOD's
    radians = sign * radians
    quarter = round(axis / 90.0)
    rest = axis - 90.0 * quarter
    rotated = np.ascontiguousarray(np.rot90(raw, k=quarter, axes=(1, 2)))
    check = check_tilt_axis(rotated)
    log.info("stack %s: %d tilts of %d x %d px, %.3g A/px; tilt axis %.2f deg (%d quarter turns, %.2f in the "
             "operator); %s", args.stack, *raw.shape[:1], raw.shape[2], raw.shape[1], pixel, axis, quarter, rest,
             check.describe())
    if check.direction == "columns" and abs(rest) < 20:
        raise ValueError(f"{args.stack}: {check.describe()}; give --tilt-axis-angle (e.g. {axis + 90:g} or "
                         f"{axis - 90:g})")
    if args.intensities:
        rotated, how = line_integrals(rotated, radians)
        log.info("--intensities: aligned as -ln(I / I0), I0 %s", how)
    # the contrast is checked before the specimen's kind (a darker object's border reads as specimen); --invert
    # turns the stack about the border's level in place, and back before the aligned stack is made
    pivot = _background(rotated, args.background)
    check_stack(rotated, pivot, args.stack, args.invert)
    if args.invert:
        np.subtract(np.float32(2 * pivot), rotated, out=rotated)
    kind, why = specimen_kind(rotated, radians, args.specimen)
    log.info("specimen: %s (%s)", kind, why)
    K, ny, nx = rotated.shape
    check_sizes(args, nx, ny)
    thickness = args.thickness or nx // 2
    b = args.bin or choose_binning(nx, ny, thickness, K, budget, 3 * raw.nbytes, args.interpolation)
    if kind == "slab" and args.bin is None:
        b = max(b, SLAB_FINEST)                 # the leave-one-out volumes of the wide box at bin 1 cost too much
    steps = levels(nx, ny, b, args.coarse_bin)
    level = slab_background(rotated, radians, args.background, _background) if kind == "slab" else pivot
    out.mkdir(parents=True, exist_ok=True)
    if kind == "slab":
        est = slab_alignment(rotated - level, radians, rest, steps, args.rounds, args.fine_rounds, args.thickness,
                             (args.max_shift * nx, args.max_shift * ny), args.axis_from_stack,
                             args.fiducials or "auto")
        M, d, res, beads = est["M"], est["d"], est["result"], est["fiducials"]
        history = [{"bin": r["bin"], "round": r["round"], "record": r} for r in res.history]
        at_bound = [int(k) for k in np.flatnonzero(res.at_bound.any(1))]
        from_stack = None if est["search"] is None else {"method": "common lines", **est["search"].__dict__}
    else:
        if args.fiducials is not None:
            log.warning("--fiducials %s is not used: the gold beads are fitted on the slab path only (this "
                        "specimen is compact; --specimen slab takes that path)", args.fiducials)
        M, d, history, from_stack, op, x, data, at_bound = compact_alignment(
            args, rotated, radians, rest, steps, level, thickness, raw.nbytes, budget, start)
    if at_bound:
        log.warning("%d tilt(s) with a shift at its bound (--max-shift %g of the detector: %s): the data may be "
                    "misaligned beyond it; raise --max-shift, or check the tilt axis and the stack", len(at_bound),
                    args.max_shift, at_bound)
    alignment = _raw_alignment(M, d, quarter, raw.shape, sign * radians)
    record = write_alignment(out, alignment, pixel_size=pixel, extra={"stack": str(args.stack),
                                                                      "at_bound": at_bound})
    if args.invert:   # the aligned stack in the stack's own contrast; the reconstruction from the inverted one
        np.subtract(np.float32(2 * pivot), rotated, out=rotated)
    contrast, level_given = (-1.0, 2 * pivot - level) if args.invert else (1.0, level)
    rot_full = _aligned_stack(rotated, M, d)
    io.write_tilt_series(out / "aligned.mrc", rot_full, sign * radians, pixel_size=pixel)
    rb = args.recon_bin or (steps[0] if kind == "slab" else b)
    before = None if kind == "slab" else history[0]["rounds"][0][0]
    if kind == "slab":
        volume, after = wide_reconstruction(contrast * (_bin(rot_full, rb)[0] - level_given), radians,
                                            res.thickness / rb, res.centre / rb, args.iters)
    elif args.recon_bin:
        stack_r = contrast * (_bin(rot_full, rb)[0] - level_given)
        nz = max(thickness // rb, 4)
        rows = slab_rows(stack_r.shape[2], stack_r.shape[1], nz, K, budget - 3 * raw.nbytes)
        log.info("reconstruction binned by %d: %d x %d x %d in slabs of %d rows", rb, stack_r.shape[2],
                 stack_r.shape[1], nz, rows)
        del data, x, op
        volume, after = _slab_sirt(stack_r, radians, nz, args.iters, rows)
    else:
        after = _residual(op, x, data)
        volume = _reconstruct(op, data, x, args.recon, args.iters, args.tv_weight)
    h = rb * pixel
    origin = [-(n - 1) / 2 * h for n in volume.shape]
    write_mrc(out / "reconstruction.mrc", volume.float().numpy(), (h, h, h), origin)
    if args.zarr:
        write_ome_zarr(out / "reconstruction.zarr", volume.float().numpy(), (h, h, h), origin)
    shifts = alignment.shifts
    summary = {"residual_before": before, "residual_after": after, "specimen": kind, "specimen_reason": why,
               "convention": args.convention, "axis_angle_deg": alignment.axis_angle_deg,
               "shift_range_px": [float(shifts.min()), float(shifts.max())], "max_shift": args.max_shift,
               "at_bound": at_bound, "binning": b, "levels": history, "recon_binning": rb, "background": level,
               "volume_shape": list(volume.shape), "seconds": time.perf_counter() - start,
               "cpu_seconds": time.process_time(), "peak_rss_bytes": _peak_rss(), "max_memory_bytes": budget,
               "rounds": [r for h_ in history for r in h_.get("rounds", [h_.get("record")])],
               "alignment": record["files"], "reconstruction": args.recon, "axis_from_stack": from_stack,
               "inverted": bool(args.invert)}
    if kind == "slab":
        summary["slab"] = {"thickness_px": res.thickness, "centre_px": res.centre,
                           "peaks": res.peaks.tolist(), "shifts_axis_frame_px": res.shifts.tolist(),
                           "fiducials": None if beads is None else beads.record()}
    if not after < 0.99:
        log.warning("the reconstruction explains almost none of the data (relative residual %.4f): check the stack's "
                    "contrast (--invert), its angles and its tilt axis", after)
    summary["warnings"], summary["warnings_by_kind"] = warning_kinds([], current())
    own = app_conventions(record["files"], pixel, rb * pixel, args.convention)
    summary.update(write_record(out / "align.json", out, own, own, **summary))
    return summary


def main(argv=None) -> int:
    """Console entry point: one-line errors, progress on stderr, one summary line on stdout."""
    from ..tally import summary, tally_warnings

    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    try:
        with tally_warnings():
            s = run(args)
    except (ValueError, TypeError, OSError, OverflowError) as e:
        print(f"indreg-align: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    before = "slab" if s["residual_before"] is None else f"{s['residual_before']:.4f}"
    print(f"indreg-align: residual {before} -> {s['residual_after']:.4f}, tilt axis "
          f"{s['axis_angle_deg']:.2f} deg, shifts {s['shift_range_px'][0]:.2f}..{s['shift_range_px'][1]:.2f} px, "
          f"bin {'>'.join(str(lv['bin']) for lv in s['levels'])}, peak {s['peak_rss_bytes'] / 2**30:.2f} GiB, "
          f"{s['seconds']:.1f} s ({s['cpu_seconds']:.1f} s CPU); {summary(s['warnings'], s['warnings_by_kind'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
