"""Tests of the training example through its real entry point (scripts/train_momentum.py, Hydra, torchrun)."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from indreg.experiments import checkpoint

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "train_momentum.py"
TINY = ["domain.n=16", "geometry.num_angles=6", "geometry.det_count=24", "shooting.num_steps=3",
        "data.num_train=8", "data.num_val=2", "model.width=4", "model.levels=2", "train.batch_size=2",
        "train.log_every=1", "train.eval_every=2", "train.checkpoint_every=1", "eval.algorithm1.max_iter=2",
        "device=cpu"]
UNROLLED = ["model=unrolled", "model.update_width=4", "model.update_levels=1", "model.updates=2", "train.steps=2"]
METRICS = {"ssim", "psnr", "residual", "min_jacobian", "min_jacobian_worst", "seconds_per_sample", "num_samples",
           "per_sample_ssim"}


def run(run_dir, *overrides, launcher=(sys.executable,)):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [*launcher, str(SCRIPT), *TINY, *overrides, f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads((Path(run_dir) / "metrics.json").read_text())


def scalars(run_dir, tag):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(Path(run_dir) / "tensorboard"), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    return acc, [e.step for e in acc.Scalars(tag)]


def parameters(run_dir):
    return checkpoint.load(Path(run_dir) / "checkpoint.pt")


@pytest.mark.slow
def test_run_logs_checkpoints_and_resumes_exactly(tmp_path):
    first = run(tmp_path / "a", "train.steps=2", "eval.algorithm1.num_samples=1")
    assert first["resumed_from"] == 0 and first["world_size"] == 1
    assert 0 <= first["network"]["ssim"] <= 1 and first["network"]["seconds_per_sample"] > 0
    assert 0 <= first["algorithm1"]["ssim"] <= 1 and first["algorithm1"]["seconds_per_sample"] > 0
    assert first["algorithm1"]["network_ssim_same_samples"] == pytest.approx(first["network"]["per_sample_ssim"][0],
                                                                              rel=1e-12)
    acc, steps = scalars(tmp_path / "a", "train/loss")
    assert steps == [1, 2]
    assert {"val/template", "val/fbp", "val/target", "val/prediction"} <= set(acc.Tags()["images"])
    assert "val/ssim" in acc.Tags()["scalars"]
    assert parameters(tmp_path / "a")["step"] == 2
    assert (tmp_path / "a" / "figure.png").stat().st_size > 10_000     # the held-out examples
    shutil.copytree(tmp_path / "a", tmp_path / "b")

    resumed = run(tmp_path / "b", "train.steps=4", "eval.algorithm1.num_samples=0")
    assert resumed["resumed_from"] == 2 and "algorithm1" not in resumed
    _, steps = scalars(tmp_path / "b", "train/loss")
    assert steps == [1, 2, 3, 4]
    run(tmp_path / "c", "train.steps=4", "eval.algorithm1.num_samples=0")  # the uninterrupted run
    b, c = parameters(tmp_path / "b"), parameters(tmp_path / "c")
    assert b["step"] == c["step"] == 4
    for name, value in c["model"].items():            # resuming gives the uninterrupted run's weights
        torch.testing.assert_close(b["model"][name], value, rtol=1e-6, atol=1e-7)
    assert c["model"]["head.weight"].abs().sum() > 0     # the zero-initialised head did train


@pytest.mark.slow
@pytest.mark.parametrize("model", ["oneshot", "unrolled"])
def test_ddp_two_processes_keep_replicas_identical(tmp_path, model):
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    extra = (*UNROLLED, "model.steps=2", "eval.ood.num_angles=[]", "eval.ood.snr_db=[]",
             "eval.ood.phantoms=[]") if model == "unrolled" else ("train.steps=3",)
    metrics = run(tmp_path, *extra, "eval.algorithm1.num_samples=0", launcher=torchrun)
    assert metrics["world_size"] == 2
    assert metrics["replica_max_abs_diff"] == 0.0
    trained = ("step_logits", "inertia_logits") if model == "unrolled" else ("head.weight",)   # unrolled: the default
    assert all(parameters(tmp_path)["model"][name].abs().min() > 0 for name in trained)       # (no correction)
    _, steps = scalars(tmp_path, "train/loss")
    assert steps == ([1, 2] if model == "unrolled" else [1, 2, 3])


@pytest.mark.slow
def test_damaged_checkpoint_ends_in_one_line(tmp_path):
    """A damaged checkpoint.pt with train.resume=true: one line on stderr, exit status 1, no traceback."""
    (tmp_path / "checkpoint.pt").write_bytes(b"indreg-checkpoint 2 sha256=00 bytes=3\nabc")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(SCRIPT), *TINY, "train.steps=1", f"hydra.run.dir={tmp_path}"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines[-1].startswith("indreg-train-momentum: error: checkpoint") and "Traceback" not in proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("space", ["velocity", "initial"])
def test_unrolled_run_benchmarks_every_scheme_and_resumes_exactly(tmp_path, space):
    """model=unrolled: the one-shot steps, then the updates (own scalars and images), every scheme in metrics.json
    in and out of distribution, and a resume inside the unrolled phase gives the uninterrupted run's weights."""
    unrolled = (*UNROLLED, f"model.space={space}", "model.correction=true")     # velocity: + U (default: none)
    first = run(tmp_path / "a", *unrolled, "model.steps=1", "eval.algorithm1.num_samples=1")
    assert first["model"] == "unrolled" and first["steps"] == 3
    schemes = first["schemes"]
    assert {"oneshot", "unrolled", "algorithm1", "oneshot+algorithm1_2"} <= set(schemes)
    assert all(METRICS <= set(m) and 0 <= m["ssim"] <= 1 and m["seconds_per_sample"] > 0 for m in schemes.values())
    assert schemes["algorithm1"]["num_samples"] == 1 and schemes["unrolled"]["num_samples"] == 2
    assert first["network"]["per_sample_ssim"] == pytest.approx(schemes["unrolled"]["per_sample_ssim"], rel=1e-12)
    assert set(first["ood"]) == {"angles_6", "angles_20", "snr_5", "phantoms"}
    assert all(set(schemes) == set(variant) for variant in first["ood"].values())
    acc, steps = scalars(tmp_path / "a", "train/loss")
    assert steps == [1, 2] and [e.step for e in acc.Scalars("unrolled/loss")] == [3]
    assert {"val/update_0", "val/update_2"} <= set(acc.Tags()["images"])
    assert [e.step for e in acc.Scalars("val/ssim_update_2")] == [3]
    shutil.copytree(tmp_path / "a", tmp_path / "b")

    quick = ("eval.algorithm1.num_samples=0", "eval.ood.num_angles=[]", "eval.ood.snr_db=[]", "eval.ood.phantoms=[]")
    resumed = run(tmp_path / "b", *unrolled, "model.steps=3", *quick)
    assert resumed["resumed_from"] == 3 and resumed["ood"] == {} and "algorithm1" not in resumed
    acc, _ = scalars(tmp_path / "b", "train/loss")
    assert [e.step for e in acc.Scalars("unrolled/loss")] == [3, 4, 5]
    run(tmp_path / "c", *unrolled, "model.steps=3", *quick)
    b, c = parameters(tmp_path / "b"), parameters(tmp_path / "c")
    assert b["step"] == c["step"] == 5
    for name, value in c["model"].items():
        torch.testing.assert_close(b["model"][name], value, rtol=1e-6, atol=1e-7)
    assert c["model"]["updates.0.head.weight"].abs().sum() > 0
    assert c["model"]["residual_scale" if space == "velocity" else "gradient_scale"] > 0
    if space == "velocity":                                      # the learned step sizes moved, and are reported
        assert c["model"]["step_logits"].abs().min() > 0 and len(first["step_sizes"]) == 2
        assert c["model"]["inertia_logits"].abs().min() > 0 and len(first["inertias"]) == 1
        assert [e.step for e in acc.Scalars("unrolled/supervised")] == [3, 4, 5]
    first_phase = parameters(tmp_path / "a")["model"]            # the one-shot network is fixed while updates train
    assert torch.equal(first_phase["initial.head.weight"], c["model"]["initial.head.weight"])


