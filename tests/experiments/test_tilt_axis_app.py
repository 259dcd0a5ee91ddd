"""The app's ``geometry.tilt_axis_angle`` and the tilt-axis check in metrics.json."""

import numpy as np
import pytest

from indreg.experiments.config import ConfigError, validate
from indreg.io import DataFileError, read_stack, write_tilt_series

from experiment_helpers import compose, run_app, write_tilt_series_files

ARGS = ["data=files", "data.half_width=8", "geometry=tilt_series", "deformation.num_steps=3", "solver.max_iter=2",
        "baseline.enabled=false", "logging.figure=false", "logging.tensorboard=false", "logging.progress=false"]


def files(d, stack):
    return [f"data.template={d / 'template.mrc'}", f"data.sinogram={stack}"]


@pytest.fixture
def raw(tmp_path):
    """The helper's aligned series, and the same turned so that its tilt axis runs along X (a 90 degree camera)."""
    write_tilt_series_files(tmp_path)
    aligned = read_stack(tmp_path / "tilts.mrc")
    angles = np.loadtxt(tmp_path / "tilts.tlt")
    write_tilt_series(tmp_path / "raw.mrc", np.rot90(aligned, -1, axes=(1, 2)), np.deg2rad(angles), pixel_size=1.0)
    return tmp_path


def test_angle_gives_the_aligned_run(raw):
    aligned = run_app(ARGS + files(raw, raw / "tilts.mrc"), raw / "aligned")
    turned = run_app(ARGS + files(raw, raw / "raw.mrc") + ["geometry.tilt_axis_angle=90"], raw / "turned")
    assert turned["tilt_axis_angle"] == 90 and aligned["tilt_axis_angle"] is None
    assert turned["tilt_axis_direction"] == aligned["tilt_axis_direction"] == "rows"
    assert turned["tilt_axis_inconsistency"] == aligned["tilt_axis_inconsistency"] < 0.05
    np.testing.assert_array_equal(np.load(raw / "turned/final.npy"), np.load(raw / "aligned/final.npy"))
    np.testing.assert_array_equal(np.load(raw / "turned/data.npy"), np.load(raw / "aligned/data.npy"))


def test_axis_along_x_without_angle_is_reported(raw):
    """The stack turned by 90 degrees without its angle: the orientation probe refuses it naming the angle to add
    (+90, the one that aligns it above); with data.orientation=warn the run reports the check's numbers."""
    with pytest.raises(ConfigError, match=r"add \+90 degrees to the tilt-axis angle \(geometry.tilt_axis_angle"):
        run_app(ARGS + files(raw, raw / "raw.mrc"), raw / "refused")
    m = run_app(ARGS + files(raw, raw / "raw.mrc") + ["data.orientation=warn"], raw / "run")
    assert m["tilt_axis_direction"] == "columns" and m["tilt_axis_inconsistency"] > \
        2 * m["tilt_axis_inconsistency_columns"]


def test_contradicting_angle_is_one_line(raw):
    with pytest.raises(DataFileError, match=r"^data\.sinogram .*raw\.mrc: geometry\.tilt_axis_angle=0\.5 "
                                            r"contradicts the data: turned by -0\.5 degrees, the tilt axis runs "
                                            r"along the image's X") as e:
        run_app(ARGS + files(raw, raw / "raw.mrc") + ["geometry.tilt_axis_angle=0.5"], raw / "run")
    assert "\n" not in str(e.value)


def test_simulated_tilt_series_reports_the_check(tmp_path):
    m = run_app(["experiment=suite_et_3d", "phantom.size=16", "geometry.det_count=16", "geometry.tilt_step=20",
                 "deformation.num_steps=3", "solver.max_iter=1", "baseline.enabled=false", "logging.figure=false",
                 "logging.tensorboard=false", "logging.progress=false"], tmp_path / "run")
    assert m["tilt_axis_direction"] == "rows" and m["tilt_axis_angle"] is None


@pytest.mark.parametrize("overrides, match", [
    (["experiment=suite_et_3d", "geometry.tilt_axis_angle=90"],
     r"geometry\.tilt_axis_angle=90\.0: expected null except for a measured tilt series"),
    (["data=files", "data.template=t.npy", "data.sinogram=s.npy", "geometry=parallel",
      "geometry.tilt_axis_angle=90"], r"geometry\.tilt_axis_angle=90\.0: expected null except"),
    (["data=files", "data.template=t.mrc", "data.sinogram=s.mrc", "geometry=tilt_series",
      "geometry.tilt_axis_angle=nan"], r"geometry\.tilt_axis_angle=nan: expected a finite number"),
])
def test_config_errors(overrides, match):
    with pytest.raises(ConfigError, match=match):
        validate(compose(overrides))
