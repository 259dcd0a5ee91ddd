"""The app selects model="residual" with one option, deformation.model=residual, and writes its parts."""
import json

from experiment_helpers import FAST, compose, run_app


def test_the_app_runs_the_residual_model(tmp_path):
    cfg = compose(["deformation.model=residual"])
    assert cfg.deformation.residual_tv == "auto" and cfg.solver.residual_finish_iter == 200 and cfg.solver.residual_start_fraction == 0.5
    run_app(["deformation.model=residual", "solver.residual_start_fraction=0.5", *FAST], tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == "completed" and metrics["iterations"] == 10
    assert (tmp_path / "intensity_part.npy").exists() and (tmp_path / "deformation_part.npy").exists()
