"""A volume reconstructed outside indreg, by scikit-image, through the walk-through's alignment, for ``indreg-score``
(docs/evaluation.md, "indreg-score").

Reads what ``examples/real_data_haadf.py`` wrote in ``--run DIR/scored`` (``stack.npy``, ``stack.tlt``,
``alignment.json``, ``sets.json``), moves the fitted tilts back by the alignment (the inverse of its shifts and
tilt-axis angle: the aligned stack, as IMOD's ``newstack -xf`` would make it; ``indreg.alignment.operator``), and
reconstructs every slice across the tilt axis with ``skimage.transform.iradon_sart`` (``--iters`` SART iterations,
no positivity, scikit-image's own projector), in scikit-image's conventions (``indreg.io.conventions``,
``skimage``: picture layout, sinogram ``(bins, angles)``, pixel sums; with as many bins as pixels its image and
detector centres meet as indreg's do: a volume projected by indreg and reconstructed so is fitted to 4 - 7 % per
slice after 10 iterations, against 8 - 18 % moved by half a pixel); writes ``DIR/skimage_sart.mrc`` (voxel size in
Angstrom, the stack's pixel). Then, from ``DIR``:

    indreg-score ... skimage_sart.mrc --scale fit   (the command ``real_data_haadf.py`` printed, with this volume)

    python examples/score_outside_volume.py --run real_data_haadf [--iters 10]
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import indreg  # noqa: F401  (first: OMP_WAIT_POLICY)
import numpy as np
import torch


def aligned_stack(folder: Path, background: float) -> tuple:
    """``(the scored tilts moved back by their alignment, less the background, angles in radians, fit indices,
    pixel in Angstrom)``."""
    from indreg.alignment.files import to_operator
    from indreg.domain import ImageDomain
    from indreg.evaluation.score_run import read_any_alignment
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform

    stack = np.load(folder / "stack.npy") - background
    radians = np.radians(np.loadtxt(folder / "stack.tlt", ndmin=1))
    sets = json.loads((folder / "sets.json").read_text())
    if not (folder / "alignment.json").exists():   # an aligned stack
        return stack, radians, sets["fit"], None
    record = json.loads((folder / "alignment.json").read_text())
    pixel = float(record["pixel_size"])
    k, rows, cols = stack.shape
    domain = ImageDomain((cols, rows, cols), (-cols / 2,) * 3, (cols / 2,) * 3)   # unit pixels
    T = TiltSeriesTransform(domain, TiltSeriesGeometry(torch.as_tensor(radians), det_count=cols,
                                                       det_min=-cols / 2, det_max=cols / 2, angle_unit="rad"))
    A = to_operator(T, read_any_alignment(str(folder / "alignment.json"), None)[0],
                    interpolation=record.get("interpolation", "linear"))
    c, s = math.cos(float(A.angle)), math.sin(float(A.angle))
    back = -A.shifts @ torch.tensor([[c, -s], [s, c]], dtype=torch.float64)   # the inverse map (square pixels)
    moved = A.warp(torch.from_numpy(stack), back, -A.angle).numpy()
    return moved, radians, sets["fit"], pixel


def reconstruct(moved: np.ndarray, radians: np.ndarray, fit: list, iters: int) -> np.ndarray:
    """Every slice (a detector row) by scikit-image's SART from the fit tilts; ``(x, y, z)`` in pixel units
    (intensity per pixel: ``indreg-score --scale fit`` takes the unit)."""
    from skimage.transform import iradon_sart

    from indreg.io.conventions import angles_from_indreg, image_to_indreg, sinogram_from_indreg

    theta = np.degrees(angles_from_indreg(radians[fit], "skimage"))
    k, rows, cols = moved.shape
    out = np.zeros((cols, rows, cols))
    for j in range(rows):
        sino = sinogram_from_indreg(moved[fit, j, :], "skimage", 1.0)
        image = None
        for _ in range(iters):
            image = iradon_sart(sino, theta=theta, image=image)
        out[:, j, :] = image_to_indreg(image, "skimage")
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", type=Path, required=True, help="the walk-through's output folder")
    p.add_argument("--iters", type=int, default=10, help="SART iterations (default 10)")
    p.add_argument("--background", type=float, help="subtracted from the stack (default: the run's)")
    p.add_argument("--pixel-size", type=float, help="Angstrom (default: the alignment record's)")
    a = p.parse_args(argv)
    metrics = json.loads((a.run / "metrics.json").read_text())
    background = metrics["registration"]["background"] if a.background is None else a.background
    moved, radians, fit, pixel = aligned_stack(a.run / "scored", background)
    pixel = a.pixel_size or pixel
    if pixel is None:
        raise SystemExit("score_outside_volume.py: error: no alignment record to take the pixel from: --pixel-size")
    volume = reconstruct(moved, radians, fit, a.iters)
    from indreg.io.volume_files import write_mrc

    h = pixel
    write_mrc(a.run / "skimage_sart.mrc", volume, (h, h, h), [-(n - 1) / 2 * h for n in volume.shape])
    print(f"wrote {a.run / 'skimage_sart.mrc'}: {volume.shape}, {a.iters} SART iterations from {len(fit)} tilts")


if __name__ == "__main__":
    main()
