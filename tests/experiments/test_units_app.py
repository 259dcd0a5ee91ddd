"""The app on measured data as they come: ``data.template_scale`` / ``data.background``, diverged runs (exit 1),
halvings in metrics.json, the paper's PSNR convention only for the paper's phantoms, files checked before the run
directory exists, the TV baseline's weight at the data's scale."""
import json
import logging

import numpy as np
import pytest

from indreg import metrics
from indreg.experiments.config import DATA_DIR, ConfigError
from indreg.forward import tv_weight_unit
from indreg.io import read_image

from experiment_helpers import FAST, TINY, compose, run_app, run_cli

OWN = ["experiment=own_data_example", "deformation.num_steps=10", "baseline.enabled=false", "logging.figure=false",
       "logging.tensorboard=false", "logging.progress=false", "device=cpu"]


def unit_files(d):
    """The own-data example's template as a PNG (grey levels 0..255, read raw by the preset) and its sinogram in 0..1
    units."""
    import imageio.v3 as iio

    grey = read_image(DATA_DIR / "own_data_template.png", integer_scale="raw")
    iio.imwrite(d / "template.png", np.rot90(np.round(grey).astype(np.uint8)))
    np.save(d / "sino01.npy", np.load(DATA_DIR / "own_data_sinogram.npy") / 255)
    return [f"data.template={d / 'template.png'}", f"data.sinogram={d / 'sino01.npy'}"]


def test_png_template_with_data_in_other_units(tmp_path, caplog):
    """Template 0..255, data 0..1: a warning naming both numbers; ``data.template_scale=auto`` fits c,
    takes the unit factor 1/255 and gives the registration of the example with template and data in 0..1 units (its
    0..255 target scored in its units: the SSIM of the 0..1 run against the 0..1 target)."""
    files = unit_files(tmp_path)
    run_app(OWN + files + ["solver.max_iter=0"], tmp_path / "plain")
    warned = [r.getMessage() for r in caplog.records if "different units" in r.getMessage()
              and r.levelname == "WARNING"]   # the last line's count names the kind too
    assert len(warned) == 1 and "data.template_scale='auto'" in warned[0] and "0.00388" in warned[0]
    np.save(tmp_path / "template01.npy", read_image(DATA_DIR / "own_data_template.png"))   # 8-bit: / 255
    np.save(tmp_path / "target01.npy", np.load(DATA_DIR / "own_data_target.npy") / 255)   # the x1 run's target too
    ref = run_app(OWN + [f"data.template={tmp_path / 'template01.npy'}", files[1], "solver.max_iter=30",
                         f"data.target={tmp_path / 'target01.npy'}"], tmp_path / "x1")
    auto = run_app(OWN + files + ["solver.max_iter=30", "data.template_scale=auto"], tmp_path / "auto")
    assert auto["scale_fit"] == pytest.approx(0.9903 / 255, rel=1e-3) and auto["template_scale"] == pytest.approx(1 / 255)
    assert json.loads((tmp_path / "auto" / "metrics.json").read_text())["template_scale"] == auto["template_scale"]
    final, final_x1 = np.load(tmp_path / "auto" / "final.npy"), np.load(tmp_path / "x1" / "final.npy")
    assert metrics.ssim(final, final_x1) >= 0.999
    assert abs(auto["ssim"] - ref["ssim"]) < 0.005
    assert "psnr_paper" not in auto and "ssim_paper" not in auto and "psnr" in auto   # user data: no paper PSNR


