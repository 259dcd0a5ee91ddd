"""The app writes the evaluation: data_part.npy, prior_part.npy, uncertainty.npy, evaluation.png and the numbers in
metrics.json (validation.split, validation.uncertainty); off where asked."""
import numpy as np

from experiment_helpers import TINY, run_app


def test_the_app_writes_the_parts_the_uncertainty_and_the_figure(tmp_path):
    out = tmp_path / "run"
    m = run_app(TINY + ["baseline.enabled=false", "validation.holdout=3", "validation.uncertainty_samples=2"], out)
    final = np.load(out / "final.npy")
    assert np.allclose(np.load(out / "data_part.npy") + np.load(out / "prior_part.npy"), final, atol=1e-9)
    assert np.load(out / "uncertainty.npy").shape == final.shape and m["uncertainty_samples"] == 2
    assert m["split_projection_difference"] <= 2e-3 and (out / "evaluation.png").stat().st_size > 0


def test_switched_off(tmp_path):
    out = tmp_path / "run"
    m = run_app(TINY + ["baseline.enabled=false", "logging.figure=false", "validation.holdout=3",
                        "validation.uncertainty=false", "validation.split=false"], out)
    assert not any(k.startswith(("split_", "uncertainty_")) for k in m)
    assert not (out / "uncertainty.npy").exists() and not (out / "data_part.npy").exists()
