"""The provenance record lists the run's own outputs only: a FIFO, a link, a foreign or corrupt file in the
directory is never opened, never blocks and never fails the record; 20,000 foreign files cost nothing."""
import json
import os
import threading
import time

import numpy as np
import pytest

from indreg.io.provenance import record, write_record

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs (POSIX)")


def _in_time(fn, seconds=20.0):
    """``fn()``'s result, failing (instead of hanging the suite) if it has not returned after ``seconds``."""
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("r", fn()), daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), "the record blocked"
    return out["r"]


def test_fifos_links_and_foreign_files_are_not_opened(tmp_path):
    np.save(tmp_path / "final.npy", np.zeros((3, 2)))
    os.mkfifo(tmp_path / "notes.npy")        # foreign: a reader would wait for a writer forever
    os.mkfifo(tmp_path / "momentum.npy")     # an own name, but a FIFO: left out unopened
    (tmp_path / "foreign.npy").write_bytes(b"x")
    outside = tmp_path.parent / f"{tmp_path.name}-outside.npy"
    np.save(outside, np.zeros(7))
    (tmp_path / "velocity.npy").symlink_to(outside)
    names = ["final.npy", "momentum.npy", "velocity.npy", "run.json"]
    out = _in_time(lambda: write_record(tmp_path / "run.json", tmp_path, names, run="t"))
    assert [e["path"] for e in out["outputs"]] == ["final.npy", "run.json"]
    assert out["outputs"][0]["shape"] == [3, 2]
    assert json.loads((tmp_path / "run.json").read_text()) == out
    assert np.load(outside).shape == (7,)


def test_a_corrupt_own_file_is_noted_not_fatal(tmp_path):
    (tmp_path / "final.npy").write_bytes(b"x")            # as `printf x > final.npy`
    (tmp_path / "final.mrc").write_bytes(b"\0" * 10)
    entries = {e["path"]: e for e in record(tmp_path, ["final.npy", "final.mrc"])}
    assert set(entries) == {"final.npy", "final.mrc"}
    assert "unreadable" in entries["final.npy"] and "\n" not in entries["final.npy"]["unreadable"]
    assert "unreadable" in entries["final.mrc"] and entries["final.npy"]["bytes"] == 1


def _touch(path):
    os.close(os.open(path, os.O_CREAT | os.O_WRONLY, 0o644))


@pytest.mark.slow   # creating 20,000 files: 2-7 s on a loaded 2-core machine
def test_twenty_thousand_foreign_files_are_not_walked(tmp_path, monkeypatch):
    import indreg.io.provenance as provenance

    monkeypatch.setattr(provenance, "MAX_WALK", 100)
    np.save(tmp_path / "final.npy", np.zeros(2))
    for i in range(20_000):
        _touch(tmp_path / f"f{i}.npy")
    board = tmp_path / "tensorboard"
    board.mkdir()
    for i in range(provenance.MAX_WALK + 5):
        _touch(board / f"e{i}")
    t0 = time.perf_counter()
    out = write_record(tmp_path / "run.json", tmp_path, ["final.npy", "tensorboard", "run.json"])
    seconds = time.perf_counter() - t0
    assert [e["path"] for e in out["outputs"]] == ["final.npy", "tensorboard", "run.json"]
    assert out["outputs"][1]["bytes_at_least"] == 0 and "bytes" not in out["outputs"][1]
    assert (tmp_path / "run.json").stat().st_size < 4000 and seconds < 2.0, seconds
