"""The app when every step overflows (``data.template_scale=1e300`` in float64): before, ``TypeError: cannot unpack
non-iterable NoneType`` from Algorithm 1; now the run ends ``failed`` with its record written, and the entry point
says so in one line."""
import json

from experiment_helpers import FAST, run_app


def test_every_trial_overflowing_ends_failed_with_its_record(tmp_path):
    result = run_app(FAST + ["dtype=float64", "solver.step_halving=true", "solver.max_iter=3",
                             "data.template_scale=1e300"], tmp_path)
    assert result["status"] == "failed" and result["iteration"] == 1
    assert "rejected after" in result["warning"] and "non-finite objective" in result["warning"]
    assert json.loads((tmp_path / "metrics.json").read_text())["status"] == "failed"
    assert len(json.loads((tmp_path / "history.json").read_text())) == 1
