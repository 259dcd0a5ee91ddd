"""The entry points as a user meets them: --help, the checks before Hydra starts (one line, exit 1, nothing
written), the launcher extras and the sweep-table command."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from indreg.experiments import cli, register
from indreg.experiments.sweep import main as sweep_main
from indreg.learn import train

from experiment_helpers import run_cli

ROOT = Path(__file__).resolve().parents[2]


def _pyproject() -> dict:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _preflight_error(capsys, fn, *args) -> str:
    """``fn(*args)`` must exit 1 with one line on stderr; returns that line."""
    with pytest.raises(SystemExit) as exc:
        fn(*args)
    assert exc.value.code == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def _register_error(capsys, argv) -> str:
    line = _preflight_error(capsys, register.preflight, argv)
    assert line.startswith("indreg-register: error: ")
    return line


def _train_error(capsys, argv) -> str:
    line = _preflight_error(capsys, cli.preflight, argv, train.PROG, train.CONFIG_DIR, train.CONFIG_NAME,
                            train.check_config, train.base_config(argv))
    assert line.startswith("indreg-train-momentum: error: ")
    return line


def _user_configs(tmp_path, text: str) -> str:
    """A config dir with ``experiment/mine.yaml``; returns the ``hydra.searchpath`` override for it."""
    (tmp_path / "confs" / "experiment").mkdir(parents=True)
    (tmp_path / "confs" / "experiment" / "mine.yaml").write_text(text)
    return f"hydra.searchpath=[file://{tmp_path / 'confs'}]"


# ---------------------------------------------------------------- checks before Hydra starts
def test_valid_command_lines_pass_and_write_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    search = _user_configs(tmp_path, "# @package _global_\nname: mine\nkernel:\n  sigma: 3.0\n")
    register.preflight(["experiment=suite3_shepp_logan", "solver=fast"])
    register.preflight([search, "experiment=mine"])            # a user's preset on hydra.searchpath
    register.preflight(["-m", "kernel.sigma=1,2", "solver.gamma=1e-7"])  # sweeps are left to the jobs
    register.preflight(["-m", "sweep=suite3_table", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2"])
    register.preflight(["--cfg", "job", "kernel.sigma=0"])    # Hydra's own flags: Hydra's business
    assert sorted(p.name for p in tmp_path.iterdir()) == ["confs"]


def test_broken_yaml_on_the_search_path_is_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    search = _user_configs(tmp_path, "solver: [1, 2\n")
    line = _register_error(capsys, [search, "experiment=mine"])
    assert str(tmp_path / "confs" / "experiment" / "mine.yaml") in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["confs"]


@pytest.mark.parametrize("key", ["hydra.run.dir", "hydra.sweep.dir"])
def test_run_dir_below_a_file_is_one_line(tmp_path, monkeypatch, capsys, key):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "blocker").write_text("")
    argv = [f"{key}=blocker/run"] + (["-m", "seed=0,1"] if key == "hydra.sweep.dir" else [])
    line = _register_error(capsys, argv)
    assert f"{key}=blocker/run cannot be created: {tmp_path / 'blocker'} is not a directory" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]


def test_unwritable_run_dir_is_one_line(tmp_path, monkeypatch, capsys):
    """A directory the user may not write (os.access says so: read-only mount, permissions)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ro").mkdir()
    real_access = os.access
    monkeypatch.setattr(cli.os, "access", lambda p, mode: Path(p) != tmp_path / "ro" and real_access(p, mode))
    line = _register_error(capsys, ["hydra.run.dir=ro/run"])
    assert f"hydra.run.dir=ro/run is not writable: {tmp_path / 'ro'}, where it would be created," in line
    line = _register_error(capsys, ["hydra.run.dir=ro"])
    assert "hydra.run.dir=ro is not writable: the run directory is read-only" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ro"] and not any((tmp_path / "ro").iterdir())


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write a read-only directory")
def test_read_only_run_dir_is_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ro").mkdir(mode=0o555)
    try:
        assert "is not writable" in _register_error(capsys, ["hydra.run.dir=ro/run"])
    finally:
        (tmp_path / "ro").chmod(0o755)


