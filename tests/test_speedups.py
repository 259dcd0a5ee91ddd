"""Pure speed-ups of the operators and solvers behind the HAADF walk-through (docs/real_data.md, "What the parts
cost"): each gives the results of the code it replaced, bit for bit or to float rounding.

- ``AlignedOperator`` keeps its interpolation weights between calls at the same alignment: the same numbers as
  recomputed weights, and new ones as soon as the shifts, the angle, the matrices, the edge or the dtype change;
- ``AlignedOperator.warp_derivatives`` (Gauss-Newton's Jacobian of the alignment) equals forward-mode autograd
  through ``warp``, for both interpolations, both edges, with and without per-projection matrices, at integer and
  fractional points (linear interpolation at integer points, where the derivative is not defined: the one-sided
  derivatives where they are of one cell);
- ``tv_reconstruction(..., norms=history["norms"])`` skips the power iterations and gives the same iterates.
"""
import pytest
import torch
from torch.func import jvp

from indreg.domain import ImageDomain
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.alignment.operator import AlignedOperator, cubic_kernel, cubic_slope
from indreg.forward.tv import tv_reconstruction

F64 = torch.float64
K = 13   # tilts of the small series below


@pytest.fixture(scope="module")
def series():
    domain = ImageDomain((16, 12, 16))
    return TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 10, det_count=20, det_min=-9.0,
                                                                  det_max=9.0))


def _alignment(seed: int, integer: bool) -> tuple:
    g = torch.Generator().manual_seed(seed)
    shifts = torch.randn(K, 2, generator=g, dtype=F64) * 2
    matrices = torch.eye(2, dtype=F64) + 0.05 * torch.randn(K, 2, 2, generator=g, dtype=F64)
    return (shifts.round(), torch.tensor(0.0, dtype=F64), matrices) if integer else \
        (shifts, torch.tensor(0.07, dtype=F64), matrices)


def test_kept_weights_are_the_recomputed_ones_until_the_alignment_changes(series):
    g = torch.Generator().manual_seed(1)
    f = torch.rand(series.domain.shape, generator=g, dtype=F64)
    y = torch.randn(series.range_shape, generator=g, dtype=F64)
    shifts, angle, matrices = _alignment(2, integer=False)
    op = AlignedOperator(series, shifts, float(angle), "cubic")

    def fresh():   # the operator recomputed from its current alignment
        return AlignedOperator(series, op.shifts, float(op.angle), op.interpolation, op.edge, op.matrices)

    for change in (lambda: None, lambda: op.shifts.add_(0.3), lambda: setattr(op, "angle", op.angle + 0.01),
                   lambda: setattr(op, "matrices", matrices), lambda: setattr(op, "edge", "zero")):
        change()
        for _ in range(2):   # the first call computes the weights, the second reuses them
            assert torch.equal(op(f), fresh()(f)) and torch.equal(op.adjoint(y), fresh().adjoint(y))
    assert torch.equal(op(f.float()), fresh()(f.float()))                      # another dtype: its own weights


def test_weights_beyond_the_bound_are_not_kept(series, monkeypatch):
    from indreg.alignment import operator as shift
    f = torch.rand(series.domain.shape, generator=torch.Generator().manual_seed(8), dtype=F64)
    op = AlignedOperator(series, _alignment(9, integer=False)[0], 0.0, "cubic")
    monkeypatch.setattr(shift, "KEEP_BYTES", 0)
    first = op(f)
    assert getattr(op, "_kept", None) is None and torch.equal(op(f), first)
    monkeypatch.setattr(shift, "KEEP_BYTES", 2 ** 28)
    assert torch.equal(op(f), first) and op._kept is not None


