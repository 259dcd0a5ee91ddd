"""Where the stack does not determine the tilt-axis angle, the fit does not wander along the valley while reporting a
tiny error: by default it holds the stack's estimate (or, without one, the given angle) and reports the stack's
standard error; ``UNDETERMINED = "prior"`` fits the angle with the stack's estimate as a Gaussian prior."""
import logging
import math

import numpy as np
import pytest
import torch

from indreg import ImageDomain, phantoms
from indreg.alignment import solver
from indreg.alignment.fit import aligned, estimate
from indreg.alignment.moments import AxisEstimate
from indreg.alignment.operator import AlignedOperator
from indreg.alignment.state import AlignmentState
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform

F64 = torch.float64


@pytest.fixture(scope="module")
def series():
    domain = ImageDomain.paper(16, ndim=3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 6, det_count=16, det_min=-16., det_max=16.))
    return T, phantoms.get("shepp_logan_3d", domain).double()


def _estimate(angle, se, reason=""):
    K = 21
    return AxisEstimate(angle, se, se <= 0.2, 1.0, np.zeros((K, 2)), np.ones(K, bool), (np.zeros(0), np.zeros(0)),
                        reason)


@pytest.mark.parametrize("policy, stack, held, angle, se, source", [
    ("hold", (-3.34, 0.45), True, -3.34, 0.45, "stack (not determined)"),
    ("hold", (-0.7, math.inf), True, 0.0, math.inf, "given"),          # flat: the given angle, s.e. inf
    ("prior", (-3.34, 0.45), False, 0.0, math.inf, "fit with the stack's prior"),
    ("fit", (-3.34, 0.45), False, 0.0, math.inf, "fit"),
])
def test_the_policy_where_the_stack_does_not_determine_the_angle(series, monkeypatch, caplog, policy, stack, held,
                                                                 angle, se, source):
    T, f = series
    monkeypatch.setattr(solver, "UNDETERMINED", policy)
    monkeypatch.setattr(solver, "stack_angle", lambda *a, **k: _estimate(*stack))
    op, state = aligned(T, "shifts+axis")
    with caplog.at_level(logging.WARNING, logger="indreg"):
        assert solver.hold_stack_angle(op, state, T(f)) is held
    assert state.held is held and math.degrees(float(op.angle)) == pytest.approx(angle)
    assert state.angle_se == pytest.approx(se) if math.isfinite(se) else state.angle_se == math.inf
    assert (state.prior is not None) is (policy == "prior")
    assert sum("tilt-axis angle not determined by the data" in m for m in caplog.messages) == 1
    state.records.append((0, op.shifts.clone(), float(op.angle)))
    summary = solver.operator_summary(op, state)
    assert summary["axis_angle_source"] == source and summary["axis_angle_determined"] is False


def test_a_prior_holds_the_angle_where_the_data_say_nothing(series):
    """Data that do not depend on the angle (a zero projection): the prior's centre comes out; without it the angle
    stays where it started."""
    T, f = series
    op = AlignedOperator(T)
    P = torch.zeros(T.range_shape, dtype=F64)
    g = 0.01 * torch.randn(T.range_shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    start = torch.tensor(0.0, dtype=F64)
    _, a, _ = estimate(op, P, g, op.shifts, start, axis=True, prior=(math.radians(-3.0), math.radians(0.5)))
    assert math.degrees(float(a)) == pytest.approx(-3.0, abs=0.05)
    _, a, _ = estimate(op, P, g, op.shifts, start, axis=True)
    assert float(a) == 0.0


def test_a_prior_gives_way_to_data_that_determine_the_angle(series):
    """Exact data of an axis at 2 degrees and a wide prior at -3 +- 5: the data win (within 0.1 degree)."""
    T, f = series
    op = AlignedOperator(T)
    P = T(f)
    g = op.warp(P, op.shifts, torch.tensor(math.radians(2.0), dtype=F64))
    g = g + 0.001 * g.abs().max() * torch.randn(g.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
    _, a, _ = estimate(op, P, g, op.shifts, torch.tensor(0.0, dtype=F64), axis=True, iterations=30,
                       prior=(math.radians(-3.0), math.radians(5.0)))
    assert math.degrees(float(a)) == pytest.approx(2.0, abs=0.1)


def test_the_prior_is_checkpointed():
    state = AlignmentState("shifts+axis", prior=(0.1, 0.02))
    d = state.state_dict()
    fresh = AlignmentState("shifts+axis")
    fresh.load_state_dict(dict(d))
    assert fresh.prior == pytest.approx((0.1, 0.02))
