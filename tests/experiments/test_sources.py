"""The app's data sources: ``data=files`` is ``indreg.load`` with the config's values (2D and tilt series); a
user's source as ``module:function`` or an ``indreg.sources`` entry point runs through the app; a bad source is one
``ConfigError`` line; ``sources`` does not import ``config`` (no import cycle)."""
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

import indreg
from indreg.experiments import sources
from indreg.experiments.config import DATA_DIR, ConfigError, validate

from experiment_helpers import FAST, compose, run_app, run_cli, write_tilt_series_files


def same(loaded, data):
    """``indreg.load``'s record and the app's ``Data`` hold the same arrays and operator."""
    assert loaded.domain == data.domain and loaded.label == data.label
    for a, b in ((loaded.template, data.template_64), (loaded.data, data.data_64), (loaded.target, data.target_64)):
        assert (a is None and b is None) or torch.equal(a, b)
    x = torch.rand(loaded.domain.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(loaded.operator(x), data.operator(x), rtol=0, atol=0)
    assert torch.equal(loaded.geometry.angles, data.geometry.angles)


def test_load_is_the_files_source_of_the_shipped_example():
    data = sources.load(compose(["experiment=own_data_example"]))
    loaded = indreg.load(DATA_DIR / "own_data_template.png", DATA_DIR / "own_data_sinogram.npy",
                         angles=DATA_DIR / "own_data_angles.tlt", det_min=-24.0, det_max=24.0,
                         target=DATA_DIR / "own_data_target.npy", integer_scale="raw")
    same(loaded, data)
    assert data.template_64.shape == (64, 64) and data.data_64.shape == (61, 92) and data.snr_db is None


def test_load_is_the_files_source_of_a_tilt_series(tmp_path):
    write_tilt_series_files(tmp_path)
    data = sources.load(compose(["data=files", f"data.template={tmp_path / 'template.mrc'}",
                                 f"data.sinogram={tmp_path / 'tilts.mrc'}", "data.half_width=8",
                                 "geometry=tilt_series"]))
    same(indreg.load(tmp_path / "template.mrc", tmp_path / "tilts.mrc", "tilt_series", half_width=8), data)
    assert data.operator.range_shape == (7, 16, 16)


def test_files_source_names_the_config_keys(tmp_path):
    np.save(tmp_path / "t.npy", np.zeros((16, 12)))
    with pytest.raises(indreg.io.DataFileError, match=r"^data\.template .*t\.npy: shape 16 x 12 is not square"):
        sources.load(compose(["data=files", f"data.template={tmp_path / 't.npy'}", "data.sinogram=s.npy"]))
    np.save(tmp_path / "t.npy", np.zeros((16, 16))), np.save(tmp_path / "s.npy", np.zeros((3, 24)))
    with pytest.raises(ConfigError, match=r"^geometry\.angles must be a list of numbers"):
        sources.load(compose(["data=files", f"data.template={tmp_path / 't.npy'}",
                              f"data.sinogram={tmp_path / 's.npy'}", "geometry=parallel", "geometry.angles=[a,b]"]))


USER_MODULE = '''
    """A user's data source: one .npz bundle with the template, the sinogram and the angles (radians)."""
    import numpy as np

    import indreg


    def bundle(cfg):
        with np.load(cfg.data.sinogram) as f:
            return indreg.load(f["template"], f["sinogram"], angles=f["angles"], angle_unit="rad",
                               det_min=cfg.geometry.det_min, det_max=cfg.geometry.det_max)


    def not_data(cfg):
        return 42
'''


@pytest.fixture
def user_source(tmp_path, monkeypatch):
    """A module ``user_source_bundle`` on sys.path, its ``bundle.npz`` and the overrides that name the file."""
    (tmp_path / "user_source_bundle.py").write_text(textwrap.dedent(USER_MODULE))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "user_source_bundle", raising=False)
    domain, angles = indreg.ImageDomain.paper(16), np.deg2rad(np.arange(-60.0, 61.0, 10.0))
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(det_count=24, det_min=-24.0, det_max=24.0,
                                                                angles=torch.from_numpy(angles)))
    template, data = indreg.phantoms.get("j", domain), T(indreg.phantoms.get("v", domain))
    np.savez(tmp_path / "bundle.npz", template=template.numpy(), sinogram=data.numpy(), angles=angles)
    yield template, data, [f"data.sinogram={tmp_path / 'bundle.npz'}", "geometry=parallel",
                           "geometry.det_min=-24", "geometry.det_max=24"]
    sys.modules.pop("user_source_bundle", None)