def test_diverged_run_exits_1_with_one_line(tmp_path):
    files = unit_files(tmp_path)
    proc = run_cli(OWN + files + ["solver.max_iter=0", f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert proc.returncode == 1
    errors = [line for line in proc.stderr.splitlines() if line.startswith("indreg-register: error:")]
    assert len(errors) == 1 and "diverged" in errors[0] and "data.template_scale=auto" in errors[0]
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["status"] == "diverged"


def test_missing_file_is_refused_before_the_run_directory_exists(tmp_path):
    run_dir = tmp_path / "run"
    proc = run_cli(["data=files", f"data.template={tmp_path / 'none.png'}", f"data.sinogram={tmp_path / 's.npy'}",
                    "geometry=parallel", "geometry.angles=[0,10]", f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert proc.returncode == 1 and not run_dir.exists()
    assert proc.stderr.strip().splitlines() == [f"indreg-register: error: data.template file {tmp_path / 'none.png'}: "
                                                "no such file"]
    proc = run_cli(["experiment=own_data_example", f"data.sinogram={tmp_path / 's.npy'}", f"hydra.run.dir={run_dir}"],
                   cwd=tmp_path)
    assert proc.returncode == 1 and not run_dir.exists()
    assert proc.stderr.strip().splitlines() == [f"indreg-register: error: data.sinogram file {tmp_path / 's.npy'}: "
                                                "no such file"]


def test_halvings_in_metrics_agree_with_the_log(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="indreg")
    m = run_app(OWN + ["solver.max_iter=10"], tmp_path)
    counts = [int(r.getMessage().split("halved ")[1].split(" time")[0]) for r in caplog.records
              if "step size halved" in r.getMessage()]
    assert m["halvings"] == sum(counts) > 0 and m["rejected_steps"] == 0
    history = json.loads((tmp_path / "history.json").read_text())
    assert m["halvings"] == sum(h["halvings"] for h in history)


def test_offset_data_with_auto_background(tmp_path):
    sino = np.load(DATA_DIR / "own_data_sinogram.npy")
    np.save(tmp_path / "offset.npy", sino + 100.0)
    ref = run_app(OWN + ["solver.max_iter=5"], tmp_path / "ref")
    m = run_app(OWN + ["solver.max_iter=5", f"data.sinogram={tmp_path / 'offset.npy'}", "data.background=auto"],
                tmp_path / "fixed")
    assert m["background"] == pytest.approx(100.0, abs=2.0)
    assert abs(m["ssim"] - ref["ssim"]) < 0.005
    assert np.load(tmp_path / "fixed" / "data.npy") == pytest.approx(sino + 100.0 - m["background"])


def test_a_step_that_overflows_in_the_run_is_one_line_naming_the_config_key(tmp_path):
    """solver.step_size=1e38 without halving overflows float32 only in the run: one line naming solver.step_size,
    no traceback."""
    proc = run_cli(OWN + ["solver.max_iter=2", "solver.step_size=1e38", "solver.step_halving=false",
                          f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "indreg-register: error: invalid configuration: solver.step_size=1e+38 makes the iterate non-finite in float32 "
        "(velocity contains non-finite values (nan or inf)): give a smaller solver.step_size (or solver.step_rel)"]


def test_poor_fit_in_metrics_and_the_last_line(tmp_path, caplog):
    """The example's template offset by a third of its range: the run ends far above the noise (the preset's absolute
    step stalls it); the warning, ``poor_fit`` in metrics.json and the last line say so; the example reports none."""
    caplog.set_level(logging.INFO, logger="indreg")
    grey = read_image(DATA_DIR / "own_data_template.png", integer_scale="raw")
    np.save(tmp_path / "offset.npy", grey + grey.max() / 3)
    m = run_app(OWN + ["solver.max_iter=30", f"data.template={tmp_path / 'offset.npy'}"], tmp_path / "offset")
    ref = run_app(OWN + ["solver.max_iter=30"], tmp_path / "ref")
    assert m["poor_fit"] is True and m["status"] in ("completed", "stalled") and ref["poor_fit"] is False
    assert json.loads((tmp_path / "offset" / "metrics.json").read_text())["poor_fit"] is True
    lines = [r.getMessage() for r in caplog.records]
    assert sum(line.startswith("poor fit: ") for line in lines) == 1
    assert sum("iterations (poor fit: see the warning)" in line for line in lines) == 1


@pytest.mark.parametrize("override,key", [("data.template_scale=0", "data.template_scale"),
                                          ("data.background=nan", "data.background"),
                                          ("data.template_scale=fitted", "data.template_scale")])
def test_bad_unit_values_name_the_key(tmp_path, override, key):
    with pytest.raises(ConfigError, match=f"invalid config value {key}="):
        run_app(FAST + [override], tmp_path)


def test_tv_weight_scales_with_the_data_and_paper_scores_stay(tmp_path):
    m = run_app(TINY + ["logging.figure=false", "logging.tensorboard=false"], tmp_path)
    cfg = compose(TINY)
    data = np.load(tmp_path / "data.npy")
    from indreg.experiments import sources
    T = sources.load(cfg).operator
    import torch
    assert m["tv_mu_absolute"] == pytest.approx(cfg.baseline.tv_mu * tv_weight_unit(T, torch.from_numpy(data)))
    assert {"ssim_paper", "psnr_paper", "tv_ssim"} <= set(m) and m["template_scale"] == 1.0 and m["background"] == 0


def test_measured_data_take_the_relative_weights_and_presets_keep_the_paper_s():
    """``data=files`` with the default experiment: ``gamma`` / ``step_size`` unset (relative to the data term,
    indreg.units); the paper's presets, the own-data example included, keep their absolute values."""
    files = compose(["data=files", "data.template=T.npy", "data.sinogram=S.npy"])
    assert files.solver.gamma is None and files.solver.step_size is None and files.solver.gamma_rel > 0
    for preset, gamma in (("suite1_jv", 1e-6), ("suite3_shepp_logan", 1e-7), ("own_data_example", 1e-6)):
        cfg = compose([f"experiment={preset}"])
        assert cfg.solver.gamma == gamma and cfg.solver.step_size == 0.02


def test_relative_weights_are_in_metrics(tmp_path):
    """metrics.json reports the data-term scale S and the absolute gamma and step the run used."""
    m = run_app(OWN + ["solver.max_iter=2", "solver.gamma=null", "solver.step_size=null"], tmp_path)
    S = m["data_scale"]
    assert S > 0 and m["noise_residual"] > 0
    assert m["hparams"]["gamma"] == pytest.approx(1.7e-7 * S, rel=1e-6)
    assert json.loads((tmp_path / "metrics.json").read_text())["data_scale"] == S


def test_template_and_target_at_255_score_in_the_target_s_units(tmp_path):
    """The example's template and ground truth at 0..255 with 0..1 data (``data.template_scale=auto``): metrics.json's
    SSIM / PSNR are the 0..1 run's (the reconstruction scored in the target's units), as is TensorBoard's and the
    log line's (the same figures_of_merit)."""
    files = unit_files(tmp_path)
    np.save(tmp_path / "target255.npy", np.load(DATA_DIR / "own_data_target.npy"))
    np.save(tmp_path / "target01.npy", np.load(DATA_DIR / "own_data_target.npy") / 255)
    np.save(tmp_path / "template01.npy", read_image(DATA_DIR / "own_data_template.png"))
    ref = run_app(OWN + [f"data.template={tmp_path / 'template01.npy'}", files[1], "solver.max_iter=10",
                         f"data.target={tmp_path / 'target01.npy'}"], tmp_path / "x1")
    auto = run_app(OWN + files + ["solver.max_iter=10", "data.template_scale=auto",
                                  f"data.target={tmp_path / 'target255.npy'}"], tmp_path / "auto")
    saved = json.loads((tmp_path / "auto" / "metrics.json").read_text())
    assert saved["target_units"] == "template"
    assert abs(saved["ssim"] - ref["ssim"]) < 0.005 and abs(saved["psnr"] - ref["psnr"]) < 0.1
