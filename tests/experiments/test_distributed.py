"""One registration across two processes (torchrun, gloo): the same iterates as one process, written once, resumed
with another number of ranks; a run that cannot be split is refused in one line."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# 16^3, velocity on 8^3, 7 tilts, N = 3, slab-wise (4 slices a slab), no baselines or figures
RUN = ["experiment=suite_et_3d", "phantom.size=16", "geometry.det_count=16", "geometry.tilt_step=20",
       "deformation.num_steps=3", "deformation.velocity_factor=2", "deformation.slab_size=4", "baseline=none",
       "logging.every=1", "logging.checkpoint_every=1", "logging.progress=false", "logging.figure=false",
       "logging.tensorboard=false", "dtype=float64", "device=cpu"]


def _run(out, *overrides, ranks=1):
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}"] \
        if ranks > 1 else [sys.executable]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [*launcher, "-m", "indreg.experiments.register", *RUN, *overrides, f"hydra.run.dir={out}"]
    return subprocess.run(cmd, cwd=out.parent, env=env, capture_output=True, text=True, timeout=300)


def _ok(proc):
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]


def _same(a, b, names=("momentum",)):
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert mb["iterations"] == ma["iterations"] and mb["objective"] == pytest.approx(ma["objective"], rel=1e-6)
    ha, hb = (json.loads((d / "history.json").read_text()) for d in (a, b))
    np.testing.assert_allclose([h["objective"] for h in hb], [h["objective"] for h in ha], rtol=1e-6)
    for name in names:
        x, y = np.load(a / f"{name}.npy"), np.load(b / f"{name}.npy")
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-6 * np.abs(x).max())


@pytest.mark.slow   # 135 s at load 15-20: the app in one process and over two (torchrun)
def test_two_ranks_equal_one_process(tmp_path):
    _ok(_run(tmp_path / "one", "solver.max_iter=3"))
    proc = _run(tmp_path / "two", "solver.max_iter=3", ranks=2)
    _ok(proc)
    # the data built by rows over the ranks (each its share of the slices) are one process's
    # and the trajectory's frames gathered from the ranks' slabs
    _same(tmp_path / "one", tmp_path / "two", ("momentum", "final", "template", "target", "data", "data_clean",
                                               "trajectory"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one", "two"]     # rank 1 wrote nowhere else
    assert "rank=0/2" in proc.stderr + proc.stdout and "slabs=4" in proc.stderr + proc.stdout


@pytest.mark.slow   # 144 s at load 15-20: two app runs, two processes each
def test_two_ranks_split_the_baselines(tmp_path):
    """FBP, SIRT and TV over two ranks (each its rows, TV with a halo) equal the one process's (FBP and SIRT slab by
    slab: its registration is slab-wise), written once, with the same figures of merit."""
    baseline = ("baseline=fbp_tv", "baseline.tv_iterations=20", "baseline.sirt_iterations=10", "solver.max_iter=1")
    _ok(_run(tmp_path / "one", *baseline))
    proc = _run(tmp_path / "two", *baseline, ranks=2)
    _ok(proc)
    assert "over 2 ranks" in proc.stderr + proc.stdout
    with np.load(tmp_path / "one" / "baselines.npz") as a, np.load(tmp_path / "two" / "baselines.npz") as b:
        assert sorted(b.files) == ["fbp", "key", "sirt", "tv"]
        for name in ("fbp", "sirt", "tv"):
            np.testing.assert_allclose(b[name], a[name], rtol=0, atol=1e-9 * np.abs(a[name]).max())
    ma, mb = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("one", "two"))
    for name in ("fbp_ssim", "sirt_ssim", "tv_ssim"):
        assert mb[name] == pytest.approx(ma[name], rel=1e-9)


@pytest.mark.slow
def test_resume_with_another_number_of_ranks(tmp_path):
    _ok(_run(tmp_path / "one", "solver.max_iter=4"))
    _ok(_run(tmp_path / "two", "solver.max_iter=2", ranks=2))                  # two ranks, 2 iterations
    _ok(_run(tmp_path / "two", "solver.max_iter=4", "resume=true"))           # resumed in one process
    _ok(_run(tmp_path / "three", "solver.max_iter=2"))                         # one process, then two ranks
    _ok(_run(tmp_path / "three", "solver.max_iter=4", "resume=true", ranks=2))
    _same(tmp_path / "one", tmp_path / "two")
    _same(tmp_path / "one", tmp_path / "three")


@pytest.mark.slow
def test_two_ranks_refuse_a_registration_that_does_not_split(tmp_path):
    proc = _run(tmp_path / "run", "solver.max_iter=1", "deformation.velocity_factor=1", "deformation.slab_size=null",
                ranks=2)
    assert proc.returncode != 0
    assert "distributed=True: expected False (one process) here: the registration does not split into slabs" \
        in proc.stderr and "no coarse velocity grid" in proc.stderr
