"""RestrictedOperator: an operator restricted to some rows (angles, tilts) of its range."""
import pytest
import torch

from indreg import ImageDomain, phantoms
from indreg.forward import ParallelBeamGeometry, RayTransform, TiltSeriesGeometry, TiltSeriesTransform, adjointness
from indreg.forward.stacking import RestrictedOperator
from indreg.forward.operator import check_operator

DOM = ImageDomain.paper(16)
ANGLES = torch.linspace(0.0, 3.0, 12, dtype=torch.float64)
ROWS = [0, 2, 3, 7, 11]


def ray(angles):
    return RayTransform(DOM, ParallelBeamGeometry(angles=angles, det_count=23, det_min=-20.0, det_max=20.0,
                                                  angle_unit="rad"))


def test_is_the_operator_of_the_kept_angles():
    """Forward, adjoint and data inner product equal the ray transform built with only those angles."""
    S, R = RestrictedOperator(ray(ANGLES), ROWS), ray(ANGLES[ROWS])
    assert S.range_shape == R.range_shape == (5, 23)
    f = phantoms.get("shepp_logan", DOM).expand(2, *DOM.shape)            # a batch
    y = torch.randn(2, *R.range_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(S(f), R(f), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(S.adjoint(y), R.adjoint(y), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(S.inner_data(y, S(f)), R.inner_data(y, R(f)), rtol=1e-12, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_adjoint_by_the_inner_product_identity(dtype):
    tilt = TiltSeriesTransform(ImageDomain((8, 6, 7)), TiltSeriesGeometry.uniform(-60, 60, 20, det_count=11))
    for op, rows in ((ray(ANGLES), ROWS), (tilt, [1, 4, 6])):
        S = RestrictedOperator(op, rows)
        check_operator(S)
        assert adjointness(S, dtype=dtype) < (1e-14 if dtype == torch.float64 else 1e-6)


def test_gradient_through_the_restriction():
    S = RestrictedOperator(ray(ANGLES), ROWS)
    f = phantoms.get("j", DOM).requires_grad_()
    y = torch.randn(S.range_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    (0.5 * S.inner_data(S(f) - y, S(f) - y)).backward()
    # d/df 0.5 <S f - y, S f - y> = S^*(S f - y) in the weighted inner products (grad = cell_volume * gradient)
    expected = S.adjoint(S(f.detach()) - y) * DOM.cell_volume
    torch.testing.assert_close(f.grad, expected, rtol=1e-10, atol=1e-12)


def test_on_domain_keeps_the_rows():
    tilt = TiltSeriesTransform(ImageDomain((8, 6, 8)), TiltSeriesGeometry.uniform(-60, 60, 20, det_count=11))
    S = RestrictedOperator(tilt, [0, 3])
    coarse = S.on_domain(ImageDomain((4, 3, 4), tilt.domain.min_pt, tilt.domain.max_pt))
    assert coarse.range_shape == (2, 3, 11) and coarse.rows.tolist() == [0, 3]

    class Plain:   # an operator without on_domain
        domain, range_shape = DOM, (3, 4)

        def __call__(self, f):
            return f[..., :3, :4]

        adjoint = inner_data = __call__

    assert RestrictedOperator(Plain(), [1]).on_domain is None


@pytest.mark.parametrize("rows", [[], [0, 12], [-1], [3, 3], [4, 2]])
def test_bad_rows_one_line(rows):
    with pytest.raises(ValueError, match=r"^rows must be strictly increasing indices in \[0, 12\)"):
        RestrictedOperator(ray(ANGLES), rows)
