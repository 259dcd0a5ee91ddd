"""Operator algebra (indreg.forward.algebra): compositions, sums, multiples, stacks and restrictions are linear
operators of the protocol, with exact adjoints, autograd gradients, coarse-to-fine rebuilds and one-line errors."""
import math

import pytest
import torch

import indreg
from indreg import ImageDomain
from indreg.forward import (ImageOperator, ParallelBeamGeometry, RayTransform, StackedOperator, TiltSeriesGeometry,
                            TiltSeriesTransform, TimeSeriesOperator, add, compose, restrict, scale, stack)
from indreg.forward.operator import check_operator, operator_norm

DOM2, DOM3 = ImageDomain.paper(16), ImageDomain((8, 6, 7))


def shift(f, step=1):
    """A non-self-adjoint image operator: a periodic shift along the last axis (adjoint: the shift back)."""
    return f.roll(step, -1)


def blur(f, ndim=2):
    """3-point periodic blur along the ``ndim`` image axes (self-adjoint)."""
    for dim in range(-ndim, 0):
        f = 0.5 * f + 0.25 * (f.roll(1, dim) + f.roll(-1, dim))
    return f


def ray(num_angles=6, det=24, domain=DOM2, offset=0.0):
    return RayTransform(domain, ParallelBeamGeometry(angles=offset + torch.arange(num_angles) * math.pi / num_angles,
                                                     det_count=det, det_min=-24.0, det_max=24.0, angle_unit="rad"))


def tilt(lo=-60, hi=60, domain=DOM3):
    """5 tilts, 30 degrees apart."""
    return TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(lo, hi, 30, det_count=11))


def parts(ndim):
    """A projector ``A``, a second one ``A2`` of the same data space, an image operator ``B`` with its adjoint."""
    if ndim == 2:
        A, A2 = ray(), ray(offset=0.3)
    else:
        A, A2 = tilt(), tilt(-45, 75)
    dom = A.domain
    return A, A2, ImageOperator(dom, shift, lambda f: shift(f, -1)), ImageOperator(dom, lambda f: blur(f, ndim))


CASES = {
    "A * B": lambda A, A2, B, C: A * B,
    "A * B * C": lambda A, A2, B, C: A * B * C,
    "compose(A, C, B)": lambda A, A2, B, C: compose(A, C, B),
    "B * C (image space)": lambda A, A2, B, C: B * C,
    "A + A2": lambda A, A2, B, C: A + A2,
    "A - 0.5 * A2 * B": lambda A, A2, B, C: A - 0.5 * A2 * B,
    "-A": lambda A, A2, B, C: -A,
    "3 * A": lambda A, A2, B, C: 3 * A,
    "A * -2": lambda A, A2, B, C: A * -2,
    "stack(A, A2 * B, A)": lambda A, A2, B, C: stack(A, A2 * B, A),
    "restrict(A * C, rows)": lambda A, A2, B, C: restrict(A * C, [0, 2, 3]),
    "restrict(stack(..), rows)": lambda A, A2, B, C: restrict(stack(A, A2, A * B), [0, 2]),
    "stack(restrict(A), restrict(A2))": lambda A, A2, B, C: stack(restrict(A, [1, 4]), restrict(A2, [0, 3])),
}


def identity_error(T, batch=(2,), dtype=torch.float64):
    """``max |<T f, y>_data - <f, T^* y>| / (||T f|| ||y||)`` over a batch of random pairs."""
    gen = torch.Generator().manual_seed(3)
    f = torch.randn((*batch, *T.domain.shape), generator=gen, dtype=dtype)
    y = torch.randn((*batch, *T.range_shape), generator=gen, dtype=dtype)
    tf, ty = T(f), T.adjoint(y)
    assert tf.shape == y.shape and ty.shape == f.shape
    lhs, rhs = T.inner_data(tf, y), T.domain.inner(f, ty)
    assert lhs.shape == batch
    return float(((lhs - rhs).abs() / (T.inner_data(tf, tf) * T.inner_data(y, y)).sqrt()).max())


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("case", list(CASES))
def test_adjoint_by_the_inner_product_identity(ndim, case):
    T = check_operator(CASES[case](*parts(ndim)))
    assert identity_error(T) < 1e-12
    assert identity_error(T, batch=(2, 1)) < 1e-12