@pytest.mark.parametrize("argv, message", [
    (["data=files", "data.templat=t.png"], "data.templat=t.png: the config has no key data.templat; did you mean "
                                           "data.template=t.png?"),
    (["+data.templat=t.png"], "unknown config key(s) data.templat: not in the schema "
                              "indreg.experiments.config.RegisterConfig (data.templat: did you mean data.template?)"),
    (["sover.gamma=1e-6"], "did you mean solver.gamma=1e-6?"),
    (["xyz.abc=1"], "xyz.abc=1: the config has no key xyz.abc; --help lists the keys"),
])
def test_a_misspelt_key_is_answered_with_the_nearest_valid_one(tmp_path, monkeypatch, capsys, argv, message):
    """Not Hydra's hint to append the misspelt key with ``+`` (which the schema then refuses)."""
    monkeypatch.chdir(tmp_path)
    line = _register_error(capsys, argv)
    assert message in line and "To append" not in line
    assert not any(tmp_path.iterdir())


def test_nearest_key_looks_under_the_given_parent_first():
    from indreg.experiments.errors import nearest_key

    known = ["data", "data.template", "data.sinogram", "solver", "solver.gamma", "train", "train.steps", "model",
             "model.name"]
    assert [nearest_key(k, known) for k in ("data.templat", "sover.gamma", "templat", "model.steps", "qq")] == \
        ["data.template", "solver.gamma", "data.template", None, None]


@pytest.mark.parametrize("launcher, extra", [("joblib", "joblib"), ("slurm", "submitit"),
                                             ("submitit_local", "submitit"), ("ray", "ray")])
def test_launcher_without_its_plugin_names_the_extra(monkeypatch, capsys, launcher, extra):
    monkeypatch.setattr(cli, "_plugin_installed", lambda module: False)
    line = _register_error(capsys, ["-m", f"hydra/launcher={launcher}", "seed=0,1"])
    assert line.endswith(f'hydra/launcher={launcher} needs its Hydra plugin, which is not installed: '
                         f'pip install "indreg[{extra}]"')


def test_every_extra_named_for_a_launcher_exists():
    extras = _pyproject()["project"]["optional-dependencies"]
    for extra, module in cli.LAUNCHER_EXTRAS.values():
        plugin = module.split(".")[-1].replace("_", "-")
        assert any(dep.startswith(plugin) for dep in extras[extra]), (extra, plugin)


# ---------------------------------------------------------------- indreg-train-momentum
@pytest.mark.parametrize("override, message", [
    ("solver=lbfgs", "solver=lbfgs: indreg-train-momentum has no key 'solver'; the keys of indreg-train-momentum "
                     "are seed, dtype, device, domain,"),
    ("+foo=1", "has no key 'foo'"),
    ("train.stepz=3", "has no key 'train.stepz' (did you mean train.steps?); the keys of 'train' are steps,"),
    ("~train.resume", "needs every key of its config"),
])
def test_train_momentum_refuses_keys_it_does_not_have(capsys, override, message):
    assert message in _train_error(capsys, [override])