def test_kept_weights_leave_the_gradient_in_the_shifts(series):
    f = torch.rand(series.domain.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    op = AlignedOperator(series, _alignment(4, integer=False)[0], 0.0, "cubic")
    op(f)                                                                        # weights kept
    op.shifts = op.shifts.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(op(f).square().sum(), op.shifts)
    assert grad.abs().max() > 0


def test_cubic_slope_is_the_kernels_derivative():
    x = torch.linspace(-2.5, 2.5, 1001, dtype=F64)
    h = 1e-6
    assert torch.allclose(cubic_slope(x), (cubic_kernel(x + h) - cubic_kernel(x - h)) / (2 * h), atol=1e-5)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
@pytest.mark.parametrize("edge", ["nearest", "zero"])
@pytest.mark.parametrize("integer", [False, True])
@pytest.mark.parametrize("with_matrices", [False, True])
def test_warp_derivatives_equal_forward_mode_autograd(series, interpolation, edge, integer, with_matrices):
    P = torch.randn(series.range_shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    shifts, angle, matrices = _alignment(6, integer)
    op = AlignedOperator(series, interpolation=interpolation, edge=edge, matrices=matrices if with_matrices else None)

    def model(s, a):
        return op.warp(P, s, a)

    directions = [(torch.zeros_like(shifts).index_fill_(1, torch.tensor([c]), 1.0), torch.zeros_like(angle))
                  for c in range(2)] + [(torch.zeros_like(shifts), torch.ones_like(angle))]
    warped, columns = op.warp_derivatives(P, shifts, angle, axis=True)
    assert torch.equal(warped, op.warp(P, shifts, angle))
    if interpolation == "linear" and integer and not with_matrices:
        _check_one_sided(op, model, shifts, angle, directions, columns)   # every point on a kink: no derivative
        return
    expected = [jvp(model, (shifts, angle), d)[1] for d in directions]
    for got, want in zip(columns, expected, strict=True):
        assert want.abs().max() > 0
        assert torch.allclose(got, want, rtol=0, atol=1e-13 * float(want.abs().max()))
    assert len(op.warp_derivatives(P, shifts, angle, axis=False)[1]) == 2


def _check_one_sided(op, model, shifts, angle, directions, columns, h=2.0 ** -14):
    """Integer shifts at angle 0 put every point of linear interpolation on a kink of its weights (a grid point, to
    rounding), where the derivative is not defined (forward-mode autograd's value there is a convention, which
    torch 2.14 changed). ``warp_derivatives`` differentiates the interpolant of the cell the point's floored indices
    name; where a direction moves the point into that cell along both indices, that is the one-sided derivative
    forwards, where it moves it out of the cell along both, backwards: the one-sided difference quotients at ``h``
    and ``h / 2`` extrapolated (Richardson: exact for the shifts, which move the points linearly, ``O(h^2)`` for
    the angle, which turns them; ``h`` a power of two, so that ``s +- h d`` are exact). A move into the cell along
    one index and out of it along the other has no one-sided derivative of that cell: those entries are left out."""
    at = model(shifts, angle)

    def quotient(sign, step, ds, da):
        return sign * (model(shifts + sign * step * ds, angle + sign * step * da) - at) / step

    def points(s, a):
        return op._points(s, a, at)

    low = [p - p.floor() < 0.5 for p in points(shifts, angle)]   # on the cell's lower edge (else its upper one)
    for got, (ds, da) in zip(columns, directions, strict=True):
        moves = jvp(points, (shifts, angle), (ds, da))[1]
        enters = [torch.where(lo, m >= 0, m <= 0) for lo, m in zip(low, moves)]
        leaves = [torch.where(lo, m <= 0, m >= 0) for lo, m in zip(low, moves)]
        into, out = enters[0] & enters[1], leaves[0] & leaves[1]
        forward, backward = (2 * quotient(sign, h / 2, ds, da) - quotient(sign, h, ds, da) for sign in (1, -1))
        scale = float(torch.maximum(forward.abs(), backward.abs()).max())
        assert scale > 0 and (forward - backward).abs().max() > 0.1 * scale   # the kinks are there
        assert float((into | out).double().mean()) > 0.4                       # most entries are compared
        assert torch.allclose(got[into], forward[into], rtol=0, atol=1e-7 * scale)
        assert torch.allclose(got[out], backward[out], rtol=0, atol=1e-7 * scale)


def test_tv_with_given_norms_skips_the_power_iterations_and_keeps_the_iterates(series):
    g = torch.Generator().manual_seed(7)
    y = series(torch.rand(series.domain.shape, generator=g, dtype=F64))
    for balanced in (True, False):
        first, h1 = tv_reconstruction(series, y, mu=0.1, num_iter=5, nonneg=True, balanced=balanced)
        again, h2 = tv_reconstruction(series, y, mu=0.1, num_iter=5, nonneg=True, balanced=balanced,
                                      norms=h1["norms"])
        assert torch.equal(first, again) and h1["norms"] == h2["norms"] and len(h1["norms"]) == 2 - (not balanced)
    for bad in ((1.0,), (1.0, -2.0), "ab", (1.0, float("nan"))):
        with pytest.raises(ValueError, match="norms must be 2 positive"):
            tv_reconstruction(series, y, mu=0.1, num_iter=1, norms=bad)
