"""Checkpoints: no code runs on load, damaged files are refused in one line, writes are atomic, resuming keeps
the bookkeeping exact; the app's user errors (config, run dir, checkpoint) stop it before any computing."""
import hashlib
import io
import json
import os
import random
import shutil

import numpy as np
import pytest
import torch

from indreg.experiments import checkpoint, runner
from indreg.experiments.checkpoint import CheckpointError
from indreg.experiments.config import ConfigError, validate

from experiment_helpers import FAST, compose, run_app, run_cli

F64 = FAST + ["dtype=float64", "device=cpu"]
KEYS = ("iteration", "state", "solver", "rng", "history", "seconds", "problem")


class _Payload:
    """Unpickling this creates the file ``marker`` (what an attacker's code would do)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def _framed(data: bytes) -> bytes:
    """``data`` behind a valid header with the right checksum (an attacker can compute it too)."""
    digest = hashlib.sha256(data).hexdigest()
    return f"indreg-checkpoint {checkpoint.VERSION} sha256={digest} bytes={len(data)}\n".encode() + data


def _forbid_build(cfg):
    raise AssertionError("build() was called: the error must come before any computing")


@pytest.fixture
def no_build(monkeypatch):
    """Fail the test if the app gets as far as building the problem."""
    monkeypatch.setattr(runner, "build", _forbid_build)


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A float64 run stopped (checkpointed) after 2 of 10 iterations."""
    out = tmp_path_factory.mktemp("stopped")
    assert run_app(F64 + ["stop_after=2"], out)["status"] == "stopped"
    return out


