"""End to end: the indreg-register app on tiny problems (32^2, N = 5, 10 iterations)."""
import json
import math
import os
import signal

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from indreg.experiments import checkpoint
from indreg.experiments.config import ConfigError
from indreg.experiments.tblog import METRICS, SCALARS
from indreg.solvers import Algorithm1

from experiment_helpers import FAST, TINY, run_app, run_cli

REQUIRED = ("ssim", "psnr", "ssim_paper", "psnr_paper", "fbp_ssim", "fbp_psnr", "tv_ssim", "tv_psnr", "snr_db",
            "objective", "data_fit", "iterations", "seconds_per_iteration", "min_jacobian")
ARRAYS = {"final": (32, 32), "trajectory": (6, 32, 32), "velocity": (6, 2, 32, 32), "deformation": (2, 32, 32),
          "fbp": (32, 32), "tv": (32, 32), "data": (10, 92)}
IMAGES = ("images/deformed_template", "images/trajectory", "images/target", "images/template", "images/fbp",
          "images/tv", "images/deformed_grid")
F64 = FAST + ["dtype=float64", "device=cpu"]


@pytest.mark.slow
def test_console_entry_point_end_to_end(tmp_path):
    """metrics.json, arrays, figure and TensorBoard events from the real ``indreg-register``."""
    out = tmp_path / "run"
    proc = run_cli(TINY + [f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    for key in REQUIRED:
        assert isinstance(metrics[key], (int, float)) and math.isfinite(metrics[key]), key
    assert metrics["iterations"] == 10 and metrics["status"] == "completed"
    assert abs(metrics["snr_db"] - 4.87) < 1e-9
    assert metrics["objective"] < json.loads((out / "history.json").read_text())[0]["objective"]
    assert metrics["ssim"] > metrics["template_ssim"]  # registration moved the J towards the V
    for name, shape in ARRAYS.items():
        assert np.load(out / f"{name}.npy").shape == shape, name
    assert (out / "figure.png").stat().st_size > 10_000
    assert (out / ".hydra" / "config.yaml").is_file()
    first, second = [line.split(" - ", 1)[-1] for line in (out / "register.log").read_text().splitlines()[:2]]
    assert first.startswith("suite1_jv: model lddmm, solver algorithm1 (10 iterations), data phantom j -> v")
    assert second.startswith("suite1_jv | IndirectRegistration(")   # the problem built: the second line

    ea = EventAccumulator(str(out / "tensorboard"), size_guidance={"images": 0, "scalars": 0})
    ea.Reload()
    tags = ea.Tags()
    # every scalar but metamorphosis' (source_*) and solver=fast's level (grid)
    lddmm = [t for k, t in SCALARS.items() if not k.startswith("source_") and k != "grid"]
    for tag in lddmm + [f"metrics/{k}" for k in METRICS] + [f"hparam/{k}" for k in METRICS]:
        assert tag in tags["scalars"], tag
    assert [e.step for e in ea.Scalars("loss/objective")] == list(range(1, 11))
    assert [e.step for e in ea.Scalars("metrics/ssim")] == [0, 5, 10]
    assert ea.Scalars("metrics/ssim")[-1].value == pytest.approx(metrics["ssim"], rel=1e-5)
    for tag in IMAGES:
        assert tag in tags["images"], tag
    assert [e.step for e in ea.Images("images/deformed_template")] == [0, 5, 10]
    assert "_hparams_/session_start_info" in ea.PluginTagToContent("hparams")


def test_seeds_reproducible(tmp_path):
    a = run_app(FAST + ["seed=3"], tmp_path / "a")
    b = run_app(FAST + ["seed=3"], tmp_path / "b")
    c = run_app(FAST + ["seed=4"], tmp_path / "c")
    for key in ("objective", "ssim", "psnr", "min_jacobian", "snr_db"):
        assert a[key] == b[key], key
    np.testing.assert_array_equal(np.load(tmp_path / "a/final.npy"), np.load(tmp_path / "b/final.npy"))
    np.testing.assert_array_equal(np.load(tmp_path / "a/data.npy"), np.load(tmp_path / "b/data.npy"))
    assert not np.array_equal(np.load(tmp_path / "a/data.npy"), np.load(tmp_path / "c/data.npy"))
    assert a["objective"] != c["objective"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted float64 run of 10 iterations."""
    out = tmp_path_factory.mktemp("reference")
    return run_app(F64, out), out


def _assert_same_run(out, ref_out, ref):
    for name in ("final", "momentum", "trajectory"):
        np.testing.assert_allclose(np.load(out / f"{name}.npy"), np.load(ref_out / f"{name}.npy"), rtol=0,
                                   atol=1e-10, err_msg=name)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 10
    assert metrics["objective"] == pytest.approx(ref["objective"], rel=1e-10, abs=1e-10)
    history = json.loads((out / "history.json").read_text())
    assert [h["iteration"] for h in history] == list(range(1, 11))


def test_resume_after_stop_equals_uninterrupted(tmp_path, reference):
    ref, ref_out = reference
    out = tmp_path / "run"
    first = run_app(F64 + ["stop_after=5"], out)
    assert first["status"] == "stopped" and first["iteration"] == 5
    assert checkpoint.load(out / "checkpoint.pt")["iteration"] == 5
    assert not (out / "metrics.json").exists()
    second = run_app(F64 + ["resume=true"], out)
    assert second["status"] == "completed"
    _assert_same_run(out, ref_out, ref)


def test_sigterm_checkpoints_and_resume_equals_uninterrupted(tmp_path, reference, monkeypatch):
    """SIGTERM during iteration 6: the handler lets the iteration finish, checkpoints, and the run stops."""
    ref, ref_out = reference
    out = tmp_path / "run"
    step = Algorithm1.step

    def step_and_signal(self, state):
        info = step(self, state)
        if state.iteration == 6:
            os.kill(os.getpid(), signal.SIGTERM)
        return info

    monkeypatch.setattr(Algorithm1, "step", step_and_signal)
    with_tb = [o for o in F64 if not o.startswith("logging.tensorboard")] + ["logging.checkpoint_every=4"]
    first = run_app(with_tb, out)
    assert first["status"] == "interrupted" and first["signal"] == signal.SIGTERM
    assert checkpoint.load(out / "checkpoint.pt")["iteration"] == 6
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # handlers restored
    monkeypatch.setattr(Algorithm1, "step", step)
    run_app(with_tb + ["resume=true"], out)
    _assert_same_run(out, ref_out, ref)
    ea = EventAccumulator(str(out / "tensorboard"), size_guidance={"scalars": 0})
    ea.Reload()
    assert [e.step for e in ea.Scalars("loss/objective")] == list(range(1, 11))
    assert [e.step for e in ea.Scalars("metrics/ssim")] == [0, 5, 10]


def test_killed_run_resumes_from_last_periodic_checkpoint(tmp_path, reference):
    """A run killed without a chance to checkpoint (here: an exception at iteration 7) resumes from iteration 4."""
    ref, ref_out = reference
    out = tmp_path / "run"
    step = Algorithm1.step

    def step_and_die(self, state):
        if state.iteration == 7:
            raise RuntimeError("killed")
        return step(self, state)

    cfg = [o for o in F64 if not o.startswith("logging.tensorboard")] + ["logging.checkpoint_every=4"]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Algorithm1, "step", step_and_die)
        with pytest.raises(RuntimeError, match="killed"):
            run_app(cfg, out)
    assert checkpoint.load(out / "checkpoint.pt")["iteration"] == 4
    run_app(cfg + ["resume=true"], out)
    _assert_same_run(out, ref_out, ref)
    ea = EventAccumulator(str(out / "tensorboard"), size_guidance={"scalars": 0})
    ea.Reload()
    assert [e.step for e in ea.Scalars("loss/objective")] == list(range(1, 11))


def test_resume_refuses_a_different_problem(tmp_path):
    out = tmp_path / "run"
    run_app(F64 + ["stop_after=2"], out)
    with pytest.raises(ConfigError, match=r"solver\.gamma"):
        run_app(F64 + ["resume=true", "solver.gamma=1e-3"], out)
    # the iteration budget may change: extend to 12 iterations
    result = run_app(F64 + ["resume=true", "solver.max_iter=12"], out)
    assert result["iterations"] == 12


def test_atomic_checkpoint_keeps_previous_on_failure(tmp_path):
    path = tmp_path / "checkpoint.pt"
    checkpoint.save(path, {"iteration": 1})

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("boom")

    with pytest.raises(TypeError, match="bad"):   # only tensors and plain data are stored
        checkpoint.save(path, {"iteration": 2, "bad": Unpicklable()})
    assert checkpoint.load(path)["iteration"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


@pytest.mark.parametrize("solver", ["adam", "lbfgs"])
def test_torch_optim_solver_resume_equals_uninterrupted(tmp_path, solver):
    """The optimizer's internals (Adam moments, L-BFGS history) travel in the checkpoint."""
    cfg = F64 + [f"solver={solver}", "solver.max_iter=6"]
    ref = run_app(cfg, tmp_path / "ref")
    history = json.loads((tmp_path / "ref/history.json").read_text())
    assert ref["status"] == "completed" and ref["objective"] < history[0]["objective"]
    assert run_app(cfg + ["stop_after=3"], tmp_path / "run")["status"] == "stopped"
    res = run_app(cfg + ["resume=true"], tmp_path / "run")
    np.testing.assert_allclose(np.load(tmp_path / "run/momentum.npy"), np.load(tmp_path / "ref/momentum.npy"),
                               rtol=0, atol=1e-10)
    assert res["objective"] == pytest.approx(ref["objective"], rel=1e-10)