def test_module_function_source_runs_through_the_app(tmp_path, user_source):
    template, data, args = user_source
    m = run_app(["data=files", "data.source=user_source_bundle:bundle", *args, *FAST], tmp_path / "run")
    assert m["status"] == "completed" and m["hparams"]["template"] == "array" and "ssim" not in m
    assert m["config"]["data"]["source"] == "user_source_bundle:bundle" and m["config"]["solver"]["step_halving"]
    np.testing.assert_array_equal(np.load(tmp_path / "run" / "template.npy"), template.numpy())
    np.testing.assert_array_equal(np.load(tmp_path / "run" / "data.npy"), data.numpy())
    assert m["objective"] < json.loads((tmp_path / "run" / "history.json").read_text())[0]["objective"]


@pytest.mark.slow
def test_module_function_source_from_the_cli(tmp_path, user_source):
    """``indreg-register data.source=module:function`` with the module on PYTHONPATH; an unimportable one is one
    line, exit status 1, nothing written."""
    path = os.pathsep.join(p for p in (str(tmp_path), os.environ.get("PYTHONPATH")) if p)
    quick = ["deformation.num_steps=3", "solver.max_iter=3", "baseline=none", "logging.figure=false",
             "logging.progress=false", "logging.tensorboard=false"]
    proc = run_cli(["data=files", "data.source=user_source_bundle:bundle", *user_source[2], *quick,
                    f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path, env={"PYTHONPATH": path})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["iterations"] == 3
    proc = run_cli(["data.source=user_source_bundl:bundle", f"hydra.run.dir={tmp_path / 'bad'}"], cwd=tmp_path,
                   env={"PYTHONPATH": path})
    assert proc.returncode == 1 and not (tmp_path / "bad").exists()
    assert proc.stderr.strip().splitlines() == ["indreg-register: error: invalid config value data.source="
                                                "'user_source_bundl:bundle': cannot import it (ModuleNotFoundError: "
                                                "No module named 'user_source_bundl')"]


def test_entry_point_source(tmp_path, user_source):
    """An installed package's entry point ``bundle = user_source_bundle:bundle`` of the group indreg.sources."""
    _, data, args = user_source
    info = tmp_path / "user_sources-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: user-sources\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[indreg.sources]\nbundle = user_source_bundle:bundle\n")
    cfg = compose(["data.source=bundle", *args])
    validate(cfg)
    assert torch.equal(sources.load(cfg).data_64, data.double())
    with pytest.raises(ConfigError, match=r"data\.source='nope': expected one of dynamic, files, phantom, bundle or"):
        validate(compose(["data.source=nope"]))


@pytest.mark.parametrize("name,match", [
    ("nope", r"^invalid config value data\.source='nope': expected one of dynamic, files, phantom or an importable "
             r"module:function"),
    ("no_such_module_x:fn", r"data\.source='no_such_module_x:fn': cannot import it \(ModuleNotFoundError: No "
                            r"module named 'no_such_module_x'\)"),
    ("user_source_bundle:nope", r"cannot import it \(AttributeError: .*'nope'"),
    ("math:pi", r"float is not callable"),
])
def test_bad_source_is_one_config_error_line(tmp_path, user_source, name, match):
    with pytest.raises(ConfigError, match=match) as info:
        run_app([f"data.source={name}", *user_source[2], *FAST], tmp_path / "run")
    assert "\n" not in str(info.value) and not (tmp_path / "run").exists()


def test_source_returning_something_else(tmp_path, user_source):
    with pytest.raises(ConfigError, match=r"data\.source=user_source_bundle:not_data returned a int"):
        run_app(["data.source=user_source_bundle:not_data", *user_source[2], *FAST], tmp_path / "run")


def test_sources_does_not_import_config():
    """``config`` imports ``sources`` (to resolve ``data.source``), never the other way round; the built-in
    sources register themselves on import."""
    code = ("import sys, indreg.experiments.builtin_sources, indreg.experiments.sources as s; s.resolve('files'); "
            "assert 'indreg.experiments.config' not in sys.modules, 'sources imported config'; "
            "from indreg.experiments.config import ConfigError; assert ConfigError is s.ConfigError")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
