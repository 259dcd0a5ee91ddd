"""The shipped example (``indreg-register experiment=own_data_example``) as one ``indreg.register`` call.

Reads the files of ``indreg/data/own_data_*`` (see ``make_own_data_example.py``), builds the parallel-beam ray
transform of the tilt series, registers the template to the limited-angle data and saves the deformed template.

    python examples/own_data.py [out.npy]
"""
import logging
import sys
from pathlib import Path

import numpy as np

import indreg
from indreg import io

DATA = Path(indreg.__file__).parent / "data"

logging.basicConfig(level=logging.INFO, format="%(message)s")     # progress and warnings (logger "indreg")
template = io.read_image(DATA / "own_data_template.png")          # (64, 64), grey levels 0..255, axis 0 = x
sinogram = io.read_sinogram(DATA / "own_data_sinogram.npy")        # (61 tilts, 92 bins)
angles = io.read_angles(DATA / "own_data_angles.tlt", "deg")       # radians
target = io.read_image(DATA / "own_data_target.npy")               # ground truth (optional)

n = template.shape[0]
domain = indreg.ImageDomain((n, n), (-16.0, -16.0), (16.0, 16.0))  # n x n square cells on [-16, 16]^2
geometry = indreg.ParallelBeamGeometry(det_count=sinogram.shape[1], det_min=-24.0, det_max=24.0, angles=angles)
T = indreg.RayTransform(domain, geometry)

result = indreg.register(template, sinogram, T, sigma=3.0, max_iter=200, target=target, progress=True)
print(f"{result.status} after {result.iterations} iterations: SSIM {result.ssim:.4f}, PSNR {result.psnr:.2f} dB, "
      f"relative data residual {result.residual:.4f}, min Jacobian {result.min_jacobian:.3f}, "
      f"{result.warnings} warnings")
np.save(sys.argv[1] if len(sys.argv) > 1 else "own_data_deformed.npy", result.deformed.cpu().numpy())
