"""Measured data as they come: the template's units (``template_scale``), the data's offset (``background``), and
what a run reports (diverged / stalled runs, halvings, rounding-level objective increases, radian-looking angles,
the TV baseline's weight at the data's scale)."""
import logging
import math

import numpy as np
import pytest
import torch

import indreg
from indreg import io, metrics, phantoms
from indreg.registration import run
from indreg.forward import intensity_scale, tv_reconstruction
from indreg.solvers.state import StepControl, problems, rounding_tolerance

#: register()'s defaults before indreg.kernel_width (the runs these tests were sized with)
PAPER = dict(sigma=6.0, interpolation="reinterpolate")


def tiny(n=32, noise=False):
    """J -> V on n^2 cells, 10 x 46 parallel beam (the paper's partition), float64; noise-free unless ``noise``."""
    domain = indreg.ImageDomain.paper(n)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(10, 46))
    template = phantoms.get("j", domain).double()
    target = phantoms.get("v", domain).double()
    data = T(target)
    if noise:
        data, _ = indreg.noise.add_white_noise(data, snr_db=15.0, seed=0)
    return template, data, T, target


QUICK = dict(max_iter=8, num_steps=5, sigma=6.0)


def warnings_of(caplog):
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


# ---------------------------------------------------------------------------------------------------- units
def test_unit_mismatch_warns_before_the_run_naming_both_numbers(caplog):
    template, data, T, _ = tiny()
    caplog.set_level(logging.INFO, logger="indreg")
    r = indreg.register(255 * template, data, T, max_iter=0)
    message = [m for m in warnings_of(caplog) if "different units" in m]
    assert len(message) == 1
    ratio = math.sqrt(float(T.inner_data(T(255 * template), T(255 * template)).sum())
                      / float(T.inner_data(data, data).sum()))
    assert f"{ratio:.4g}" in message[0] and f"{r.units.scale_fit:.4g}" in message[0]
    assert "template_scale='auto'" in message[0]
    assert r.units.projection_ratio == pytest.approx(ratio) and r.units.template_scale == 1.0
    first = next(i for i, rec in enumerate(caplog.records) if "different units" in rec.getMessage())
    assert all("iteration" not in rec.getMessage() for rec in caplog.records[:first])   # before the run


def test_matching_units_do_not_warn(caplog):
    template, data, T, _ = tiny(noise=True)
    r = indreg.register(template, data, T, **QUICK)
    assert not [m for m in warnings_of(caplog) if "units" in m or "offset" in m]
    assert 1 / 3 <= r.units.scale_fit <= 3 and 1 / 3 <= r.units.projection_ratio <= 3


def test_auto_scale_is_the_least_squares_fit_and_removes_the_units():
    """``template_scale="auto"`` multiplies by c = <T I, g> / <T I, T I> (here 0.5 I against data of I, so no unit
    factor is near): the run of 255 c I equals the run of c I."""
    template, data, T, target = tiny(noise=True)
    template = 0.5 * template
    a = indreg.register(template, data, T, template_scale="auto", **QUICK)
    b = indreg.register(255 * template, data, T, template_scale="auto", **QUICK)
    TI = T(template)
    c = float(T.inner_data(TI, data).sum() / T.inner_data(TI, TI).sum())
    assert 1.5 < c < 2.5 and indreg.units.unit_factor(c) == c
    assert a.units.template_scale == pytest.approx(c, rel=1e-12)
    assert b.units.template_scale == pytest.approx(c / 255, rel=1e-12)
    assert torch.allclose(a.deformed, b.deformed, rtol=1e-9, atol=1e-9 * float(a.deformed.abs().max()))
    assert a.status == b.status == "completed"


@pytest.mark.parametrize("c, expected", [(0.9735 / 255, 1 / 255), (1.04, 1.0), (1.01e-3, 1e-3), (1 / 66000, 1 / 65535),
                                         (4000.0, 4095.0), (1.08, 1.08), (0.5, 0.5), (37.0, 37.0), (0.095, 0.095)])
def test_unit_factor_takes_a_format_factor_only_when_near(c, expected):
    assert indreg.units.unit_factor(c) == pytest.approx(expected, rel=1e-12)


def test_a_number_scales_the_template():
    template, data, T, _ = tiny()
    a = indreg.register(template, data, T, **QUICK)
    b = indreg.register(255 * template, data, T, template_scale=1 / 255, **QUICK)
    assert b.units.template_scale == pytest.approx(1 / 255)
    assert torch.allclose(a.deformed, b.deformed, atol=1e-9)