def test_two_steps_in_process_write_every_output(tmp_path):
    """The training of the entry point (``train.train`` on the app's config) in this process, two steps: the fast
    stand-in of the end-to-end runs above (marked slow)."""
    from omegaconf import OmegaConf

    from indreg.learn import train

    cfg = OmegaConf.merge(train.base_config(), OmegaConf.from_dotlist([*TINY, "train.steps=2",
                                                                        "eval.algorithm1.num_samples=1"]))
    metrics = train.train(cfg, tmp_path)
    assert metrics["steps"] == 2 and metrics["resumed_from"] == 0 and metrics["world_size"] == 1
    assert 0 <= metrics["network"]["ssim"] <= 1 and 0 <= metrics["algorithm1"]["ssim"] <= 1
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 2
    _, steps = scalars(tmp_path, "train/loss")
    assert steps == [1, 2] and parameters(tmp_path)["step"] == 2
    assert (tmp_path / "figure.png").stat().st_size > 10_000
    changed = OmegaConf.merge(cfg, OmegaConf.from_dotlist(["data.snr_db=-5", "train.steps=3"]))   # as the app
    with pytest.raises(checkpoint.CheckpointError, match="data.snr_db: checkpoint 10.0, config -5"):
        train.train(changed, tmp_path)       # refused before anything is built or trained
    assert parameters(tmp_path)["step"] == 2


