"""Held-out validation (``holdout`` / ``patience``): indices, the fit without the held-out angles, the residual
curve, early stopping and bad values."""
import math

import pytest
import torch

import indreg
from indreg import noise, phantoms
from indreg.options import OptionError
from indreg.evaluation.validation import holdout_rows

DOMAIN = indreg.ImageDomain.paper(24)
ANGLES = torch.arange(12, dtype=torch.float64) * (math.pi / 12)
FAST = {"num_steps": 4, "max_iter": 8, "log_every": 2}


def ray(angles):
    return indreg.RayTransform(DOMAIN, indreg.ParallelBeamGeometry(angles=angles, det_count=36, det_min=-24.0,
                                                                   det_max=24.0, angle_unit="rad"))


@pytest.fixture(scope="module")
def tiny():
    T = ray(ANGLES)
    template, target = phantoms.get("j", DOMAIN), phantoms.get("v", DOMAIN)
    data, _ = noise.add_white_noise(T(target), snr_db=15.0, seed=0)
    return T, template, target, data


def test_holdout_rows():
    assert holdout_rows(5, 30) == ([i for i in range(30) if i % 5 != 2], [2, 7, 12, 17, 22, 27])
    assert holdout_rows(2, 5) == ([0, 2, 4], [1, 3])
    assert holdout_rows([4, 0], 6) == ([1, 2, 3, 5], [0, 4])


def test_fit_ignores_the_held_out_angles(tiny):
    """The fit is that of the kept angles alone: the same iterates as a ray transform of only those angles, and
    whatever the held-out rows contain."""
    T, template, target, data = tiny
    r = indreg.register(template, data, T, holdout=3, **FAST)
    kept, held = holdout_rows(3, 12)
    alone = indreg.register(template, data[kept], ray(ANGLES[kept]), **FAST)
    torch.testing.assert_close(r.momentum, alone.momentum, rtol=1e-10, atol=1e-12)
    garbage = data.clone()
    garbage[held] = 1e3
    other = indreg.register(template, garbage, T, holdout=3, **FAST)
    torch.testing.assert_close(other.momentum, r.momentum, rtol=0, atol=0)
    assert other.holdout["holdout_residual"] > 0.99 > r.holdout["holdout_residual"]   # measured on the rows


def test_held_out_residual_and_curve(tiny):
    T, template, target, data = tiny
    r = indreg.register(template, data, T, holdout=[1, 6, 10], **FAST)
    held = [1, 6, 10]
    res = T(r.deformed)[held] - data[held]
    expected = math.sqrt(float((res ** 2).sum() / (data[held] ** 2).sum()))   # uniform weights per datum
    assert r.holdout["holdout_residual"] == pytest.approx(expected, rel=1e-12)
    assert r.holdout["holdout_indices"] == held
    curve = [(h["iteration"], h["holdout_residual"]) for h in r.history if "holdout_residual" in h]
    assert [c[0] for c in curve] == [2, 4, 6, 8]                          # every log_every iterations
    assert curve[-1][1] == pytest.approx(r.holdout["holdout_residual"], rel=1e-12)
    best = min(curve, key=lambda c: c[1])
    assert (r.holdout["holdout_best_iteration"], r.holdout["holdout_best_residual"]) == best
    assert curve[-1][1] < curve[0][1]                                    # fitting the others predicts these
    # the residual of the fit is that of the kept angles
    kept = [i for i in range(12) if i not in held]
    res = T(r.deformed)[kept] - data[kept]
    assert r.residual == pytest.approx(math.sqrt(float((res ** 2).sum() / (data[kept] ** 2).sum())), rel=1e-10)



def test_holdout_after_units(tiny):
    """``template_scale`` / ``background`` act first (``indreg.units.prepare``), the split is of the prepared data:
    the same run and held-out residuals as with the inputs already in one unit."""
    T, template, target, data = tiny
    r = indreg.register(template, data + 5.0, T, holdout=3, template_scale=2.0, background=5.0, **FAST)
    ref = indreg.register(2.0 * template, data, T, holdout=3, **FAST)
    torch.testing.assert_close(r.momentum, ref.momentum, rtol=1e-9, atol=1e-12)
    assert r.holdout["holdout_residual"] == pytest.approx(ref.holdout["holdout_residual"], rel=1e-9)
    assert (r.units.template_scale, r.units.background) == (2.0, 5.0)
    assert r.status == ref.status == "completed"

def test_early_stopping(tiny):
    """Held-out rows that hold the template's projections: their residual grows from the first evaluation, so
    the run stops ``patience`` evaluations later."""
    T, template, target, data = tiny
    y = data.clone()
    y[[4, 8]] = T(template)[[4, 8]]
    r = indreg.register(template, y, T, holdout=[4, 8], patience=2, num_steps=4, max_iter=50, log_every=3)
    assert r.status == "early_stopped" and r.iterations == 9
    assert r.holdout["holdout_best_iteration"] == 3
    assert r.holdout["holdout_residual"] > r.holdout["holdout_best_residual"]
    assert indreg.register(template, data, T, holdout=4, patience=50, **FAST).status == "completed"


@pytest.mark.parametrize("holdout, kind, message", [
    (1, ValueError, r"holdout must be an integer k >= 2 \(every k-th angle; 1 leaves no angle to fit\)"),
    ([0, 12], ValueError, r"holdout must be indices in 0..11 \(the data have 12 angles\), got \[0, 12\]"),
    (list(range(12)), ValueError, "holdout must be a selection that leaves at least one of the 12 angles to fit"),
    (30, ValueError, r"holdout must be an integer k with k // 2 < 12"),
    ([], ValueError, "holdout must be None, an integer k >= 2"),
    ([2, 2], ValueError, "holdout must be a list of distinct indices >= 0"),
    ([-1], ValueError, "holdout must be a list of distinct indices >= 0"),
    ("every 5", TypeError, "holdout must be None, an integer k >= 2"),
    (2.5, TypeError, "holdout must be None, an integer k >= 2"),
    (True, TypeError, "holdout must be None, an integer k >= 2"),
])
def test_bad_holdout_one_line(tiny, holdout, kind, message):
    T, template, target, data = tiny
    with pytest.raises(kind, match=message) as e:
        indreg.register(template, data, T, holdout=holdout, max_iter=1)
    assert "\n" not in str(e.value) and not isinstance(e.value, OptionError)


def test_patience_needs_holdout(tiny):
    T, template, target, data = tiny
    with pytest.raises(ValueError, match=r"^patience must be None without holdout .*, got 3$"):
        indreg.register(template, data, T, patience=3, max_iter=1)
    with pytest.raises(ValueError, match="^patience must be an integer >= 1"):
        indreg.register(template, data, T, holdout=3, patience=0, max_iter=1)


def test_numpy_indices_and_tilt_series():
    """Indices as an array; a tilt series holds out tilts (the first data axis)."""
    dom = indreg.ImageDomain((10, 8, 10))
    T = indreg.forward.TiltSeriesTransform(dom, indreg.forward.TiltSeriesGeometry.uniform(-60, 60, 20,
                                                                                          det_count=14))
    template = phantoms.get("shepp_logan_3d", dom)
    data = T(phantoms.get("shepp_logan_3d_swirl", dom))
    import numpy as np

    r = indreg.register(template, data, T, holdout=np.array([1, 5]), num_steps=3, max_iter=2, log_every=1,
                        sigma=3.0)
    assert r.holdout["holdout_indices"] == [1, 5] and r.problem.data.shape == (5, 8, 14)
