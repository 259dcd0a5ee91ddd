"""The kernel width when none is given (``indreg.kernel_width``): 1/16 of the box's largest side, or
``sigma="auto"``, the candidate width whose registration predicts held-out angles best; and ``register()``'s
interpolation default (compose)."""
import math

import pytest
import torch

import indreg
from indreg import phantoms
from indreg.kernel_width import AUTO_FRACTIONS, AUTO_HOLDOUT, candidates, choose_sigma, default_sigma

OPTIONS = dict(max_iter=4, num_steps=3, log_every=2, dtype="float64")


@pytest.fixture(scope="module")
def case():
    """J -> V on 16^2 cells of [-8, 8]^2 (the default width 2, not the paper's box), 20 angles."""
    domain = indreg.ImageDomain((16, 16), (-8.0, -8.0), (8.0, 8.0))
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=torch.linspace(0, math.pi, 21)[:-1].double(),
                                                                det_count=24, det_min=-12.0, det_max=12.0))
    template = phantoms.get("j", indreg.ImageDomain.paper(16))
    return template, T(phantoms.get("v", indreg.ImageDomain.paper(16))), T


def test_default_width_is_a_fraction_of_the_box():
    assert default_sigma(indreg.ImageDomain.paper(64)) == 4.0            # [-16, 16]^2: 32 / 8
    assert default_sigma(indreg.ImageDomain((8, 4), (0.0, 0.0), (80.0, 4.0))) == 10.0    # the largest side
    assert candidates(indreg.ImageDomain.paper(8)) == tuple(32 * f for f in AUTO_FRACTIONS)


def test_register_without_sigma_uses_the_default_width_and_composes(case):
    template, data, T = case
    r = indreg.register(template, data, T, **OPTIONS)
    assert r.problem.kernel.sigma == default_sigma(T.domain) == 2.0
    assert r.problem.deformation.interpolation == "compose"
    given = indreg.register(template, data, T, sigma=2.0, interpolation="compose", **OPTIONS)
    assert torch.equal(r.deformed, given.deformed)


def test_auto_chooses_the_width_with_the_least_held_out_residual(case):
    template, data, T = case
    scores = {s: indreg.register(template, data, T, sigma=s, holdout=AUTO_HOLDOUT, **OPTIONS)
              .holdout["holdout_best_residual"] for s in candidates(T.domain)}
    assert len(set(scores.values())) == len(scores)                      # the choice is not a tie
    chosen = indreg.register(template, data, T, sigma="auto", **OPTIONS)
    assert chosen.problem.kernel.sigma == chosen.sigma == min(scores, key=scores.get)
    assert chosen.sigma_scores == pytest.approx(scores, rel=1e-12)        # each width's held-out residual
    assert not chosen.holdout                                             # the run itself fits every angle


def test_auto_says_each_width_and_the_choice(case, capfd, caplog):
    """Off a terminal (as here) the default prints nothing; the lines, one per width with its score and the width
    chosen, go through logging (with ``progress=True`` and no logging set up: to stderr; on a terminal: above the
    bars)."""
    template, data, T = case
    with caplog.at_level("INFO", logger="indreg"):
        r = indreg.register(template, data, T, sigma="auto", **OPTIONS)
    assert capfd.readouterr().err == ""
    lines = [m for m in caplog.messages if m.startswith("sigma='auto'")]
    widths = candidates(T.domain)
    assert [line.split("gives held-out residual ")[1] for line in lines[:-1]] == \
        [f"{r.sigma_scores[w]:.4f}" for w in widths]
    assert lines[-1] == f"sigma='auto': chose sigma {r.sigma:.4g} of {', '.join(f'{w:.4g}' for w in widths)}"


def test_auto_scores_the_last_iterate_of_a_run_shorter_than_log_every(case):
    """With fewer iterations than ``log_every`` the held-out curve is empty: each width is scored on its last
    iterate (not NaN, which would leave the choice to the order of the widths)."""
    template, data, T = case
    r = indreg.register(template, data, T, sigma="auto", **dict(OPTIONS, log_every=10))
    widths = candidates(T.domain)
    last = {s: indreg.register(template, data, T, sigma=s, holdout=AUTO_HOLDOUT, **dict(OPTIONS, log_every=10))
            .holdout["holdout_residual"] for s in widths}
    assert r.sigma_scores == pytest.approx(last, rel=1e-12) and r.sigma == min(last, key=last.get)


def test_a_given_width_is_in_the_result_without_scores(case):
    template, data, T = case
    r = indreg.register(template, data, T, sigma=3.0, **OPTIONS)
    assert r.sigma == 3.0 and r.sigma_scores == {}


def test_choose_sigma_takes_the_least_score_and_the_first_of_equal_ones():
    assert choose_sigma({1.0: 0.3, 2.0: 0.1, 4.0: 0.2}.get, (1.0, 2.0, 4.0)) == (2.0, {1.0: 0.3, 2.0: 0.1, 4.0: 0.2})
    assert choose_sigma(lambda s: 0.5, (1.0, 2.0))[0] == 1.0


@pytest.mark.parametrize("bad", ["wide", -1.0, 0.0, math.nan])
def test_a_bad_width_is_one_line_naming_sigma(case, bad):
    template, data, T = case
    with pytest.raises((ValueError, TypeError), match="sigma"):
        indreg.register(template, data, T, sigma=bad, **OPTIONS)