def test_schedule_and_learning_rate_of_the_two_phases():
    from omegaconf import OmegaConf

    from indreg.learn import train

    cfg = train.base_config(["model=unrolled"])
    cfg.train.steps, cfg.model.steps = 10, 4
    assert train.schedule(cfg) == (10, 14)
    lrs = [train.learning_rate(cfg, s, 10, 14) for s in range(14)]
    assert lrs[:10] == [cfg.train.lr] * 10 and lrs[10] == cfg.model.lr
    assert all(a > b > 0 for a, b in zip(lrs[10:], lrs[11:]))         # cosine decay over the unrolled steps
    cfg.model.init = "zero"                                           # from m_0 = 0: no one-shot phase
    assert train.schedule(cfg) == (0, 4)
    oneshot = train.base_config()
    oneshot.train.steps = 7
    assert train.schedule(oneshot) == (7, 7) and train.learning_rate(oneshot, 5, 7, 7) == oneshot.train.lr
    assert OmegaConf.to_container(oneshot.model) == {"name": "oneshot", "width": 16, "levels": 3}


def test_step_sizes_learn_at_their_own_rate():
    from indreg import GeodesicShooting, ImageDomain, IndirectShootingLoss, ParallelBeamGeometry, RayTransform
    from indreg.deform.kernel import GaussianKernel
    from indreg.learn import UnrolledDescent, train

    cfg = train.base_config(["model=unrolled"])
    dom = ImageDomain.paper(8)
    loss = IndirectShootingLoss(GeodesicShooting(dom, GaussianKernel(dom, 5.0), 2),
                                RayTransform(dom, ParallelBeamGeometry.paper(3, 12)), gamma=1e-3)
    model = UnrolledDescent(loss, num_updates=2, width=2, levels=1, heavy_ball=True)
    optimizer = torch.optim.Adam(train.parameter_groups(cfg, model), lr=1.0)
    rest, steps = optimizer.param_groups
    assert steps["params"] == [model.step_logits, model.inertia_logits]
    assert len(rest["params"]) == len(list(model.parameters())) - 2
    assert steps["scale"] * cfg.model.lr == pytest.approx(cfg.model.step_lr) and rest["scale"] == 1.0


def test_supervised_term_is_the_weighted_distance_to_the_target():
    """model.supervised: the unrolled phase of an UnrolledDescent adds w cell_volume sum (f - target)^2 to 2 E; the
    one-shot phase and w = 0 leave the loss as it is."""
    from indreg import GeodesicShooting, ImageDomain, IndirectShootingLoss, ParallelBeamGeometry, RayTransform
    from indreg.deform.kernel import GaussianKernel
    from indreg.learn import UnrolledDescent, descent_terms, train

    cfg = train.base_config(["model=unrolled"])
    dom = ImageDomain.paper(8)
    loss = IndirectShootingLoss(GeodesicShooting(dom, GaussianKernel(dom, 5.0), 2),
                                RayTransform(dom, ParallelBeamGeometry.paper(3, 12)), gamma=1e-3)
    model = UnrolledDescent(loss, num_updates=2, width=2, levels=1).double()
    gen = torch.Generator().manual_seed(0)
    batch = {k: torch.rand(2, 8, 8, generator=gen, dtype=torch.float64) for k in ("template", "fbp", "target")}
    batch["data"] = loss.transforms[0](torch.rand(2, 8, 8, generator=gen, dtype=torch.float64))
    parts = {"loss": loss, "domain": dom}
    terms = train.training_terms(cfg, model, model, parts, batch, unrolled=True)
    plain = descent_terms(loss, model(batch["template"], batch["fbp"], batch["data"]), batch["template"], batch["data"])
    distance = torch.stack([((f - t) ** 2).sum() * (4.0 ** 2) for f, t in zip(plain["deformed"], batch["target"])])
    torch.testing.assert_close(terms["supervised"], distance)          # 8 x 8 pixels of side 4 on [-16, 16]^2
    torch.testing.assert_close(terms["loss"], plain["loss"] + cfg.model.supervised * distance)
    cfg.model.supervised = 0.0
    assert "supervised" not in train.training_terms(cfg, model, model, parts, batch, unrolled=True)
    cfg.model.supervised = 30.0
    assert "supervised" not in train.training_terms(cfg, model, model, parts, batch, unrolled=False)
