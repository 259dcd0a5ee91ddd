"""Structured configs: the paper's presets, the packaged config dir, and errors naming the bad key."""
import json
import re
from pathlib import Path

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from indreg.experiments.config import CONFIG_DIR, ConfigError, to_plain, validate
from indreg.experiments.sweep import SUITE3_GAMMAS, SUITE3_SIGMAS

from experiment_helpers import compose, run_cli

# The paper's suites: (size, angles, bins, snr, N, step, gamma, sigma, iterations, template)
PAPER = {
    "suite1_jv": (64, 10, 92, 4.87, 20, 0.02, 1e-6, 6.0, 200, "j"),
    "suite2_six_objects": (438, 6, 620, 4.75, 20, 0.04, 1e-7, 2.0, 200, "six_objects_template"),
    "suite3_shepp_logan": (256, 10, 362, 7.06, 20, 0.02, 1e-7, 2.0, 500, "shepp_logan_template"),
    "suite4_missing_object": (256, 10, 362, 7.06, 20, 0.02, 1e-7, 2.0, 1000, "shepp_logan_template_missing"),
    "suite4_extra_object": (256, 10, 362, 6.46, 20, 0.02, 1e-7, 2.0, 1000, "shepp_logan_template_extra"),
}


def _message(exc) -> str:
    parts, e = [], exc
    while e is not None:
        parts.append(str(e))
        e = e.__cause__ or e.__context__
    return "\n".join(parts)


def test_default_is_suite1():
    cfg = compose()
    assert cfg.name == "suite1_jv" and cfg.phantom.template.value == "j" and cfg.kernel.sigma == 6.0


@pytest.mark.parametrize("name", sorted(PAPER))
def test_presets_have_the_papers_parameters(name):
    cfg = compose([f"experiment={name}"])
    validate(cfg)
    got = (cfg.phantom.size, cfg.geometry.num_angles, cfg.geometry.det_count, cfg.noise.snr_db,
           cfg.deformation.num_steps, cfg.solver.step_size, cfg.solver.gamma, cfg.kernel.sigma,
           cfg.solver.max_iter, cfg.phantom.template.value)
    assert got == PAPER[name]
    assert cfg.name == name and cfg.noise.convention.value == "code" and cfg.geometry.partition.value == "paper"
    assert cfg.baseline.fbp_filter.value == "hamming" and cfg.baseline.fbp_frequency_scaling == 0.4
    # baseline.tv_mu is relative to the TV weight unit: on the preset's data it is the paper's mu
    from indreg.experiments import sources
    from indreg.forward import tv_weight_unit

    data = sources.load(cfg)
    mu = cfg.baseline.tv_mu * tv_weight_unit(data.operator, data.data_64)
    assert mu == pytest.approx({"suite1_jv": 3.0}.get(name, 1.0), rel=1e-3)


def test_configs_ship_inside_the_package():
    """One source of truth: the app reads indreg/conf (package data), never a top-level site-packages/configs."""
    import indreg

    assert CONFIG_DIR == Path(indreg.__file__).resolve().parent / "conf"
    presets = {p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml")}
    assert set(PAPER) <= presets
    for group in ("solver", "baseline", "logging", "noise", "deformation", "geometry", "phantom", "sweep"):
        assert any((CONFIG_DIR / group).glob("*.yaml")), group


def test_sweep_preset_is_the_papers_table():
    cfg = compose(["sweep=suite3_table"], return_hydra_config=True)
    assert cfg.name == "suite3_shepp_logan" and cfg.solver.max_iter == 500
    params = cfg.hydra.sweeper.params
    assert [float(g) for g in params["solver.gamma"].split(",")] == list(SUITE3_GAMMAS)
    assert [float(s) for s in params["kernel.sigma"].split(",")] == list(SUITE3_SIGMAS)


@pytest.mark.parametrize("override, key", [
    ("solver.gama=1e-3", "solver.gama"),                 # unknown key
    ("solver.gamma=abc", "solver.gamma"),                # wrong type
    ("solver.max_iter=1.5", "solver.max_iter"),          # wrong type
    ("phantom.target=cat", "phantom.target"),            # unknown phantom
    ("dtype=float16", "dtype"),
])
def test_composition_errors_name_the_key(override, key):
    with pytest.raises(ConfigCompositionException) as err:
        compose([override])
    assert key in _message(err.value)


@pytest.mark.parametrize("override, key", [
    ("solver.gamma=-1e-7", "solver.gamma"),
    ("kernel.sigma=0", "kernel.sigma"),
    ("solver.step_size=-0.1", "solver.step_size"),
    ("deformation.num_steps=0", "deformation.num_steps"),
    ("device=gpu", "device"),
    ("noise.std=1.0", "noise.snr_db"),    # both snr_db and std
    ("+solver.foo=1", "solver.foo"),      # appended key the schema lacks
    ("logging.every=0", "logging.every"),
    ("deformation.action=affine", "deformation.action"),  # unknown action (indreg.options: one check for both)
    ("solver.name=newton", "solver.name"),
])
def test_invalid_values_name_the_key(override, key):
    cfg = compose([override])
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate(cfg)


@pytest.mark.parametrize("overrides, message", [
    (["phantom.size=4"], "phantom.size=4: expected an integer >= 7 (the SSIM window)"),
    (["phantom.size=6"], "phantom.size=6: expected an integer >= 7 (the SSIM window)"),
    (["experiment=suite_et_3d", "geometry.tilt_axis_angle=1e300"],   # the range: tests/alignment/test_tilt_axis.py
     "invalid config value geometry.tilt_axis_angle=1e+300: expected"),
    (["experiment=suite_dynamic_2d", "geometry=tilt_series"],
     "geometry='tilt_series': expected parallel (the dynamic source simulates 2D parallel-beam frames)"),
])
def test_issue_26_config_cases_are_one_line_before_the_run(overrides, message):
    """Values that once ran (and failed after the run, or ran something else than recorded) are refused by the
    config's validation, before any computing."""
    with pytest.raises(ConfigError, match=re.escape(message)) as e:
        validate(compose(overrides))
    assert "\n" not in str(e.value)


@pytest.mark.slow
def test_entry_point_rejects_invalid_value(tmp_path):
    proc = run_cli(["solver.gamma=-1", f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert proc.returncode != 0
    assert "solver.gamma" in proc.stderr and "-1" in proc.stderr
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_plain_config_is_json_serialisable():
    json.dumps(to_plain(compose(["experiment=suite3_shepp_logan"])))
    assert OmegaConf.is_config(compose())


@pytest.mark.parametrize("solver, lr", [("lbfgs", 1.0), ("adam", 0.01)])
def test_experiment_preset_keeps_the_optimizers_learning_rate(solver, lr):
    """``experiment=suite1_jv solver=lbfgs`` runs L-BFGS at lbfgs.yaml's lr, not at suite 1's Algorithm-1 step."""
    from indreg.experiments.build import build

    cfg = compose(["experiment=suite1_jv", f"solver={solver}", "phantom.size=16", "deformation.num_steps=2"])
    assert cfg.solver.lr == lr and cfg.solver.step_size == 0.02
    assert build(cfg).solver.optimizer.param_groups[0]["lr"] == lr