def test_train_momentum_accepts_its_own_keys(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for argv in (["train.steps=3", "domain.n=16"], ["model=unrolled", "model.steps=3", "model.gradient=exact"],
                 ["model=unrolled", "model.space=initial", "model.correction=false"],
                 ["model=unrolled", "model.heavy_ball=false", "model.supervised=0"]):
        argv = [*argv, f"hydra.run.dir={tmp_path / 'run'}"]
        cli.preflight(argv, train.PROG, train.CONFIG_DIR, train.CONFIG_NAME, train.check_config,
                      train.base_config(argv))
    assert not any(tmp_path.iterdir())
    assert cli.compose(train.CONFIG_DIR, train.CONFIG_NAME, ["model=unrolled"]).model.updates == 10


@pytest.mark.parametrize("argv, message", [
    (["model.steps=3"], "has no key 'model.steps'; the keys of 'model' are name, width, levels"),
    (["model=unet"], "Could not find 'model/unet' Available options in 'model': oneshot"),
    (["model=unrolled", "model.init=random"], "model.init must be one of oneshot, zero, got 'random'"),
    (["model=unrolled", "model.gradient=double"], "model.gradient must be one of detached, exact, got 'double'"),
    (["model=unrolled", "model.space=momentum"], "model.space must be one of velocity, initial, got 'momentum'"),
    (["model=unrolled", "model.step_size=0"], "model.step_size must be"),
    (["model=unrolled", "model.supervised=-1"], "model.supervised must be"),
    (["eval.ood.num_angles=[6,0]"], "eval.ood.num_angles must be an integer >= 1, got 0"),
    (["eval.ood.num_angles=[6.5]"], "eval.ood.num_angles must be an integer >= 1, got 6.5"),
    (["eval.ood.num_angles=6"], "eval.ood.num_angles must be a list (e.g. [6, 20], or []), got 6"),
    (["eval.ood.snr_db=[inf]"], "eval.ood.snr_db must be a finite number"),
    (["eval.ood.phantoms=[j,w]"], "eval.ood.phantoms: unknown phantom 'w'; valid names: j, v,"),
    (["eval.ood.phantoms=[shepp_logan_3d]"], "eval.ood.phantoms: 'shepp_logan_3d' is a 3D phantom"),
])
def test_train_momentum_models(capsys, argv, message):
    """model=oneshot | unrolled: the keys of the chosen model only; an unknown model, a bad option of the model or
    of eval.ood: one line, before anything runs."""
    line = _train_error(capsys, argv)
    assert message in line


# ---------------------------------------------------------------- indreg-sweep-table
def test_sweep_table_is_a_console_script():
    scripts = _pyproject()["project"]["scripts"]
    assert scripts["indreg-sweep-table"] == "indreg.experiments.sweep:main"


def _one_run(root: Path) -> Path:
    run = root / "0"
    run.mkdir(parents=True)
    (run / "metrics.json").write_text(json.dumps({"hparams": {"gamma": 1e-7, "sigma": 2.0}, "iterations": 5,
                                                  "ssim": 0.8, "psnr": 20.0, "ssim_paper": 0.9, "psnr_paper": 26.0}))
    return run


def test_python_m_sweep_writes_the_table(tmp_path):
    _one_run(tmp_path / "mr")
    proc = subprocess.run([sys.executable, "-m", "indreg.experiments.sweep", str(tmp_path / "mr")], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "0.9000 / 26.00 (0.9039 / 26.96)" in proc.stdout and (tmp_path / "mr" / "table.csv").is_file()


def test_sweep_table_usage_and_bad_input(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        sweep_main([])
    assert exc.value.code == 2 and "usage: indreg-sweep-table" in capsys.readouterr().err
    line = _preflight_error(capsys, sweep_main, [str(tmp_path / "nothing")])
    assert line == f"indreg-sweep-table: error: no metrics.json below {tmp_path / 'nothing'} (a multirun dir of " \
                   "indreg-register)"
    run = _one_run(tmp_path / "mr")
    (run / "metrics.json").write_text(json.dumps({"status": "failed", "iteration": 3}))
    line = _preflight_error(capsys, sweep_main, [str(tmp_path / "mr")])
    assert line.startswith(f"indreg-sweep-table: error: {run / 'metrics.json'} is not the metrics.json of a "
                           "finished indreg-register run with a target (status 'failed', missing 'hparams')")
    assert not (tmp_path / "mr" / "table.md").exists()


@pytest.mark.parametrize("argv", [["--experimental-rerun", "f.pickle"], ["--experimental-rerun=f.pickle"],
                                  ["--exp", "f.pickle", "--help"]])
def test_experimental_rerun_is_refused_by_preflight(capsys, argv):
    """(Every entry point as a subprocess, with a crafted pickle: test_rerun_guard.py.)"""
    with pytest.raises(SystemExit) as exc:
        register.preflight(argv)
    lines = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(lines) == 1 and "(--experimental-rerun) is not supported" in lines[0]


def test_register_help_imports_no_torch(tmp_path):
    """``--help`` composes the help text without the config schema, so without torch (0.45 s instead of 3.7 s
    measured on the reference machine); the text is the full one."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "indreg.experiments.register", "--help"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert proc.returncode == 0, proc.stderr[-3000:]
    imported = {line.rsplit("|", 1)[-1].strip() for line in proc.stderr.splitlines() if line.startswith("import time")}
    assert "indreg.experiments.cli" in imported and "hydra" in imported
    assert "torch" not in imported and "indreg.experiments.config" not in imported
    assert "experiment: own_data_example," in proc.stdout and "solver: adam, algorithm1" in proc.stdout
    assert not any(tmp_path.iterdir())


def test_register_names_the_schema_and_config_dir_of_config():
    from indreg.experiments import config

    assert register._SCHEMA == config.SCHEMA_NAME and register._CONFIG == config.CONFIG_DIR
    assert register.CONFIG_DIR == config.CONFIG_DIR and register._CONFIG_NAME == "config"


# ---------------------------------------------------------------- through the entry points
@pytest.mark.slow
def test_register_help_describes_the_tool(tmp_path):
    proc = run_cli(["--help"], cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert out.startswith("indreg-register: indirect image registration") and "powered by Hydra" not in out
    assert "experiment: own_data_example," in out and "suite_et_3d" in out
    for text in (cli.DOCS_URL, "indreg-sweep-table", 'pip install "indreg[ray]"', "--cfg job",
                 "help(indreg.register)"):
        assert text in out
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_train_momentum_help_and_a_group_of_the_other_app(tmp_path):
    cmd = [sys.executable, "-m", "indreg.learn.train"]
    proc = subprocess.run(cmd + ["--help"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert out.startswith("indreg-train-momentum: learned LDDMM") and "powered by Hydra" not in out
    assert "experiment:" not in out and "solver:" not in out and "num_train: 256" in out
    # the unrolled model as it is today (no correction network by default), its keys, the run's duration, the docs
    for text in ("no correction network (model.correction=false", "model.updates (K, 10)", "about 8 minutes",
                 cli.DOCS_URL):
        assert text in " ".join(out.split()), text
    proc = subprocess.run(cmd + ["solver=lbfgs"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[0].startswith("indreg-train-momentum: error: solver=lbfgs: ")
    assert len(proc.stderr.strip().splitlines()) == 1 and not any(tmp_path.iterdir())


@pytest.mark.slow
def test_cli_errors_before_hydra_are_one_line_and_write_nothing(tmp_path):
    search = _user_configs(tmp_path, "solver: [1, 2\n")
    (tmp_path / "blocker").write_text("")
    cases = [[search, "experiment=mine"], ["hydra.run.dir=blocker/run"]]
    missing = [name for name, (_, module) in cli.LAUNCHER_EXTRAS.items() if not cli._plugin_installed(module)]
    cases += [["-m", f"hydra/launcher={name}", "seed=0,1"] for name in missing[:1]]
    for args in cases:
        proc = run_cli(args, cwd=tmp_path, timeout=120)
        assert proc.returncode == 1, proc.stderr[-3000:]
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("indreg-register: error: "), lines
        assert proc.stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker", "confs"]


def test_error_chain_follows_causes_and_honours_from_none():
    """``raise ... from None`` hides the context, as in Python's tracebacks; causes are followed."""
    try:
        try:
            raise KeyError("inner")
        except KeyError:
            raise ValueError("outer") from None
    except ValueError as e:
        assert cli.error_chain(e) == "outer"
    try:
        try:
            raise KeyError("inner")
        except KeyError as k:
            raise ValueError("outer") from k
    except ValueError as e:
        assert cli.error_chain(e) == "outer: 'inner'"