@pytest.mark.slow
def test_suite1_at_255_with_auto_matches_the_x1_run(caplog):
    """The README example (suite 1, 64^2) with the template at 0..255: a warning naming the scale before the run;
    with ``template_scale="auto"`` the fitted c = 0.9735 / 255 is taken as the unit factor 1 / 255, and the run
    equals the x1 run (SSIM against the target within 0.005)."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parents[1] / "experiments"))
    from golden_helpers import suite1_problem

    template, data, T, target = suite1_problem()
    x1 = indreg.register(template, data, T, target=target, max_iter=40)
    caplog.clear()
    auto = indreg.register(255 * template, data, T, target=target, max_iter=40, template_scale="auto")
    assert not [m for m in warnings_of(caplog) if "different units" in m]
    assert auto.units.scale_fit == pytest.approx(0.9735 / 255, rel=1e-3)
    assert auto.units.template_scale == pytest.approx(1 / 255)
    assert metrics.ssim(auto.deformed.double(), x1.deformed.double()) >= 0.999
    assert abs(auto.ssim - x1.ssim) < 0.005
    indreg.register(255 * template, data, T, max_iter=0)
    assert any("c = <T I, g> / <T I, T I> = 0.003818" in m for m in warnings_of(caplog))


@pytest.mark.parametrize("value,kind,match", [
    (0, ValueError, "template_scale must be None, 'auto', 'fit', 'fit\\+offset' or a finite number > 0, got 0"),
    (-2.0, ValueError, "template_scale must be"),
    (float("nan"), ValueError, "template_scale must be"),
    ("fitted", ValueError, "template_scale must be None, 'auto', 'fit', 'fit\\+offset' or a finite number > 0, got "
               "'fitted'"),
    (True, TypeError, "template_scale must be"),
])
def test_bad_template_scale_is_one_line(value, kind, match):
    template, data, T, _ = tiny()
    with pytest.raises(kind, match=match):
        indreg.register(template, data, T, template_scale=value)


def test_auto_scale_of_an_unrelated_template_is_refused():
    template, data, T, _ = tiny()
    with pytest.raises(ValueError, match="template_scale='auto' found no positive scale"):
        indreg.register(-template, data, T, template_scale="auto")


# ---------------------------------------------------------------------------------------------------- offsets
def test_border_level_is_the_median_of_the_outermost_columns():
    g = torch.zeros(5, 32)
    g[:, 2:30] = 7.0
    assert indreg.units.border_level(g + 3.0) == 3.0            # k = 2 columns each side, object inside
    stack = torch.full((3, 4, 16), 1.5)               # a tilt series: the last axis is the columns
    assert indreg.units.border_level(stack) == 1.5


def test_offset_data_warn_and_auto_background_gives_the_clean_result(caplog):
    template, data, T, _ = tiny()
    clean = indreg.register(template, data, T, **QUICK)
    offset = data + 0.2 * float(data.max())
    indreg.register(template, offset, T, max_iter=0)
    assert any("data look offset" in m and "background='auto'" in m for m in warnings_of(caplog))
    caplog.clear()
    fixed = indreg.register(template, offset, T, background="auto", **QUICK)
    assert not [m for m in warnings_of(caplog) if "offset" in m]
    assert fixed.units.background == pytest.approx(0.2 * float(data.max()), rel=1e-12)
    assert torch.allclose(fixed.deformed, clean.deformed, atol=1e-9)
    assert fixed.residual == pytest.approx(clean.residual, rel=1e-9)


def test_noisy_offset_data_with_auto_background_match_the_clean_run():
    template, data, T, target = tiny(noise=True)
    clean = indreg.register(template, data, T, target=target, **QUICK)
    fixed = indreg.register(template, data - 3.0, T, target=target, background="auto", **QUICK)
    given = indreg.register(template, data - 3.0, T, target=target, background=-3.0, **QUICK)
    assert fixed.units.background == pytest.approx(-3.0, abs=0.05 * float(data.std()))
    assert abs(fixed.ssim - clean.ssim) < 0.005
    assert torch.allclose(given.deformed, clean.deformed, atol=1e-9)


@pytest.mark.parametrize("value,match", [(float("nan"), "background must be None, 'auto' or a finite number, "
                                                         "got nan"),
                                         ("border", "background must be"), (math.inf, "background must be")])
def test_bad_background_is_one_line(value, match):
    template, data, T, _ = tiny()
    with pytest.raises(ValueError, match=match):
        indreg.register(template, data, T, background=value)


def test_a_template_scale_that_overflows_the_dtype_is_one_line():
    template, data, T, _ = tiny()
    with pytest.raises(ValueError, match=r"^template_scale=1e\+300 makes the template non-finite in float32 \(scale "
                                         r"factor 1e\+300\)$"):
        indreg.register(template.float(), data.float(), T, template_scale=1e300)


def test_a_background_that_zeroes_the_data_is_one_line_naming_it(caplog):
    """Constant data with background='auto': one line naming the background and what it subtracted, before any
    comparison of units (no warning about them first)."""
    template, _, T, _ = tiny()
    caplog.set_level(logging.WARNING, logger="indreg")
    with pytest.raises(ValueError, match=r"^data must not be all zero \(\|\|g\|\|\^2 = 0\): .*; background='auto' "
                                         r"subtracted 2\.5 from every value$"):
        indreg.register(template, torch.full(T.range_shape, 2.5, dtype=torch.float64), T, background="auto")
    with pytest.raises(ValueError, match="data must not be all zero"):
        indreg.register(template, torch.zeros(T.range_shape, dtype=torch.float64), T)
    assert warnings_of(caplog) == []


# ---------------------------------------------------------------------------------------------------- reports
def test_a_run_worse_than_a_zero_image_has_diverged(caplog):
    template, data, T, _ = tiny()
    r = indreg.register(255 * template, data, T, max_iter=0)
    assert r.residual >= 1 and r.status == "diverged"
    assert any("diverged" in m and f"{r.residual:.4g}" in m for m in warnings_of(caplog))
    assert run.final_status("completed", 0.5) == "completed" and run.final_status("stopped", 2.0) == "stopped"
    assert run.final_status("converged", math.nan) == "diverged"


def test_objective_increases_within_rounding_are_not_warnings():
    tol = rounding_tolerance(torch.float32)
    assert 1e-5 < tol < 2e-5 and rounding_tolerance(torch.float64) < 1e-13
    assert problems(183.6369, 1.0, 183.6354, tol) == []            # the paper's fixed step in float32: 8e-6
    assert problems(183.7, 1.0, 183.6354, tol) == ["objective increased from 183.6354 to 183.7"]
    assert problems(183.6369, 1.0, 183.6354) != []                 # no tolerance: every increase
    # step halving still rejects every increase; without it only larger ones are reported
    trial = lambda steps: (steps, 100.0 * (1 + 5e-6), 1.0)   # noqa: E731
    assert StepControl(False, 5).search([1.0], 100.0, trial, tol)[3] == []
    out = StepControl(True, 2).search([1.0], 100.0, trial, tol)
    assert out[4] is True and out[5] == 2


class _FlatSolver:
    """Algorithm 1's interface with a step that halves once and never changes the objective."""
    halves_steps, step_sizes, max_iter = True, [1.0], 50

    def step(self, state):
        state.iteration += 1
        self.step_sizes[0] /= 2
        return {"iteration": state.iteration, "objective": 10.0, "data_fit": 10.0, "grad_norm": 1.0,
                "min_jacobian": 1.0, "step_size": self.step_sizes[0], "halvings": 1, "rejected": False,
                "warning": ""}

    def status(self, info):
        return "completed" if info["iteration"] >= self.max_iter else None


