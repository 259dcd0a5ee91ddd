"""The orientation probe before a run (indreg.io.orientation): each wrong reading of a 2D and a 3D problem is named
(warned or refused, with its fix), its right reading is silent; orientation='warn' runs anyway, 'off' skips it."""
import logging

import numpy as np
import pytest
import torch

import indreg
from indreg import phantoms
from indreg.io import orientation


def problem_2d():
    """A 48^2 template (suite 3's, plus an off-centre disc: no mirror symmetry) and the noise-free data of its
    target over 0..180 degrees."""
    domain = indreg.ImageDomain.paper(48)
    x, y = domain.points()
    disc = 0.6 * ((x - 7) ** 2 + (y - 4) ** 2 < 9).double()
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(num_angles=24, det_count=68))
    template = phantoms.get("shepp_logan_template", domain) + disc
    return template, T(phantoms.get("shepp_logan", domain) + disc), T


def problem_3d():
    """A 24^3 Shepp-Logan with an off-centre ball (no mirror symmetry), its swirled target's tilt series (-60..60
    degrees in 6-degree steps)."""
    domain = indreg.ImageDomain.paper(24, ndim=3)
    x, y, z = domain.points()
    ball = 1.5 * ((x - 6) ** 2 + (y + 5) ** 2 + (z - 8) ** 2 < 16).double()
    T = indreg.TiltSeriesTransform(domain, indreg.TiltSeriesGeometry.uniform(-60, 60, 6, 24, -16.0, 16.0))
    return (phantoms.get("shepp_logan_3d", domain) + ball,
            T(phantoms.get("shepp_logan_3d_swirl", domain) + ball), T)


WRONG_2D = {"the detector reversed": lambda g: g.flip(-1),
            "the angles in the opposite sense": lambda g: None}
WRONG_3D = {"the stack turned by 180 degrees": lambda g: g.flip(-1, -2),
            "the detector reversed": lambda g: g.flip(-1)}


def test_right_readings_are_silent(caplog):
    for template, data, T in (problem_2d(), problem_3d()):
        with caplog.at_level(logging.WARNING, logger="indreg"):
            assert orientation.check(template, data, T) == ""
        table = {k: v for k, (v, _) in orientation.scores(template, data, T).items()}
        assert caplog.text == "" and max(table.values()) - table["as given"] <= orientation.WARN


def test_reversed_detector_2d_is_refused_naming_the_fix():
    template, data, T = problem_2d()
    with pytest.raises(ValueError, match=r"reverse the detector bins.*\(or orientation='warn' to run anyway\)$"):
        orientation.check(template, data.flip(-1), T)


def test_opposite_angles_2d_names_imod(caplog):
    """Data of the angles -theta given with theta (IMOD's sense read as indreg's)."""
    template, _, T = problem_2d()
    domain = T.domain
    angles = T.geometry.angles
    T_neg = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=-angles, det_count=68))
    data = T_neg(phantoms.get("shepp_logan", domain) + (template - phantoms.get("shepp_logan_template", domain)))
    level, message = orientation.verdict(orientation.scores(template, data, T))
    assert level == "refuse" and "the angles in the opposite sense" in message.split(" at ")[1]
    assert "convention=imod" in message and "\n" not in message
    with caplog.at_level(logging.WARNING, logger="indreg"):
        orientation.check(template, data, T, mode="warn")
    assert "the data were probably read wrongly" in caplog.text


@pytest.mark.parametrize("wrong", list(WRONG_3D))
def test_wrong_3d_readings_are_named(wrong, caplog):
    template, data, T = problem_3d()
    table = orientation.scores(template, WRONG_3D[wrong](data), T)
    level, message = orientation.verdict(table)
    assert level in ("warn", "refuse") and wrong in message.split(" at ")[1].split(" (")[0]


def test_register_runs_the_probe_and_its_modes(caplog):
    template, data, T = problem_2d()
    with pytest.raises(ValueError, match="reverse the detector bins"):
        indreg.register(template, data.flip(-1), T, max_iter=1, num_steps=2)
    with caplog.at_level(logging.WARNING, logger="indreg"):
        r = indreg.register(template, data.flip(-1), T, max_iter=1, num_steps=2, orientation="warn")
    assert r.iterations == 1 and "reverse the detector bins" in caplog.text
    assert r.poor_fit.startswith("poor fit: the run fitted data that were probably read wrongly")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="indreg"):
        indreg.register(template, data.flip(-1), T, max_iter=1, num_steps=2, orientation="off")
    assert "read wrongly" not in caplog.text
    with pytest.raises(ValueError, match="orientation"):
        indreg.register(template, data, T, max_iter=1, orientation="sometimes")


def test_unrelated_template_says_nothing():
    """A template that fits no reading (random) is left to the poor-fit warning: no verdict."""
    _, data, T = problem_2d()
    noise = torch.from_numpy(np.random.default_rng(0).uniform(size=T.domain.shape))
    assert orientation.verdict(orientation.scores(noise, data, T))[0] == ""


def test_template_turned_2d_names_the_convention():
    """A template stored as displayed (ASTRA's, scikit-image's) read as indreg's: the turned reading is named with
    convention=astra; stored as an MRC section: transposed, convention=imod."""
    template, data, T = problem_2d()
    for stored, fix in ((template.rot90(1, (0, 1)), "data.convention=astra"), (template.T, "data.convention=imod")):
        level, message = orientation.verdict(orientation.scores(stored, data, T))
        assert level in ("warn", "refuse") and fix in message


