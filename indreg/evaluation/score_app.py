"""``indreg-score``: reconstructions from any tool scored on held-out tilts of a stack, through a given alignment and
indreg's operator, with the score of the walk-throughs (:mod:`indreg.evaluation.score`); a table across the files.

    indreg-score STACK VOLUME [VOLUME ...] [--angles STACK.tlt] [--alignment FILE.xf|.aln|.json] [--bin 4]
        [--tilts test=1,3,5 --tilts validation=">=42"] [--scale 1|fit] [--csv table.csv] [--markdown table.md]

Notes
-----
- The stack as stored (``indreg.io.read_tilt_series``: sections = tilts, ``(Y, X)`` images, the tilt axis along
  Y after the alignment), its angles from ``--angles`` or the ``.tlt`` / ``.rawtlt`` beside it; ``--bin b``
  averages ``b x b`` pixels; ``--background`` is subtracted (``auto``: the median of the outermost detector
  columns, ``indreg.units.border_level``; ``none``; or a number in the stack's counts).
- The alignment (``--alignment``): IMOD ``.xf`` (with the stack's angles), AreTomo ``.aln`` or indreg's record
  (the ``.json`` of ``indreg-align`` or of a walk-through), in pixels of the stack as stored
  (``indreg.alignment.files``); applied in the operator, not by resampling. Without it the stack is taken
  as aligned, its tilt axis turned onto Y by ``--tilt-axis-angle`` (degrees, IMOD's;
  ``indreg.alignment.tilt_axis``).
- A volume ``(nx, ny, nz)`` in indreg's layout (x across the tilt axis, y along it, z the beam at tilt 0; an MRC
  file's sections are z): ``.mrc``, ``.npy`` / ``.npz`` / ``.h5``, or OME-Zarr (``.zarr``, optional package
  ``ome-zarr``); ``--swap-yz`` for a volume stored with y and z exchanged (IMOD's ``tilt`` output before
  ``trimvol -rx``), ``--flip-z`` for the other handedness. One slice per detector row: ``ny`` must be the
  binned stack's rows and the voxel side along y its pixel (``--pixel-size`` times ``--bin``; voxel sizes from
  the MRC header or ``--voxel-size``, Angstrom).
- ``--scale 1``: the volume is in the data's units (intensity per ``--length-unit``); a volume whose
  least-squares scale on the scored tilts is outside [1/3, 3] is refused in one line. ``--scale fit``: each
  volume's scale fitted by least squares on ``--scale-tilts`` (default: the aligned tilts in no scored set).
- ``--tilts NAME=SPEC`` (repeatable; default ``all=all``): SPEC is a comma list (union) of ``i`` / ``i-j``
  (0-based section indices), ``odd``, ``even``, ``all``, ``>=D`` / ``<D`` (``|angle|`` in degrees), joined by
  ``&`` for an intersection: ``odd&>=42``.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .tilt_sets import parse_sets, tilt_set  # noqa: F401 (the command line's --tilts)

__all__ = ["main", "tilt_set", "parse_sets"]

log = logging.getLogger("indreg.score")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="indreg-score", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stack", help="tilt series (.mrc/.st/.ali, .npy, .h5:/dataset): (tilts, Y, X) as stored")
    p.add_argument("volumes", nargs="+", help="reconstructions (.mrc, .npy, .npz, .h5, .zarr): (x, y, z)")
    p.add_argument("--angles", help="tilt angles (a .tlt file or a comma list, degrees); default: beside the stack")
    p.add_argument("--alignment", help="an IMOD .xf, an AreTomo .aln or indreg's alignment .json")
    p.add_argument("--tilt-axis-angle", type=float, default=0.0,
                   help="without --alignment: the tilt axis' angle in the images (degrees from Y, IMOD's)")
    p.add_argument("--bin", type=int, default=1, help="pixels averaged per side (default 1)")
    p.add_argument("--pixel-size", type=float, help="the stack's pixel (Angstrom; default: its MRC header, else the "
                                                   "volume's voxel / --bin)")
    p.add_argument("--voxel-size", type=float, help="the volumes' voxel side (Angstrom; default: the MRC header, "
                                                   "else the binned stack's pixel)")
    p.add_argument("--length-unit", default="A", choices=("A", "nm"), help="the unit of the volumes' intensities "
                                                                          "per length (default A)")
    p.add_argument("--background", default="auto", help="auto, none or a number (the stack's counts)")
    p.add_argument("--tilts", action="append", default=[], metavar="NAME=SPEC", help="a set of scored tilts")
    p.add_argument("--scale", default="1", choices=("1", "fit"), help="the volumes' intensity scale (default 1)")
    p.add_argument("--scale-tilts", help="SPEC of the tilts that fit --scale fit (default: the others)")
    p.add_argument("--interpolation", choices=("linear", "cubic"),
                   help="how the alignment moves a projection (default: the record's, else linear)")
    p.add_argument("--swap-yz", action="store_true", help="the volumes are stored (x, z, y)")
    p.add_argument("--flip-z", action="store_true", help="mirror the volumes along z (the other handedness)")
    p.add_argument("--csv", help="write the table as CSV here")
    p.add_argument("--markdown", help="write the table as Markdown here")
    return p


def _check_paths(args) -> None:
    for path in [args.stack, *args.volumes, *([args.alignment] if args.alignment else [])]:
        plain = path.split(":")[0] if ":" in path and not Path(path).exists() else path
        if not Path(plain).exists():
            raise ValueError(f"{path}: no such file")
    if args.bin < 1:
        raise ValueError(f"--bin must be a positive integer, got {args.bin}")
    for name in ("pixel_size", "voxel_size"):
        v = getattr(args, name)
        if v is not None and not v > 0:
            raise ValueError(f"--{name.replace('_', '-')} must be > 0, got {v}")


def main(argv=None) -> int:
    """Console entry point: the table on stdout, one-line errors (exit code 2)."""
    args = _parser().parse_intermixed_args(argv)   # volumes may follow the options
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    try:
        _check_paths(args)
        from .score_run import run   # torch from here on

        table, _ = run(args)
    except (ValueError, TypeError, OSError) as e:
        print(f"indreg-score: error: {e}", file=sys.stderr)
        return 2
    print(table, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