def test_a_collapsed_step_is_a_stall(caplog):
    caplog.set_level(logging.INFO, logger="indreg")
    state = indreg.SolverState(torch.zeros(2, 2, 4, 4))
    loop = run.RegistrationLoop(None, _FlatSolver(), state, max_iter=50)
    assert loop.run() == "stalled" and state.iteration == run.STALL_WINDOW + 1
    halved = [r.getMessage() for r in caplog.records if "step size halved" in r.getMessage()]
    assert len(halved) == state.iteration and all("1 time(s)" in m for m in halved)
    assert run.count_halvings(loop.history) == len(halved)
    assert any("stalled" in m for m in warnings_of(caplog))


def test_halvings_are_counted_and_agree_with_the_log(caplog):
    """255 times the intensities with the paper's absolute step: step halving halves in the first iterations."""
    template, data, T, _ = tiny()
    caplog.set_level(logging.INFO, logger="indreg")
    r = indreg.register(255 * template, 255 * data, T, step_size=0.02, **QUICK)
    counts = [int(m.split("halved ")[1].split(" time")[0]) for m in
              (rec.getMessage() for rec in caplog.records) if "step size halved" in m]
    assert sum(counts) == run.count_halvings(r.history) > 0
    assert all("halvings" in h for h in r.history)


