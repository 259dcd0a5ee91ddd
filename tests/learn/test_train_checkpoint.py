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
