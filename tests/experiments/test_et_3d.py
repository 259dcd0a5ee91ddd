"""The 3D app: suite_et_3d through the CLI on a tiny volume, tilt-series files, 3D config errors."""
import json

import numpy as np
import pytest

from experiment_helpers import compose, run_app, run_cli, write_tilt_series_files

# 16^3, 7 tilts (-60..60 step 20), N = 3, 3 iterations
TINY_3D = ["experiment=suite_et_3d", "phantom.size=16", "geometry.det_count=16", "geometry.tilt_step=20",
           "deformation.num_steps=3", "solver.max_iter=3", "baseline.tv_iterations=5", "baseline.sirt_iterations=5",
           "logging.every=1", "logging.checkpoint_every=1", "logging.progress=false"]


@pytest.mark.slow   # 120 s at load 15-20: the 3D app through its console script
def test_cli_suite_et_3d_tiny(tmp_path):
    out = tmp_path / "run"
    proc = run_cli(TINY_3D + [f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "completed" and m["iterations"] == 3
    for key in ("ssim", "psnr", "ssim_paper", "fbp_ssim", "sirt_ssim", "tv_ssim", "template_ssim", "min_jacobian"):
        assert np.isfinite(m[key]), key
    assert m["objective"] < json.loads((out / "history.json").read_text())[0]["objective"]
    final = np.load(out / "final.npy")
    assert final.shape == (16, 16, 16) and np.load(out / "data.npy").shape == (7, 16, 16)
    assert np.load(out / "trajectory.npy").shape == (4, 16, 16, 16)
    from indreg.io import read_voxel_size, read_volume
    np.testing.assert_allclose(read_volume(out / "final.mrc"), final, rtol=1e-6, atol=1e-6)  # float32 in MRC
    assert read_voxel_size(out / "final.mrc") == pytest.approx((2.0, 2.0, 2.0))
    assert (out / "figure.png").stat().st_size > 10_000 and (out / "sirt.npy").is_file()


# solver=fast on the tiny volume: one coarse level 8^3 (N = 3, 2 iterations), then 16^3
FAST_3D = ["solver=fast", "solver.optimizer_kwargs.levels=[2]", "solver.optimizer_kwargs.level_steps=[3]",
           "solver.optimizer_kwargs.level_iter=[2]", "solver.optimizer_kwargs.min_size=8"]


def _check_3d_outputs(out, iterations):
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "completed" and m["iterations"] == iterations
    assert np.isfinite(m["ssim"]) and m["min_jacobian"] > 0
    assert m["objective"] < json.loads((out / "history.json").read_text())[0]["objective"]
    from indreg.io import read_volume
    np.testing.assert_allclose(read_volume(out / "final.mrc"), np.load(out / "final.npy"), rtol=1e-6, atol=1e-6)
    return m


@pytest.mark.slow
def test_cli_suite_et_3d_fast(tmp_path):
    """``experiment=suite_et_3d solver=fast``: coarse to fine on the volume, 2 iterations on 8^3, 2 on 16^3."""
    out = tmp_path / "run"
    proc = run_cli(TINY_3D + FAST_3D + ["solver.max_iter=4", "baseline=none", f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = _check_3d_outputs(out, 4)
    history = json.loads((out / "history.json").read_text())
    assert [h["level"] for h in history] == [0, 0, 1, 1] and [h["grid"] for h in history] == [8, 8, 16, 16]
    assert m["hparams"]["solver"] == "fast" and np.load(out / "momentum.npy").shape == (4, 3, 16, 16, 16)


@pytest.mark.slow
def test_cli_suite_et_3d_metamorphosis(tmp_path):
    """``experiment=suite_et_3d deformation=metamorphosis``: the volume, its source and parts, parts.png."""
    out = tmp_path / "run"
    proc = run_cli(TINY_3D + ["deformation=metamorphosis", "baseline=none", f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = _check_3d_outputs(out, 3)
    assert m["hparams"]["model"] == "metamorphosis" and m["source_regulariser"] > 0
    assert np.isfinite(m["deformation_part_ssim"])
    assert np.load(out / "source.npy").shape == (4, 16, 16, 16)
    final, parts = np.load(out / "final.npy"), [np.load(out / f"{k}.npy") for k in ("deformation_part", "intensity_part")]
    np.testing.assert_allclose(parts[0] + parts[1], final, atol=1e-5)
    assert (out / "parts.png").stat().st_size > 10_000 and (out / "figure.png").is_file()


@pytest.mark.slow
def test_fast_3d_resume_like_uninterrupted(tmp_path):
    """solver=fast on the volume stopped on the coarse level and on the fine level, resumed: the uninterrupted
    run's history exactly."""
    args = TINY_3D + FAST_3D + ["solver.max_iter=5", "baseline.enabled=false", "logging.figure=false",
                                "logging.tensorboard=false", "dtype=float64"]
    ref = run_app(args, tmp_path / "ref")
    out = tmp_path / "run"
    assert run_app(args + ["stop_after=1"], out)["status"] == "stopped"
    assert run_app(args + ["stop_after=3", "resume=true"], out)["status"] == "stopped"
    res = run_app(args + ["resume=true"], out)
    a, b = (json.loads((d / "history.json").read_text()) for d in (tmp_path / "ref", out))
    assert [h["level"] for h in a] == [0, 0, 1, 1, 1] and [h["grid"] for h in a] == [8, 8, 16, 16, 16]
    for key in ("iteration", "objective", "evaluations", "grad_norm", "step_size", "level"):
        assert [h[key] for h in b] == [h[key] for h in a], key
    assert res["objective"] == ref["objective"] and res["evaluations"] == ref["evaluations"]
    np.testing.assert_array_equal(np.load(out / "final.npy"), np.load(tmp_path / "ref" / "final.npy"))


def test_tilt_series_files_resume_like_uninterrupted(tmp_path):
    """data=files with geometry=tilt_series: an MRC volume and an MRC stack with its .tlt; stopping after 2
    iterations and resuming gives the numbers of an uninterrupted run."""
    write_tilt_series_files(tmp_path)
    args = ["data=files", f"data.template={tmp_path / 'template.mrc'}", f"data.sinogram={tmp_path / 'tilts.mrc'}",
            "data.half_width=8", "geometry=tilt_series", "deformation.num_steps=3",
            "solver.max_iter=4", "baseline.enabled=false", "logging.figure=false", "logging.tensorboard=false",
            "logging.progress=false", "logging.checkpoint_every=1", "dtype=float64"]
    whole = run_app(args, tmp_path / "whole")
    assert whole["status"] == "completed" and 0 < whole["residual"] < 1
    assert run_app(args + ["stop_after=2"], tmp_path / "split")["status"] == "stopped"
    resumed = run_app(args + ["resume=true"], tmp_path / "split")
    assert resumed["objective"] == whole["objective"]
    exp_cfg = compose(args)
    from indreg.experiments.build import build
    exp = build(exp_cfg)
    assert exp.domain.shape == (16, 16, 12) and exp.domain.cell_sides == (1.0, 1.0, 1.0)
    assert exp.geometry.det_min == -8.0 and exp.ray_transform.range_shape == (7, 16, 16)


@pytest.mark.parametrize("overrides,match", [
    (["geometry=tilt_series", "geometry.det_count=32"], r"phantom\.ndim.*3 for geometry\.kind=tilt_series"),
    (["experiment=suite_et_3d", "geometry=parallel", "geometry.num_angles=10", "geometry.det_count=64"],
     r"phantom\.ndim.*2 for geometry\.kind=parallel"),
    (["experiment=suite_et_3d", "geometry.tilt_step=0"], r"geometry\.tilt_step"),
    (["experiment=suite_et_3d", "geometry.tilt_min=70"], r"geometry\.tilt_min"),
    (["experiment=suite_et_3d", "phantom.ndim=4"], r"phantom\.ndim"),
    (["experiment=suite_et_3d_slab", "phantom.thickness=300"], r"phantom\.thickness.*\[7, phantom\.size\]"),
    (["experiment=suite_et_3d_slab", "phantom.thickness=6"], r"phantom\.thickness"),
    (["phantom.thickness=8"], r"phantom\.thickness.*for volumes"),
    (["experiment=suite_et_3d_1024_slab", "phantom.rows=2000"], r"phantom\.rows.*\[7, phantom\.size\]"),
    (["experiment=suite_et_3d_1024_slab", "phantom.rows=6"], r"phantom\.rows"),
    (["phantom.rows=8"], r"phantom\.rows.*for volumes"),
])
def test_3d_config_errors(overrides, match):
    from indreg.experiments.config import ConfigError, validate

    with pytest.raises(ConfigError, match=match):
        validate(compose(overrides))


def test_slab_preset_through_the_app(tmp_path):
    """suite_et_3d_slab at 16 x 16 x 8: cubic cells on [-8, 8]^2 x [-4, 4] (1-unit voxels), the phantom flattened
    into the slab (its mean over the box as in the cube), a completed run."""
    from indreg.experiments.build import build

    args = ["experiment=suite_et_3d_slab", "phantom.size=16", "phantom.thickness=8", "phantom.half_width=8",
            "geometry.det_count=16", "geometry.det_min=-8", "geometry.det_max=8", "solver.max_iter=2",
            "baseline.enabled=false", "logging.figure=false", "logging.tensorboard=false", "logging.progress=false"]
    exp = build(compose(args))
    assert exp.domain.shape == (16, 16, 8) and exp.domain.cell_sides == (1.0, 1.0, 1.0)
    assert exp.domain.min_pt == (-8.0, -8.0, -4.0) and exp.ray_transform.range_shape == (61, 16, 16)
    cube = build(compose(args[:1] + ["phantom.size=16", "phantom.half_width=8", "phantom.thickness=16",
                                     "geometry.det_count=16", "geometry.det_min=-8", "geometry.det_max=8"]))
    # the phantom lives on the box's normalised coordinates: flattened, its mean over the box is the cube's
    assert float(exp.template.mean()) == pytest.approx(float(cube.template.mean()), rel=0.03)
    assert float(exp.template.mean()) > 0.05
    m = run_app(args, tmp_path)
    assert m["status"] == "completed" and m["iterations"] == 2 and np.isfinite(m["ssim"])
    assert np.load(tmp_path / "final.npy").shape == (16, 16, 8)


def test_full_width_slab_preset_through_the_app(tmp_path):
    """suite_et_3d_1024_slab shrunk to 32 x 8 x 8 (phantom.rows: a slab of rows along the tilt axis y): cubic cells,
    the detector as wide as x, the data term slab-wise (slabs of 4 slices here), a completed run."""
    from indreg.experiments.build import build
    from indreg.problems.slabs import SlabwiseRegistration

    args = ["experiment=suite_et_3d_1024_slab", "phantom.size=32", "phantom.rows=8", "phantom.thickness=8",
            "geometry.det_count=32", "deformation.slab_size=4", "solver.max_iter=2", "baseline.enabled=false",
            "logging.figure=false", "logging.tensorboard=false", "logging.progress=false"]
    exp = build(compose(args))
    assert exp.domain.shape == (32, 8, 8) and exp.domain.cell_sides == (1.0, 1.0, 1.0)
    assert exp.domain.min_pt == (-16.0, -4.0, -4.0) and exp.ray_transform.range_shape == (61, 8, 32)
    assert isinstance(exp.problem, SlabwiseRegistration) and len(exp.problem.slab_ranges) == 2
    m = run_app(args, tmp_path)
    assert m["status"] == "completed" and m["iterations"] == 2 and np.isfinite(m["ssim"])
    assert np.load(tmp_path / "final.npy").shape == (32, 8, 8)


def test_velocity_factor_through_the_app(tmp_path):
    """deformation.velocity_factor=2: the momentum and velocity on 8^3, the volumes and phi_{1,0} on 16^3."""
    m = run_app(TINY_3D + ["deformation.velocity_factor=2", "baseline.enabled=false", "logging.figure=false",
                           "logging.tensorboard=false"], tmp_path)
    assert m["status"] == "completed" and m["iterations"] == 3 and np.isfinite(m["ssim"]) and m["min_jacobian"] > 0
    assert np.load(tmp_path / "momentum.npy").shape == np.load(tmp_path / "velocity.npy").shape == (4, 3, 8, 8, 8)
    assert np.load(tmp_path / "deformation.npy").shape == (3, 16, 16, 16)
    assert np.load(tmp_path / "final.npy").shape == (16, 16, 16)


@pytest.mark.parametrize("overrides,match", [
    (["experiment=suite_et_3d", "phantom.size=16", "deformation.velocity_factor=3"],
     r"velocity_factor=3: expected an integer >= 1 dividing every axis of the grid \(16, 16, 16\)"),
    (["deformation.velocity_factor=2", "deformation.interpolation=reinterpolate"],
     r"deformation\.interpolation='reinterpolate': expected 'compose'"),
])
def test_velocity_factor_config_errors(overrides, match):
    from indreg.experiments.build import build
    from indreg.experiments.config import ConfigError, validate

    cfg = compose(overrides)
    with pytest.raises(ConfigError, match=match):
        validate(cfg)
        build(cfg)
