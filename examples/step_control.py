"""Step control at another intensity scale (suite 1 with template and data x10).

The objective's gradient scales with the square of the intensities, so the paper's fixed absolute step (0.02 with
gamma 1e-6, tuned for grey levels 0..1) is 100 times too long at x10 and folds the deformation;
``indreg.register``'s defaults (the step relative to the data term, and step halving) give the same result at every
scale. Prints one line per run (docs/accuracy.md, "Step control": x10 fixed step SSIM 0.3761, min Jacobian -467).

    python examples/step_control.py [scale]
"""
import logging
import sys

import indreg
from indreg import noise, phantoms

logging.basicConfig(level=logging.WARNING, format="%(message)s")
scale = float(sys.argv[1]) if len(sys.argv) > 1 else 10.0
domain = indreg.ImageDomain.paper(64)
T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(10, 92))
template, target = phantoms.get("j", domain), phantoms.get("v", domain)
data, _ = noise.add_white_noise(T(target), snr_db=4.87, seed=0)       # suite 1's data
for label, options in (("paper's fixed step", {"step_size": 0.02, "gamma": 1e-6, "step_halving": False}),
                       ("default (step halving)", {})):
    for s in (1.0, scale):
        r = indreg.register(s * template, s * data, T, dtype="float32", target=s * target, **options)
        print(f"x{s:g}, {label}: SSIM {r.ssim:.4f}, PSNR {r.psnr:.2f} dB, min Jacobian {r.min_jacobian:.3g}, "
              f"{r.warnings} warnings ({sum(h['rejected'] for h in r.history)} rejected steps), "
              f"final step {r.history[-1]['step_size']:.3g}")
