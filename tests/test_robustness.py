"""Crashes and raw tracebacks turned into clear errors or clear statuses (issue 34): callbacks that raise or
return a wrong status, Algorithm 1 when every halving trial overflows, a one-pixel template, ``restrict`` with
times it cannot use, an obscure ``TorchOptimSolver`` optimizer."""
import math

import numpy as np
import pytest
import torch

import indreg
import indreg.registration.run  # noqa: F401 (the module, for indreg.registration.run.setup)
from indreg import phantoms
from indreg.callbacks import Callback, Callbacks
from indreg.io import DataFileError


@pytest.fixture(scope="module")
def setup():
    domain = indreg.ImageDomain.paper(16)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(8, 24))
    template, target = phantoms.get("j", domain).double(), phantoms.get("v", domain).double()
    return indreg.registration.run.setup(template, T(target), T, num_steps=3, max_iter=4)


def _loop(setup, callbacks):
    return indreg.registration.run.RegistrationLoop(setup.problem, setup.solver, indreg.registration.run.initial_state(setup.problem), 4,
                                       callbacks=callbacks)


class _Log(Callback):
    def __init__(self, name, log, fail=()):
        self.name, self.log, self.fail = name, log, fail

    def begin(self, loop):
        self.log.append((self.name, "begin"))
        if "begin" in self.fail:
            raise RuntimeError(f"{self.name} begin")

    def after(self, loop, info, done):
        if "after" in self.fail:
            raise RuntimeError(f"{self.name} after")

    def end(self, loop):
        self.log.append((self.name, "end"))
        if "end" in self.fail:
            raise RuntimeError(f"{self.name} end")


def test_a_begin_that_raises_still_runs_every_end(setup):
    log = []
    with pytest.raises(RuntimeError, match="^a begin$"):
        _loop(setup, _Log("a", log, ["begin"]) & _Log("b", log)).run()
    assert log == [("a", "begin"), ("a", "end"), ("b", "end")]


def test_an_end_that_raises_does_not_skip_the_later_ones(setup):
    log = []
    with pytest.raises(RuntimeError, match="^a end$"):
        _loop(setup, _Log("a", log, ["end"]) & _Log("b", log, ["end"]) & _Log("c", log)).run()
    assert log[-3:] == [("a", "end"), ("b", "end"), ("c", "end")]


def test_the_first_exception_is_the_one_reported(setup, caplog):
    log = []
    with caplog.at_level("ERROR", logger="indreg"), pytest.raises(RuntimeError, match="^a after$"):
        _loop(setup, _Log("a", log, ["after"]) & _Log("b", log, ["end"])).run()
    assert log[-2:] == [("a", "end"), ("b", "end")] and "b end" in caplog.text


def test_the_app_restores_its_signal_handlers_when_an_earlier_end_raises(setup):
    import signal

    from indreg.experiments.runner import Signals

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(RuntimeError, match="^a end$"):
        _loop(setup, _Log("a", [], ["end"]) & Signals()).run()
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.parametrize("value", [5, True, "done", 1.0])
def test_a_status_that_is_not_a_stop_status_is_refused(setup, value):
    class Returns(Callback):
        def after(self, loop, info, done):
            return value

    with pytest.raises(TypeError, match=rf"^Returns\.after\(\) returned {value!r}: a callback returns None to go on "
                                        r"or one of 'stopped', 'early_stopped', 'interrupted'"):
        _loop(setup, Returns()).run()


def test_stop_statuses_and_false_are_taken(setup):
    class Stops(Callback):
        def before(self, loop):
            return False

        def after(self, loop, info, done):
            return "early_stopped" if loop.state.iteration == 2 else None

    loop = _loop(setup, Stops())
    assert loop.run() == "early_stopped" and loop.state.iteration == 2
    assert isinstance(Stops() & Stops(), Callbacks)


