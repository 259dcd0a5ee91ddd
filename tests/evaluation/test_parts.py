"""The split of a volume into the part the data determine and the part the prior fills (indreg.evaluation.parts)."""
import math

import pytest
import torch

import indreg
from indreg.evaluation.parts import data_split, wedge_mask, wedge_split
from indreg.alignment.operator import AlignedOperator


def _packet(domain, direction_deg: float, cycles: float = 6.0, width: float = 3.0) -> torch.Tensor:
    """A Gaussian wave packet: a plane wave of ``cycles`` per box along ``direction_deg`` (its wave vector), under a
    Gaussian of ``width``: its Fourier transform is concentrated around that wave vector (and its negative)."""
    x, y = domain.points(torch.float64).unbind(0) if domain.points(torch.float64).shape[0] == 2 else \
        domain.points(torch.float64).unbind(-1)
    k = 2 * math.pi * cycles / domain.extent[0]
    a = math.radians(direction_deg)
    return torch.exp(-(x ** 2 + y ** 2) / (2 * width ** 2)) * torch.cos(k * (math.cos(a) * x + math.sin(a) * y))


@pytest.fixture(scope="module")
def wedge():
    """A 2D parallel tilt series -40..40 degrees in 2-degree steps on 48^2 cells of [-12, 12]^2."""
    d = indreg.ImageDomain((48, 48), (-12.0, -12.0), (12.0, 12.0))
    return d, indreg.RayTransform(d, indreg.ParallelBeamGeometry.tilt_series(-40, 40, 2, 68))


def test_the_range_split_sums_to_the_volume_and_its_prior_part_projects_to_zero(wedge):
    """8 tilts (a large null space): the prior part projects to at most tol of the volume's projections and is
    orthogonal to the data part (the range of T^* and T's null space)."""
    d, _ = wedge
    T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.tilt_series(-40, 40, 10, 68))
    f = torch.rand(d.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    s = data_split(f, T, tol=1e-3)
    assert torch.allclose(s.data + s.prior, f, atol=1e-12)
    Tf, Tp = T(f), T(s.prior)
    assert s.projection_difference <= 1e-3 and 0.3 < s.prior_fraction < 0.6
    assert math.sqrt(float(T.inner_data(Tp, Tp))) <= 1.01e-3 * math.sqrt(float(T.inner_data(Tf, Tf)))
    assert abs(float(d.inner(s.data, s.prior))) < 1e-3 * float(d.norm(f)) ** 2   # orthogonal


def test_a_packet_in_the_missing_wedge_is_prior_filled_and_one_in_the_wedge_is_data(wedge):
    """The analytic case: a packet whose wave vector lies at 90 degrees (the missing wedge of -40..40) goes to the
    prior-filled part by both splits and projects to almost nothing on the tilts; one at 10 degrees (measured) is
    data-determined by both."""
    d, T = wedge
    missing, measured = _packet(d, 90.0), _packet(d, 10.0)
    for split in (lambda f: wedge_split(f, T), lambda f: data_split(f, T, tol=1e-2, max_iter=30)):
        m, k = split(missing), split(measured)
        assert m.prior_fraction > 0.97 and k.prior_fraction < 0.1
        assert torch.allclose(m.data + m.prior, missing, atol=1e-12)
    Tm, Tk = T(missing), T(measured)
    assert float(Tm.norm()) < 0.01 * float(Tk.norm())   # the missing wedge is invisible in the data


def test_the_wedge_mask_covers_the_tilt_range_and_everything_for_a_half_turn():
    m = wedge_mask((64, 64), (1.0, 1.0), torch.deg2rad(torch.arange(-60.0, 61.0, 2.0)))
    assert bool(m[0, 0])                                   # the zero frequency
    assert bool(m[5, 0]) and bool(m[5, 2]) and not bool(m[0, 5])   # along u (tilt 0) measured, along v missing
    assert abs(float(m.double().mean()) - 0.7229) < 0.01   # |angle| <= 61 deg of a square: 1 - cot(61) / 2 = 0.7229
    full = wedge_mask((16, 16), (1.0, 1.0), torch.linspace(0, math.pi, 30, dtype=torch.float64)[:-1])
    assert bool(full.all())


def test_a_tilt_series_through_an_alignment_splits_slice_by_slice():
    d = indreg.ImageDomain((16, 6, 12), (-8.0, -3.0, -6.0), (8.0, 3.0, 6.0))
    T = indreg.TiltSeriesTransform(d, indreg.TiltSeriesGeometry.uniform(-50, 50, 10, det_count=18, det_min=-9.0,
                                                                      det_max=9.0))
    gen = torch.Generator().manual_seed(1)
    A = AlignedOperator(T, 0.5 * torch.randn(11, 2, generator=gen, dtype=torch.float64), 0.01)
    f = torch.rand(d.shape, generator=gen, dtype=torch.float64)
    s = data_split(f, indreg.restrict(A, [0, 2, 4, 6, 8, 10]), tol=1e-3)
    assert s.projection_difference <= 1e-3 and 0.2 < s.prior_fraction < 1
    w = wedge_split(f, A)   # the wedge of the aligned tilts: the same angles
    assert torch.allclose(w.data + w.prior, f, atol=1e-12) and 0.05 < w.prior_fraction < 0.6


def test_bad_inputs_are_one_line_errors(wedge):
    d, T = wedge
    with pytest.raises(ValueError, match="volume"):
        data_split(torch.zeros(8, 8, dtype=torch.float64), T)
    with pytest.raises(ValueError, match="tol"):
        data_split(torch.zeros(d.shape, dtype=torch.float64), T, tol=0.0)
    fan = indreg.RayTransform(d, indreg.FanBeamGeometry(det_count=40, src_radius=40.0, det_radius=20.0,
                                                        det_min=-30.0, det_max=30.0,
                                                        angles=torch.linspace(0, 6.0, 20, dtype=torch.float64),
                                                        angle_unit="rad"))
    with pytest.raises(TypeError, match="parallel-beam"):
        wedge_split(torch.zeros(d.shape, dtype=torch.float64), fan)
    assert data_split(torch.zeros(d.shape, dtype=torch.float64), fan).iterations == 0   # any operator
