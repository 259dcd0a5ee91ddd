"""The app's ``data.alignment``: a raw stack with its tilt axis along X and IMOD's .xf of the quarter turn gives the
run on the aligned stack (the turn applied in the operator, at whole pixels: exactly)."""
import numpy as np
import pytest

from indreg.io import read_stack, write_tilt_series

from experiment_helpers import run_app, write_tilt_series_files

ARGS = ["data=files", "data.half_width=8", "geometry=tilt_series", "deformation.num_steps=3", "solver.max_iter=2",
        "baseline.enabled=false", "logging.figure=false", "logging.tensorboard=false", "logging.progress=false"]


@pytest.mark.slow
def test_xf_of_a_quarter_turn_gives_the_aligned_run(tmp_path):
    write_tilt_series_files(tmp_path)
    aligned = read_stack(tmp_path / "tilts.mrc")
    angles = np.loadtxt(tmp_path / "tilts.tlt")
    write_tilt_series(tmp_path / "raw.mrc", np.rot90(aligned, -1, axes=(1, 2)), np.deg2rad(angles), pixel_size=1.0)
    # raw[r, c] = aligned[n-1-c, r]: centred (x, y) of the raw image is (y, -x) of the aligned one, u' = A u
    np.savetxt(tmp_path / "raw.xf", np.tile([0.0, 1.0, -1.0, 0.0, 0.0, 0.0], (len(angles), 1)))
    np.savetxt(tmp_path / "raw.tlt", angles)
    files = [f"data.template={tmp_path / 'template.mrc'}"]
    plain = run_app(ARGS + files + [f"data.sinogram={tmp_path / 'tilts.mrc'}"], tmp_path / "aligned")
    turned = run_app(ARGS + files + [f"data.sinogram={tmp_path / 'raw.mrc'}", f"data.alignment={tmp_path / 'raw.xf'}"],
                     tmp_path / "turned")
    np.testing.assert_allclose(np.load(tmp_path / "turned/final.npy"), np.load(tmp_path / "aligned/final.npy"),
                               atol=1e-5)   # the app runs in float32
    assert abs(turned["residual"] - plain["residual"]) < 1e-5 and turned["alignment"]["mode"] == "fixed"
