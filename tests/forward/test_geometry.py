"""ParallelBeamGeometry: angles, detector bins, data weights (ODL's), validation."""
import math

import pytest
import torch

from indreg import ImageDomain
from indreg.forward import ParallelBeamGeometry


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
])
def test_invalid_geometry(kwargs, error, match):
    with pytest.raises(error, match=match):
        ParallelBeamGeometry(**kwargs)


def test_repr():
    assert "num_angles=10" in repr(ParallelBeamGeometry.paper(10, 92))
