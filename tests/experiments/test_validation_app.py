"""The app's ``validation`` group: held-out angles in metrics.json, history.json and TensorBoard, early stopping,
resuming, bad values."""
import json

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from indreg.experiments.config import ConfigError

from experiment_helpers import FAST, TINY, run_app

# 10 angles of the paper's suite 1 partition: every 3rd held out = 1, 4, 7
HOLDOUT = FAST + ["validation.holdout=3"]


def test_metrics_history_and_tensorboard(tmp_path):
    out = tmp_path / "run"
    m = run_app(TINY + ["baseline.enabled=false", "logging.figure=false", "validation.holdout=3"], out)
    assert m["status"] == "completed" and m["holdout_indices"] == [1, 4, 7]
    history = json.loads((out / "history.json").read_text())
    curve = [(h["iteration"], h["holdout_residual"]) for h in history if "holdout_residual" in h]
    assert [c[0] for c in curve] == [5, 10]                                    # every logging.every
    assert curve[-1][1] == pytest.approx(m["holdout_residual"], rel=1e-6)
    assert (m["holdout_best_iteration"], m["holdout_best_residual"]) == min(curve, key=lambda c: c[1])
    data = np.load(out / "data.npy")
    assert data.shape[0] == 10                                                   # all angles are saved
    ea = EventAccumulator(str(out / "tensorboard"), size_guidance={"scalars": 0})
    ea.Reload()
    assert [(e.step, pytest.approx(e.value, rel=1e-6)) for e in ea.Scalars("validation/residual")] == curve


def test_without_holdout_nothing_changes(tmp_path):
    m = run_app(FAST, tmp_path / "run")
    assert not any(k.startswith("holdout") for k in m)


def test_early_stopping_writes_the_outputs(tmp_path):
    """Files whose held-out rows hold the template's projections: the held-out residual grows from the first
    evaluation on, so the run stops ``patience`` evaluations later and still writes its outputs."""
    import indreg
    from indreg import phantoms

    domain = indreg.ImageDomain.paper(32)
    angles = np.arange(10) * 18.0
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=angles, det_count=46, det_min=-24.0,
                                                                det_max=24.0, angle_unit="deg"))
    template = phantoms.get("j", domain)
    sinogram = T(phantoms.get("v", domain))
    sinogram[[2, 7]] = T(template)[[2, 7]]
    np.save(tmp_path / "template.npy", template.numpy())
    np.save(tmp_path / "sino.npy", sinogram.numpy())
    out = tmp_path / "run"
    m = run_app(FAST + ["data=files", f"data.template={tmp_path / 'template.npy'}",
                        f"data.sinogram={tmp_path / 'sino.npy'}", "geometry=parallel",
                        f"geometry.angles=[{','.join(map(str, angles))}]", "geometry.det_min=-24",
                        "geometry.det_max=24", "validation.holdout=[2,7]", "validation.patience=2",
                        "logging.every=2", "solver.max_iter=50"], out)
    assert m["status"] == "early_stopped" and m["iterations"] == 6 and m["holdout_best_iteration"] == 2
    assert m["holdout_residual"] > m["holdout_best_residual"]
    assert (out / "final.npy").is_file() and (out / "checkpoint.pt").is_file()


def test_resume_keeps_the_curve(tmp_path):
    ref = run_app(HOLDOUT + ["dtype=float64"], tmp_path / "ref")
    out = tmp_path / "run"
    assert run_app(HOLDOUT + ["dtype=float64", "stop_after=5"], out)["status"] == "stopped"
    again = run_app(HOLDOUT + ["dtype=float64", "resume=true"], out)
    for key in ("holdout_residual", "holdout_best_residual", "holdout_best_iteration", "objective"):
        assert again[key] == pytest.approx(ref[key], rel=1e-10), key


@pytest.mark.parametrize("override, message", [
    ("validation.holdout=[3,10]", r"validation.holdout=\[3, 10\]: expected indices in 0..9 \(the data have 10 angles\)"),
    ("validation.holdout=[0,1,2,3,4,5,6,7,8,9]", "validation.holdout=.*: expected a selection that leaves at least one"),
    ("validation.holdout=1", "validation.holdout=1: expected an integer k >= 2"),
    ("validation.patience=2", "validation.patience=2: expected None without validation.holdout"),
])
def test_bad_values_one_line(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message) as e:
        run_app(FAST + [override], tmp_path / "run")
    assert "\n" not in str(e.value)
