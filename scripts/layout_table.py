"""The app's outputs in the user's layout (docs/own_data.md, "Results in your layout"): for each of scikit-image's,
ASTRA's, TomoPy's and IMOD's conventions, 64^2 files as that tool holds them (the paper's J as the truth, J shifted
by (2, -1) cells as the template, 30 angles over 180 degrees; the data by scikit-image's ``radon`` or by indreg's
operator exported in the tool's layout, angles and units, plus 2 % white noise), run through ``indreg-register
data=files data.convention=<name>`` with the app's defaults. Prints, for ``final.npy`` and the baselines, the SSIM
against the truth as given of the file as written, the best of its seven other flips and turns, and the file in
indreg's layout (as it was written before).

    python scripts/layout_table.py
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch

import indreg
from indreg import phantoms
from indreg.experiments import register
from indreg.io import conventions
from indreg.metrics import ssim

N, HALF = 64, 16.0
DEG = np.linspace(0.0, 180.0, 30, endpoint=False)
NAMES = ("skimage", "astra", "tomopy", "imod")
OUTPUTS = ("final", "fbp", "sirt", "tv")


def turns(a: np.ndarray) -> list:
    """The eight flips and turns of a square array, ``a`` itself first."""
    return [np.rot90(b, k) for b in (a, a.T) for k in range(4)]


def files(name: str, d: Path) -> tuple:
    """The user's files in ``d`` (``t.npy``, ``s.npy``, ``g.npy``, ``a.tlt``); returns (app overrides, truth as
    given)."""
    c = conventions.CONVENTIONS[name]
    domain = conventions.domain_for(c, N, HALF)
    truth = phantoms.get("j", domain).numpy()
    h = 2 * HALF / N
    if name == "skimage":
        from skimage.transform import radon
        sino, angles = radon(conventions.image_from_indreg(truth, c), theta=DEG, circle=False), DEG
    else:
        lo, hi = conventions.detector_for(c, 92, h)
        T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=torch.from_numpy(np.radians(DEG)),
                                                                    det_count=92, det_min=lo, det_max=hi))
        sino = conventions.sinogram_from_indreg(T(torch.from_numpy(truth)).numpy(), c, h)
        angles = np.degrees(conventions.angles_from_indreg(np.radians(DEG), c))
    sino = sino + 0.02 * np.abs(sino).max() * np.random.default_rng(0).standard_normal(sino.shape)
    given = conventions.image_from_indreg(truth, c)
    np.save(d / "t.npy", conventions.image_from_indreg(np.roll(truth, (2, -1), axis=(0, 1)), c))
    np.save(d / "g.npy", given)
    np.save(d / "s.npy", sino)
    (d / "a.tlt").write_text("".join(f"{float(a)!r}\n" for a in angles))
    return ["data=files", f"data.template={d / 't.npy'}", f"data.sinogram={d / 's.npy'}",
            f"data.target={d / 'g.npy'}", f"data.half_width={HALF}", f"data.convention={name}", "geometry=parallel",
            f"geometry.angles={d / 'a.tlt'}", "logging.progress=false", "logging.tensorboard=false"], given


def run(overrides, out: Path) -> dict:
    """The app in-process (what ``indreg-register`` runs, with the run directory ``out``)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(version_base="1.3", config_dir=str(register.CONFIG_DIR), job_name="layout"):
        return register.run(compose(register._CONFIG_NAME, overrides=list(overrides)), out)


def main() -> None:
    print("| convention | " + " | ".join(f"`{k}.npy`" for k in OUTPUTS) + " |")
    print("|---" * (len(OUTPUTS) + 1) + "|")
    for name in NAMES:
        with tempfile.TemporaryDirectory() as tmp:
            overrides, given = files(name, Path(tmp))
            run(overrides, Path(tmp) / "run")
            cells = []
            for key in OUTPUTS:
                a = np.load(Path(tmp) / "run" / f"{key}.npy")
                scores = [ssim(torch.from_numpy(t.copy()), torch.from_numpy(given)) for t in turns(a)]
                before = ssim(torch.from_numpy(conventions.image_to_indreg(a, name).copy()), torch.from_numpy(given))
                cells.append(f"{scores[0]:.4f} / {max(scores[1:]):.4f} / {before:.4f}")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
