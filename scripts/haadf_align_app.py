"""indreg-align on the measured HAADF raw stack (docs/real_data.md: HAADF.mrc + HAADF.rawtlt of etspy 1.3.0's test
data, tilt axis along X: --tilt-axis-angle 90, 3.36 nm pixels), then its shifts against ETSpy's recorded ones
(HAADF_Aligned.hspy) in raw pixels, RMS with a common offset removed and in the gauge of docs/alignment.md, and
SIRT residuals through no shifts, indreg-align's alignment and ETSpy's shifts, on the same binned operator.

    OMP_NUM_THREADS=1 python scripts/haadf_align_app.py /path/to/haadf out_dir [indreg-align options]
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch

from indreg.alignment.app import _bin, _operator, _residual, main as align
from indreg.alignment.files import read_xf
from indreg.alignment.operator import AlignedOperator
from indreg.forward.sirt import sirt

SHIFTS_KEY = "/Experiments/__unnamed__/metadata/Tomography/_sig_shifts/data"   # (tilts, [row, col]), raw px


def etspy_shifts(folder: Path) -> np.ndarray:
    """ETSpy's alignment as the raw-frame shift ``d`` (x, y) of ``raw(M q + d) = aligned(q)``, ``M = I``: ETSpy moved
    each raw image by ``s`` (``aligned(p + s) = raw(p)``), so ``d = -s`` (x = column, y = row)."""
    import h5py

    with h5py.File(folder / "HAADF_Aligned.hspy", "r") as f:
        s = np.asarray(f[SHIFTS_KEY], dtype=np.float64)
    return -s[:, ::-1]


def binned_operator(stack_b, radians, nz, M_raw, d_raw, b, delta):
    """The binned, quarter-turned series' operator with a raw-frame alignment (``indreg.alignment.app``'s frames)."""
    Q = np.round(np.array([[0.0, -1.0], [1.0, 0.0]]))        # R(90): raw = Q rotated
    M = Q.T @ M_raw
    d = (d_raw @ Q - np.einsum("kij,j->ki", np.eye(2) - M, delta)) / b
    T = _operator(stack_b, radians, nz, 0.0).operator
    return AlignedOperator(T, torch.from_numpy(d), 0.0, matrices=torch.from_numpy(M))


def gauge(d: np.ndarray, theta: np.ndarray, offset: bool) -> np.ndarray:
    """Across the axis (raw rows: y) without (1,) cos, sin; along it (x) without its mean."""
    basis = np.stack(([np.ones_like(theta)] if offset else []) + [np.cos(theta), np.sin(theta)], 1)
    across = d[:, 1] - basis @ np.linalg.lstsq(basis, d[:, 1], rcond=None)[0]
    return np.stack([across, d[:, 0] - d[:, 0].mean()], 1)


def run(folder: Path, out: Path, options: list) -> dict:
    from indreg import io

    code = align([str(folder / "HAADF.mrc"), "--tilt-axis-angle", "90", "--pixel-size", "33.6", "--out", str(out)]
                 + options)
    assert code == 0
    summary = json.loads((out / "align.json").read_text())
    raw, radians = io.read_tilt_series(folder / "HAADF.mrc", folder / "HAADF.rawtlt")
    mine = read_xf(out / "alignment.xf")
    theirs = etspy_shifts(folder)
    common = (mine.shifts - theirs) - (mine.shifts - theirs).mean(0)
    b, nz = summary["binning"], summary["volume_shape"][2]
    stack_b, delta = _bin(np.ascontiguousarray(np.rot90(raw, 1, axes=(1, 2)), dtype=np.float32), b)
    stack_b -= summary["background"]
    data = torch.from_numpy(stack_b)
    eye = np.tile(np.eye(2), (len(radians), 1, 1))
    residuals = {}
    for name, (M, d) in {"none": (np.tile(np.round([[0.0, -1.0], [1.0, 0.0]]), (len(radians), 1, 1)),
                                  np.zeros_like(theirs)),
                         "indreg-align": (mine.matrices, mine.shifts),
                         "etspy": (np.round([[0.0, -1.0], [1.0, 0.0]]) @ eye, theirs)}.items():
        op = binned_operator(stack_b, radians, nz, M, d, b, delta)
        x, _ = sirt(op, data, num_iter=100, nonneg=True)
        residuals[name] = _residual(op, x, data)
    result = {"shift_rms_common_offset_px": np.sqrt((common[:, ::-1] ** 2).mean(0)).tolist(),   # [across, along]
              "shift_rms_gauge_px": np.sqrt(((gauge(mine.shifts, radians, True) - gauge(theirs, radians, True)) ** 2)
                                            .mean(0)).tolist(),
              "sirt100_residual": residuals, "axis_angle_deg": summary["axis_angle_deg"],
              "align_residual_before_after": [summary["residual_before"], summary["residual_after"]],
              "seconds": summary["seconds"], "binning": b, "components": ["across", "along"]}
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    run(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:])
