"""The orientation probe in the app (the same run.setup as indreg.register): the example's sinogram with its
detector reversed is refused in one line naming data.orientation; with data.orientation=warn it runs and
metrics.json reports the poor fit; the example as it is says nothing."""
import json
import logging

import numpy as np
import pytest

from indreg.experiments.config import DATA_DIR

from experiment_helpers import run_app, run_cli

OWN = ["experiment=own_data_example", "deformation.num_steps=5", "baseline.enabled=false", "logging.figure=false",
       "logging.tensorboard=false", "logging.progress=false", "device=cpu", "solver.max_iter=12"]


@pytest.mark.slow
def test_reversed_detector_is_refused_then_warned(tmp_path, caplog):
    np.save(tmp_path / "reversed.npy", np.load(DATA_DIR / "own_data_sinogram.npy")[:, ::-1])
    proc = run_cli(OWN + [f"data.sinogram={tmp_path / 'reversed.npy'}", f"hydra.run.dir={tmp_path / 'refused'}"],
                   tmp_path)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "reverse the detector bins" in last and "data.orientation='warn'" in last
    caplog.set_level(logging.WARNING, logger="indreg")
    m = run_app(OWN + [f"data.sinogram={tmp_path / 'reversed.npy'}", "data.orientation=warn"], tmp_path / "warned")
    assert m["poor_fit"] is True
    assert json.loads((tmp_path / "warned" / "metrics.json").read_text())["poor_fit"] is True
    assert any("read wrongly" in r.getMessage() for r in caplog.records)


def test_the_example_says_nothing(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="indreg")
    m = run_app(OWN, tmp_path / "ref")
    assert m["poor_fit"] is False and not [r for r in caplog.records if "read wrongly" in r.getMessage()]
