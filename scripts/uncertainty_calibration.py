"""The calibration of ``indreg.evaluation.uncertainty`` on synthetic cases with a known truth (docs/evaluation.md).

Cases: the paper's suite 1 (J -> V, 64^2, 10 angles, 4.87 dB), a 3D tilt series with a missing wedge (3D Shepp-Logan
-> bent and swirled, 32^3, tilts -60..60 in 4-degree steps, 10 dB) and the metamorphosis case (suite 4: the template
lacks a ventricle, 64^2, 10 angles, 7.06 dB); each registered with ``register()``'s defaults, every 5th (3D: 4th)
angle held out, per model (``lddmm``, ``residual``). The method was chosen on these; ``--cases`` also takes others it
was checked on afterwards: ``et3d45`` (the 3D case over -45..45 in 3-degree steps), ``six`` (suite 2's six triangles
-> six stars at 64^2, 6 angles, 4.75 dB), ``extra`` and ``contrast`` (suite 4's other templates: an extra object, a
changed contrast). Printed per case and model: the fraction of voxels whose error
against the truth lies within 1 and 2 reported standard deviations, over all voxels and over the object's support
(truth or result above 2 % of the truth's maximum, dilated by 2 voxels: outside it template and truth are both
background and every error is 0), the seconds of the registration and of the uncertainty: the mean over the noise
draws ``--seeds`` (default 0, 1, 2; a coverage varies by up to 8 points between draws), with the range.
``--noise-given``: the uncertainty takes the noise's standard deviation as the case drew it (the option
``uncertainty_noise``) instead of estimating it from the data.

    python scripts/uncertainty_calibration.py [--cases suite1,et3d,missing] [--models lddmm,residual] [--noise-given]
        [--seeds 0,1,2]
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


#: The cases the method was chosen on, and cases with the same settings it was checked on afterwards.
CASES, OTHERS = ("suite1", "et3d", "missing"), ("et3d45", "six", "extra", "contrast")


def case(name: str, seed: int = 0) -> tuple:
    """``(template, truth, data, operator, options)``; ``options["noise_sd"]``: the noise drawn, per datum."""
    if name == "suite1":
        d = indreg.ImageDomain.paper(64)
        T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(10, 92))
        I, V, snr, o = phantoms.get("j", d), phantoms.get("v", d), 4.87, dict(sigma=6.0, max_iter=200, holdout=5)
    elif name in ("et3d", "et3d45"):
        end, step = (60, 4) if name == "et3d" else (45, 3)   # the largest tilt, the step (degrees)
        d = indreg.ImageDomain.paper(32, 3)
        T = indreg.TiltSeriesTransform(d, indreg.TiltSeriesGeometry.uniform(-end, end, step, det_count=32,
                                                                            det_min=-16.0, det_max=16.0))
        I, V = phantoms.get("shepp_logan_3d", d), phantoms.get("shepp_logan_3d_swirl", d)
        snr, o = 10.0, dict(sigma=3.0, max_iter=60, num_steps=10, holdout=4, interpolation="compose")
    elif name == "six":
        d = indreg.ImageDomain.paper(64)
        T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(6, 92))
        I, V = phantoms.get("six_objects_template", d), phantoms.get("six_objects_target", d)
        snr, o = 4.75, dict(sigma=2.0, max_iter=200, holdout=5)
    elif name in ("missing", "extra", "contrast"):
        d = indreg.ImageDomain.paper(64)
        T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(10, 92))
        I, V = phantoms.get(f"shepp_logan_template_{name}", d), phantoms.get("shepp_logan", d)
        snr, o = 7.06, dict(sigma=2.0, max_iter=300, holdout=5)
    else:
        raise ValueError(f"unknown case {name!r}: one of {', '.join(CASES + OTHERS)}")
    clean = T(V.double())
    g, _ = noise.add_white_noise(clean, snr_db=snr, seed=seed)
    return I.double(), V.double(), g, T, dict(o, noise_sd=float((g - clean).std()))


def support(truth: torch.Tensor, result: torch.Tensor) -> torch.Tensor:
    """Where the truth or the result exceeds 2 % of the truth's maximum, dilated by 2 voxels."""
    level = 0.02 * float(truth.max())
    return torch.from_numpy(ndimage.binary_dilation(((truth > level) | (result > level)).numpy(), iterations=2))


def row(name: str, model: str, noise_given: bool = False, seed: int = 0) -> dict:
    I, V, g, T, o = case(name, seed)
    sd = o.pop("noise_sd")
    t0 = time.perf_counter()
    r = indreg.register(I, g, T, model=model, uncertainty=True, uncertainty_noise=sd if noise_given else None, **o)
    seconds = time.perf_counter() - t0
    err, sd = r.deformed.double() - V, r.uncertainty.double()
    every, inside = coverage(err, sd), coverage(err, sd, support(V, r.deformed.double()))
    u = r.evaluation["uncertainty_seconds"]
    return {"case": name, "model": model, "ssim": indreg.metrics.ssim(r.deformed.double(), V), "all": every,
            "support": inside, "registration_s": seconds - u, "uncertainty_s": u}


def _cell(values: list) -> str:
    """The mean over the noise draws, with their range when there are several."""
    mean = f"{np.mean(values):.3f}"
    return mean if len(values) == 1 else f"{mean} ({min(values):.3f}-{max(values):.3f})"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", default=",".join(CASES), help=f"also {', '.join(OTHERS)}")
    p.add_argument("--models", default="lddmm,residual")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--noise-given", action="store_true", help="the noise's standard deviation given, not estimated")
    p.add_argument("--seeds", default="0,1,2", help="the noise draws (the table: their mean and range)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    print("| case | model | SSIM | all voxels: 1 s.d. / 2 s.d. | support: 1 s.d. / 2 s.d. | registration s | "
          "uncertainty s |\n|---|---|---|---|---|---|---|", flush=True)
    for name in a.cases.split(","):
        for model in a.models.split(","):
            xs = [row(name, model, a.noise_given, int(seed)) for seed in a.seeds.split(",")]
            mean = lambda key: float(np.mean([x[key] for x in xs]))   # noqa: E731
            cov = lambda where, k: _cell([x[where][k] for x in xs])   # noqa: E731
            print(f"| {name} | {model} | {mean('ssim'):.3f} | {cov('all', 1)} / {cov('all', 2)} | "
                  f"{cov('support', 1)} / {cov('support', 2)} | {mean('registration_s'):.1f} | "
                  f"{mean('uncertainty_s'):.1f} |", flush=True)
    print(f"(68.3 % / 95.4 % for a Gaussian error; the noise {'given' if a.noise_given else 'estimated'}; numpy "
          f"{np.__version__}, torch {torch.__version__})")


if __name__ == "__main__":
    main()
