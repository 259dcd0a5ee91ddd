"""Every entry point's first check (``indreg.experiments.cli.guard``), whatever the flags: the rerun flag with a help
flag (Hydra reads the rerun flag before ``--help``), and overrides of Hydra's own section that run code
(``hydra.callbacks``, ``_target_``) or put files outside the run directory (``hydra.job.name=../../x``,
``hydra.output_subdir=../../x``). Tested in-process: without the guard Hydra would run and create the marker."""
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest

from indreg.experiments import cli

ROOT = Path(__file__).resolve().parents[2]
FLAG = "--experimental-rerun"
HELP = ("--help", "-h", "--hydra-help")


class _Opens:
    """Unpickling this creates ``marker``."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def _mains():
    from indreg.experiments import register
    from indreg.learn import entry, train

    return {"indreg-train-momentum (learn.entry)": entry.main, "python -m indreg.learn.train": train.main,
            "indreg-register": register.main}


def _exit_code(main, argv, monkeypatch, capsys) -> tuple:
    monkeypatch.setattr(sys, "argv", ["prog", *argv])
    with pytest.raises(SystemExit) as e:
        main()
    return e.value.code, capsys.readouterr().err.strip().splitlines()


def _spellings():
    """Every help flag with every prefix of the rerun flag Hydra reads as it (``--e`` ... ``--experimental-rerun``),
    as ``X FILE`` and ``X=FILE``, the help flag before or after."""
    prefixes = [FLAG[:n] for n in range(3, len(FLAG) + 1)]
    out = []
    for h in HELP:
        for p in prefixes:
            out += [[h, p, "{f}"], [f"{p}={{f}}", h]]
    return out


@pytest.mark.parametrize("name", ["indreg-train-momentum (learn.entry)", "python -m indreg.learn.train",
                                  "indreg-register"])
def test_help_with_rerun_flag_is_refused_and_nothing_unpickled(tmp_path, monkeypatch, capsys, name):
    evil, marker = tmp_path / "e.pickle", tmp_path / "unpickled"
    evil.write_bytes(pickle.dumps(_Opens(marker)))
    monkeypatch.chdir(tmp_path)
    main = _mains()[name]
    spellings = _spellings()
    assert len(spellings) == 2 * len(HELP) * (len(FLAG) - 2)
    for args in spellings:
        code, err = _exit_code(main, [a.format(f=evil) for a in args], monkeypatch, capsys)
        assert not marker.exists(), (name, args)
        assert code == 2 and len(err) == 1 and f"({FLAG}) is not supported" in err[0], (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.pickle"]


REFUSED = {
    "hydra.job.name=../../x": "hydra.job.name",
    "hydra.job.name=a,../../x": "hydra.job.name",                     # a sweep's second value
    "hydra.job.name=${oc.env:HOME}": "hydra.job.name",
    "hydra.output_subdir=../../x": "hydra.output_subdir",
    "hydra.output_subdir=/tmp/x": "hydra.output_subdir",
    "hydra.sweep.subdir=../x": "hydra.sweep.subdir",
    "+hydra.callbacks.p._target_=os.makedirs": "hydra.callbacks.p._target_",
    "++hydra.callbacks.p.name=/anywhere": "hydra.callbacks.p.name",
    "hydra={callbacks:{p:{_target_:os.makedirs}}}": "hydra.callbacks.p._target_",
    "hydra.job={name:../../x}": "hydra.job.name",
    "hydra.launcher._target_=os.system": "hydra.launcher._target_",
    "+hydra.job_logging.handlers.file.filename=../../x.log": "hydra.job_logging.handlers.file.filename",
    "hydra.job_logging.handlers.file.class=os.makedirs": "hydra.job_logging.handlers.file.class",
    "+cb@hydra.callbacks=x": "cb@hydra.callbacks",
}
ACCEPTED = ["hydra.run.dir=out/r1", "hydra.sweep.dir=multirun/s", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
            "hydra.job.name=run-1.a", "hydra.output_subdir=null", "hydra.output_subdir=.hydra",
            "hydra.sweep.subdir=${hydra.job.num}", "hydra.job.chdir=false", "hydra.verbose=true",
            "hydra/job_logging=disabled", "hydra.job_logging.root.level=DEBUG", "name=x", "data.template=../t.png"]


@pytest.mark.parametrize("arg", list(REFUSED))
def test_unsafe_hydra_override_is_found(arg):
    found = cli.hydra_override(["x=1", arg])
    assert found is not None and found[0] == arg and found[1] == REFUSED[arg]


@pytest.mark.parametrize("arg", ACCEPTED)
def test_other_overrides_pass(arg):
    assert cli.hydra_override([arg, "-m", "--cfg", "job"]) is None


def test_hydra_would_take_the_callback():
    """The oracle: the override is real (Hydra composes it into its callbacks, which it instantiates at a run)."""
    from indreg.learn.conf import CONFIG_DIR

    cfg = cli.compose(CONFIG_DIR, "train_momentum", ["+hydra.callbacks.p._target_=os.makedirs"])
    assert cfg.hydra.callbacks.p._target_ == "os.makedirs"
    with pytest.raises(cli.UsageError, match="hydra.callbacks"):
        cli.check_hydra_section(cfg)


@pytest.mark.parametrize("name", ["indreg-train-momentum (learn.entry)", "indreg-register"])
@pytest.mark.parametrize("extra", [[], ["--help"], ["-r"], ["--cfg", "job"]])
def test_entry_points_refuse_before_hydra(tmp_path, monkeypatch, capsys, name, extra):
    monkeypatch.chdir(tmp_path)
    outside = tmp_path / "outside"
    args = [f"+hydra.callbacks.p._target_=os.makedirs", f"+hydra.callbacks.p.name={outside}",
            f"hydra.run.dir={tmp_path / 'a' / 'b'}"]
    for bad in (args, [f"hydra.run.dir={tmp_path / 'a' / 'b'}", "hydra.job.name=../../x"],
                [f"hydra.run.dir={tmp_path / 'a' / 'b'}", "hydra.output_subdir=../../x"]):
        code, err = _exit_code(_mains()[name], extra + bad, monkeypatch, capsys)
        assert code == 2 and len(err) == 1 and "is not accepted" in err[0], err
    assert not outside.exists() and sorted(os.listdir(tmp_path)) == []


# subprocesses: 0.3 s (the guard refuses before torch is imported)
def test_console_script_refuses_help_and_rerun(tmp_path):
    exe = Path(sys.executable).parent / "indreg-train-momentum"
    if not exe.exists():
        pytest.skip("indreg-train-momentum is not installed (pip install -e .)")
    evil, marker = tmp_path / "e.pickle", tmp_path / "unpickled"
    evil.write_bytes(pickle.dumps(_Opens(marker)))
    for cmd in ([str(exe), "--help", "--exp", str(evil)],
                [sys.executable, "-m", "indreg.learn.entry", "--help", "--exp", str(evil)]):
        proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=120,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
        assert not marker.exists() and proc.returncode == 2, proc.stderr[-2000:]
        assert len(proc.stderr.strip().splitlines()) == 1
