"""A run directory with planted symbolic links: outputs are never written through a link (each goes to a fresh
file renamed over its name), and a run directory holding one is refused in one line before anything runs."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from indreg._outfiles import check_no_links, links_in, open_replacing, replacing, LinkError
from indreg.experiments import checkpoint, register
from indreg.experiments.checkpoint import CheckpointError

from experiment_helpers import FAST, run_app

ROOT = Path(__file__).resolve().parents[2]
SECRET = "the victim's content\n"


def _victim(tmp_path, name="victim") -> Path:
    outside = tmp_path / "outside"
    outside.mkdir(exist_ok=True)
    victim = outside / name
    victim.write_text(SECRET)
    return victim


@pytest.mark.parametrize("mode", ["w", "wb"])
def test_open_replacing_replaces_a_link_and_leaves_its_target(tmp_path, mode):
    victim, path = _victim(tmp_path), tmp_path / "metrics.json"
    path.symlink_to(victim)
    with open_replacing(path, mode) as f:
        f.write("new" if mode == "w" else b"new")
    assert victim.read_text() == SECRET and not path.is_symlink() and path.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json", "outside"]   # no scratch left


def test_replacing_discards_the_new_file_on_an_error(tmp_path):
    path = tmp_path / "final.npy"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with replacing(path) as new:
            new.write_text("half")
            raise RuntimeError("writer failed")
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["final.npy"]


def test_links_are_found_below_and_named_in_one_line(tmp_path):
    run = tmp_path / "run"
    (run / "tensorboard").mkdir(parents=True)
    (run / "tensorboard" / "events").symlink_to(_victim(tmp_path))
    (run / ".hydra").symlink_to(tmp_path / "outside")
    assert links_in(run) == [run / ".hydra", run / "tensorboard" / "events"]
    with pytest.raises(LinkError, match=r"^run directory .*: \.hydra is a symbolic link \(to .*outside\) \(and 1 "
                                        r"more\); indreg never writes through links") as e:
        check_no_links(run)
    assert "\n" not in str(e.value)
    check_no_links(tmp_path / "nothing")     # a run directory still to be created


@pytest.mark.parametrize("planted", ["checkpoint.pt", "checkpoint.pt.tmp"])
def test_checkpoint_write_lands_in_the_run_directory_not_in_the_victim(tmp_path, planted):
    victim = _victim(tmp_path)
    (tmp_path / planted).symlink_to(victim)
    checkpoint.save(tmp_path / "checkpoint.pt", {"iteration": 3})
    assert victim.read_text() == SECRET
    assert checkpoint.load(tmp_path / "checkpoint.pt")["iteration"] == 3


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished tiny run (its outputs: metrics.json, history.json, final.npy, checkpoint.pt, ...)."""
    out = tmp_path_factory.mktemp("finished")
    run_app(FAST + ["solver.max_iter=2", "logging.checkpoint_every=1"], out)
    return out


@pytest.mark.parametrize("name", ["metrics.json", "final.npy", "history.json", "checkpoint.pt.tmp", "tensorboard"])
def test_resume_refuses_a_run_directory_with_a_planted_link(tmp_path, finished, name):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished, run)
    victim = _victim(tmp_path)
    if (run / name).is_dir():
        shutil.rmtree(run / name)
    (run / name).unlink(missing_ok=True)
    (run / name).symlink_to(victim)
    with pytest.raises(CheckpointError, match=rf"^run directory {run}: {name} is a symbolic link .*indreg never "
                                              "writes through links"):
        run_app(FAST + ["solver.max_iter=3", "resume=true"], run)
    assert victim.read_text() == SECRET


def test_preflight_refuses_the_run_directory_in_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").symlink_to(_victim(tmp_path))
    with pytest.raises(SystemExit) as exc:
        register.preflight([f"hydra.run.dir={run}", "resume=true"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 1 and len(lines) == 1
    assert lines[0].startswith(f"indreg-register: error: run directory {run}: metrics.json is a symbolic link")
    assert lines[0].endswith("choose another hydra.run.dir")


@pytest.mark.slow   # a training run in a subprocess (torch import, seconds)
def test_trainer_refuses_a_run_directory_with_a_planted_link(tmp_path):
    victim = _victim(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").symlink_to(victim)
    script = ROOT / "scripts" / "train_momentum.py"
    proc = subprocess.run([sys.executable, str(script), "domain.n=16", "train.steps=1", "device=cpu",
                           f"hydra.run.dir={run}"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1"))
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1, proc.stderr[-2000:]
    assert "metrics.json is a symbolic link" in lines[0] and victim.read_text() == SECRET


def test_trainer_outputs_are_written_without_following_links(tmp_path, monkeypatch):
    """The trainer's own check, past the preflight (``train.train`` called directly)."""
    from omegaconf import OmegaConf

    from indreg.learn import train

    victim = _victim(tmp_path)
    (tmp_path / "figure.png").symlink_to(victim)
    cfg = train.base_config(["model=oneshot"])
    monkeypatch.setattr(train, "build", lambda *a: pytest.fail("built before the run directory was checked"))
    with pytest.raises(CheckpointError, match="figure.png is a symbolic link"):
        train.train(OmegaConf.merge(cfg, {"device": "cpu"}), tmp_path)
    assert victim.read_text() == SECRET
