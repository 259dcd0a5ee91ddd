"""A deformation model from outside indreg with options of its own: from ``indreg.register`` and from the command
line (``deformation.model=module:attribute deformation.<option>=...``), the module in the working directory."""
import json
import sys
import textwrap

import pytest
import torch

import indreg
from indreg import phantoms

from experiment_helpers import run_cli

PLUGIN = textwrap.dedent('''
    """A plug-in model: LDDMM of the template times ``brightness``, with ``extra_steps`` more time steps."""
    import indreg
    from indreg.registration.models import Model, Option, number

    class Scaled(indreg.IndirectRegistration):
        def __init__(self, *args, brightness, extra_steps, **kwargs):
            super().__init__(*args, **kwargs)
            self.brightness, self.extra_steps = brightness, extra_steps

        def hparams(self):
            return {"brightness": self.brightness, "extra_steps": self.extra_steps}

    def build(operator, template, data, kernel, o):
        W = indreg.LDDMMDeformation(kernel.domain, o["num_steps"] + o["extra_steps"], o["action"],
                                    o["backward"] or "paper", o["interpolation"] or "reinterpolate")
        return Scaled(operator, W, kernel, o["brightness"] * template, data, o["gamma"],
                      brightness=o["brightness"], extra_steps=o["extra_steps"]), {}

    MODEL = Model("scaled", build, doc="LDDMM of a brighter template", options=(
        Option("brightness", "deformation", "brightness", 1.0, number(0.0, strict=True), "template factor", float,
               models=("scaled",)),
        Option("extra_steps", "deformation", "extra_steps", 0, number(0, integer=True), "more time steps", int,
               models=("scaled",)),
    ))
''')


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """The plug-in's folder on the path; its model unregistered afterwards (other tests see the core table)."""
    (tmp_path / "my_plugin.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    before = set(indreg.options.MODELS)
    yield tmp_path
    for name in set(indreg.options.MODELS) - before:
        indreg.options.MODELS.pop(name)
    sys.modules.pop("my_plugin", None)


def _tiny_suite1():
    """Suite 1 at 16^2 with 6 angles x 24 bins: the domain, the ray transform and the template J."""
    domain = indreg.ImageDomain.paper(16)
    return domain, indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(6, 24)), phantoms.get("j", domain)


#: The app at 16^2, 3 time steps, nothing drawn or compared: what every command-line run of a plug-in adds.
TINY_APP = ["phantom.size=16", "deformation.num_steps=3", "baseline.enabled=false", "logging.figure=false",
            "logging.tensorboard=false", "device=cpu"]


def _run_tiny_app(plugin_args: list, cwd, max_iter: int = 2) -> tuple:
    """``(args, metrics)``: the app run in ``cwd`` with ``plugin_args`` first (the plug-in, then its option), then
    :data:`TINY_APP`; ``args`` the whole command line, for the runs that change one of them."""
    out = cwd / "run"
    args = [*plugin_args, f"solver.max_iter={max_iter}", *TINY_APP, f"hydra.run.dir={out}"]
    p = run_cli(args, cwd=cwd)   # the module is found in the working directory, as with python -m
    assert p.returncode == 0, p.stderr[-2000:]
    return args, json.loads((out / "metrics.json").read_text())


def _refused_in_one_line(args: list, cwd, key: str) -> None:
    p = run_cli(args, cwd=cwd)
    assert p.returncode == 1 and key in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_plugin_model_options_from_python(plugin):
    domain, T, template = _tiny_suite1()
    r = indreg.register(template, T(phantoms.get("v", domain)), T, model="my_plugin:MODEL", brightness=2.0,
                        extra_steps=1, num_steps=3, max_iter=2)
    assert r.problem.hparams() == {"brightness": 2.0, "extra_steps": 1} and r.problem.num_steps == 4
    torch.testing.assert_close(r.problem.template, 2.0 * template)
    with pytest.raises(TypeError, match="brightness"):   # an option of the plug-in, given to another model
        indreg.register(template, T(template), T, brightness=2.0, max_iter=1)


