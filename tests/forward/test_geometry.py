"""Geometries: angles (units, arrays), detector bins and extent, tilt series, quadrature cells, data weights
(ODL's), fan beam, validation."""
import math

import numpy as np
import pytest
import torch

from indreg import ImageDomain
from indreg.forward import FanBeamGeometry, ParallelBeamGeometry, RayTransform
from indreg.forward.geometry import midpoint_cells, parse_angles


def test_default_angles_and_detector():
    g = ParallelBeamGeometry(num_angles=4, det_count=5, det_min=-2.5, det_max=2.5)
    assert g.angles.dtype == torch.float64
    torch.testing.assert_close(g.angles, torch.tensor([0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4],
                                                      dtype=torch.float64))
    torch.testing.assert_close(g.det_points, torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0], dtype=torch.float64))
    assert g.det_cell == 1.0 and g.shape == (4, 5) and g.num_angles == 4
    assert g.angle_cell == pytest.approx(math.pi / 4)
    assert g.data_weight == pytest.approx(math.pi / 4)


def test_explicit_angles():
    g = ParallelBeamGeometry(angles=[0.1, 0.5, 2.0], det_count=3, det_min=0.0, det_max=3.0)
    assert g.num_angles == 3 and g.angle_cell == pytest.approx(math.pi / 3)
    torch.testing.assert_close(g.angles, torch.tensor([0.1, 0.5, 2.0], dtype=torch.float64))
    ParallelBeamGeometry(3, angles=torch.tensor([0.1, 0.5, 2.0]), det_count=2)   # consistent num_angles is fine


def test_paper_preset_matches_odl_partition():
    g = ParallelBeamGeometry.paper(num_angles=10, det_count=92)
    deg = g.angles * 180 / math.pi
    assert float(deg[1]) == pytest.approx(180 / 9.5) and float(deg[-1]) == pytest.approx(170.5263, abs=1e-4)
    assert (g.det_min, g.det_max) == (-24.0, 24.0)
    assert float(g.det_points[0]) == pytest.approx(-24 + 24 / 92)
    assert g.angle_cell == pytest.approx(math.pi / 10)


@pytest.mark.parametrize("n, bins, ratio", [(64, 92, 0.656), (256, 362, 2.67)])
def test_data_to_image_weight_ratio_from_paper_notes(n, bins, ratio):
    g = ParallelBeamGeometry.paper(num_angles=10, det_count=bins)
    assert g.data_weight / ImageDomain.paper(n).cell_volume == pytest.approx(ratio, abs=1e-3 * ratio * 2)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(num_angles=3, det_count=4, det_min=1.0, det_max=1.0), ValueError, "det_min must be < det_max"),
    (dict(num_angles=3, det_count=4, det_min=2.0, det_max=1.0), ValueError, "det_min must be < det_max"),
    (dict(num_angles=3, det_count=4, det_min=-math.inf, det_max=1.0), ValueError, "finite"),
    (dict(num_angles=0, det_count=4), ValueError, "num_angles"),
    (dict(angles=[], det_count=4), ValueError, "at least one angle"),
    (dict(angles=[0.0, math.nan], det_count=4), ValueError, "finite"),
    (dict(angles=[0.0, math.inf], det_count=4), ValueError, "finite"),
    (dict(num_angles=3, det_count=0), ValueError, "det_count"),
    (dict(num_angles=3, det_count=2.5), TypeError, "det_count"),
    (dict(num_angles=2, angles=[0.0, 1.0, 2.0], det_count=3), ValueError, "num_angles=2"),
    (dict(det_count=3), ValueError, "num_angles"),
    (dict(num_angles=3, det_count=3, angle_weights=[1.0, 1.0]), ValueError, "angle_weights must be 3 finite positive"),
    (dict(num_angles=2, det_count=3, angle_weights=[1.0, -1.0]), ValueError, "angle_weights"),
])
def test_invalid_geometry(kwargs, error, match):
    with pytest.raises(error, match=match):
        ParallelBeamGeometry(**kwargs)


def test_repr():
    assert "num_angles=10" in repr(ParallelBeamGeometry.paper(10, 92))


# --- angle units, angle arrays, detector extent, tilt series, quadrature cells, fan beam -----------------


def test_degree_like_angles_need_a_unit():
    with pytest.raises(ValueError, match="look like degrees.*angle_unit='deg'"):
        ParallelBeamGeometry(angles=[0.0, 30.0, 60.0], det_count=3)
    g = ParallelBeamGeometry(angles=[0.0, 30.0, 60.0], det_count=3, angle_unit="deg")
    torch.testing.assert_close(g.angles, torch.tensor([0.0, math.pi / 6, math.pi / 3], dtype=torch.float64))
    assert ParallelBeamGeometry(angles=[0.0, 7.0], det_count=3, angle_unit="rad").angles[1] == 7.0
    assert ParallelBeamGeometry(angles=[0.0, -2 * math.pi], det_count=3).num_angles == 2   # 2 pi itself is fine
    with pytest.raises(ValueError, match="angle_unit must be"):
        ParallelBeamGeometry(angles=[0.0], det_count=3, angle_unit="degrees")


