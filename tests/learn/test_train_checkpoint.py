"""The training checkpoint: exact round trip of model / optimizer / RNG, damaged or crafted files refused."""
import hashlib
import io

import pytest
import torch

from indreg.experiments.checkpoint import VERSION, CheckpointError
from indreg.learn.train import load_checkpoint, save_checkpoint
from indreg.learn.unet import MomentumUNet


def _trained(seed=0):
    torch.manual_seed(seed)
    model = MomentumUNet(2, width=4, levels=2).double()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(2):
        optimizer.zero_grad()
        model(torch.randn(2, 2, 8, 8, dtype=torch.float64)).square().sum().backward()
        optimizer.step()
    return model, optimizer


def test_round_trip_restores_model_optimizer_step_and_rng(tmp_path):
    path = tmp_path / "checkpoint.pt"
    model, optimizer = _trained()
    save_checkpoint(path, model, optimizer, 2)
    expected = torch.rand(3)
    fresh, fresh_optimizer = _trained(seed=1)
    assert load_checkpoint(path, fresh, fresh_optimizer) == 2
    assert torch.equal(torch.rand(3), expected)
    for (name, a), b in zip(model.state_dict().items(), fresh.state_dict().values()):
        assert torch.equal(a, b), name
    a, b = optimizer.state_dict()["state"], fresh_optimizer.state_dict()["state"]
    assert all(torch.equal(a[k]["exp_avg_sq"], b[k]["exp_avg_sq"]) for k in a)


class _Payload:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def test_damaged_or_crafted_checkpoint_is_refused(tmp_path):
    path = tmp_path / "checkpoint.pt"
    model, optimizer = _trained()
    save_checkpoint(path, model, optimizer, 2)
    blob = path.read_bytes()
    path.write_bytes(blob[:-100])
    with pytest.raises(CheckpointError, match="truncated.*delete it or run without train.resume=true$"):
        load_checkpoint(path, model, optimizer)
    marker = tmp_path / "marker"
    buf = io.BytesIO()
    torch.save({"model": _Payload(marker), "optimizer": {}, "step": 1, "rng": None}, buf)
    data = buf.getvalue()
    path.write_bytes(f"indreg-checkpoint {VERSION} sha256={hashlib.sha256(data).hexdigest()} "
                     f"bytes={len(data)}\n".encode() + data)
    with pytest.raises(CheckpointError, match="refused to unpickle"):
        load_checkpoint(path, model, optimizer)
    assert not marker.exists()
    other = MomentumUNet(2, width=8, levels=2).double()
    save_checkpoint(path, other, optimizer, 2)            # a verified file of another network: one line too
    with pytest.raises(CheckpointError, match="does not fit this run") as err:
        load_checkpoint(path, model, optimizer)
    assert "\n" not in str(err.value)


def _config(overrides=()):
    from indreg.learn.conf import CONFIG_DIR
    from indreg.experiments import cli
    from indreg.learn.train import CONFIG_NAME, training_config

    return training_config(cli.job_config(cli.compose(CONFIG_DIR, CONFIG_NAME, list(overrides))))


def test_resume_with_another_training_config_is_refused(tmp_path):
    """As the registration app: a checkpoint records the config that defines its training; a resume with other
    values (``data.snr_db=-5 domain.n=24``, ``model.lr``) is refused in one line naming them; logging, the length of
    the training and the final comparison may change."""
    from indreg.learn.train import read_checkpoint

    path = tmp_path / "checkpoint.pt"
    model, optimizer = _trained()
    save_checkpoint(path, model, optimizer, 2, _config())
    with pytest.raises(CheckpointError) as err:
        read_checkpoint(path, _config(["data.snr_db=-5", "domain.n=24"]))
    line = str(err.value)
    assert "\n" not in line and "data.snr_db: checkpoint 10.0, config -5" in line and "domain.n: checkpoint 64" in line
    read_checkpoint(path, _config(["train.log_every=3", "train.steps=2000", "eval.algorithm1.max_iter=5",
                                   "device=cpu"]))
    save_checkpoint(path, model, optimizer, 2, _config(["model=unrolled"]))
    read_checkpoint(path, _config(["model=unrolled", "train.steps=2000", "model.steps=9"]))
    with pytest.raises(CheckpointError, match="model.lr: checkpoint 0.001, config 0.002"):
        read_checkpoint(path, _config(["model=unrolled", "model.lr=2e-3"]))
    save_checkpoint(path, model, optimizer, 2)     # an older checkpoint, without its config: not resumed blindly
    with pytest.raises(CheckpointError, match="does not record its training's config"):
        read_checkpoint(path, _config())


def test_scratch_left_by_kill_9_is_removed_on_resume(tmp_path):
    """kill -9 while a checkpoint is written leaves the writer's private directory (``.checkpoint.pt.<8>.tmp``,
    empty or with a partial file); the next start (resume or not) removes it, and nothing else."""
    from indreg.experiments.checkpoint import check_location

    empty, partial = tmp_path / ".checkpoint.pt.a1b2c3d4.tmp", tmp_path / ".metrics.json.zz_9yy8x.tmp"
    empty.mkdir()
    partial.mkdir()
    (partial / "metrics.json").write_text("{")
    (tmp_path / ".notes.tmp").mkdir()                # not a writer's name: kept
    (tmp_path / "checkpoint.pt").write_bytes(b"x")
    check_location(tmp_path / "checkpoint.pt", resume=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".notes.tmp", "checkpoint.pt"]