def test_angles_in_degrees_that_look_like_radians_warn(caplog, tmp_path):
    io.read_angles(list(np.linspace(0, 3.1, 10)), "deg")
    assert any("may be radians" in m for m in warnings_of(caplog))
    caplog.clear()
    io.read_angles(list(np.arange(-60.0, 61.0, 2.0)), "deg")
    io.read_angles(list(np.linspace(0, 3.1, 10)), "rad")
    assert not warnings_of(caplog)
    template, _, T, target = tiny()
    (tmp_path / "a.tlt").write_text("".join(f"{a}\n" for a in np.linspace(-1.0, 1.0, 10)))
    indreg.load(template, np.zeros((10, 46)), angles=tmp_path / "a.tlt", det_min=-24, det_max=24)
    assert any("may be radians" in m and "-1 .. 1" in m for m in warnings_of(caplog))


def test_tv_weight_at_the_data_scale():
    """``intensity_scale`` scales with the data, and TV with ``mu`` times it is scale-equivariant."""
    _, data, T, _ = tiny(noise=True)
    u = intensity_scale(T, data)
    assert intensity_scale(T, 255 * data) == pytest.approx(255 * u, rel=1e-12)
    a = tv_reconstruction(T, data, mu=3.0 * u, num_iter=30)[0]
    b = tv_reconstruction(T, 255 * data, mu=3.0 * intensity_scale(T, 255 * data), num_iter=30)[0]
    assert torch.allclose(b, 255 * a, rtol=1e-8, atol=1e-8 * float(b.abs().max()))


@pytest.fixture(scope="module")
def j_to_v_square():
    """J to V on 32^2 with 32 angles x 32 bins (a square sinogram), 15 dB, and the run of the right layout."""
    domain = indreg.ImageDomain.paper(32)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(32, 32))
    template, target = phantoms.get("j", domain), phantoms.get("v", domain)
    data, _ = indreg.noise.add_white_noise(T(target), snr_db=15, seed=0)
    return T, template, data, indreg.register(template, data, T, num_steps=5, max_iter=40, **PAPER)


def test_a_layout_mistake_is_reported_as_a_poor_fit(caplog, j_to_v_square):
    """A square sinogram with angles and bins swapped fits far worse than its noise: the run keeps its status and
    warns; the same data the right way round do not."""
    T, template, data, right = j_to_v_square
    caplog.set_level(logging.WARNING, logger="indreg")
    swapped = indreg.register(template, data.T.contiguous(), T, num_steps=5, max_iter=40, **PAPER)
    poor = [m for m in warnings_of(caplog) if "poor fit" in m]
    assert swapped.status == right.status == "completed" and len(poor) == 1
    assert swapped.residual > 2 * swapped.units.noise_residual + 0.1 > right.residual
    assert poor[0] == swapped.poor_fit and "levelled off" in poor[0] and right.poor_fit == ""


def test_an_offset_template_still_falling_far_above_the_noise_is_a_poor_fit(caplog, j_to_v_square):
    """A template offset by +0.3 has not levelled off after 40 iterations but ends far above the noise: a poor-fit
    warning that says the objective is still falling and names fit+offset; the right template gets none."""
    T, template, data, right = j_to_v_square
    caplog.set_level(logging.WARNING, logger="indreg")
    offset = indreg.register(template + 0.3, data, T, num_steps=5, max_iter=40, **PAPER)
    assert right.poor_fit == "" and offset.status == "completed" and not run.levelled_off(offset.history)
    assert offset.residual > 2 * offset.units.noise_residual + 0.1
    assert "still falling" in offset.poor_fit and "template_scale='fit+offset'" in offset.poor_fit
    assert [m for m in warnings_of(caplog) if "poor fit" in m] == [offset.poor_fit]


def test_poor_fit_counts_the_held_out_residual_and_needs_a_finished_run():
    """The larger of the fitted and the held-out residual counts; short, failed or stopped runs get no verdict."""
    levelled = [{"objective": 1.0}] * (run.STALL_WINDOW + 1)
    assert run.poor_fit("completed", 0.1, 0.02, levelled) == ""                       # 0.1 < 2 * 0.02 + 0.1
    held = run.poor_fit("completed", 0.1, 0.02, levelled, held_out=0.5)
    assert held.startswith("poor fit: the objective levelled off at a relative data residual on the held-out "
                           "angles 0.5, far above the 0.02")
    assert "residual 0.5," in run.poor_fit("early_stopped", 0.5, 0.02, levelled, held_out=0.3)
    assert run.poor_fit("stopped", 0.9, 0.02, levelled) == run.poor_fit("failed", 0.9, 0.02, levelled) == ""
    assert run.poor_fit("completed", 0.9, 0.02, levelled[:run.STALL_WINDOW]) == ""


