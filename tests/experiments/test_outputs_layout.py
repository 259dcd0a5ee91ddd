"""``data=files`` with another tool's convention: the app writes its images (``final``, the baselines,
``template``, ``target``, the trajectory) in the files' layout and its data as the tool holds them, so that a user
compares them with a ground truth as held; the vector fields stay in indreg's; ``outputs.json``, metrics.json and
the last line say so."""
import json
import math

import numpy as np
import pytest
import torch

import indreg
from indreg import phantoms
from indreg.io import conventions
from indreg.metrics import ssim

from experiment_helpers import run_app

N, HALF = 32, 16.0
DEG = np.linspace(0.0, 180.0, 24, endpoint=False)
RUN = ["deformation.num_steps=4", "solver.max_iter=10", "baseline.tv_iterations=20", "baseline.sirt_iterations=20",
       "logging.every=5", "logging.checkpoint_every=5", "logging.progress=false", "logging.figure=false",
       "logging.tensorboard=false"]


def turns(a: np.ndarray) -> list:
    """The eight flips and turns of a square array, ``a`` itself first."""
    return [np.rot90(b, k) for b in (a, a.T) for k in range(4)]


def files(tmp_path, name: str) -> tuple:
    """The user's files in ``name``'s convention: J (truth, no mirror symmetry), J shifted (template), the data
    (scikit-image's own ``radon``, or indreg's operator exported in the tool's layout, angles and units)."""
    c = conventions.CONVENTIONS[name]
    domain = conventions.domain_for(c, N, HALF)
    truth = phantoms.get("j", domain).numpy()
    h = 2 * HALF / N
    if name == "skimage":
        from skimage.transform import radon
        sinogram = radon(conventions.image_from_indreg(truth, c), theta=DEG, circle=False)
        angles = DEG
    else:
        det_min, det_max = conventions.detector_for(c, 46, h)
        T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=torch.from_numpy(np.radians(DEG)),
                                                                    det_count=46, det_min=det_min, det_max=det_max))
        sinogram = conventions.sinogram_from_indreg(T(torch.from_numpy(truth)).numpy(), c, h)
        angles = np.degrees(conventions.angles_from_indreg(np.radians(DEG), c))
    given = {"t": np.roll(truth, 1, axis=0), "g": truth}
    for key, image in given.items():
        np.save(tmp_path / f"{key}.npy", conventions.image_from_indreg(image, c))
    np.save(tmp_path / "s.npy", sinogram)
    (tmp_path / "a.tlt").write_text("".join(f"{float(a)!r}\n" for a in angles))
    args = ["data=files", f"data.template={tmp_path / 't.npy'}", f"data.sinogram={tmp_path / 's.npy'}",
            f"data.target={tmp_path / 'g.npy'}", f"data.half_width={HALF}", f"data.convention={name}",
            "geometry=parallel", f"geometry.angles={tmp_path / 'a.tlt'}"]
    return args, conventions.image_from_indreg(truth, c), sinogram


@pytest.mark.slow
@pytest.mark.parametrize("name", ["skimage", "imod"])
def test_outputs_in_the_files_layout(tmp_path, name):
    args, truth, sinogram = files(tmp_path, name)
    out = tmp_path / "run"
    m = run_app(args + RUN, out)
    for key in ("final", "fbp", "sirt", "tv", "target"):
        scores = [ssim(torch.from_numpy(t.copy()), torch.from_numpy(truth)) for t in turns(np.load(out / f"{key}.npy"))]
        assert scores[0] == max(scores) and scores[0] > sorted(scores)[-2] + 0.1, (key, np.round(scores, 3))
    assert m["ssim"] == pytest.approx(ssim(torch.from_numpy(np.load(out / "final.npy")), torch.from_numpy(truth)),
                                       rel=1e-12)
    np.testing.assert_allclose(np.load(out / "target.npy"), truth, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.load(out / "data.npy"), sinogram, rtol=1e-12, atol=1e-12 * np.abs(sinogram).max())
    trajectory = np.load(out / "trajectory.npy")
    np.testing.assert_array_equal(trajectory[-1], np.load(out / "final.npy"))
    assert np.load(out / "velocity.npy").shape[1:] == (2, N, N)          # components first, indreg's
    assert m["layout"] == name
    record = {e["path"]: e for e in json.loads((out / "outputs.json").read_text())["outputs"]}
    assert record["final.npy"]["convention"] == name and "rows = y" in record["final.npy"]["axis_order"]
    assert record["data.npy"]["convention"] == name and "convention" not in record["velocity.npy"]
    assert record["velocity.npy"]["axis_order"].startswith("(N + 1, d components, *(nx, ny))")
