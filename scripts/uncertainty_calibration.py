"""The calibration of ``indreg.evaluation.uncertainty`` on synthetic cases with a known truth (docs/evaluation.md).

Cases: the paper's suite 1 (J -> V, 64^2, 10 angles, 4.87 dB), a 3D tilt series with a missing wedge (3D Shepp-Logan
-> bent and swirled, 32^3, tilts -60..60 in 4-degree steps, 10 dB) and the metamorphosis case (suite 4: the template
lacks a ventricle, 64^2, 10 angles, 7.06 dB); each registered with ``register()``'s defaults, every 5th (3D: 4th)
angle held out, per model (``lddmm``, ``residual``). Printed per case and model: the fraction of voxels whose error
against the truth lies within 1 and 2 reported standard deviations, over all voxels and over the object's support
(truth or result above 2 % of the truth's maximum, dilated by 2 voxels: outside it template and truth are both
background and every error is 0), the seconds of the registration and of the uncertainty.

    python scripts/uncertainty_calibration.py [--cases suite1,et3d,missing] [--models lddmm,residual]
"""
from __future__ import annotations

import argparse
import time

import indreg  # first: OMP_WAIT_POLICY (indreg._openmp)
import numpy as np
import torch
from scipy import ndimage

from indreg import noise, phantoms
from indreg.evaluation.uncertainty import coverage


def case(name: str) -> tuple:
    """``(template, truth, data, operator, options)``."""
    if name == "suite1":
        d = indreg.ImageDomain.paper(64)
        T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(10, 92))
        I, V, snr, o = phantoms.get("j", d), phantoms.get("v", d), 4.87, dict(sigma=6.0, max_iter=200, holdout=5)
    elif name == "et3d":
        d = indreg.ImageDomain.paper(32, 3)
        T = indreg.TiltSeriesTransform(d, indreg.TiltSeriesGeometry.uniform(-60, 60, 4, det_count=32, det_min=-16.0,
                                                                            det_max=16.0))
        I, V = phantoms.get("shepp_logan_3d", d), phantoms.get("shepp_logan_3d_swirl", d)
        snr, o = 10.0, dict(sigma=3.0, max_iter=60, num_steps=10, holdout=4, interpolation="compose")
    elif name == "missing":
        d = indreg.ImageDomain.paper(64)
        T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(10, 92))
        I, V = phantoms.get("shepp_logan_template_missing", d), phantoms.get("shepp_logan", d)
        snr, o = 7.06, dict(sigma=2.0, max_iter=300, holdout=5)
    else:
        raise ValueError(f"unknown case {name!r}: suite1, et3d or missing")
    g, _ = noise.add_white_noise(T(V.double()), snr_db=snr, seed=0)
    return I.double(), V.double(), g, T, o


def support(truth: torch.Tensor, result: torch.Tensor) -> torch.Tensor:
    """Where the truth or the result exceeds 2 % of the truth's maximum, dilated by 2 voxels."""
    level = 0.02 * float(truth.max())
    return torch.from_numpy(ndimage.binary_dilation(((truth > level) | (result > level)).numpy(), iterations=2))


def row(name: str, model: str) -> dict:
    I, V, g, T, o = case(name)
    t0 = time.perf_counter()
    r = indreg.register(I, g, T, model=model, uncertainty=True, **o)
    seconds = time.perf_counter() - t0
    err, sd = r.deformed.double() - V, r.uncertainty.double()
    every, inside = coverage(err, sd), coverage(err, sd, support(V, r.deformed.double()))
    u = r.evaluation["uncertainty_seconds"]
    return {"case": name, "model": model, "ssim": indreg.metrics.ssim(r.deformed.double(), V), "all": every,
            "support": inside, "registration_s": seconds - u, "uncertainty_s": u}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", default="suite1,et3d,missing")
    p.add_argument("--models", default="lddmm,residual")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    print("| case | model | SSIM | all voxels: 1 s.d. / 2 s.d. | support: 1 s.d. / 2 s.d. | registration s | "
          "uncertainty s |\n|---|---|---|---|---|---|---|", flush=True)
    for name in a.cases.split(","):
        for model in a.models.split(","):
            x = row(name, model)
            print(f"| {x['case']} | {x['model']} | {x['ssim']:.3f} | {x['all'][1]:.3f} / {x['all'][2]:.3f} | "
                  f"{x['support'][1]:.3f} / {x['support'][2]:.3f} | {x['registration_s']:.1f} | "
                  f"{x['uncertainty_s']:.1f} |", flush=True)
    print(f"(68.3 % / 95.4 % for a Gaussian error; numpy {np.__version__}, torch {torch.__version__})")


if __name__ == "__main__":
    main()
