"""``data=files``: the app on the user's own files (every format), without a target, limited angle, bad input."""
import json
import warnings

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import indreg
from indreg import phantoms
from indreg.experiments.config import ConfigError
from indreg.io import DataFileError

from experiment_helpers import compose, run_app, run_cli

N, DEG = 16, np.arange(-60.0, 61.0, 10.0)          # 16^2 template, 13 tilts over -60..60 degrees
QUICK = ["deformation.num_steps=3", "solver.max_iter=4", "logging.every=2", "logging.checkpoint_every=2",
         "logging.progress=false", "baseline=none", "logging.figure=false", "logging.tensorboard=false"]


def problem():
    """Template J, target V (16^2 on [-16, 16]^2) and the target's sinogram at DEG, 24 bins on [-24, 24]."""
    domain = indreg.ImageDomain.paper(N)
    template, target = phantoms.get("j", domain).numpy(), phantoms.get("v", domain).numpy()
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(det_count=24, det_min=-24.0, det_max=24.0,
                                                                angles=torch.from_numpy(np.deg2rad(DEG))))
    return template, target, T(torch.from_numpy(target)).numpy()


def files_args(template, sinogram, *extra):
    return ["data=files", f"data.template={template}", f"data.sinogram={sinogram}", "geometry=parallel",
            "geometry.det_min=-24", "geometry.det_max=24", *extra]


