"""Which volume to trust beyond the measured range (indreg.registration.extrapolation): the edge split, the choice."""
import numpy as np
import pytest
import torch

import indreg
from indreg import phantoms
from indreg.registration.extrapolation import edge_split, register_extrapolating, row_angles


def test_the_edges_of_a_tilt_range_and_of_a_range_through_zero():
    deg = np.arange(-40.0, 41.0, 5.0)                         # 17 tilts
    inner, edge = edge_split(deg, fraction=0.25)
    assert edge == [0, 1, 2, 14, 15, 16] and inner == list(range(3, 14))
    full_turn = np.array([330.0, 340.0, 350.0, 0.0, 10.0, 20.0, 30.0])   # a fan beam's range through 0
    inner, edge = edge_split(full_turn, fraction=0.2)
    assert edge == [0, 6] and inner == [1, 2, 3, 4, 5]
    assert edge_split(deg, rows=[0, 4, 8, 12, 16], fraction=0.1)[1] == [0, 16]   # the outermost of the rows
    with pytest.raises(ValueError, match="at least 4"):
        edge_split(deg, rows=[1, 2, 3])
    with pytest.raises(ValueError, match="edge_fraction"):
        edge_split(deg, fraction=1.0)


def _case(right: bool):
    d = indreg.ImageDomain.paper(24)
    deg = np.arange(-45.0, 46.0, 5.0)
    T = indreg.RayTransform(d, indreg.ParallelBeamGeometry(det_count=34, angles=torch.tensor(deg), angle_unit="deg"))
    truth = phantoms.get("v", d).double()
    template = truth.clone() if right else phantoms.get("j", d).double()
    g = T(truth) + 0.02 * float(T(truth).abs().max()) * torch.randn(T.range_shape,
                                                                      generator=torch.Generator().manual_seed(0),
                                                                      dtype=torch.float64)
    return template, g, T


@pytest.mark.parametrize("right", [True, False])
def test_the_choice_keeps_a_right_template_and_deforms_a_wrong_one(right):
    template, g, T = _case(right)
    assert np.allclose(row_angles(T), np.arange(-45.0, 46.0, 5.0))
    r = register_extrapolating(template, g, T, models=("lddmm",), alphas=(0.0, 1.0), sigma=3.0, max_iter=20,
                               uncertainty=False)
    e = r.extrapolation
    res = e["extrapolation_edge_residuals"]
    assert e["extrapolation_edge_rows"] == [0, 1, 2, 16, 17, 18]
    assert set(res) == {"template", "lddmm"} and set(res["lddmm"]) == {"0.0", "1.0"}
    best = min([res["template"], *res["lddmm"].values()])
    if right:
        assert e["extrapolation_choice"] == "template" and r.iterations == 0
        assert torch.allclose(r.deformed, template, atol=1e-6)
    else:
        assert e["extrapolation_choice"] == "lddmm" and res["lddmm"][str(e["extrapolation_alpha"])] == best
        assert best < 0.8 * res["template"] and r.iterations == 20


@pytest.mark.slow
def test_register_takes_the_option():
    """Both models tried, a residual model's own option kept from the LDDMM runs, the run's held-out rows left out
    of the trials and kept in the final run."""
    template, g, T = _case(False)
    r = indreg.register(template, g, T, extrapolation=True, sigma=3.0, max_iter=5, holdout=[3, 9, 15],
                        residual_finish_iter=10, uncertainty=False)
    assert r.extrapolation["extrapolation_choice"] in ("template", "lddmm", "residual")
    assert 3 not in r.extrapolation["extrapolation_edge_rows"] and r.holdout["holdout_indices"] == [3, 9, 15]


def test_a_subset_of_angles_is_an_operator_alignment_can_wrap():
    from indreg.registration.extrapolation import subset

    d = indreg.ImageDomain((8, 6, 8))
    T = indreg.TiltSeriesTransform(d, indreg.TiltSeriesGeometry.uniform(-60, 60, 10, det_count=10))
    f = torch.rand(d.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert type(subset(T, [1, 3, 5])) is type(T) and torch.allclose(subset(T, [1, 3, 5])(f), T(f)[[1, 3, 5]])
    d2 = indreg.ImageDomain.paper(16)
    g = torch.rand(d2.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    for geometry in (indreg.ParallelBeamGeometry.paper(10, 20),
                     indreg.FanBeamGeometry(det_count=30, src_radius=40.0, det_radius=20.0, det_min=-30.0,
                                            det_max=30.0, angles=torch.linspace(0, 6, 12, dtype=torch.float64),
                                            angle_unit="rad")):
        R = indreg.RayTransform(d2, geometry)
        assert torch.allclose(subset(R, [0, 4, 7])(g), R(g)[[0, 4, 7]])
