"""A crafted or damaged ``baselines.npz`` in a run directory: never unpickled, never trusted (names, shapes and
values checked against the run), only a warning; the baselines are recomputed and the cache rewritten."""
import numpy as np
import pytest

from indreg.experiments.baselines import _cached

from experiment_helpers import TINY, run_app

KEY = np.array(["ram-lak", "1.0"], dtype=str)
SHAPE = (4, 4)


class _Opens:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def _write(path, **arrays):
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("case", ["not a zip", "object key", "object array", "wrong shape", "non-finite",
                                  "missing name", "extra name"])
def test_a_crafted_cache_is_ignored_with_a_warning(tmp_path, caplog, case):
    good = np.zeros(SHAPE)
    arrays = {"not a zip": None, "object key": dict(key=np.array([_Opens(tmp_path / "m")], dtype=object)),
              "object array": dict(key=KEY, fbp=np.array([_Opens(tmp_path / "m")], dtype=object), tv=good),
              "wrong shape": dict(key=KEY, fbp=np.zeros((3, 3)), tv=good),
              "non-finite": dict(key=KEY, fbp=np.full(SHAPE, np.nan), tv=good),
              "missing name": dict(key=KEY, fbp=good),
              "extra name": dict(key=KEY, fbp=good, tv=good, sirt=good)}[case]
    path = tmp_path / "baselines.npz"
    if arrays is None:
        path.write_bytes(b"PK\x03\x04 not really a zip")
    else:
        _write(path, **arrays)
    with caplog.at_level("WARNING"):
        assert _cached(path, KEY, ("fbp", "tv"), SHAPE) is None
    assert "recomputing the baselines" in caplog.text and not (tmp_path / "m").exists()


def test_a_good_cache_is_used_and_another_key_is_not(tmp_path):
    path = _write(tmp_path / "baselines.npz", key=KEY, fbp=np.ones(SHAPE), tv=np.zeros(SHAPE))
    rec = _cached(path, KEY, ("fbp", "tv"), SHAPE)
    assert sorted(rec) == ["fbp", "tv"] and float(rec["fbp"].sum()) == 16
    assert _cached(path, KEY[:1], ("fbp", "tv"), SHAPE) is None


def test_the_app_recomputes_over_a_crafted_cache(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    _write(out / "baselines.npz", key=np.array([_Opens(tmp_path / "m")], dtype=object))
    result = run_app(TINY + ["solver.max_iter=2", "logging.figure=false", "logging.tensorboard=false"], out)
    assert result["status"] == "completed" and not (tmp_path / "m").exists()
    assert np.load(out / "fbp.npy").shape == (32, 32)
    with np.load(out / "baselines.npz") as z:   # rewritten by the run
        assert z["key"].dtype.kind == "U" and z["fbp"].shape == (32, 32)
