"""Warnings counted by kind: the set-up's (logged before the loop), the iterations' (from the history, once) and the
end's (a poor fit), in ``result.warnings`` / ``warnings_by_kind``; without a handler they still reach stderr."""
import logging

import pytest

import indreg
from indreg import phantoms
from indreg import tally


def test_kind_of_drops_numbers_and_detail():
    assert tally.kind_of("objective increased from 1.25 to 1.5e3") == "objective increased from # to #"
    assert tally.kind_of("tilt-axis angle not determined by the data (0.45 deg): held") == \
        "tilt-axis angle not determined by the data"
    assert tally.kind_of("step rejected after 20 halvings (kept the iterate): nan") == "step rejected after # halvings"


def test_setup_iteration_and_end_warnings_are_counted_once(caplog):
    domain = indreg.ImageDomain.paper(16)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(6, 24))
    template, data = phantoms.get("j", domain), T(phantoms.get("v", domain))
    setup_log = logging.getLogger("indreg.test_setup")

    def setup_warning(state, info):     # a warning logged outside the loop's own lines, as a set-up's is
        if info["iteration"] == 1:
            setup_log.warning("the tilt-axis angle is not determined by the data (%.2f deg)", 0.45)

    with caplog.at_level(logging.INFO, logger="indreg"):
        r = indreg.register(10 * template, 10 * data, T, num_steps=4, max_iter=6, step_halving=False,
                            step_size=0.02, log_every=3, callback=setup_warning)
    iterations = sum(1 for h in r.history if h["warning"])
    assert iterations > 0
    assert r.warnings_by_kind["the tilt-axis angle is not determined by the data"] == 1
    logged = [rec for rec in caplog.records if rec.levelno >= logging.WARNING]
    others = [rec for rec in logged if not getattr(rec, "indreg_counted", False)]   # set-up, the callback's, end
    assert len(others) < len(logged) and len(others) >= 1 + bool(r.poor_fit)
    assert r.warnings == iterations + len(others)
    assert sum(r.warnings_by_kind.values()) >= r.warnings
    assert tally.summary(r.warnings, r.warnings_by_kind).startswith(f"{r.warnings} warnings (")


def test_without_handlers_warnings_still_reach_stderr(capsys):
    root, indreg_log = logging.getLogger(), logging.getLogger("indreg")
    saved = (root.handlers[:], indreg_log.handlers[:], indreg_log.propagate)
    root.handlers[:] = []
    indreg_log.handlers[:] = []
    try:
        with tally.tally_warnings() as t:
            logging.getLogger("indreg.x").warning("a warning of %d", 7)
        assert t.kinds == {"a warning of #": 1}
        assert "a warning of 7" in capsys.readouterr().err      # logging's last resort, as without the tally
    finally:
        root.handlers[:], indreg_log.handlers[:], indreg_log.propagate = saved


@pytest.mark.parametrize("nested", [False, True])
def test_tallies_nest(nested):
    with tally.tally_warnings() as outer:
        if nested:
            with tally.tally_warnings() as inner:
                assert tally.current() is inner
        assert tally.current() is outer
    assert tally.current() is None
