"""docs/extending.md: its Python blocks, run in order as one module, add an operator, a model, a data source, a
solver, a correction and a file format that work through ``indreg.register`` / ``indreg.load`` and through the app
without any change to indreg, each by one registration at most."""
import importlib
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import indreg
import indreg.registration.run  # noqa: F401 (the module, for indreg.registration.run.setup)

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """The guide's code as an importable module ``toy_extending`` (as a user's own module would be)."""
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert len(blocks) >= 5
    folder = tmp_path_factory.mktemp("toy")
    (folder / "toy_extending.py").write_text("\n".join(blocks))
    sys.path.insert(0, str(folder))
    try:
        yield importlib.import_module("toy_extending")
    finally:
        sys.path.remove(str(folder))
        sys.modules.pop("toy_extending", None)
        indreg.registration.models.MODELS.pop("brightness", None)
        indreg.options.SOLVERS.pop("heavy_ball", None)
        indreg.options.CORRECTIONS.pop("data_offset", None)
        indreg.io.formats.FILE_FORMATS.pop("grid", None)


def test_toy_operator_is_adjoint_and_registers(toy):
    assert toy.T.adjointness_test() < 1e-10
    assert toy.blurred.status == "completed" and toy.blurred.ssim > 0.6


def test_toy_model_recovers_a_brightness_and_runs_with_every_solver(toy):
    assert float(toy.result.brightness) > 1.2          # the data are 1.5 x the target's
    args = (toy.template, toy.R(1.5 * toy.target), toy.R)
    for options in ({"solver": "lbfgs"}, {"solver": "algorithm1", "step_halving": True}):
        r = indreg.register(*args, model="brightness", num_steps=4, max_iter=4, **options)
        assert r.history[-1]["objective"] < r.history[0]["objective"]
        assert r.outputs["brightness"].shape == (1,)


def test_toy_model_gradient_is_the_directional_derivative(toy):
    """``h`` of the guide's model against central differences of E (float64)."""
    dom = indreg.ImageDomain.paper(16)
    R = indreg.RayTransform(dom, indreg.ParallelBeamGeometry.paper(6, 24))
    I = indreg.phantoms.get("j", dom).double()
    K = indreg.GaussianKernel(dom, 6.0)
    W = indreg.LDDMMDeformation(dom, 3, backward="exact")
    p = toy.BrightnessLDDMM(R, W, K, I, R(1.3 * indreg.phantoms.get("v", dom).double()), 1e-3)
    g = torch.Generator().manual_seed(0)
    x = (0.3 * torch.randn(p.momentum_shape, dtype=torch.float64, generator=g), torch.tensor([0.1], dtype=torch.float64))
    d = (0.3 * torch.randn(p.momentum_shape, dtype=torch.float64, generator=g), torch.tensor([0.2], dtype=torch.float64))
    _, h, _ = p.gradient(x)
    eps = 1e-5
    e = [p.evaluate_iterate(tuple(a + s * eps * b for a, b in zip(x, d)))["objective"] for s in (1, -1)]
    fd = (e[0] - e[1]) / (2 * eps)
    # dE/dm = time_weight K h_0 (h_0: the L2 gradient in nu = K m); h_1 = s dE/da, s = N / cell_volume
    s = p.num_steps / dom.cell_volume
    pairing = p.time_weight * float((p.velocity(h[0]) * d[0]).sum()) + float((h[1] * d[1]).sum()) / s
    assert pairing == pytest.approx(fd, rel=1e-6)


@pytest.mark.slow
def test_toy_source_and_model_run_through_the_app(toy, tmp_path):
    from experiments.experiment_helpers import run_app

    m = run_app(["data.source=toy_extending:blurred_phantoms", "phantom.size=32", "geometry.det_count=46",
                 "deformation.model=toy_extending:BRIGHTNESS", "deformation.num_steps=4", "solver.max_iter=4",
                 "baseline.enabled=false", "logging.tensorboard=false", "logging.progress=false"], tmp_path)
    assert m["status"] == "completed" and m["hparams"]["model"] == "brightness"   # the plug-in by its own name
    assert (tmp_path / "brightness.npy").is_file() and (tmp_path / "figure.png").is_file()


