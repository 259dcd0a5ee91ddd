"""The LinearOperator protocol: check_operator, adjointness, operator_norm on user objects and RayTransforms."""
import math

import pytest
import torch

from indreg import ImageDomain
from indreg.forward import (FanBeamGeometry, LinearOperator, ParallelBeamGeometry, RayTransform, adjointness,
                            check_operator)
from indreg.forward.operator import norm_data, operator_norm

DOM = ImageDomain((6, 4), (-3.0, -2.0), (3.0, 2.0))


class Scaling:
    """``T f = c f`` with data weight ``w``: ``w c sum f y = cell_volume sum f T^*y`` gives
    ``T^* y = (c w / cell_volume) y``; ``adjoint_factor`` builds a wrong adjoint on purpose."""

    def __init__(self, c=2.0, weight=0.5, adjoint_factor=None):
        self.domain, self.range_shape, self.c, self.weight = DOM, DOM.shape, c, weight
        self.factor = c * weight / DOM.cell_volume if adjoint_factor is None else adjoint_factor

    def __call__(self, f):
        return self.c * f

    def adjoint(self, y):
        return self.factor * y

    def inner_data(self, y1, y2):
        return self.weight * (y1 * y2).sum(dim=(-2, -1))


def test_user_object_is_an_operator():
    op = Scaling()
    assert isinstance(op, LinearOperator) and check_operator(op) is op
    assert adjointness(op) < 1e-15
    assert adjointness(Scaling(adjoint_factor=3.0)) > 0.1           # a wrong adjoint is caught
    # ||T|| = c sqrt(weight / cell_volume) for this weighted scaling
    assert operator_norm(op, num_iter=3) == pytest.approx(2.0 * math.sqrt(0.5 / DOM.cell_volume), rel=1e-12)
    y = torch.ones(2, *DOM.shape, dtype=torch.float64)
    torch.testing.assert_close(norm_data(op, y), torch.full((2,), math.sqrt(0.5 * 24), dtype=torch.float64))


def test_check_operator_names_missing_members():
    class NoAdjoint:
        domain, range_shape = DOM, (3,)

        def __call__(self, f):
            return f

        def inner_data(self, a, b):
            return (a * b).sum(-1)

    with pytest.raises(TypeError, match=r"^operator must be .*; NoAdjoint lacks adjoint$"):
        check_operator(NoAdjoint())
    with pytest.raises(TypeError, match="T must be .*int lacks domain, range_shape, __call__, adjoint, inner_data"):
        check_operator(3, "T")
    bad = Scaling()
    bad.domain = (6, 4)
    with pytest.raises(TypeError, match="T.domain must be an ImageDomain, got tuple"):
        check_operator(bad, "T")
    assert not isinstance(NoAdjoint(), LinearOperator)


@pytest.mark.parametrize("geometry", [ParallelBeamGeometry(7, 11), FanBeamGeometry(9, 13, src_radius=12.0)])
def test_ray_transforms_follow_the_protocol(geometry):
    T = RayTransform(DOM, geometry)
    assert isinstance(T, LinearOperator) and check_operator(T) is T
    assert adjointness(T) < 1e-14
    assert T.operator_norm(num_iter=30) == operator_norm(T, num_iter=30)


def test_inner_data_checks_both_arguments_against_the_range():
    # issue #19: T.inner_data(g, g[:3]) ended in a torch broadcasting traceback
    dom = ImageDomain.paper(16)
    T = RayTransform(dom, ParallelBeamGeometry(6, 20))
    g = T(torch.rand(2, 16, 16, dtype=torch.float64))
    for bad, match in ((g[0, :3], r"y2 must have shape \(\.\.\., 6, 20\), got \(3, 20\)"),
                       (g[..., :-1], r"y2 must have shape \(\.\.\., 6, 20\), got \(2, 6, 19\)"),
                       (g[0, 0], r"y2 must have shape \(\.\.\., 6, 20\), got \(20,\)")):
        with pytest.raises(ValueError, match="^" + match):
            T.inner_data(g, bad)
    with pytest.raises(ValueError, match=r"^y1 must have shape \(\.\.\., 6, 20\), got \(3, 20\)"):
        T.inner_data(g[0, :3], g)
    for bad, error, match in ((g.tolist(), TypeError, "y2 must be a torch.Tensor, got list"),
                              (2.0, TypeError, "y2 must be a torch.Tensor, got float"),
                              (g.to(torch.complex128), TypeError, "y2 must have a floating dtype"),
                              (g.long(), TypeError, "y2 must have a floating dtype"),
                              (g.float(), TypeError, "y1 has dtype torch.float64 but y2 has dtype torch.float32"),
                              (torch.cat([g, g, g]), ValueError, r"batch dims of y1 \(2,\) and y2 \(6,\) do not "
                                                                 r"broadcast")):
        with pytest.raises(error, match="^" + match):
            T.inner_data(g, bad)
    with pytest.raises(ValueError, match=r"^y1 must have shape"):
        T.norm_data(g[0, 0])
    # a residual's non-finite values are the caller's to report: they show in the sum, batch dims broadcast
    assert torch.isnan(T.inner_data(g * math.nan, g)).all()
    torch.testing.assert_close(T.inner_data(g, g[0]), T.inner_data(g, g[[0, 0]]))


def test_adjointness_seed_and_dtype_are_checked():
    T = RayTransform(ImageDomain.paper(8), ParallelBeamGeometry(4, 12))
    for bad in (True, "0", 0.5, -1, None):
        with pytest.raises((TypeError, ValueError), match="^seed must be an integer >= 0, got "):
            adjointness(T, seed=bad)
    with pytest.raises(TypeError, match="^dtype must be torch.float32 or torch.float64, got torch.int64"):
        operator_norm(T, dtype=torch.int64)