def test_plugin_model_options_from_the_command_line(plugin):
    args, m = _run_tiny_app(["deformation.model=my_plugin:MODEL", "deformation.brightness=3",
                             "deformation.extra_steps=2"], plugin)
    assert m["hparams"]["brightness"] == 3.0 and m["hparams"]["extra_steps"] == 2 and m["status"] == "completed"
    assert m["config"]["name"] == "suite1_jv-MODEL"   # not filed as suite 1's run
    _refused_in_one_line(args[:1] + ["deformation.brightness=-1"] + args[2:], plugin, "deformation.brightness")


def test_plugin_that_fails_to_import_is_one_line_and_not_registered(tmp_path, monkeypatch):
    (tmp_path / "broken_plugin.py").write_text("import indreg\nraise RuntimeError('boom at import')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ValueError, match="cannot be imported: RuntimeError: boom at import"):
        indreg.options.model("broken_plugin:MODEL")
    assert "broken_plugin:MODEL" not in indreg.options.MODELS


@pytest.mark.slow
def test_plugin_whose_build_raises_is_one_line_naming_the_model(tmp_path, monkeypatch):
    """A plug-in's build that raises (a KeyError here) is one ValueError naming the model and the error, the original
    chained; from the command line one line, no traceback; a syntax error's line is not repeated."""
    (tmp_path / "raising_plugin.py").write_text(textwrap.dedent('''
        from indreg.registration.models import Model

        def build(operator, template, data, kernel, o):
            raise KeyError("no such option")

        MODEL = Model("raising", build)
    '''))
    (tmp_path / "syntax_plugin.py").write_text("def build(:\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    domain, T, template = _tiny_suite1()
    with pytest.raises(ValueError, match=r"^model 'raising': build raised KeyError: 'no such option'$") as e:
        indreg.register(template, T(template), T, model="raising_plugin:MODEL", max_iter=1)
    assert isinstance(e.value.__cause__, KeyError)
    args = ["phantom.size=16", "solver.max_iter=1", "baseline.enabled=false", "logging.figure=false",
            "logging.tensorboard=false", "device=cpu", f"hydra.run.dir={tmp_path / 'run'}"]
    p = run_cli(["deformation.model=raising_plugin:MODEL", *args], cwd=tmp_path)
    assert p.returncode == 1 and p.stderr.strip().splitlines() == [
        "indreg-register: error: invalid configuration: model 'raising': build raised KeyError: 'no such option'"]
    p = run_cli(["deformation.model=syntax_plugin:MODEL", *args], cwd=tmp_path)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1
    assert p.stderr.count("cannot be imported: SyntaxError") == 1


SOURCE = textwrap.dedent('''
    """A plug-in data source with a key of its own: the paper's phantoms, template and data times ``my_gain``."""
    import dataclasses

    from indreg.experiments.builtin_sources import phantom_data
    from indreg.experiments.sources import Source

    def load(cfg):
        d = phantom_data(cfg)
        g = cfg.data.my_gain
        return dataclasses.replace(d, template_64=g * d.template_64, data_64=g * d.data_64, label=f"gain{g:g}")

    SOURCE = Source("gained", load, options=(("my_gain", float, 1.0),),
                    check=lambda c, require: require(c.data.my_gain > 0, "data.my_gain", "a number > 0",
                                                     c.data.my_gain))
''')


@pytest.mark.slow
def test_plugin_source_with_a_key_of_its_own_from_the_command_line(tmp_path):
    (tmp_path / "my_source.py").write_text(SOURCE)
    args, m = _run_tiny_app(["data.source=my_source:SOURCE", "data.my_gain=2"], tmp_path)
    assert m["hparams"]["template"] == "gain2" and m["config"]["data"]["my_gain"] == 2.0
    assert m["config"]["name"] == "SOURCE"
    _refused_in_one_line(args[:1] + ["data.my_gain=-1"] + args[2:], tmp_path, "data.my_gain")


SOLVER = textwrap.dedent('''
    """A plug-in solver with an option of its own: Adam with its first moment's decay ``my_beta``."""
    import indreg
    from indreg.options import Option, number
    from indreg.registration.solver_registry import Solver

    def build(problem, o, model_kwargs):
        return indreg.solvers.TorchOptimSolver(problem, "adam", lr=0.05, max_iter=o["max_iter"],
                                               betas=(o["my_beta"], 0.999), **model_kwargs)

    SOLVER = Solver("my_adam", build, options=(
        Option("my_beta", "solver", "my_beta", 0.9, number(0.0), "Adam's first decay", float, solvers=("my_adam",)),
    ))
''')


@pytest.mark.slow
def test_plugin_solver_with_an_option_from_python_and_the_command_line(tmp_path, monkeypatch):
    """``solver="module:SOLVER"`` / ``solver.name=module:SOLVER solver.my_beta=...``: nothing of indreg edited."""
    (tmp_path / "my_solver.py").write_text(SOLVER)
    monkeypatch.syspath_prepend(str(tmp_path))
    domain, T, template = _tiny_suite1()
    try:
        r = indreg.register(template, T(phantoms.get("v", domain)), T, solver="my_solver:SOLVER", my_beta=0.5,
                            num_steps=3, max_iter=2)
        assert r.status == "completed" and r.history[-1]["step_size"] == 0.05
        with pytest.raises(TypeError, match="my_beta must be left unset"):
            indreg.register(template, T(template), T, my_beta=0.5, max_iter=1)
    finally:
        for key in ("my_adam", "my_solver:SOLVER"):
            indreg.options.SOLVERS.pop(key, None)
    args, m = _run_tiny_app(["solver.name=my_solver:SOLVER", "solver.my_beta=0.5"], tmp_path)
    assert m["status"] == "completed" and m["hparams"]["solver"] == "my_adam"
    assert m["config"]["solver"]["my_beta"] == 0.5
    _refused_in_one_line(args[:1] + ["solver.my_beta=-1"] + args[2:], tmp_path, "solver.my_beta")


CORRECTION = textwrap.dedent('''
    """A plug-in in-the-fit correction with an option: the template's mean matched to the data's every k iterations."""
    import torch
    from indreg.registration.corrections import Correction, register_correction
    from indreg.options import Option, number
    from indreg.solvers.state import RefitSolver

    class Counted(RefitSolver):
        name, what = "counted", "a count"

        def refit(self, state):
            self.count = getattr(self, "count", 0) + 1

        def summary(self):
            return {"refits": self.count}

    register_correction(Correction("counted", lambda solver, fit: solver if not fit.options["count_every"] else
                                   Counted(solver, fit.options["count_every"]), options=(
        Option("count_every", "data", "count_every", 0, number(0, integer=True), "refit period (0: off)", int),
    )))
''')


@pytest.mark.slow
def test_plugin_correction_with_an_option_from_python_and_the_command_line(tmp_path, monkeypatch):
    """``import module`` / ``plugins=[module] data.count_every=...``: the chain runs it, nothing of indreg edited."""
    import importlib

    (tmp_path / "my_correction.py").write_text(CORRECTION)
    monkeypatch.syspath_prepend(str(tmp_path))
    domain, T, template = _tiny_suite1()
    try:
        importlib.import_module("my_correction")
        r = indreg.register(template, T(phantoms.get("v", domain)), T, count_every=2, num_steps=3, max_iter=5)
        assert r.corrections == {"counted": {"refits": 3}}   # before iterations 0, 2 and 4
    finally:
        indreg.options.CORRECTIONS.pop("counted", None)
        sys.modules.pop("my_correction", None)
    args, m = _run_tiny_app(["plugins=[my_correction]", "data.count_every=2"], tmp_path, max_iter=5)
    assert m["status"] == "completed" and m["counted"] == {"refits": 3}
    _refused_in_one_line(args[:1] + ["data.count_every=-1"] + args[2:], tmp_path, "data.count_every")
    _refused_in_one_line(["plugins=[no_such_module]"] + args[2:], tmp_path, "plugins")
