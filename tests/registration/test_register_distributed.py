"""``indreg.register`` under ``torchrun --nproc_per_node=2`` (gloo): a 3D tilt series registered over two processes
gives every rank the same result, and the one process's to rounding."""
import os
import subprocess
import sys
import textwrap

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# 16^3 on [-16, 16]^3, velocity on 8^3, 13 tilts, N = 3, float64, slabs chosen automatically; each rank saves its
# result to <out>.<rank>
SCRIPT = textwrap.dedent("""
    import os, sys
    import torch
    import indreg
    from indreg import noise, phantoms

    dom = indreg.ImageDomain((16, 16, 16), (-16.0,) * 3, (16.0,) * 3)
    T = indreg.TiltSeriesTransform(dom, indreg.TiltSeriesGeometry.uniform(-60, 60, 10, det_count=16))
    template, target = phantoms.get("shepp_logan_3d", dom), phantoms.get("shepp_logan_3d_swirl", dom)
    data, _ = noise.add_white_noise(T(target), snr_db=10.0, seed=0, event_dims=3)
    r = indreg.register(template, data, T, sigma=4.0, num_steps=3, velocity_factor=2, max_iter=4, dtype=torch.float64,
                        target=target, progress=False)
    split = getattr(r.problem, "world", 1), getattr(r.problem, "slab_size", None)
    torch.save({"objective": r.objective, "history": [h["objective"] for h in r.history], "momentum": r.momentum,
                "deformed": r.deformed, "ssim": r.ssim, "status": r.status, "split": split},
               f"{sys.argv[1]}.{os.environ.get('RANK', '0')}")
    if torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
""")


def _run(tmp_path, name, ranks):
    script = tmp_path / "register_script.py"
    script.write_text(SCRIPT)
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}"] \
        if ranks > 1 else [sys.executable]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("WORLD_SIZE", None)
    proc = subprocess.run([*launcher, str(script), str(tmp_path / name)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return [torch.load(tmp_path / f"{name}.{r}") for r in range(ranks)]


@pytest.mark.slow
def test_register_over_two_ranks_equals_one_process(tmp_path):
    (one,) = _run(tmp_path, "one", 1)
    ranks = _run(tmp_path, "two", 2)
    assert [r["split"][0] for r in ranks] == [2, 2] and one["split"][0] == 1      # slab-wise over the two ranks
    for r in ranks[1:]:                                                            # every rank the same result
        assert r["history"] == ranks[0]["history"] and r["ssim"] == ranks[0]["ssim"]
        assert torch.equal(r["momentum"], ranks[0]["momentum"]) and torch.equal(r["deformed"], ranks[0]["deformed"])
    two = ranks[0]
    assert two["status"] == one["status"] and len(two["history"]) == len(one["history"]) == 4
    assert two["objective"] == pytest.approx(one["objective"], rel=1e-6)
    assert two["history"] == pytest.approx(one["history"], rel=1e-6)
    assert two["history"][-1] < 0.9 * two["history"][0]                          # it did register
    for name in ("momentum", "deformed"):
        torch.testing.assert_close(two[name], one[name], rtol=0, atol=1e-6 * float(one[name].abs().max()))
    assert two["ssim"] == pytest.approx(one["ssim"], abs=1e-6)
