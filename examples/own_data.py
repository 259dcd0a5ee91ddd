"""The shipped example in Python: indreg.load + indreg.register with indreg's defaults (docs/own_data.md).

Reads the files of ``indreg/data/own_data_*`` (see ``make_own_data_example.py``) as the preset
``indreg/conf/experiment/own_data_example.yaml`` does, registers the template to the limited-angle data with no
solver, interpolation or kernel-width option (sigma 1/8 of the box: 4; compose; SSIM 0.969 in float32, where the
preset's recorded sigma 3 with re-interpolation gives 0.907) and saves the deformed template.

    python examples/own_data.py [out.npy]
"""
import logging
import sys
from pathlib import Path

import numpy as np

import indreg

DATA = Path(indreg.__file__).parent / "data"

logging.basicConfig(level=logging.INFO, format="%(message)s")     # progress and warnings (logger "indreg")
d = indreg.load(DATA / "own_data_template.png",                    # (64, 64), grey levels 0..255, axis 0 = x
                DATA / "own_data_sinogram.npy",                    # (61 tilts, 92 bins)
                "parallel", angles=DATA / "own_data_angles.tlt",   # degrees (angle_unit="deg")
                det_min=-24.0, det_max=24.0,                       # the detector, in the domain's units
                half_width=16.0,                                   # the domain [-16, 16]^2
                integer_scale="raw",                               # grey levels 0..255: the data's intensity unit
                target=DATA / "own_data_target.npy")               # ground truth (optional)

result = indreg.register(d.template, d.data, d.operator, target=d.target, progress=True)     # the defaults
print(f"{result.status} after {result.iterations} iterations: SSIM {result.ssim:.4f}, PSNR {result.psnr:.2f} dB, "
      f"relative data residual {result.residual:.4f}, min Jacobian {result.min_jacobian:.3f}, "
      f"{result.warnings} warnings")
out = Path(sys.argv[1] if len(sys.argv) > 1 else "own_data_deformed.npy").resolve()
np.save(out, result.deformed.cpu().numpy())
print(f"output: the deformed template in {out}")
