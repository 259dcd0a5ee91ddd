"""Multirun through the local joblib launcher, and the suite-3 table built from a multirun dir."""
import csv
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest

from indreg.experiments.sweep import SUITE3_GAMMAS, SUITE3_SIGMAS
from indreg.experiments.sweep import PAPER, collect, csv_text, main, markdown

from experiment_helpers import FAST, run_cli

def _fake_multirun(root: Path, cells):
    for k, (sigma, gamma) in enumerate(cells):
        d = root / str(k)
        d.mkdir(parents=True)
        (d / "metrics.json").write_text(json.dumps({
            "hparams": {"gamma": gamma, "sigma": sigma}, "iterations": 500, "ssim": 0.5 + sigma / 100,
            "psnr": 20.0 + gamma, "ssim_paper": 0.6 + sigma / 100, "psnr_paper": 21.0 + gamma}))


def test_table_layout_sigma_rows_gamma_columns(tmp_path):
    cells = [(s, g) for s in SUITE3_SIGMAS for g in SUITE3_GAMMAS]
    _fake_multirun(tmp_path, cells)
    records = collect(tmp_path)
    assert len(records) == 30
    lines = markdown(records).splitlines()
    assert lines[2] == "| sigma \\ gamma | 1e-07 | 1e-05 | 0.001 | 0.1 | 10 |"
    rows = [line for line in lines[4:] if line.startswith("|")]
    assert [r.split("|")[1].strip() for r in rows] == ["1", "2", "2.5", "3", "4", "8"]
    # sigma 2, gamma 1e-7: ours (paper convention) then the paper's value
    assert rows[1].split("|")[2].strip() == "0.6200 / 21.00 (0.9039 / 26.96)"
    assert "0.5200 / 20.00" in markdown(records, "range")
    table = list(csv.DictReader(io.StringIO(csv_text(records))))
    assert len(table) == 30
    row = next(r for r in table if float(r["sigma"]) == 8.0 and float(r["gamma"]) == 10.0)
    assert (float(row["paper_ssim"]), float(row["paper_psnr"])) == PAPER[8.0][10.0] == (0.7960, 21.27)


def test_sweep_table_main_and_missing_dir(tmp_path, capsys):
    _fake_multirun(tmp_path / "mr", [(2.0, 1e-7), (2.0, 1e-5)])
    main([str(tmp_path / "mr")])
    assert "(0.9039 / 26.96)" in capsys.readouterr().out
    assert (tmp_path / "mr" / "table.md").read_text().count("(0.9039 / 26.96)") == 2
    assert len((tmp_path / "mr" / "table.csv").read_text().splitlines()) == 3
    with pytest.raises(FileNotFoundError, match="no metrics.json"):
        collect(tmp_path / "empty")


@pytest.mark.slow
def test_two_job_multirun_with_joblib_launcher(tmp_path):
    sweep_dir = tmp_path / "multirun"
    tiny = [o for o in FAST if not o.startswith("logging.tensorboard")]
    proc = run_cli(["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep_dir}",
                    "solver.gamma=1e-7,1e-5", "kernel.sigma=2"] + tiny, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    records = collect(sweep_dir)
    assert sorted(r["gamma"] for r in records) == [1e-7, 1e-5]
    assert all(r["sigma"] == 2.0 and r["iterations"] == 10 for r in records)
    for job in ("0", "1"):
        assert list((sweep_dir / job / "tensorboard").glob("events.out.tfevents.*"))
    proc = subprocess.run([sys.executable, "-m", "indreg.experiments.sweep", str(sweep_dir)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "| 2 |" in (sweep_dir / "table.md").read_text()