@pytest.mark.parametrize("angles, error, match", [
    ([[0.0, 0.5], [1.0, 1.5]], ValueError, r"1D list/array, got shape \(2, 2\)"),
    (np.zeros((3, 1)), ValueError, r"1D list/array, got shape \(3, 1\)"),
    ([0.0, 1.0 + 0.5j], TypeError, "real numbers.*complex"),
    (torch.tensor([0.3 + 0.0j]), TypeError, "complex"),
    (["0", "1"], TypeError, "real numbers"),
    ([True, False], TypeError, "boolean"),
])
def test_angle_arrays_are_not_flattened_or_truncated(angles, error, match):
    with pytest.raises(error, match=match):
        parse_angles(angles, None)
    with pytest.raises(error, match=match):
        FanBeamGeometry(angles=angles, det_count=3, src_radius=10.0)


def test_explicit_angles_keep_float64_values():
    g = ParallelBeamGeometry(angles=[0.1, 0.7], det_count=2, det_min=-1.0, det_max=1.0)
    assert float(g.angles[0]) == 0.1 and g.angles.dtype == torch.float64
    assert ParallelBeamGeometry(angles=0.3, det_count=2).num_angles == 1           # a scalar is one angle


def test_detector_extent_defaults_to_the_domain():
    g = ParallelBeamGeometry(10, 92)
    assert not g.is_resolved
    with pytest.raises(ValueError, match="no detector extent.*resolve"):
        g.det_cell
    T = RayTransform(ImageDomain.paper(32), g)
    assert (T.geometry.det_min, T.geometry.det_max) == pytest.approx((-16 * math.sqrt(2), 16 * math.sqrt(2)))
    assert g.det_min is None and T.geometry is not g                 # the user's geometry is not changed
    off = ImageDomain((8, 8), (0.0, -1.0), (4.0, 3.0))               # farthest corner (4, 3): radius 5
    assert ParallelBeamGeometry(3, 5).resolve(off).det_max == pytest.approx(5.0)
    fixed = ParallelBeamGeometry(3, 5, -2.0, 2.0)
    assert fixed.resolve(off) is fixed
    with pytest.raises(ValueError, match="both det_min and det_max, or neither"):
        ParallelBeamGeometry(3, 5, det_min=-1.0)


def test_tilt_series():
    g = ParallelBeamGeometry.tilt_series(-60, 60, 2, det_count=64)
    assert g.num_angles == 61
    torch.testing.assert_close(g.angles[[0, 30, 60]] * 180 / math.pi,
                               torch.tensor([-60.0, 0.0, 60.0], dtype=torch.float64))
    torch.testing.assert_close(g.angle_weights, torch.full((61,), math.radians(2), dtype=torch.float64))
    assert g.angle_cell == pytest.approx(math.pi / 61)             # the data weight is unchanged (ODL's)
    with pytest.raises(ValueError, match="not a multiple of step_deg"):
        ParallelBeamGeometry.tilt_series(-60, 61, 2, det_count=8)
    with pytest.raises(ValueError, match="less than 180 degrees"):
        ParallelBeamGeometry.tilt_series(-90, 90, 1, det_count=8)
    with pytest.raises(ValueError, match="step_deg"):
        ParallelBeamGeometry.tilt_series(-60, 60, 0, det_count=8)


def test_midpoint_cells():
    n = 12
    uniform = torch.arange(n, dtype=torch.float64) * math.pi / n
    torch.testing.assert_close(midpoint_cells(uniform, math.pi), torch.full((n,), math.pi / n, dtype=torch.float64))
    # the paper's angles k pi / (n - 1/2): the wrap gap is half a step, so the end cells get 3/4 of a step
    step = math.pi / (n - 0.5)
    cells = midpoint_cells(torch.arange(n, dtype=torch.float64) * step, math.pi)
    assert float(cells[0]) == pytest.approx(0.75 * step) and float(cells[5]) == pytest.approx(step)
    assert float(cells.sum()) == pytest.approx(math.pi)
    # non-uniform, unsorted: sorted 0, 0.2, 0.6, 1.0 -> 0.1+0.1, 0.1+0.2, 0.2+0.2, 0.2+0.2
    torch.testing.assert_close(midpoint_cells(torch.tensor([0.6, 0.0, 1.0, 0.2], dtype=torch.float64), math.pi),
                               torch.tensor([0.4, 0.2, 0.4, 0.3], dtype=torch.float64))
    # a full turn measured by a parallel beam covers every line twice: pi / n each
    full = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    torch.testing.assert_close(midpoint_cells(full, math.pi), torch.full((n,), math.pi / n, dtype=torch.float64))
    assert ParallelBeamGeometry.paper(10, 92).angle_weights.eq(math.pi / 10).all()   # the authors' weights