def test_fit_intensity_solves_the_normal_equations():
    from indreg.registration.intensity import fit_intensity

    g0 = torch.Generator().manual_seed(0)
    P, Q = torch.rand(7, 9, generator=g0, dtype=torch.float64), torch.ones(7, 9, dtype=torch.float64)
    inner = lambda a, b: (a * b).sum(dim=(-2, -1))   # noqa: E731
    c, b = fit_intensity(P, Q, 2.5 * P - 0.7 * Q, inner)
    assert c == pytest.approx(2.5, rel=1e-12) and b == pytest.approx(-0.7, rel=1e-12)
    c, b = fit_intensity(P, None, 2.5 * P - 0.7 * Q, inner)   # no offset: the least-squares factor
    assert b == 0.0 and c == pytest.approx(float((P * (2.5 * P - 0.7)).sum() / (P * P).sum()), rel=1e-12)


def _limited_angle():
    domain = indreg.ImageDomain.paper(32)
    angles = torch.linspace(-math.pi / 3, math.pi / 3, 21, dtype=torch.float64)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=angles, det_count=46, det_min=-24, det_max=24))
    template = phantoms.get("shepp_logan_template", domain).double()
    target = phantoms.get("shepp_logan", domain).double()
    data, _ = indreg.noise.add_white_noise(T(target), snr_db=20, seed=0)
    return template, data, T, target


def test_template_scale_fit_is_the_same_in_any_units_and_close_to_the_template_in_the_data_units():
    """template_scale='fit' fits the factor with the deformation: a template in 0..255 gives the same run as one in
    the data's units, within 0.01 SSIM of the run that needs no factor at all."""
    template, data, T, target = _limited_angle()
    options = dict(sigma=2.0, num_steps=6, max_iter=60, target=target, interpolation="reinterpolate")
    ref = indreg.register(template, data, T, **options)
    fit = indreg.register(template, data, T, template_scale="fit", **options)
    grey = indreg.register(255 * template, data, T, template_scale="fit", **options)
    assert grey.units.template_scale == pytest.approx(fit.units.template_scale / 255, rel=1e-6)
    assert grey.ssim == pytest.approx(fit.ssim, abs=1e-6) and abs(fit.ssim - ref.ssim) < 0.01
    assert grey.units.template_offset == 0.0 and fit.history[-1]["template_scale"] == fit.units.template_scale


def test_template_scale_fit_with_offset_removes_a_constant():
    """A template offset by a constant: 'fit+offset' finds the offset and recovers most of the lost SSIM."""
    template, data, T, target = _limited_angle()
    options = dict(sigma=2.0, num_steps=6, max_iter=60, target=target)
    auto = indreg.register(template + 0.3, data, T, template_scale="auto", **options)
    fit = indreg.register(template + 0.3, data, T, template_scale="fit+offset", **options)
    assert fit.units.template_offset == pytest.approx(-0.3, abs=0.1)
    assert fit.ssim > auto.ssim + 0.1


def test_template_scale_fit_needs_lddmm_with_the_geometric_action():
    template, data, T, _ = _limited_angle()
    for options in ({"model": "metamorphosis"}, {"action": "mass_preserving"}):
        with pytest.raises(ValueError, match="template_scale must be None, 'auto' or a number with model") as e:
            indreg.register(template, data, T, template_scale="fit", max_iter=1, **options)
        assert "\n" not in str(e.value)


def test_ssim_at_255_is_scored_in_the_target_s_units():
    """A template at x255 (``template_scale="auto"``: 1 / 255) with its ground truth read like it (also x255): SSIM /
    PSNR score the reconstruction in the target's units and equal the x1 run's; a target in the data's units is
    scored as it is (the same numbers)."""
    template, data, T, target = tiny()
    x1 = indreg.register(template, data, T, target=target, **QUICK)
    like_template = indreg.register(255 * template, data, T, target=255 * target, template_scale="auto", **QUICK)
    like_data = indreg.register(255 * template, data, T, target=target, template_scale="auto", **QUICK)
    assert like_template.units.target_units == "template" and like_data.units.target_units == "data"
    for r in (like_template, like_data):
        assert r.ssim == pytest.approx(x1.ssim, abs=1e-6) and r.psnr == pytest.approx(x1.psnr, abs=1e-4)
    assert metrics.ssim(like_template.deformed, 255 * target) < x1.ssim - 0.1    # what was reported before
