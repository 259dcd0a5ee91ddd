"""What ``indreg-align`` checks before it writes anything: its options' values, the output directory (no link in
it, and the default one not a link itself), and the stack (not constant; its object brighter than its background, as
projections of a nonnegative volume are, unless ``--invert``); and after the estimate, the shifts that ended at
their bound. Every problem is a ``ValueError`` whose message is the one line the app prints."""
from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path

import numpy as np

__all__ = ["parse_bytes", "check_options", "check_sizes", "output_dir", "check_stack", "at_bound", "MIN_BINNED",
           "MAX_BYTES"]

log = logging.getLogger("indreg.align")

#: A binned image keeps at least this many pixels along each side (``--bin``, ``--recon-bin``).
MIN_BINNED = 8
#: ``--max-memory`` beyond this (1 EiB) is not a size this machine has.
MAX_BYTES = 2 ** 60


def _integer(args, name: str, minimum: int, maximum: int | None = None) -> None:
    value = getattr(args, name.lstrip("-").replace("-", "_"))
    if value is None:
        return
    if value < minimum or (maximum is not None and value > maximum):
        bound = f"an integer >= {minimum}" if maximum is None else f"an integer in [{minimum}, {maximum}]"
        raise ValueError(f"{name} must be {bound}, got {value}")


def _number(args, name: str, positive: bool = False, nonnegative: bool = False) -> None:
    value = getattr(args, name.lstrip("-").replace("-", "_"))
    if value is None:
        return
    if not math.isfinite(value) or (positive and value <= 0) or (nonnegative and value < 0):
        kind = "a finite number > 0" if positive else "a finite number >= 0" if nonnegative else "a finite number"
        raise ValueError(f"{name} must be {kind}, got {value}")


def parse_bytes(text: str) -> int:
    """``"8GiB"``, ``"512MiB"``, ``"8G"``, ``"1e9"`` -> bytes; a one-line ValueError otherwise."""
    m = re.fullmatch(r"\s*([0-9.eE+]+)\s*([KMGT]?)(i?B?)\s*", str(text))
    if not m:
        raise ValueError(f"--max-memory must be a size such as 8GiB or 512MiB, got {text!r}")
    value = float(m.group(1)) * 1024 ** "_KMGT".index(m.group(2) or "_")
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"--max-memory must be a finite size > 0, got {text!r}")
    return int(value)


def check_options(args) -> int:
    """The options' values (one line naming the option and the value); returns ``--max-memory`` in bytes."""
    budget = parse_bytes(args.max_memory)
    if budget > MAX_BYTES:
        raise ValueError(f"--max-memory must be a finite size of at most 1 EiB, got {args.max_memory!r}")
    _number(args, "--tilt-axis-angle")
    _number(args, "--pixel-size", positive=True)
    _number(args, "--tv-weight", nonnegative=True)
    for name, low in (("--rounds", 1), ("--fine-rounds", 0), ("--iters", 1), ("--bin", 1), ("--coarse-bin", 1),
                      ("--recon-bin", 1), ("--thickness", 1)):
        _integer(args, name, low)
    _integer(args, "--threads", 1, 4 * (os.cpu_count() or 1))
    if not 0 < args.max_shift <= 0.5:   # nan fails too
        raise ValueError(f"--max-shift must be a fraction of the detector in (0, 0.5], got {args.max_shift}")
    if args.recon_bin is not None and args.recon != "sirt":
        raise ValueError(f"--recon-bin must be a positive integer with --recon sirt (TV runs at the estimation's "
                         f"binning), got {args.recon_bin} with --recon {args.recon}")
    return budget


def check_sizes(args, nx: int, ny: int) -> None:
    """The options that depend on the stack's images ``nx x ny`` (after the tilt axis' quarter turns): a binning
    must leave :data:`MIN_BINNED` pixels a side, a thickness at most 4 times the width."""
    largest = min(nx, ny) // MIN_BINNED
    for name in ("--bin", "--coarse-bin", "--recon-bin"):
        value = getattr(args, name[2:].replace("-", "_"))
        if value is not None and value > max(largest, 1):
            raise ValueError(f"{name} {value} leaves less than {MIN_BINNED} pixels of the {nx} x {ny} images: "
                             f"at most {max(largest, 1)}")
    if args.thickness is not None and args.thickness > 4 * nx:
        raise ValueError(f"--thickness {args.thickness} is more than 4 times the images' width ({nx} px)")


def output_dir(args) -> Path:
    """The output directory, checked before anything is written: the default ``STACK_align`` must not be a
    symbolic link (one planted there would take the outputs elsewhere; a ``--out`` link is the user's choice), and
    an existing directory must hold no link (``indreg._outfiles.check_no_links``)."""
    from .._outfiles import check_no_links

    if args.out:
        out = Path(args.out)
    else:
        out = Path(Path(args.stack).with_suffix("").as_posix() + "_align")
        if out.is_symlink():
            raise ValueError(f"the default output directory {out} is a symbolic link (to {os.readlink(out)}); "
                             "indreg never writes through links: remove it or give --out")
    if os.path.lexists(out) and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a directory")
    if out.is_dir():
        check_no_links(out, what="output directory", remedy="give another --out")
    return out


def check_stack(stack: np.ndarray, level: float, path, invert: bool) -> None:
    """The stack (less its background ``level``) can be aligned: not constant, and its object brighter than its
    background (projections of a nonnegative volume; bright-field images, an object darker than the background,
    need ``--invert``)."""
    lo, hi = float(stack.min()), float(stack.max())
    if not hi > lo:
        raise ValueError(f"{path}: the stack is constant (every value {lo:.6g}): there is nothing to align")
    sign = -1.0 if invert else 1.0
    mass = sign * (float(stack.mean(dtype=np.float64)) - level)
    spread = float(np.abs(stack - np.float32(level)).mean(dtype=np.float64))
    if mass < -0.2 * spread:
        fix = "drop --invert" if invert else "give --invert (bright-field contrast)"
        raise ValueError(f"{path}: the object is darker than the background ({level:.6g}, the images' outer frame; "
                         f"mean {sign * mass + level:.6g}): projection matching reconstructs a nonnegative volume; "
                         f"{fix}")


def at_bound(shifts: np.ndarray, bound: np.ndarray, binning: int = 1) -> list:
    """The tilts (indices) whose shift reached its bound in some component (``shifts (K, c)``, ``bound (c,)``
    pixels of images binned by ``binning``), with a warning naming them: the true shift may lie beyond (a tilt that
    matched nothing, or the bound too tight)."""
    hit = sorted({int(k) for k, _ in zip(*np.nonzero(np.abs(shifts) >= np.asarray(bound) - 1e-6))})
    if hit:
        log.warning("%d tilt(s) ended with a shift at its bound (%s px of the stack, a quarter of the image): tilts "
                    "%s; their images may not have matched the reconstruction: check them (align.json: at_bound)",
                    len(hit), ", ".join(f"{b * binning:g}" for b in np.asarray(bound)),
                    ", ".join(map(str, hit[:20])) + (" ..." if len(hit) > 20 else ""))
    return hit
