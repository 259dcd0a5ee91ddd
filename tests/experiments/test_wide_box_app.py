"""The app on a slab specimen wider than the field of view (data=files, a tilt series): the wide box chosen from the
data (data.wide_box=auto), the baselines on it, the files, figure and scores of the field of view, final_wide.npy the
whole box; data.wide_box=false keeps the detector-wide box."""
import json

import numpy as np
import pytest
import torch

from indreg import ImageDomain
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.forward.wide_box import wide_box
from indreg.io import write_tilt_series, write_volume

from experiment_helpers import run_app

ARGS = ["data=files", "data.half_width=8", "geometry=tilt_series", "deformation.num_steps=3", "solver.max_iter=3",
        "kernel.sigma=3", "baseline.tv_iterations=5", "baseline.sirt_iterations=5", "logging.tensorboard=false",
        "logging.progress=false", "device=cpu"]


def slab_files(d):
    """A slab 4 thick in a 16 x 7 x 8 box (unit voxels), its 7 tilts about y of the slab with blobs, three times wider
    than the detector: template.mrc, target.mrc, tilts.mrc (+ .tlt)."""
    dom = ImageDomain((16, 7, 8), (-8.0, -3.5, -4.0), (8.0, 3.5, 4.0))
    g = TiltSeriesGeometry.uniform(-60, 60, 20, det_count=16, det_min=-8.0, det_max=8.0)
    T = TiltSeriesTransform(dom, g)
    box = wide_box(T, thickness=4.0)
    x, _, z = box.domain.points(dtype=torch.float64)
    slab = (z.abs() <= 2.0).double()
    truth = slab + 0.8 * ((((x - 3) / 2.0) ** 2 + (z / 1.2) ** 2) <= 1).double() \
        + 0.8 * ((((x + 13) / 2.0) ** 2 + (z / 1.2) ** 2) <= 1).double()
    write_volume(d / "template.mrc", box.crop(slab).numpy(), dom)
    write_volume(d / "target.mrc", box.crop(truth).numpy(), dom)
    write_tilt_series(d / "tilts.mrc", box.widen(T)(truth).numpy(), g.angles, pixel_size=1.0)
    return [f"data.template={d / 'template.mrc'}", f"data.target={d / 'target.mrc'}",
            f"data.sinogram={d / 'tilts.mrc'}"]


@pytest.mark.slow
def test_app_runs_slab_data_on_the_wide_box(tmp_path):
    files = slab_files(tmp_path)
    m = run_app(ARGS + files, tmp_path / "wide")
    assert m["border"] == "specimen" and m["box_width"] > 1.5 and m["slab_thickness"] == pytest.approx(4.0)
    final, whole = np.load(tmp_path / "wide/final.npy"), np.load(tmp_path / "wide/final_wide.npy")
    assert final.shape == (16, 7, 8) and whole.shape[0] > 16 and whole.shape[1:] == (7, 8)
    assert np.load(tmp_path / "wide/sirt.npy").shape == (16, 7, 8) and (tmp_path / "wide/figure.png").is_file()
    record = json.loads((tmp_path / "wide/outputs.json").read_text())
    assert "final_wide.npy" in json.dumps(record)
    narrow = run_app(ARGS + files + ["data.wide_box=false"], tmp_path / "narrow")
    assert narrow["box_width"] == 1.0 and not (tmp_path / "narrow/final_wide.npy").exists()
    assert m["residual"] < narrow["residual"] and m["sirt_ssim"] > narrow["sirt_ssim"]