def test_fan_beam_geometry():
    g = FanBeamGeometry(8, 10, src_radius=30.0, det_radius=10.0, det_min=-20.0, det_max=20.0)
    torch.testing.assert_close(g.angles, torch.arange(8, dtype=torch.float64) * math.pi / 4)
    assert g.magnification == pytest.approx(4 / 3) and g.det_cell == 4.0
    assert g.angle_cell == pytest.approx(math.pi / 4) and g.data_weight == pytest.approx(math.pi)
    torch.testing.assert_close(g.angle_weights, torch.full((8,), math.pi / 4, dtype=torch.float64))
    # default detector: the fan through the farthest corner (radius 16 sqrt 2) of the domain
    r = 16 * math.sqrt(2)
    fitted = FanBeamGeometry(8, 10, src_radius=30.0, det_radius=10.0).resolve(ImageDomain.paper(16))
    assert fitted.det_max == pytest.approx(40 * r / math.sqrt(30 ** 2 - r ** 2))
    assert "src_radius=30.0" in repr(g)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(num_angles=4, det_count=3), ValueError, "src_radius.*required"),
    (dict(num_angles=4, det_count=3, src_radius=-1.0), ValueError, "src_radius"),
    (dict(num_angles=4, det_count=3, src_radius=10.0, det_radius=-1.0), ValueError, "det_radius"),
    (dict(num_angles=4, det_count=3, src_radius=10.0, det_radius=math.nan), ValueError, "det_radius"),
    (dict(angles=[0.0, 400.0], det_count=3, src_radius=10.0), ValueError, "look like degrees"),
    (dict(num_angles=4, det_count=3, src_radius=10.0, det_min=2.0, det_max=1.0), ValueError, "det_min must be <"),
])
def test_invalid_fan_beam_geometry(kwargs, error, match):
    with pytest.raises(error, match=match):
        FanBeamGeometry(**kwargs)


def test_fan_source_inside_the_domain_is_rejected():
    with pytest.raises(ValueError, match="src_radius=20.0 must exceed the domain radius 22.6"):
        RayTransform(ImageDomain.paper(16), FanBeamGeometry(8, 10, src_radius=20.0))
    with pytest.raises(ValueError, match="src_radius=20.0 must exceed"):
        RayTransform(ImageDomain.paper(16), FanBeamGeometry(8, 10, src_radius=20.0, det_min=-30.0, det_max=30.0))


def test_scalar_parameters_refuse_str_bool_and_complex():
    # float() took "1" and True; the detector extent, fan distances and tilt range go through _checks now
    for kwargs, error, match in (
            (dict(det_min="-1", det_max=1.0), TypeError, "^det_min must be a finite number, got '-1'"),
            (dict(det_min=-1.0, det_max=True), TypeError, "^det_max must be a finite number, got True"),
            (dict(det_min=-1.0, det_max=1 + 0j), TypeError, r"^det_max must be a finite number, got \(1\+0j\)"),
            (dict(det_min=-1.0, det_max=math.inf), ValueError, "^det_max must be a finite number, got inf"),
            (dict(angle_weights=[1.0 + 0j] * 3), TypeError, "^angle_weights must be real numbers, got dtype "
                                                             "torch.complex"),
            (dict(angle_weights=[True] * 3), TypeError, "^angle_weights must be real numbers, got dtype torch.bool"),
            (dict(angle_weights=["1"] * 3), TypeError, "^angle_weights must be 3 finite positive numbers, got list")):
        with pytest.raises(error, match=match):
            ParallelBeamGeometry(3, 4, **kwargs)
    for bad, error in (("5", TypeError), (True, TypeError), (math.inf, ValueError)):
        with pytest.raises(error, match="^det_radius must be a finite number >= 0, got "):
            FanBeamGeometry(4, 3, src_radius=10.0, det_radius=bad)
    with pytest.raises(TypeError, match="^src_radius must be a positive number, got '10'"):
        FanBeamGeometry(4, 3, src_radius="10")
    with pytest.raises(TypeError, match="^min_deg must be a finite number, got '-60'"):
        ParallelBeamGeometry.tilt_series("-60", 60, 2, det_count=8)
    with pytest.raises(ValueError, match=r"^step_deg = 1e-320 is too small for \[-60.0, 60.0\]"):
        ParallelBeamGeometry.tilt_series(-60, 60, 1e-320, det_count=8)
    with pytest.raises(TypeError, match="^num_angles must be an integer >= 1, got True"):
        ParallelBeamGeometry(True, 4)
    g = ParallelBeamGeometry(np.int64(3), 4, np.float32(-1), torch.tensor(1.0))  # numpy / torch scalars are fine
    assert (g.num_angles, g.det_min, g.det_max) == (3, -1.0, 1.0)