def test_toy_solver_runs_with_its_own_options(toy):
    """The guide's heavy ball descends; its option reaches the optimizer; given to another solver it is refused."""
    assert toy.ball.status == "completed" and toy.ball.history[-1]["objective"] < toy.ball.history[0]["objective"]
    args = (toy.template, toy.T(toy.target), toy.T)
    r = indreg.register(*args, solver="heavy_ball", ball_momentum=0.25, num_steps=4, max_iter=2)
    assert r.history[-1]["step_size"] == 2e-5   # the option's default reached the solver
    with pytest.raises(TypeError, match="ball_momentum must be left unset: it is an option of solver='heavy_ball'"):
        indreg.register(*args, ball_momentum=0.25, max_iter=1)
    with pytest.raises(ValueError, match="ball_momentum must be a finite number >= 0"):
        indreg.register(*args, solver="heavy_ball", ball_momentum=-1.0, max_iter=1)


@pytest.mark.slow
def test_toy_solver_runs_through_the_app(toy, tmp_path):
    from experiments.experiment_helpers import run_app

    from indreg.experiments.config import register_schema

    register_schema(["solver.name=toy_extending:HEAVY_BALL"])   # what the app does with its command line
    m = run_app(["solver.name=toy_extending:HEAVY_BALL", "solver.ball_momentum=0.25", "phantom.size=16",
                 "deformation.num_steps=3", "solver.max_iter=2", "baseline.enabled=false", "logging.tensorboard=false",
                 "logging.progress=false", "logging.figure=false"], tmp_path)
    assert m["status"] == "completed" and m["hparams"]["solver"] == "heavy_ball"


def test_toy_correction_finds_the_offset_and_resumes(toy):
    """The guide's data offset: found from Python (summary, history), off by default, refused when negative, and
    its checkpoint state restored."""
    summary = toy.shifted.corrections["data_offset"]
    assert summary["offset"] == pytest.approx(0.5, rel=1e-3) and summary["every"] == 5
    assert "data_offset" in toy.shifted.history[0]
    args = (toy.template, toy.T(toy.target), toy.T)
    assert "data_offset" not in indreg.register(*args, num_steps=3, max_iter=1).corrections
    with pytest.raises(ValueError, match="offset_every must be an integer >= 0"):
        indreg.register(*args, offset_every=-1, max_iter=1)
    s = indreg.registration.run.setup(*args, offset_every=2, num_steps=3, max_iter=4)
    state = indreg.registration.run.initial_state(s.problem)
    s.solver.step(state)
    saved = s.solver.state_dict()
    again = indreg.registration.run.setup(*args, offset_every=2, num_steps=3, max_iter=4)
    again.solver.load_state_dict(saved)
    assert again.solver.offset == s.solver.offset and torch.equal(again.problem.data, s.problem.data)


@pytest.mark.slow
def test_toy_correction_runs_through_the_app(toy, tmp_path):
    from experiments.experiment_helpers import run_app

    from indreg.experiments.config import register_schema

    register_schema(["plugins=[toy_extending]"])   # what the app does with its command line
    m = run_app(["plugins=[toy_extending]", "data.offset_every=2", "phantom.size=16", "deformation.num_steps=3",
                 "solver.max_iter=4", "baseline.enabled=false", "logging.tensorboard=false", "logging.progress=false",
                 "logging.figure=false"], tmp_path)
    assert m["status"] == "completed" and m["data_offset"]["every"] == 2


def test_each_extension_is_one_module_and_at_most_one_registration():
    """Every numbered section's code (the user's one module) calls at most one ``register_*`` of indreg."""
    sections = re.split(r"^## (?=\d+\. )", DOC.read_text(), flags=re.M)[1:]
    assert len(sections) == 7
    for text in sections:
        code = "".join(re.findall(r"```python\n(.*?)```", text, re.S))
        calls = re.findall(r"\bregister_(?:model|solver|correction|source|format)\(", code)
        assert len(calls) <= 1, (text.splitlines()[0], calls)


