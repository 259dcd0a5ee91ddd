"""A volume's run in memory: no float64 copy of a fine array in the experiment, outputs written in chunks and frame
by frame with the numbers of whole float64 arrays (the trajectory, the figures of merit, the files)."""
import json
import math

import numpy as np
import pytest
import torch

from experiment_helpers import compose, run_app
from test_et_3d import TINY_3D

# 16^3 with the velocity on 8^3 (velocity_factor 2), slab-wise (4 slabs of 4 slices)
SLABS_3D = TINY_3D + ["deformation.velocity_factor=2", "deformation.slab_size=4"]


def _tensors(obj):
    """The tensors among an object's attributes (one level), by name."""
    return {k: v for k, v in vars(obj).items() if isinstance(v, torch.Tensor)}


@pytest.mark.parametrize("overrides", [TINY_3D, SLABS_3D], ids=["whole", "slabwise"])
def test_3d_experiment_holds_no_float64_fine_volume(overrides):
    from indreg.experiments.build import build, seed_everything

    cfg = compose(overrides + ["baseline=none"])
    seed_everything(cfg.seed)
    exp = build(cfg)
    assert (type(exp.problem).__name__ == "SlabwiseRegistration") == (overrides is SLABS_3D)
    arrays = {f"data.{k}": v for k, v in _tensors(exp.data).items()}
    arrays.update({f"exp.{k}": v for k, v in _tensors(exp).items()})
    arrays.update({f"problem.{k}": v for k, v in _tensors(exp.problem).items()})
    fine = {k: v for k, v in arrays.items() if v.numel() >= math.prod(exp.ray_transform.range_shape)}
    assert {"data.template_64", "data.target_64", "data.data_64", "data.clean_64", "exp.template_64",
            "exp.noisy_data_64", "problem.template", "problem.data"} <= set(fine)
    assert {k: v.dtype for k, v in fine.items()} == {k: torch.float32 for k in fine}
    # one template and one data tensor: the run's are the experiment's (the CPU, no units applied)
    assert exp.problem.template.data_ptr() == exp.template_64.data_ptr() == exp.data.template_64.data_ptr()
    assert exp.problem.data.data_ptr() == exp.noisy_data_64.data_ptr()


def test_2d_experiment_keeps_float64():
    from indreg.experiments.build import build

    exp = build(compose(["phantom.size=32", "baseline=none"]))
    assert exp.template.dtype == torch.float32
    assert {exp.data.template_64.dtype, exp.target_64.dtype, exp.noisy_data_64.dtype} == {torch.float64}


@pytest.mark.parametrize("overrides", [pytest.param(TINY_3D, marks=pytest.mark.slow), SLABS_3D],
                         ids=["whole", "slabwise"])
def test_3d_outputs_equal_whole_float64_arrays(tmp_path, overrides):
    """The files and metrics of a 3D run equal what whole arrays give: the trajectory (written frame by frame) is
    the problem's ``image_trajectory`` of the saved momentum, bit for bit; SSIM / PSNR (float64 chunks) are
    scikit-image's on the saved float64 volumes to rounding; a baseline's too."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from indreg.experiments.build import build, seed_everything

    args = overrides + ["baseline.enabled=true", "logging.tensorboard=true", "logging.figure=true"]
    m = run_app(args, tmp_path)
    assert m["status"] == "completed"
    final, target = np.load(tmp_path / "final.npy"), np.load(tmp_path / "target.npy")
    assert final.dtype == target.dtype == np.float64
    r = float(target.max() - target.min())
    assert m["ssim"] == pytest.approx(structural_similarity(final, target, data_range=r), rel=1e-13)
    assert m["ssim_paper"] == pytest.approx(structural_similarity(final, target, data_range=2.0), rel=1e-13)
    assert m["psnr"] == pytest.approx(peak_signal_noise_ratio(target, final, data_range=r), rel=1e-13)
    sirt = np.load(tmp_path / "sirt.npy")
    assert m["sirt_ssim"] == pytest.approx(structural_similarity(sirt, target, data_range=r), rel=1e-13)
    cfg = compose(args)
    seed_everything(cfg.seed)
    exp = build(cfg)
    np.testing.assert_array_equal(target, exp.target_64.double().numpy())   # float32 -> float64: exact
    momentum = torch.from_numpy(np.load(tmp_path / "momentum.npy")).float()
    trajectory = exp.problem.image_trajectory((momentum,))
    np.testing.assert_array_equal(np.load(tmp_path / "trajectory.npy"), trajectory.double().numpy())
    np.testing.assert_array_equal(final, trajectory[-1].double().numpy())
    assert (tmp_path / "figure.png").stat().st_size > 10_000 and any((tmp_path / "tensorboard").iterdir())
    assert json.loads((tmp_path / "metrics.json").read_text())["iterations"] == 3


@pytest.mark.parametrize("shape", [(5, 4, 3), (2, 3, 4, 5), (7,)])
def test_save_array_and_frames_write_what_np_save_writes(tmp_path, monkeypatch, shape):
    from indreg.experiments import outputs

    monkeypatch.setattr(outputs, "SAVE_CHUNK", 7)
    a = torch.randn(shape, generator=torch.Generator().manual_seed(0)).float()
    np.save(tmp_path / "expected.npy", a.double().numpy())
    outputs.save_array(tmp_path / "a.npy", a)
    assert (tmp_path / "a.npy").read_bytes() == (tmp_path / "expected.npy").read_bytes()
    if len(shape) > 1:
        kept = outputs.save_frames(tmp_path / "f.npy", iter(a), shape[0], keep={0, shape[0] - 1})
        assert (tmp_path / "f.npy").read_bytes() == (tmp_path / "expected.npy").read_bytes()
        assert sorted(kept) == sorted({0, shape[0] - 1}) and torch.equal(kept[0], a[0])
        for wrong in (shape[0] - 1, shape[0] + 1):
            with pytest.raises(ValueError, match=f"expected {wrong} frames"):
                outputs.save_frames(tmp_path / "g.npy", iter(a), wrong)
