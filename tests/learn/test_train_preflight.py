"""``indreg-train-momentum``'s preflight refuses the values that used to fail minutes later with a traceback
(``model.lr=0``: ZeroDivisionError, ``data.num_train=0``, NaNs, ...) in one line, before any data are built."""
import pytest

from indreg.experiments import cli
from indreg.learn import train


def _error(capsys, argv) -> str:
    with pytest.raises(SystemExit) as exc:
        cli.preflight(argv, train.PROG, train.CONFIG_DIR, train.CONFIG_NAME, train.check_config,
                      train.base_config(argv))
    lines = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 1 and len(lines) == 1, lines
    return lines[0]


@pytest.mark.parametrize("override, message", [
    ("model.lr=0", "model.lr must be a finite number > 0, got 0"),
    ("model.lr=nan", "model.lr must be a finite number > 0, got nan"),
    ("model.updates=0", "model.updates must be an integer >= 1, got 0"),
    ("model.updates=1.5", "model.updates must be an integer >= 1, got 1.5"),
    ("model.step_lr=-1", "model.step_lr must be a finite number > 0, got -1"),
    ("data.num_train=0", "data.num_train must be an integer >= 1, got 0"),
    ("data.snr_db=nan", "data.snr_db must be a finite number, got nan"),
    ("data.displacement=nan", "data.displacement must be a finite number > 0, got nan"),
    ("train.batch_size=0", "train.batch_size must be an integer >= 1, got 0"),
])
def test_unrolled_values_that_cannot_train_are_refused_in_one_line(tmp_path, capsys, monkeypatch, override,
                                                                   message):
    monkeypatch.setattr(train, "datasets", lambda *a: pytest.fail("data were built"))
    line = _error(capsys, ["model=unrolled", override, f"hydra.run.dir={tmp_path / 'run'}"])
    assert line == f"indreg-train-momentum: error: {message}" and not (tmp_path / "run").exists()


def test_the_defaults_pass(tmp_path):
    for argv in (["model=unrolled"], ["model=oneshot"]):
        cli.preflight(argv + [f"hydra.run.dir={tmp_path / 'run'}"], train.PROG, train.CONFIG_DIR,
                      train.CONFIG_NAME, train.check_config, train.base_config(argv))


@pytest.mark.parametrize("override, message", [
    ("model.width=0", "model.width must be an integer >= 1, got 0"),
    ("model.levels=0", "model.levels must be an integer >= 1, got 0"),
    ("domain.n=4", "domain.n must be an integer >= 7, got 4"),
    ("domain.n=10", "domain.n must be divisible by 4 (the U-Net's 3 levels halve it 2 times), got 10: e.g. "
                    "domain.n=12"),
    ("data.snr_db=-400", "data.snr_db must be in [-300, 300] dB, got -400"),
    ("eval.ood.snr_db=[1e9]", "eval.ood.snr_db must hold values in [-300, 300] dB, got 1000000000.0"),
    ("geometry.num_angles=0", "geometry.num_angles must be an integer >= 1, got 0"),
    ("geometry.det_count=0", "geometry.det_count must be an integer >= 1, got 0"),
    ("shooting.num_steps=0", "shooting.num_steps must be an integer >= 1, got 0"),
    ("shooting.corrector_steps=-1", "shooting.corrector_steps must be an integer >= 0, got -1"),
    ("kernel.sigma=0", "kernel.sigma must be None, 'auto' or a finite number > 0, got 0"),
    ("train.gamma=-1", "train.gamma must be a finite number >= 0, got -1"),
    ("eval.algorithm1.step_size=0", "eval.algorithm1.step_size must be a finite number > 0, got 0"),
])
def test_problem_values_that_end_in_tracebacks_are_refused(tmp_path, capsys, monkeypatch, override, message):
    monkeypatch.setattr(train, "build", lambda *a: pytest.fail("the problem was built"))
    line = _error(capsys, [override, f"hydra.run.dir={tmp_path / 'run'}"])
    assert line == f"indreg-train-momentum: error: {message}" and not (tmp_path / "run").exists()