def test_algorithm1_every_halving_trial_overflows_ends_failed_with_the_iterate_kept(setup, monkeypatch):
    """Every trial raises the dtype's overflow (what ``template_scale=1e300`` does): the step is rejected and
    the iterate kept, the halved step stays (no TypeError)."""
    from indreg.solvers import Algorithm1

    solver = Algorithm1(setup.problem, step_halving=True, max_halvings=3, max_iter=2)
    state = indreg.registration.run.initial_state(setup.problem)
    start = [x.clone() for x in state.iterate]
    solver.report(state)   # the iterate's own evaluation is finite
    evaluate = solver._evaluate

    def overflow(x, counted=True):
        if any(not torch.equal(a, b) for a, b in zip(x, start)):
            raise ValueError("the velocity is non-finite (the step overflowed)")
        return evaluate(x, counted)

    monkeypatch.setattr(solver, "_evaluate", overflow)
    step = solver.step_size
    info = solver.step(state)
    assert info["rejected"] and "rejected after 3 halvings" in info["warning"]
    assert all(torch.equal(a, b) for a, b in zip(state.iterate, start)) and state.iteration == 1
    assert math.isfinite(info["objective"]) and solver.step_size == step / 8


def test_register_with_an_overflowing_template_ends_with_a_status():
    """``template_scale=1e300`` in float64: before, ``TypeError: cannot unpack non-iterable NoneType``."""
    domain = indreg.ImageDomain.paper(16)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(8, 24))
    template, target = phantoms.get("j", domain).double(), phantoms.get("v", domain).double()
    r = indreg.register(template, T(target), T, num_steps=3, max_iter=2, step_halving=True, max_halvings=2,
                        template_scale=1e300)
    assert r.status == "failed" and len(r.history) == 1 and r.history[0]["rejected"]
    assert "non-finite objective" in r.history[0]["warning"]


@pytest.mark.parametrize("shape", [(1, 1), (1, 4)])
def test_a_template_of_one_pixel_along_an_axis_is_refused_in_one_line(shape):
    with pytest.raises(DataFileError, match=r"^template: shape .* has a single pixel along an axis"):
        indreg.load(np.ones(shape), np.ones((4, 8)), angles=np.linspace(0, 180, 4, endpoint=False), det_min=-16,
                    det_max=16)


@pytest.fixture(scope="module")
def ray():
    return indreg.RayTransform(indreg.ImageDomain.paper(8), indreg.ParallelBeamGeometry.paper(4, 12))


@pytest.mark.parametrize("rows, error, match", [
    ([0.5, 1.5], ValueError, r"got \[0\.5, 1\.5\] \(not integers\)"),
    ([[0, 1], [2, 3]], ValueError, r"got an array of shape \(2, 2\)"),
    ("0,1", TypeError, "got '0,1'"), (None, TypeError, "got None"),
    ([True, False], TypeError, r"got \[True, False\] \(dtype bool\)"), ([0, [1]], TypeError, r"got \[0, \[1\]\]")])
def test_restrict_refuses_rows_that_are_not_integer_indices(ray, rows, error, match):
    with pytest.raises(error, match=r"^rows must be a 1D sequence of integer indices in \[0, 4\), " + match):
        indreg.restrict(ray, rows)


@pytest.mark.parametrize("rows", [[1, 3], np.array([1, 3], dtype=np.float32), [np.float32(1), np.float32(3)],
                                  torch.tensor([1, 3]), (np.int64(1), 3)])
def test_restrict_takes_integer_rows_in_any_container(ray, rows):
    assert indreg.restrict(ray, rows).rows.tolist() == [1, 3]


def test_times_as_a_list_of_numpy_scalars_are_the_same_as_the_array():
    from indreg.problems.spatiotemporal import time_indices

    times = np.array([0.25, 0.5, 1.0], dtype=np.float32)
    assert time_indices(list(times), 8, 3) == time_indices(times, 8, 3) == [2, 4, 8]
    with pytest.raises(ValueError, match="times must be a list of 2 numbers"):
        time_indices([np.bool_(True), 1.0], 8, 2)


@pytest.mark.parametrize("optimizer", ["optimizer", "Optimizer", torch.optim.Optimizer])
def test_torch_optim_solver_refuses_the_abstract_base_optimizer(setup, optimizer):
    from indreg.solvers import TorchOptimSolver

    with pytest.raises(ValueError, match=r"^optimizer must be a subclass of torch\.optim\.Optimizer \(not the base "
                                         r"class itself\) or one of \[.*'adam'"):
        TorchOptimSolver(setup.problem, optimizer=optimizer)
