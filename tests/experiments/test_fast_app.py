"""``solver=fast`` in the app and ``indreg.register(..., solver="fast")``: config, runs, resume."""
import json

import pytest

import indreg
from indreg import noise, phantoms
from indreg.experiments.build import build
from indreg.experiments.config import ConfigError, validate
from indreg.solvers import MultilevelSolver

from experiment_helpers import FAST, compose, run_app

F64 = FAST + ["dtype=float64", "device=cpu", "solver=fast"]


@pytest.mark.parametrize("experiment, shapes", [
    ("suite1_jv", [16, 32, 64]),
    pytest.param("suite3_shepp_logan", [64, 128, 256], marks=pytest.mark.slow)])
def test_fast_config_composes_validates_and_builds_the_multilevel_solver(experiment, shapes):
    cfg = compose([f"experiment={experiment}", "solver=fast"])
    validate(cfg)
    assert cfg.solver.name == "fast" and cfg.deformation.interpolation is None   # the model's rule: compose
    # the suite's objective is kept (gamma, iterations from the experiment preset)
    assert cfg.solver.gamma == compose([f"experiment={experiment}"]).solver.gamma
    exp = build(cfg)
    solver = exp.solver
    assert exp.options["interpolation"] == "compose"
    assert isinstance(solver, MultilevelSolver) and solver.inner == "algorithm1"
    assert [s[0][0] for s in solver.schedule] == shapes
    assert [s[1] for s in solver.schedule] == [10, 10, 20] and solver.max_iter == cfg.solver.max_iter


def test_fast_config_unknown_option_names_the_key():
    cfg = compose(["solver=fast", "+solver.optimizer_kwargs.levls=[2]"])
    with pytest.raises(ConfigError, match=r"solver\.optimizer_kwargs\.levls"):
        validate(cfg)


@pytest.mark.slow
def test_fast_app_run_resumes_exactly(tmp_path):
    """Stopped on the coarse level and on the fine level, resumed: the uninterrupted run's history exactly."""
    cfg = F64 + ["solver.max_iter=5", "solver.optimizer_kwargs.level_iter=[2,2]"]
    ref = run_app(cfg, tmp_path / "ref")
    out = tmp_path / "run"
    assert run_app(cfg + ["stop_after=1"], out)["status"] == "stopped"
    assert run_app(cfg + ["stop_after=3", "resume=true"], out)["status"] == "stopped"
    res = run_app(cfg + ["resume=true"], out)
    a, b = (json.loads((d / "history.json").read_text()) for d in (tmp_path / "ref", out))
    assert [h["level"] for h in a] == [0, 0, 1, 1, 1] and [h["grid"] for h in a] == [16, 16, 32, 32, 32]
    for key in ("iteration", "objective", "evaluations", "grad_norm", "step_size", "level"):
        assert [h[key] for h in b] == [h[key] for h in a], key
    assert res["objective"] == ref["objective"] and res["evaluations"] == ref["evaluations"]
    # metrics.json / HParams: fast's Algorithm 1 step (its option), not the unused torch.optim lr
    assert res["hparams"]["solver"] == "fast" and res["hparams"]["step_size"] == 0.08


def test_register_solver_fast():
    domain = indreg.ImageDomain.paper(32)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(10, 46))
    template, target = phantoms.get("j", domain), phantoms.get("v", domain)
    data, _ = noise.add_white_noise(T(target), snr_db=15.0, seed=0)
    r = indreg.register(template, data, T, solver="fast", num_steps=4, max_iter=8, target=target,
                        optimizer_kwargs={"level_iter": [3, 3]})
    assert r.problem.deformation.interpolation == "compose" and r.momentum.shape == (5, 2, 32, 32)
    assert [h["grid"] for h in r.history] == [16] * 3 + [32] * 5
    start = r.problem.evaluate(r.problem.zero_momentum())["objective"]
    assert r.objective < 0.5 * start and r.ssim > indreg.metrics.ssim(template, target)
    with pytest.raises(TypeError, match=r"optimizer_kwargs.levls must be an option of solver='fast'"):
        indreg.register(template, data, T, solver="fast", optimizer_kwargs={"levls": [2]})
    with pytest.raises(TypeError, match="step_size must be left unset: it is an option of solver='algorithm1'"):
        indreg.register(template, data, T, solver="fast", step_size=0.1)