def test_float32_and_the_parts_values():
    A, A2, B, C = parts(2)
    assert identity_error(A * B - A2, dtype=torch.float32) < 1e-5
    f = indreg.phantoms.get("shepp_logan", DOM2)
    torch.testing.assert_close((A * B)(f), A(f.roll(1, -1)), rtol=0, atol=0)
    torch.testing.assert_close((A - 0.5 * A2)(f), A(f) - 0.5 * A2(f), rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(stack(A, A2)(f), torch.stack([A(f), A2(f)]), rtol=0, atol=0)
    g = torch.randn(A.range_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close((A * C).inner_data(g, g), A.inner_data(g, g), rtol=0, atol=0)
    torch.testing.assert_close(stack(A, A2).inner_data(torch.stack([g, g]), torch.stack([g, 2 * g])),
                               3 * A.inner_data(g, g), rtol=1e-14, atol=0)


def test_norms_of_sums_multiples_and_stacks():
    """``||c A|| = |c| ||A||``, ``||A + A|| = 2 ||A||``, ``||(A, A)|| = sqrt(2) ||A||`` (power iteration)."""
    A = ray()
    n = operator_norm(A, num_iter=200)
    assert operator_norm(-3 * A, num_iter=200) == pytest.approx(3 * n, rel=1e-10)
    assert (-(3 * A)).factor == -3.0 and (-(3 * A)).operator is A     # c (d A) = (c d) A
    assert operator_norm(A + A, num_iter=200) == pytest.approx(2 * n, rel=1e-10)
    assert stack(A, A).operator_norm(num_iter=200) == pytest.approx(math.sqrt(2) * n, rel=1e-10)
    assert operator_norm(A * ImageOperator(DOM2, lambda f: 2.0 * f), num_iter=200) == pytest.approx(2 * n, rel=1e-10)


@pytest.mark.parametrize("ndim", [2, 3])
def test_gradient_of_a_composition(ndim):
    """gradcheck of ``f -> A B f`` (float64), and autograd's gradient of ``0.5 ||A B f - g||^2`` is the L2 gradient
    ``(A B)^*(A B f - g)`` times the cell volume (so the image operator's given adjoint is that of its forward)."""
    A, _, B, C = parts(ndim)
    if ndim == 2:
        A = ray(4, 12, ImageDomain.paper(8))
        B = ImageOperator(A.domain, shift, lambda f: shift(f, -1))
        C = ImageOperator(A.domain, blur)
    T = A * C * B
    f = torch.randn(A.domain.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    if ndim == 2:
        assert torch.autograd.gradcheck(T, (f.clone().requires_grad_(),))
    g = torch.randn(T.range_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    x = f.clone().requires_grad_()
    r = T(x) - g
    (0.5 * T.inner_data(r, r)).backward()
    torch.testing.assert_close(x.grad, T.adjoint(r.detach()) * T.domain.cell_volume, rtol=1e-10, atol=1e-12)


def test_on_domain_rebuilds_every_part():
    A, A2, B, C = parts(3)
    coarse = ImageDomain((4, 3, 7), DOM3.min_pt, DOM3.max_pt)
    for T in (A * C, A - 2 * A2, stack(A, A2 * C), restrict(A * C, [1, 2])):
        Tc = T.on_domain(coarse)
        assert Tc.domain == coarse and Tc.range_shape[0] == T.range_shape[0] and identity_error(Tc) < 1e-12
    series = TimeSeriesOperator([A, A2])
    assert isinstance(series, StackedOperator) and type(series.on_domain(coarse)) is TimeSeriesOperator

    class Foreign:   # the protocol without on_domain
        domain, range_shape = A.domain, A.range_shape

        def __call__(self, f):
            return A(f)

        def adjoint(self, y):
            return A.adjoint(y)

        def inner_data(self, y1, y2):
            return A.inner_data(y1, y2)

    F = Foreign()
    for T in (F * C, A + F, F + A, F - 2 * A, stack(A, F), scale(2, F), -scale(2, F)):
        assert T.on_domain is None and identity_error(T) < 1e-12


def test_a_composition_registers_coarse_to_fine_and_with_held_out_angles():
    """``solver="fast"`` rebuilds ``R * B`` on its coarse grids (``on_domain``); ``holdout`` restricts it."""
    A, B = ray(), ImageOperator(DOM2, blur)
    template, target = indreg.phantoms.get("j", DOM2), indreg.phantoms.get("v", DOM2)
    for options in ({"solver": "fast", "optimizer_kwargs": {"min_size": 4, "level_iter": (3, 3)}}, {"holdout": 3}):
        r = indreg.register(template, (A * B)(target), A * B, num_steps=4, max_iter=6, **options)
        assert r.status == "completed" and r.history[-1]["objective"] < r.history[0]["objective"], options
        if "solver" in options:
            assert sorted({h["level"] for h in r.history}) == [0, 1, 2]     # two coarse grids, then 16^2


def test_foreign_operators_through_the_functions_and_operators():
    """Arithmetic with a protocol operator that is not indreg's: ``foreign * B`` and ``foreign + A`` work through
    the indreg operand's reflected methods, ``compose`` / ``add`` / ``scale`` always."""
    A, A2, B, C = parts(2)

    class Blur:   # an image-space operator without range_domain: its range is found by shape and inner product
        domain, range_shape = DOM2, DOM2.shape

        def __call__(self, f):
            return blur(f)

        adjoint = __call__

        def inner_data(self, y1, y2):
            return DOM2.inner(y1, y2)

    for T in (A * Blur(), compose(A, Blur(), B), add(A * Blur(), A2), scale(0.5, Blur()) + C):
        assert identity_error(T) < 1e-12


def test_errors_one_line():
    A, A2, B, C = parts(2)
    B8 = ImageOperator(ImageDomain.paper(8), blur)
    cases = [
        (lambda: A * A, ValueError, r"^cannot compose A \* B \(A: RayTransform, B: RayTransform\): B's range_shape "
                                    r"\(6, 24\) is not A's domain shape \(16, 16\)$"),
        (lambda: A * B8, ValueError, r"^cannot compose A \* B \(A: RayTransform, B: ImageOperator\): B maps to "
                                     r"ImageDomain\(shape=\(8, 8\).* A acts on ImageDomain\(shape=\(16, 16\)"),
        (lambda: B * A, ValueError, r"B's range_shape \(6, 24\) is not A's domain shape \(16, 16\)"),
        (lambda: A + ray(4), ValueError, r"^terms\[1\].range_shape \(4, 24\) differs from terms\[0\]'s \(6, 24\)$"),
        (lambda: A + ray(domain=ImageDomain.paper(8)), ValueError, r"^terms\[1\].domain ImageDomain\(shape=\(8, 8\)"),
        (lambda: A + 2 * (A * C) + RayTransform(DOM2, ParallelBeamGeometry(
            angles=torch.arange(6) * math.pi / 6, det_count=24, det_min=-12.0, det_max=12.0, angle_unit="rad")),
         ValueError, r"^the data spaces of terms\[0\] .* and terms\[1\] \(RayTransform\) have different inner "
                     r"products"),
        (lambda: stack(A, ray(domain=ImageDomain.paper(8))), ValueError, r"^operators\[1\].domain"),
        (lambda: stack(), ValueError, "non-empty list"),
        (lambda: compose(A), ValueError, "at least 2 operators, got 1"),
        (lambda: add(A), ValueError, "at least 2 operators, got 1"),
        (lambda: scale(math.nan, A), ValueError, "^factor must be a finite real number, got nan$"),
        (lambda: "2" * A, TypeError, "can't multiply|unsupported operand"),
        (lambda: scale("2", A), TypeError, "^factor must be a finite real number, got '2'$"),
        (lambda: A * torch.ones(16, 16), TypeError, "unsupported operand"),
        (lambda: A + 1.0, TypeError, "unsupported operand"),
        (lambda: compose(A, "blur"), TypeError, r"^B \(of A \* B\) must be a linear operator .*; str lacks domain"),
        (lambda: ImageOperator((16, 16), blur), TypeError, "^domain must be an ImageDomain, got tuple$"),
        (lambda: ImageOperator(DOM2, "blur"), TypeError, "^forward must be a function of an image tensor, got str$"),
        (lambda: ImageOperator(DOM2, lambda f: f[..., :4])(DOM2.zeros()), ValueError,
         r"^the image operator's function returned \(16, 4\) for an image of shape \(16, 16\)"),
        (lambda: (A * C)(ImageDomain.paper(8).zeros()), ValueError, r"image must have shape \(\.\.\., 16, 16\)"),
        (lambda: (A * C).adjoint(torch.zeros(6, 23, dtype=torch.float64)), ValueError,
         r"data must have shape \(\.\.\., 6, 24\)"),
    ]
    for call, kind, match in cases:
        with pytest.raises(kind, match=match) as e:
            call()
        assert "\n" not in str(e.value), match

    class Unweighted:   # right shape, but a plain sum as its inner product: not A's images
        domain, range_shape = DOM2, DOM2.shape
        __call__ = adjoint = staticmethod(blur)

        def inner_data(self, y1, y2):
            return (y1 * y2).sum(dim=(-2, -1))

    with pytest.raises(ValueError, match=r"B's data and A's images have different inner products \(<1, 1> = 256 "
                                         r"and 1024\)$"):
        compose(A, Unweighted())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_a_cuda_device():
    A, A2, B, C = parts(3)
    T = restrict(stack(A * C * B, A2 - A), [1])
    f = torch.randn(2, *DOM3.shape, dtype=torch.float64, device="cuda")
    y = T(f)
    assert y.device.type == "cuda" and T.adjoint(y).device.type == "cuda"
    assert T.adjointness_test(device="cuda") < 1e-12