def test_imod_sense_3d_names_imod():
    """A tilt series in IMOD's sense of rotation read as indreg's: the probe names the opposite sense and
    data.convention=imod."""
    template, _, T = problem_3d()
    x, y, z = T.domain.points()
    target = phantoms.get("shepp_logan_3d_swirl", T.domain) + 1.5 * ((x - 6) ** 2 + (y + 5) ** 2 + (z - 8) ** 2 < 16)
    T_imod = indreg.TiltSeriesTransform(T.domain, indreg.TiltSeriesGeometry(-T.geometry.angles, 24, -16.0, 16.0,
                                                                             angle_unit="rad"))
    level, message = orientation.verdict(orientation.scores(template, T_imod(target.double()), T))
    assert level in ("warn", "refuse") and "the angles in the opposite sense" in message.split(" at ")[1]
    assert "data.convention=imod" in message


def test_poor_fit_repeats_the_probe():
    """A finished run after a probe warning is a poor fit whatever its residual; a failed one is not."""
    from indreg.registration.run import poor_fit

    assert poor_fit("completed", 0.01, 0.01, [], None, "read as X").startswith(
        "poor fit: the run fitted data that were probably read wrongly (read as X)")
    assert poor_fit("failed", 0.01, 0.01, [], None, "read as X") == ""
    assert poor_fit("completed", 0.01, 0.01, [], None, "") == ""


def test_a_long_tilt_axis_is_probed_on_fewer_slices():
    """A tilt series of 80 slices along its axis is probed on 32 (the sub-problem is the problem's rows exactly,
    symmetric about the middle), and still names a turned stack."""
    domain = indreg.ImageDomain((16, 80, 16), (-16.0, -80.0, -16.0), (16.0, 80.0, 16.0))
    T = indreg.TiltSeriesTransform(domain, indreg.TiltSeriesGeometry.uniform(-60, 60, 10, 16, -16.0, 16.0))
    f = torch.from_numpy(np.random.default_rng(3).uniform(size=domain.shape))
    small_f, small_g, small_T = orientation._fewer_slices(f, T(f), T)
    assert small_f.shape[1] == small_g.shape[-2] == orientation.SLICES
    torch.testing.assert_close(small_T(small_f), small_g, rtol=1e-10, atol=1e-10)
    x, y, z = domain.points()
    f = (x ** 2 / 100 + (y - 30) ** 2 / 900 + z ** 2 / 64 < 1).double() + ((x - 5) ** 2 + (y + 40) ** 2 < 30).double()
    assert orientation.verdict(orientation.scores(f, T(f).flip(-1, -2), T))[0] in ("warn", "refuse")
    assert orientation.verdict(orientation.scores(f, T(f), T))[0] == ""


def test_a_target_in_another_layout_than_the_data_is_named():
    """The own-data example read with ``convention="astra"``: the picture is read as displayed in every
    convention, the arrays (sinogram, target) in ASTRA's, so the target comes out turned by 90 degrees against
    the data; the template fits, the probe is silent, and only the target's check names it (the SSIM against the
    turned target would score a right reconstruction 0.49 instead of 0.89)."""
    import logging
    from pathlib import Path

    import indreg
    from indreg.io.orientation import target_hint

    d = Path(indreg.__file__).parent / "data"
    kw = dict(angles=str(d / "own_data_angles.tlt"), target=str(d / "own_data_target.npy"), half_width=16.0,
              det_min=-24.0, det_max=24.0, integer_scale="raw")
    right = indreg.load(str(d / "own_data_template.png"), str(d / "own_data_sinogram.npy"), "parallel", **kw)
    assert target_hint(right.target, right.data, right.operator) == ""
    records = []
    handler = logging.Handler()
    handler.emit = records.append
    logging.getLogger("indreg").addHandler(handler)
    try:
        wrong = indreg.load(str(d / "own_data_template.png"), str(d / "own_data_sinogram.npy"), "parallel",
                            convention="astra", **kw)
    finally:
        logging.getLogger("indreg").removeHandler(handler)
    hint = target_hint(wrong.target, wrong.data, wrong.operator)
    assert "turned by +90 degrees" in hint and "at 0.19 as read" in hint
    assert any("own_data_target.npy: the target's projection" in r.getMessage() for r in records)


def test_a_reading_must_remove_a_fifth_of_the_misfit_and_beat_the_sampling_error():
    """The measured false warnings (J against V: 0.366 as given, 0.418 for a wrong reading, at 48 px) say nothing now;
    the documented catches (ASTRA's layout 0.533 -> 0.663, a 3D stack turned by 180 degrees 0.668 -> 0.794) still
    warn; a margin within the sampling error of few gradient values says nothing."""
    from indreg.io import orientation

    def table(own, best, samples=1e6):
        r = orientation.Reading("x", None, None, "fix it")
        t = orientation.Table({"as given": (own, r), "the detector reversed": (best, r)})
        t.samples = samples
        return orientation.verdict(t)[0]

    assert table(0.366, 0.418) == "" and table(0.618, 0.671) == ""
    assert table(0.533, 0.663) == "warn" and table(0.668, 0.794) == "warn" and table(0.716, 0.971) == "refuse"
    assert table(0.85, 0.95, samples=50) == "" and table(0.85, 0.95, samples=1e4) == "warn"
    assert orientation.margin_needed(orientation.Table({"as given": (0.9, None)})) == orientation.WARN
