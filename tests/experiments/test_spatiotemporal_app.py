"""The spatiotemporal model in the indreg-register app: a tiny dynamic run, its outputs, resume, the CLI."""
import json
import logging

import imageio.v2 as imageio
import numpy as np
import pytest

from experiment_helpers import run_app, run_cli

DYN = ["experiment=suite_dynamic_2d", "phantom.size=24", "data.frames=3", "geometry.num_angles=3",
       "geometry.det_count=36", "deformation.num_steps=3", "solver.max_iter=6", "logging.every=3",
       "logging.checkpoint_every=3", "logging.progress=false", "dtype=float64", "device=cpu"]


@pytest.mark.slow
def test_dynamic_run_outputs_and_resume(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="indreg")
    ref = run_app(DYN, tmp_path / "ref")
    assert ref["status"] == "completed" and ref["iterations"] == 6 and 0 < ref["frames_ssim"] <= 1
    headline = [r.getMessage() for r in caplog.records if r.getMessage().startswith("done: 6 iterations")]
    # the model's summary, the means over the frames, not the last frame's SSIM
    assert len(headline) == 1 and f"SSIM {ref['frames_ssim']:.4f}, PSNR {ref['frames_psnr']:.2f} dB (means over the " \
        "3 frames)" in headline[0], headline
    assert np.load(tmp_path / "ref" / "frames.npy").shape == (3, 24, 24)
    assert (tmp_path / "ref" / "frames.png").stat().st_size > 10_000
    assert np.asarray(imageio.mimread(tmp_path / "ref" / "frames.gif")[0]).shape[:2] == (264, 264)  # 24 px x 11
    out = tmp_path / "run"
    assert run_app(DYN + ["stop_after=3"], out)["status"] == "stopped"
    second = run_app(DYN + ["resume=true"], out)
    assert second["objective"] == pytest.approx(ref["objective"], rel=1e-12)
    np.testing.assert_allclose(np.load(out / "frames.npy"), np.load(tmp_path / "ref" / "frames.npy"), atol=1e-12)


@pytest.mark.parametrize("update", ["joint", "intertwined"])
def test_unknown_template_resume(tmp_path, update):
    over = DYN + ["data.template_known=false", f"solver.template_update={update}", "solver.registration_steps=2",
                  "solver.template_steps=5",
                  "solver.template_tv_weight=0.05", "logging.figure=false", "logging.tensorboard=false"]
    ref = run_app(over, tmp_path / "ref")
    assert np.load(tmp_path / "ref" / "template.npy").shape == (24, 24) and "template_ssim" in ref
    out = tmp_path / "run"
    run_app(over + ["stop_after=3"], out)
    second = run_app(over + ["resume=true"], out)
    assert second["objective"] == pytest.approx(ref["objective"], rel=1e-12)
    np.testing.assert_allclose(np.load(out / "template.npy"), np.load(tmp_path / "ref" / "template.npy"), atol=1e-12)


@pytest.mark.slow
def test_cli_dynamic_with_resume(tmp_path):
    run_dir = tmp_path / "cli"
    args = DYN + ["logging.figure=false", "logging.tensorboard=false", f"hydra.run.dir={run_dir}"]
    first = run_cli(args + ["stop_after=3"], tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    second = run_cli(args + ["resume=true"], tmp_path)
    assert second.returncode == 0, second.stderr[-2000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["status"] == "completed" and metrics["iterations"] == 6
    bad = run_cli(DYN + ["deformation.backward=paper", f"hydra.run.dir={tmp_path / 'bad'}"], tmp_path)
    assert bad.returncode == 1 and "deformation.backward" in bad.stderr and bad.stderr.count("\n") <= 2


