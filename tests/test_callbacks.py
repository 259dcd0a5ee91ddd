"""Callbacks of the registration loop: composition with ``&``, the first stop status wins, begin / end around the
run, the held-out residual before the callbacks after it, the user's ``callback(state, info)``."""
import pytest
import torch

import indreg
import indreg.registration.run  # noqa: F401 (the module, for indreg.registration.run.setup)
from indreg import phantoms
from indreg.callbacks import Callback, Callbacks, HeldOut, UserCallback


class Recorder(Callback):
    def __init__(self, name, log, stop_at=None):
        self.name, self.log, self.stop_at = name, log, stop_at

    def begin(self, loop):
        self.log.append((self.name, "begin"))

    def after(self, loop, info, done):
        self.log.append((self.name, loop.state.iteration, "holdout_residual" in info))
        return "stopped" if loop.state.iteration == self.stop_at else None

    def describe(self, info):
        return f" [{self.name}]"

    def end(self, loop):
        self.log.append((self.name, "end"))


@pytest.fixture(scope="module")
def setup():
    domain = indreg.ImageDomain.paper(16)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(8, 24))
    template, target = phantoms.get("j", domain).double(), phantoms.get("v", domain).double()
    return indreg.registration.run.setup(template, T(target), T, num_steps=3, max_iter=6, holdout=4)


def test_composition_flattens_and_runs_in_order():
    a, b, c = Callback(), Callback(), Callback()
    chain = a & b & c
    assert isinstance(chain, Callbacks) and chain.callbacks == [a, b, c]
    assert (a & (b & c)).callbacks == [a, b, c]
    with pytest.raises(TypeError, match="Callback instances"):
        Callbacks(a, lambda state, info: None)


def test_loop_calls_every_callback_and_the_first_status_wins(setup, caplog):
    log = []
    chain = Recorder("a", log, stop_at=3) & Recorder("b", log, stop_at=2)
    state = indreg.registration.run.initial_state(setup.problem)
    with caplog.at_level("INFO", logger="indreg"):
        loop = indreg.registration.run.RegistrationLoop(setup.problem, setup.solver, state, 6, every=2, callbacks=chain,
                                           validation=setup.validation)
        status = loop.run()
    assert status == "stopped" and state.iteration == 2          # b stopped at 2; a still ran at 2
    assert log == [("a", "begin"), ("b", "begin"), ("a", 1, False), ("b", 1, False), ("a", 2, True),
                   ("b", 2, True), ("a", "end"), ("b", "end")]   # the held-out residual came first, at iteration 2


def test_end_runs_when_a_step_raises(setup):
    class Boom(Callback):
        def after(self, loop, info, done):
            raise RuntimeError("boom")

    log = []
    loop = indreg.registration.run.RegistrationLoop(setup.problem, setup.solver, indreg.registration.run.initial_state(setup.problem), 6,
                                       callbacks=Recorder("r", log) & Boom())
    with pytest.raises(RuntimeError, match="boom"):
        loop.run()
    assert log[-1] == ("r", "end")


def test_user_callback_and_held_out_are_callbacks(setup):
    seen = []
    cb = UserCallback(lambda state, info: seen.append(state.iteration) or state.iteration == 2)
    loop = indreg.registration.run.RegistrationLoop(setup.problem, setup.solver, indreg.registration.run.initial_state(setup.problem), 6,
                                       every=1, callbacks=HeldOut(setup.validation) & cb)
    assert loop.run() == "stopped" and seen == [1, 2]
    assert all(torch.isfinite(torch.tensor(h["holdout_residual"])) for h in loop.history)


def test_register_takes_callback_objects_functions_and_lists():
    """One loop: ``register(callback=...)`` takes what the app's loop is made of (a Callback, a chain ``a & b``), a
    plain function, or a list of both; the first stop status wins, begin / end run once."""
    domain = indreg.ImageDomain.paper(16)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(8, 24))
    args = (phantoms.get("j", domain), T(phantoms.get("v", domain)), T)
    log = []
    r = indreg.register(*args, num_steps=3, max_iter=6, callback=Recorder("a", log) & Recorder("b", log, stop_at=2))
    assert r.status == "stopped" and r.iterations == 2
    assert log == [("a", "begin"), ("b", "begin"), ("a", 1, False), ("b", 1, False), ("a", 2, False),
                   ("b", 2, False), ("a", "end"), ("b", "end")]
    seen, log = [], []
    r = indreg.register(*args, num_steps=3, max_iter=4, callback=[Recorder("a", log), lambda s, i: seen.append(
        s.iteration) or s.iteration == 3])
    assert r.status == "stopped" and seen == [1, 2, 3] and log[-1] == ("a", "end")
    with pytest.raises(TypeError, match=r"^callback must be callable\(state, info\), an indreg.callbacks"
                                        r".Callback or a list of them, got 3$"):
        indreg.register(*args, max_iter=1, callback=3)