def _copy_run(stopped, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(stopped, out)
    return out


def test_round_trip_of_tensors_plain_data_and_rng_states(tmp_path):
    path = tmp_path / "checkpoint.pt"
    random.seed(1), np.random.seed(2), torch.manual_seed(3)
    random.gauss(0, 1), np.random.standard_normal()     # cached gaussians are part of the states
    payload = {"iteration": 7, "m": torch.randn(3, 2, 4, 4, dtype=torch.float64), "nan": float("nan"),
               "history": [{"warning": "", "rejected": False, "x": None}], "pair": (1, 2.5),
               "rng": checkpoint.rng_state()}
    checkpoint.save(path, payload)
    draws = [random.random(), random.gauss(0, 1), np.random.rand(), np.random.standard_normal(), torch.rand(1)]
    loaded = checkpoint.load(path, keys=("iteration", "m", "rng"))
    assert loaded["iteration"] == 7 and torch.equal(loaded["m"], payload["m"]) and loaded["pair"] == (1, 2.5)
    assert loaded["history"] == payload["history"] and np.isnan(loaded["nan"])
    assert loaded["rng"]["numpy"]["key"].dtype == torch.int64 and loaded["rng"]["python"]["key"].shape == (625,)
    checkpoint.set_rng_state(loaded["rng"])
    assert [random.random(), random.gauss(0, 1), np.random.rand(), np.random.standard_normal(), torch.rand(1)] == draws
    assert path.read_bytes().startswith(b"indreg-checkpoint 2 sha256=")


def test_a_checkpoint_cannot_run_code(tmp_path, stopped, no_build):
    """A pickle whose ``__reduce__`` creates a file: refused, bare (version 1 format) or behind a valid header,
    by ``load`` and by the app with ``resume=true``; the file is never created."""
    marker = tmp_path / "marker"
    buf = io.BytesIO()
    torch.save({name: None for name in KEYS} | {"iteration": 1, "x": _Payload(marker)}, buf)
    out = _copy_run(stopped, tmp_path)
    for name, blob in (("bare.pt", buf.getvalue()), ("framed.pt", _framed(buf.getvalue()))):
        path = tmp_path / name
        path.write_bytes(blob)
        with pytest.raises(CheckpointError, match=name):
            checkpoint.load(path)
        (out / "checkpoint.pt").write_bytes(blob)
        with pytest.raises(CheckpointError, match="checkpoint.pt"):
            run_app(F64 + ["resume=true"], out)
        assert not marker.exists()
    with pytest.raises(CheckpointError, match="refused to unpickle"):
        checkpoint.load(tmp_path / "framed.pt")


def test_save_stores_only_tensors_and_plain_data(tmp_path):
    path = tmp_path / "checkpoint.pt"
    for bad, where in (({"a": {"b": np.float64(1.0)}}, r"payload\['a'\]\['b'\] is a float64"),
                       ({"x": _Payload(tmp_path / "m")}, r"payload\['x'\] is a _Payload"),
                       ({"a": [1, object()]}, r"payload\['a'\]\[1\] is a object"),
                       ({(1, 2): 0}, "key of type tuple")):
        with pytest.raises(TypeError, match=where):
            checkpoint.save(path, bad)
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "checkpoint.pt"
    checkpoint.save(path, {"iteration": 1})

    def fsync(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save(path, {"iteration": 2})
    monkeypatch.undo()
    assert checkpoint.load(path)["iteration"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]


def _damage(path, case):
    """Damage a real checkpoint in place; returns the part of the error message that names the problem."""
    blob = path.read_bytes()
    if case == "empty":
        path.write_bytes(b"")
        return "empty"
    if case == "truncated":
        path.write_bytes(blob[:len(blob) // 2])
        return "truncated"
    if case == "trailing_bytes":
        path.write_bytes(blob + b"\0")
        return "trailing bytes"
    if case == "random_bytes":
        path.write_bytes(random.Random(0).randbytes(4096))
        return "not an indreg checkpoint"
    if case == "momentum_overwritten":       # 64 bytes inside the momentum tensor's storage
        m = checkpoint.load(path)["state"]["momentum"]
        start = blob.find(m.numpy().tobytes()) + m.numel() * m.element_size() // 2
        assert start > 64
        path.write_bytes(blob[:start] + random.Random(1).randbytes(64) + blob[start + 64:])
        return "checksum mismatch"
    if case == "header_damaged":
        path.write_bytes(blob.replace(b"sha256=", b"sha256:", 1))
        return "header line is damaged"
    if case == "other_version":
        path.write_bytes(blob.replace(b"indreg-checkpoint 2", b"indreg-checkpoint 3", 1))
        return "format version 3"
    if case == "missing_key":
        payload = checkpoint.load(path)
        del payload["solver"]
        checkpoint.save(path, payload)
        return "missing key(s) 'solver'"
    if case == "bad_content":                # verified, but the momentum is not a tensor
        payload = checkpoint.load(path)
        payload["state"]["momentum"] = "zeros"
        checkpoint.save(path, payload)
        return "does not fit this run"
    if case == "directory":
        path.unlink()
        path.mkdir()
        return "not a regular file"
    raise ValueError(case)


CASES = ["empty", "truncated", "trailing_bytes", "random_bytes", "momentum_overwritten", "header_damaged",
         "other_version", "missing_key", "bad_content", "directory"]


@pytest.mark.parametrize("case", CASES)
def test_damaged_checkpoint_is_refused_in_one_line(tmp_path, stopped, case):
    out = _copy_run(stopped, tmp_path)
    path = out / "checkpoint.pt"
    what = _damage(path, case)
    with pytest.raises(CheckpointError) as err:
        run_app(F64 + ["resume=true"], out)
    message = str(err.value)
    assert "\n" not in message and what in message, message
    assert message.startswith(f"checkpoint {path}") and message.endswith("delete it or run without resume=true")
    if case != "bad_content":    # found before building the problem (the content check needs the solver)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(runner, "build", _forbid_build)
            with pytest.raises(CheckpointError):
                run_app(F64 + ["resume=true"], out)


@pytest.mark.slow
def test_cli_damaged_checkpoint_exits_1_with_one_line(tmp_path, stopped):
    out = _copy_run(stopped, tmp_path)
    path = out / "checkpoint.pt"
    _damage(path, "momentum_overwritten")
    proc = run_cli(F64 + ["resume=true", f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"indreg-register: error: checkpoint {path}: SHA-256 checksum mismatch (the file is damaged); "
                     "delete it or run without resume=true"], proc.stderr[-3000:]


@pytest.mark.slow
def test_cli_user_errors_and_failed_runs_exit_1_with_one_line(tmp_path):
    """A bad name, an option the optimizer does not take (refused by the config check), a run whose objective
    overflows."""
    cases = [(["name=../../x"], "invalid config value name='../../x'"),
             (["solver=adam", "+solver.optimizer_kwargs.foo=1"], "solver.optimizer_kwargs.foo=1: expected a keyword"),
             (["solver.step_size=1e300"], "the run failed at iteration 1: non-finite objective")]
    for i, (overrides, message) in enumerate(cases):
        out = tmp_path / f"run{i}"
        proc = run_cli(F64 + overrides + [f"hydra.run.dir={out}"], cwd=tmp_path)
        assert proc.returncode == 1, proc.stderr[-3000:]
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("indreg-register: error: ") and message in lines[0], lines
    assert json.loads((tmp_path / "run2" / "metrics.json").read_text())["status"] == "failed"
    assert not (tmp_path.parent / "x").exists()


def test_non_finite_objective_fails_the_run(tmp_path):
    """Status "failed" (not "converged"), no final outputs, the periodic checkpoint is not overwritten."""
    out = tmp_path / "run"
    result = run_app(F64 + ["solver.step_size=1e300", "logging.checkpoint_every=1"], out)
    assert result["status"] == "failed" and result["iteration"] == 1
    assert "non-finite objective" in result["warning"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "failed" and metrics["objective"] == "nan"
    assert len(json.loads((out / "history.json").read_text())) == 1
    assert not (out / "final.npy").exists() and not (out / "checkpoint.pt").exists()


@pytest.mark.parametrize("solver", ["algorithm1", "lbfgs"])
def test_resume_keeps_evaluations_and_history_exactly(tmp_path, solver):
    """6 iterations uninterrupted vs. stopped at 2 and 4 and resumed twice: same objectives (float64, exactly)
    and the same evaluation counts (no re-evaluation of the resumed iterate is counted)."""
    cfg = F64 + [f"solver={solver}", "solver.max_iter=6"]
    ref = run_app(cfg, tmp_path / "ref")
    out = tmp_path / "run"
    assert run_app(cfg + ["stop_after=2"], out)["status"] == "stopped"
    assert run_app(cfg + ["stop_after=4", "resume=true"], out)["status"] == "stopped"
    res = run_app(cfg + ["resume=true"], out)
    a, b = (json.loads((d / "history.json").read_text()) for d in (tmp_path / "ref", out))
    for key in ("iteration", "objective", "evaluations", "grad_norm", "step_size"):
        assert [h[key] for h in b] == [h[key] for h in a], key
    assert res["evaluations"] == ref["evaluations"] and res["objective"] == ref["objective"]
    if solver == "algorithm1":
        assert ref["evaluations"] == 7          # one at the start, one per iteration


def test_checkpoint_path_that_is_a_directory_is_refused_without_resume(tmp_path, no_build):
    (tmp_path / "checkpoint.pt").mkdir()
    with pytest.raises(CheckpointError, match="not a regular file; delete it"):
        run_app(F64, tmp_path)


def test_checkpoint_past_max_iter_is_refused(tmp_path, stopped, no_build):
    out = _copy_run(stopped, tmp_path)
    with pytest.raises(CheckpointError, match=r"iteration 2, past solver\.max_iter=1"):
        run_app(F64 + ["resume=true", "solver.max_iter=1"], out)


def test_checkpoint_at_max_iter_finishes_without_iterating(tmp_path, stopped):
    out = _copy_run(stopped, tmp_path)
    result = run_app(F64 + ["resume=true", "solver.max_iter=2"], out)
    assert result["status"] == "completed" and result["iterations"] == 2
    assert len(json.loads((out / "history.json").read_text())) == 2


@pytest.mark.parametrize("name", ["../../x", "..", ".hidden", "", "a/b", "a\\b", "x\n"])
def test_name_must_be_one_safe_path_component(name):
    cfg = compose()
    cfg.name = name
    with pytest.raises(ConfigError, match="name="):
        validate(cfg)


@pytest.mark.parametrize("name", ["suite1_jv", "run-1.2", "_x"])
def test_name_accepts_safe_names(name):
    cfg = compose()
    cfg.name = name
    validate(cfg)


def _permissions_enforced(tmp_path) -> bool:
    """False when running as root: chmod does not stop writes."""
    probe = tmp_path / "probe"
    probe.mkdir()
    probe.chmod(0o555)
    try:
        (probe / "f").write_text("x")
    except PermissionError:
        return True
    finally:
        probe.chmod(0o755)
    return False


def test_read_only_run_dir_or_checkpoint_fails_before_computing(tmp_path, stopped, no_build):
    if not _permissions_enforced(tmp_path):
        pytest.skip("chmod does not stop this user (root) from writing")
    out = _copy_run(stopped, tmp_path)
    path = out / "checkpoint.pt"
    path.chmod(0o444)
    with pytest.raises(CheckpointError, match=f"checkpoint {path}: is not readable and writable"):
        run_app(F64 + ["resume=true"], out)
    out.chmod(0o555)
    try:
        with pytest.raises(CheckpointError, match=f"run directory {out} is not writable"):
            run_app(F64, out)
        with pytest.raises(CheckpointError, match=f"run directory {out / 'sub'} is not writable"):
            run_app(F64, out / "sub")
    finally:
        out.chmod(0o755)


@pytest.mark.parametrize("edit, match", [
    (lambda p: p.update(iteration=99), r"iteration 99, past solver\.max_iter=10"),
    (lambda p: p.update(iteration=-3), r"iteration -3 is not an integer"),
    (lambda p: p["state"].update(iteration=5), r"state\.iteration 5 differs from iteration 2"),
    (lambda p: p["state"].update(momentum=p["state"]["momentum"].long()), r"state\.momentum is a torch\.int64 tensor"),
    (lambda p: p["state"].update(momentum=p["state"]["momentum"][:2]), r"state\.momentum is a torch\.float64 tensor "
                                                                       r"of shape \(2,"),
    (lambda p: p.update(history=p["history"][:1]), r"history has 1 entries, expected one report per iteration \(2\)"),
    (lambda p: p.update(seconds=float("nan")), r"seconds nan is not a finite number"),
])
def test_edited_checkpoint_with_a_valid_checksum_is_checked_against_the_run(tmp_path, stopped, edit, match):
    """A checkpoint edited and re-saved (valid checksum) must still fit the run: types, shapes, ranges."""
    out = _copy_run(stopped, tmp_path)
    payload = checkpoint.load(out / "checkpoint.pt", keys=KEYS)
    edit(payload)
    checkpoint.save(out / "checkpoint.pt", payload)
    with pytest.raises(CheckpointError, match=match):
        run_app(F64 + ["resume=true"], out)
