"""Which settings give indreg's best on a user's own files, and what ``indreg.register``'s defaults give there.

Two cases, loaded with ``indreg.load`` as a user would:

    skimage   scikit-image's Shepp-Logan phantom resized to 128^2 (``skimage.data.shepp_logan_phantom``), the
              target; the template is that picture under a smooth warp (``skimage.transform.warp``); the data are
              ``skimage.transform.radon`` of the target at 60 angles over [0, 180) degrees, read with
              ``convention="skimage"``, ``half_width=16``
    own_data  the shipped example (``indreg/data/own_data_*``, examples/own_data.py): 64^2, 61 tilts over
              -60..60 degrees, 15 dB noise, ``integer_scale="raw"``

Each row is one ``indreg.register`` run (float32, 200 iterations, SSIM against the target): the defaults (no
solver, interpolation or sigma option), the settings documented before (sigma 6, re-interpolation, Algorithm 1),
``solver="fast"``, and widths around the default with both interpolations and solvers; ``sigma="auto"`` last.

    OMP_NUM_THREADS=1 python scripts/own_data_defaults.py [--cases skimage own_data]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

import indreg
from indreg.kernel_width import default_sigma

DATA = Path(indreg.__file__).parent / "data"
RUNS = [
    {},                                                           # the defaults
    {"sigma": 6.0, "interpolation": "reinterpolate"},             # documented before (the paper's suite 1)
    {"solver": "fast", "sigma": 3.0},
    {"sigma": 2.0}, {"sigma": 6.0}, {"sigma": 8.0},               # compose (the default) at other widths
    {"sigma": 4.0, "interpolation": "reinterpolate"}, {"solver": "fast", "sigma": 4.0},
    {"sigma": "auto"},
]


def skimage_case(folder: Path):
    """The scikit-image case, written as a user would save it, then loaded."""
    from skimage.data import shepp_logan_phantom
    from skimage.transform import radon, resize, warp

    n, theta = 128, np.linspace(0.0, 180.0, 60, endpoint=False)
    target = resize(shepp_logan_phantom(), (n, n), anti_aliasing=True)
    r, c = np.mgrid[:n, :n].astype(float)
    template = warp(target, np.array([r + 5.0 * np.sin(c / 18), c + 3.0 * np.cos(r / 25)]), order=1)
    np.save(folder / "template.npy", template)
    np.save(folder / "target.npy", target)
    np.save(folder / "sino.npy", radon(target, theta=theta, circle=True))
    np.savetxt(folder / "sino.tlt", theta)
    return indreg.load(folder / "template.npy", folder / "sino.npy", angles=folder / "sino.tlt",
                       convention="skimage", target=folder / "target.npy", half_width=16)


def own_data_case(folder: Path):
    return indreg.load(DATA / "own_data_template.png", DATA / "own_data_sinogram.npy", "parallel",
                       angles=DATA / "own_data_angles.tlt", det_min=-24.0, det_max=24.0, half_width=16.0,
                       integer_scale="raw", target=DATA / "own_data_target.npy")


CASES = {"skimage": skimage_case, "own_data": own_data_case}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--runs", type=json.loads, default=RUNS, help="a JSON list of option dicts")
    args = parser.parse_args()
    for name in args.cases:
        with tempfile.TemporaryDirectory() as t:
            d = CASES[name](Path(t))
        print(f"\n{name}: {tuple(d.template.shape)}, default sigma {default_sigma(d.domain):g}, template SSIM "
              f"{indreg.metrics.ssim(d.template, d.target):.4f}")
        print("| options | SSIM | residual | status | iterations | seconds |")
        print("|---|---|---|---|---|---|")
        for o in args.runs:
            t0 = time.perf_counter()
            r = indreg.register(d.template, d.data, d.operator, target=d.target, dtype="float32", **o)
            label = ", ".join(f"{k}={v!r}" for k, v in o.items()) or "(defaults)"
            if o.get("sigma") == "auto":
                label += f" -> {r.problem.kernel.sigma:g}"
            print(f"| {label} | {r.ssim:.4f} | {r.residual:.4f} | {r.status} | {r.iterations} | "
                  f"{time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