def test_toy_format_reads_and_writes_through_the_readers(toy, tmp_path):
    """The guide's ``.grid``: ``indreg.load`` gave back the arrays, the readers and writers take it (a volume, a
    stack, a sinogram), its leading bytes are checked, a key refused, and the messages that list suffixes list it."""
    assert torch.equal(toy.loaded.template, toy.template) and torch.allclose(toy.loaded.data, toy.R(toy.target))
    rng = np.random.default_rng(0)
    volume = rng.standard_normal((4, 5, 3))
    indreg.io.write_volume(tmp_path / "v.GRID", volume)                     # suffixes are matched in any case
    np.testing.assert_array_equal(indreg.io.read_volume(tmp_path / "v.GRID"), volume)
    np.testing.assert_array_equal(indreg.io.read_stack(tmp_path / "v.GRID"), volume)
    sino = rng.standard_normal((6, 8))
    indreg.io.write_image(tmp_path / "s.grid", sino)
    np.testing.assert_array_equal(indreg.io.read_sinogram(tmp_path / "s.grid"), sino)
    (tmp_path / "bad.grid").write_text("1 2 3\n")
    with pytest.raises(indreg.io.DataFileError, match=r"bad\.grid: unreadable as \.grid \(not a \.grid file: wrong "):
        indreg.io.read_image(tmp_path / "bad.grid")
    with pytest.raises(indreg.io.DataFileError, match=r"s\.grid:k: a ':KEY' suffix is only for \.npz, \.h5"):
        indreg.io.read_image(f"{tmp_path / 's.grid'}:k")
    with pytest.raises(indreg.io.DataFileError, match=r"unknown format '\.xyz'; supported: \.npy, .*\.tiff, \.grid$"):
        indreg.io.read_image(tmp_path / "a.xyz")
    with pytest.raises(indreg.io.DataFileError, match=r"cannot write format '\.png'; use \.npy, .*\.grid$"):
        indreg.io.write_image(tmp_path / "a.png", sino)


@pytest.mark.slow
def test_toy_format_through_the_app(toy, tmp_path):
    """``indreg-register data=files`` with ``.grid`` files: refused before the run in one line listing the registered
    suffixes, and run with ``plugins=[module]`` naming the module that registers the format (the guide's block)."""
    from experiments.experiment_helpers import run_cli

    block = next(b for b in re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S) if "register_format(" in b)
    (tmp_path / "grid_format.py").write_text(block)
    indreg.io.write_image(tmp_path / "t.grid", toy.template)
    indreg.io.write_image(tmp_path / "s.grid", toy.R(toy.target))
    (tmp_path / "a.tlt").write_text("".join(f"{a:.10g}\n" for a in np.rad2deg(toy.R.geometry.angles.numpy())))
    args = ["data=files", f"data.template={tmp_path / 't.grid'}", f"data.sinogram={tmp_path / 's.grid'}",
            "geometry=parallel", f"geometry.angles={tmp_path / 'a.tlt'}", "geometry.det_min=-24", "geometry.det_max=24",
            "deformation.num_steps=3", "solver.max_iter=2", "baseline=none", "logging.progress=false",
            "logging.figure=false", "logging.tensorboard=false", f"hydra.run.dir={tmp_path / 'run'}"]
    refused = run_cli(args, cwd=tmp_path)
    assert refused.returncode == 1 and not (tmp_path / "run").exists(), refused.stderr[-2000:]
    assert refused.stderr.strip().endswith("unknown format '.grid'; supported: .npy, .npz, .h5, .hdf5, .hspy, .mrc, "
                                           ".st, .ali, .png, .tif, .tiff"), refused.stderr
    ran = run_cli(args + ["plugins=[grid_format]"], cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr[-3000:]
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["status"] == "completed" and m["iterations"] == 2
    np.testing.assert_allclose(np.load(tmp_path / "run" / "data.npy"), toy.R(toy.target).numpy(), rtol=1e-12)
