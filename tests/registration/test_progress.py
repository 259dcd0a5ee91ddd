"""What a run says while it works (``indreg.registration.run``): progress on a terminal by default and nothing in
scripts, pipes and tests (``progress=None``); a fixed step's objective rises said once and counted apart from the
warnings."""
import logging
import sys

import pytest

import indreg
from indreg import noise, phantoms
from indreg.registration import run


@pytest.fixture(scope="module")
def tiny():
    domain = indreg.ImageDomain.paper(24)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(8, 36))
    data, _ = noise.add_white_noise(T(phantoms.get("v", domain)), snr_db=15.0, seed=0)
    return T, phantoms.get("j", domain), data


@pytest.mark.parametrize("tty", [False, True])
def test_progress_by_default_on_a_terminal_only(monkeypatch, tty):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)
    assert run.shows_progress(None) is tty
    assert run.shows_progress(True) is True and run.shows_progress(False) is False


def test_a_line_of_progress_shows_above_the_bars_on_a_terminal_without_logging(monkeypatch, capsys, caplog):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    monkeypatch.setattr(run.log, "hasHandlers", lambda: False)
    with caplog.at_level(logging.INFO, logger="indreg"):
        run._say("sigma='auto' 1/3: sigma 2 gives held-out residual 0.3000")
    assert capsys.readouterr().err == "[indreg] sigma='auto' 1/3: sigma 2 gives held-out residual 0.3000\n"
    assert caplog.messages == ["sigma='auto' 1/3: sigma 2 gives held-out residual 0.3000"]


def test_a_fixed_steps_rises_are_said_once_and_are_not_warnings(tiny, caplog):
    """The paper's fixed step takes every step (step 0.06 here: three rises in 12 iterations, no folding): one
    line, then a count (``objective_rises``), not "3 warnings"."""
    T, template, data = tiny
    with caplog.at_level(logging.INFO, logger="indreg"):
        r = indreg.register(template, data, T, num_steps=4, max_iter=12, step_halving=False, step_size=0.06,
                            gamma=1e-6, dtype="float64")
    rises = [h["objective_rose"] for h in r.history if h.get("objective_rose")]
    assert r.objective_rises == len(rises) == 3
    assert not any("objective" in kind for kind in r.warnings_by_kind), r.warnings_by_kind   # not warnings
    assert all(text.startswith("objective increased from") for text in rises)
    said = [m for m in caplog.messages if "objective increased" in m]
    assert len(said) == 1 and "further rises are counted (objective_rises), not printed" in said[0]
    assert not any("reported a warning" in m for m in caplog.messages)


def test_step_halving_has_no_rises(tiny):
    T, template, data = tiny
    r = indreg.register(template, data, T, num_steps=4, max_iter=12, step_size=0.06, gamma=1e-6, dtype="float64")
    assert r.objective_rises == 0 and not any(h.get("objective_rose") for h in r.history)