def write_format(fmt: str, d):
    """Template and sinogram written in ``fmt``; returns (args, template as indreg reads it, sinogram)."""
    template, target, sino = problem()
    tlt = d / "angles.tlt"
    tlt.write_text("".join(f"{a:g}\n" for a in DEG))
    angles = [f"geometry.angles={tlt}"]
    if fmt == "npy":
        np.save(d / "t.npy", template), np.save(d / "s.npy", sino)
        return files_args(d / "t.npy", d / "s.npy", *angles), template, sino
    if fmt == "npz":
        np.savez(d / "f.npz", template=template, sino=sino)
        inline = "geometry.angles=[" + ",".join(f"{a:g}" for a in DEG) + "]"
        return files_args(f"{d}/f.npz:template", f"{d}/f.npz:sino", inline), template, sino
    if fmt == "png":
        import imageio.v3 as iio
        grey = np.round(255 * template).astype(np.uint8)
        iio.imwrite(d / "t.png", np.rot90(grey))          # as displayed: upright; read as fractions of 255
        np.save(d / "s.npy", sino)
        return files_args(d / "t.png", d / "s.npy", *angles), grey / 255.0, sino
    if fmt == "tif":
        import tifffile
        tifffile.imwrite(d / "t.tif", np.rot90(template).astype(np.float32))
        tifffile.imwrite(d / "s.tif", sino.astype(np.float32))   # rows = angles, as displayed
        return (files_args(d / "t.tif", d / "s.tif", *angles), template.astype(np.float32),
                sino.astype(np.float32))
    if fmt == "h5":
        import h5py
        with h5py.File(d / "f.h5", "w") as f:
            f["template"], f["sino"] = template, sino
        rad = "geometry.angles=[" + ",".join(f"{a:.12g}" for a in np.deg2rad(DEG)) + "]"
        return (files_args(f"{d}/f.h5:/template", f"{d}/f.h5:/sino", rad, "geometry.angle_unit=rad"),
                template, sino)
    if fmt == "mrc":
        import mrcfile
        with mrcfile.new(d / "t.mrc") as m:
            m.set_data(template.astype(np.float32))
        with mrcfile.new(d / "s.mrc") as m:
            m.set_data(sino.astype(np.float32))
        (d / "s.tlt").write_text(tlt.read_text())       # the tilt series' sibling angle file
        return files_args(d / "t.mrc", d / "s.mrc"), template.astype(np.float32), sino.astype(np.float32)
    raise ValueError(fmt)


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["npy", "npz", "png", "tif", "h5", "mrc"])
def test_cli_reads_every_format(tmp_path, fmt):
    """``indreg-register data=files`` on tiny files of each format: the run sees exactly the written arrays."""
    args, template, sino = write_format(fmt, tmp_path)
    out = tmp_path / "run"
    proc = run_cli(args + QUICK + [f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    np.testing.assert_allclose(np.load(out / "template.npy"), template, rtol=1e-6)
    np.testing.assert_allclose(np.load(out / "data.npy"), sino, rtol=1e-6)
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "completed" and m["iterations"] == 4 and m["config"]["name"] == "own_data"
    assert m["objective"] < json.loads((out / "history.json").read_text())[0]["objective"]
    assert m["config"]["solver"]["step_halving"] is True          # data=files: step halving by default


def test_files_geometry_and_angles(tmp_path):
    args, _, _ = write_format("npy", tmp_path)
    cfg = compose(args)
    from indreg.experiments.build import build

    exp = build(cfg)
    assert exp.geometry.det_count == 24 and exp.domain.shape == (N, N)
    np.testing.assert_allclose(exp.geometry.angles.numpy(), np.deg2rad(DEG))
    assert exp.target_64 is None and exp.snr_db is None and exp.solver.step_halving


def test_files_convention_and_integer_scale(tmp_path):
    """``data.convention=skimage``: the picture and ``radon``'s (bins, angles) sinogram in pixel units as they come
    (skimage's centre: the domain shifted by half a pixel); ``data.integer_scale=raw`` keeps a PNG's 0..255."""
    import imageio.v3 as iio
    from skimage.transform import radon

    from indreg.experiments.build import build

    template, _, _ = problem()
    shown = np.rot90(template)
    np.save(tmp_path / "t.npy", shown)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # skimage: J reaches beyond the inscribed circle
        np.save(tmp_path / "s.npy", radon(shown, theta=DEG % 180, circle=True))
    tlt = tmp_path / "s.tlt"
    tlt.write_text("".join(f"{a:g}\n" for a in DEG % 180))
    exp = build(compose(["data=files", f"data.template={tmp_path / 't.npy'}", f"data.sinogram={tmp_path / 's.npy'}",
                         "geometry=parallel", f"geometry.angles={tlt}", "data.convention=skimage"]))
    assert exp.domain.min_pt == (-17.0, -15.0) and exp.geometry.det_count == N
    assert (exp.geometry.det_min, exp.geometry.det_max) == (-17.0, 15.0)
    np.testing.assert_array_equal(exp.template_64.numpy(), template)
    grey = np.round(255 * template).astype(np.uint8)
    iio.imwrite(tmp_path / "t.png", np.rot90(grey))
    args = files_args(tmp_path / "t.png", tmp_path / "s.npy", f"geometry.angles={tlt}", "data.convention=skimage")
    np.testing.assert_array_equal(build(compose(args + ["data.integer_scale=raw"])).template_64.numpy(), grey)
    np.testing.assert_allclose(build(compose(args)).template_64.numpy(), grey / 255.0, rtol=1e-15)


def test_no_target_writes_what_it_can(tmp_path):
    """Without a target: arrays, metrics (no SSIM / PSNR / SNR), figure without the target panel, TensorBoard."""
    args, _, _ = write_format("npy", tmp_path)
    out = tmp_path / "run"
    m = run_app(args + ["deformation.num_steps=3", "solver.max_iter=4", "logging.every=2",
                        "logging.progress=false", "baseline.tv_iterations=10"], out)
    for key in ("ssim", "psnr", "ssim_paper", "fbp_ssim", "template_ssim", "snr_db"):
        assert key not in m
    for key in ("objective", "data_fit", "residual", "min_jacobian", "warnings", "iterations"):
        assert np.isfinite(m[key]), key
    assert 0 < m["residual"] < 1
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["residual"] == m["residual"] and "ssim" not in saved
    for name in ("final", "trajectory", "velocity", "deformation", "momentum", "fbp", "tv", "data", "template"):
        assert (out / f"{name}.npy").is_file(), name
    assert not (out / "target.npy").exists() and not (out / "data_clean.npy").exists()
    assert (out / "figure.png").stat().st_size > 10_000
    ea = EventAccumulator(str(out / "tensorboard"), size_guidance={"images": 0, "scalars": 0})
    ea.Reload()
    assert "loss/objective" in ea.Tags()["scalars"] and "metrics/ssim" not in ea.Tags()["scalars"]
    assert "images/target" not in ea.Tags()["images"] and "images/fbp" in ea.Tags()["images"]


def test_limited_angle_example_preset(tmp_path):
    """The shipped example (61 tilts over -60..60 degrees, 64^2, grey levels 0..255): step halving finds a stable
    step at this intensity scale and the registration moves the template towards the ground truth."""
    m = run_app(["experiment=own_data_example", "solver.max_iter=30", "baseline=none", "logging.progress=false",
                 "logging.figure=false", "logging.tensorboard=false", "logging.every=10"], tmp_path / "run")
    assert m["config"]["name"] == "own_data_example" and m["config"]["data"]["source"] == "files"
    assert m["hparams"]["size"] == 64 and m["config"]["solver"]["step_halving"] is True
    assert m["ssim"] > m["template_ssim"] + 0.05 and m["min_jacobian"] > 0
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert m["warnings"] == sum(1 for h in history if h["warning"])
    assert history[-1]["step_size"] < 1e-4        # halved from 0.02: intensities are 255 times the paper's


def _bad(tmp_path, case):
    """Overrides for one bad input (the files of a good npy problem, one thing broken)."""
    args, template, sino = write_format("npy", tmp_path)
    d = tmp_path
    if case == "missing file":
        return files_args(d / "nope.npy", d / "s.npy", f"geometry.angles={d / 'angles.tlt'}"), "nope.npy"
    if case == "unreadable":
        (d / "junk.npy").write_bytes(b"this is not numpy")
        return files_args(d / "t.npy", d / "junk.npy", f"geometry.angles={d / 'angles.tlt'}"), "junk.npy"
    if case == "angle count":
        np.save(d / "s.npy", sino[:-1])
        return args, "12 rows"
    if case == "3D":
        np.save(d / "t.npy", np.stack([template] * 2))
        return args, "2D"
    if case == "nan":
        s = sino.copy()
        s[0, 0] = np.nan
        np.save(d / "s.npy", s)
        return args, "non-finite"
    if case == "not square":
        np.save(d / "t.npy", template[:, :12])
        return args, "not square"
    if case == "target shape":
        np.save(d / "g.npy", template[:8, :8])
        return args + [f"data.target={d / 'g.npy'}"], "data.target"
    if case == "junk angle line":
        (d / "angles.tlt").write_text("-60\n-50\nforty\n")
        return args, "line 3"
    if case == "no angles":
        return files_args(d / "t.npy", d / "s.npy"), "geometry.angles is required"
    if case == "no template":
        return ["data=files", f"data.sinogram={d / 's.npy'}", "geometry=parallel"], "data.template"
    raise ValueError(case)


CASES = ["missing file", "unreadable", "angle count", "3D", "nan", "not square", "target shape",
         "junk angle line", "no angles", "no template"]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_fails_before_any_work(tmp_path, case):
    args, needle = _bad(tmp_path, case)
    with pytest.raises((DataFileError, ConfigError), match=needle):
        run_app(args + QUICK, tmp_path / "run")
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").iterdir())


@pytest.mark.slow
@pytest.mark.parametrize("case", ["missing file", "angle count", "nan", "junk angle line"])
def test_cli_bad_input_one_line_exit_1(tmp_path, case):
    args, needle = _bad(tmp_path, case)
    out = tmp_path / "run"
    proc = run_cli(args + QUICK + [f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("indreg-register: error:") and needle in lines[0], proc.stderr
    if case == "missing file":   # refused before Hydra makes the run dir: nothing written
        assert not out.exists()
    else:                        # found while reading the data: the run dir holds the error in its log
        assert sorted(p.name for p in out.iterdir()) == [".hydra", "register.log"]
        assert needle in (out / "register.log").read_text()


@pytest.mark.slow
def test_progress_lines_without_terminal_and_multirun_job_prefix(tmp_path):
    """Piped output (no terminal): 'iteration i/total', it/s and ETA every logging.every; a multirun prefixes
    each job's lines with its job number."""
    args, _, _ = write_format("npy", tmp_path)
    proc = run_cli(["-m", "seed=0,1"] + args + QUICK + [f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for job in (0, 1):
        lines = [line for line in proc.stdout.splitlines() if line.startswith(f"[job {job}]")]
        assert any("iteration 2/4 (" in line and "it/s, ETA" in line for line in lines), proc.stdout[-3000:]
        assert any("done: 4 iterations" in line for line in lines)


def test_fan_beam_files(tmp_path):
    """``geometry=fan_flat``: the files' sinogram is read as fan-beam data (source 40, detector 40 from the
    origin, full turn) and the registration decreases the objective."""
    domain = indreg.ImageDomain.paper(N)
    template, target = phantoms.get("j", domain).numpy(), phantoms.get("v", domain).numpy()
    degrees = np.arange(0.0, 360.0, 30.0)
    geometry = indreg.forward.FanBeamGeometry(det_count=32, src_radius=40.0, det_radius=40.0,
                                              angles=torch.from_numpy(np.deg2rad(degrees)))
    sino = indreg.RayTransform(domain, geometry)(torch.from_numpy(target)).numpy()
    np.save(tmp_path / "t.npy", template), np.save(tmp_path / "s.npy", sino)
    angles = "geometry.angles=[" + ",".join(f"{a:g}" for a in degrees) + "]"
    args = ["data=files", f"data.template={tmp_path / 't.npy'}", f"data.sinogram={tmp_path / 's.npy'}",
            "geometry=fan_flat", "geometry.src_radius=40", "geometry.det_radius=40", angles]
    from indreg.experiments.build import build

    exp = build(compose(args))
    assert type(exp.geometry).__name__ == "FanBeamGeometry" and exp.geometry.det_count == 32
    np.testing.assert_allclose(exp.ray_transform(torch.from_numpy(target)).numpy(), sino)
    m = run_app(args + QUICK, tmp_path / "run")
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert m["status"] == "completed" and m["objective"] < history[0]["objective"]


def test_fan_beam_requires_src_radius(tmp_path):
    args, _, _ = write_format("npy", tmp_path)
    with pytest.raises(ConfigError, match="geometry.src_radius"):
        run_app([a if a != "geometry=parallel" else "geometry=fan_flat" for a in args] + QUICK, tmp_path / "run")


def test_files_run_resumes_like_an_uninterrupted_one(tmp_path):
    """A data=files run stopped after 2 iterations and resumed ends with the uninterrupted run's iterate."""
    args, _, _ = write_format("npy", tmp_path)
    f64 = args + QUICK + ["dtype=float64", "device=cpu"]
    whole = run_app(f64, tmp_path / "whole")
    assert run_app(f64 + ["stop_after=2"], tmp_path / "part")["status"] == "stopped"
    resumed = run_app(f64 + ["resume=true"], tmp_path / "part")
    assert resumed["iterations"] == whole["iterations"] == 4
    np.testing.assert_allclose(np.load(tmp_path / "part" / "final.npy"), np.load(tmp_path / "whole" / "final.npy"),
                               rtol=0, atol=1e-10)
