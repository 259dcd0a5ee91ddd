"""TiltSeriesTransform: adjointness, slice-by-slice agreement with the 2D projector, analytic ellipsoid line
integrals, autograd (gradcheck), batches, conventions and bad input."""
import math

import numpy as np
import pytest
import torch

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform, phantoms
from indreg.forward import LinearOperator, TiltSeriesGeometry, TiltSeriesTransform, check_operator

# A small non-cubic, off-centre box (different cell sides per axis) and irregular tilts in degrees.
DOMAIN = ImageDomain((9, 6, 7), (-4.0, -3.0, -2.0), (5.0, 3.0, 4.0))
TILTS = [-58.0, -41.0, -20.0, -3.0, 0.0, 17.0, 44.0, 61.0]


def transform(axis="y", det_count=11, domain=DOMAIN):
    return TiltSeriesTransform(domain, TiltSeriesGeometry(TILTS, det_count, tilt_axis=axis, angle_unit="deg"))


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_adjointness_inner_product_identity(axis):
    T = transform(axis)
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(2, *DOMAIN.shape, generator=gen, dtype=torch.float64)
    y = torch.randn(2, *T.range_shape, generator=gen, dtype=torch.float64)
    tx = T(x)
    lhs, rhs = T.inner_data(tx, y), DOMAIN.inner(x, T.adjoint(y))
    assert lhs.shape == (2,)
    assert bool(((lhs - rhs).abs() <= 1e-13 * T.norm_data(tx) * T.norm_data(y)).all())
    assert T.adjointness_test() < 1e-14
    assert T.adjointness_test(torch.float32) < 1e-5
    torch.testing.assert_close((tx * y).sum(), (x * T.transpose(y)).sum(), rtol=1e-13, atol=0)   # A^T exact


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_equals_2d_projector_slice_by_slice(axis):
    T = transform(axis)
    a = "xyz".index(axis)
    u, v = (b for b in range(3) if b != a)
    dom2 = ImageDomain((DOMAIN.shape[u], DOMAIN.shape[v]), (DOMAIN.min_pt[u], DOMAIN.min_pt[v]),
                       (DOMAIN.max_pt[u], DOMAIN.max_pt[v]))
    T2 = RayTransform(dom2, ParallelBeamGeometry(angles=TILTS, det_count=11, angle_unit="deg"))
    assert T.range_shape == (len(TILTS), DOMAIN.shape[a], 11)
    f = torch.randn(DOMAIN.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    y = torch.randn(T.range_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    data, back = T(f), T.transpose(y)
    for j in range(DOMAIN.shape[a]):
        torch.testing.assert_close(data[:, j, :], T2(f.select(a, j)), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(back.select(a, j), T2.transpose(y[:, j, :]), rtol=1e-12, atol=1e-12)
    assert T.adjoint_scale == pytest.approx(T2.adjoint_scale, rel=1e-14)   # the cell side along t cancels


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_negated_angles_are_the_mirrored_specimen(axis):
    """Negating every tilt angle gives the data of the specimen mirrored along v (the beam at tilt 0) exactly:
    the data of a single-axis series cannot tell the angles' sign, only the volume's handedness changes
    (docs/tilt_series.md): ``p(-theta, t, s)[f] = p(theta, t, s)[f(u, -v)]`` on a domain centred in v."""
    dom = ImageDomain((9, 6, 7), (-4.5, -2.4, -3.5), (4.5, 2.4, 3.5))       # centred, unequal cells
    v = max(b for b in range(3) if b != "xyz".index(axis))
    f = torch.rand(dom.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    plus = TiltSeriesTransform(dom, TiltSeriesGeometry(TILTS, 11, tilt_axis=axis, angle_unit="deg"))
    minus = TiltSeriesTransform(dom, TiltSeriesGeometry([-a for a in TILTS], 11, tilt_axis=axis, angle_unit="deg"))
    torch.testing.assert_close(minus(f), plus(torch.flip(f, dims=(v,))), rtol=1e-12, atol=1e-12)


def test_ball_chords_are_exact():
    """The analytic reference itself: a ball of radius 8 gives 2 sqrt(64 - s^2 - t^2) at every tilt."""
    dom = ImageDomain.paper(16, 3)
    g = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 30, det_count=24)).geometry
    ball = [(1.0, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)]
    s, t = g.det_points[None, None, :], dom.axes()[1][None, :, None]
    expected = 2 * (64 - s ** 2 - t ** 2).clamp(min=0).sqrt().expand(g.shape)
    torch.testing.assert_close(phantoms.ellipsoid_tilt_series(ball, dom, g), expected, rtol=1e-12, atol=1e-12)


def test_ellipsoid_analytic_line_integrals():
    """Projector vs exact chords of a rotated, off-centre ellipsoid plus a ball: relative L2 error below 3 % at
    64^3 and first-order convergence from 32^3 (the volume's cells are averages, the chords point samples)."""
    rows = [(1.0, 0.55, 0.35, 0.45, 0.1, -0.05, 0.08, 30.0, 20.0, 10.0),
            (0.5, 0.2, 0.2, 0.2, -0.3, 0.2, -0.2, 0.0, 0.0, 0.0)]
    errors = []
    for n in (32, 64):
        dom = ImageDomain.paper(n, 3)
        T = TiltSeriesTransform(dom, TiltSeriesGeometry.uniform(-60, 60, 6, det_count=3 * n // 2))
        exact = phantoms.ellipsoid_tilt_series(rows, dom, T.geometry)
        errors.append(float((T(phantoms.ellipsoid_phantom(dom, rows)) - exact).norm() / exact.norm()))
    assert errors[1] < 0.03
    assert errors[1] < 0.6 * errors[0]


def test_gradcheck_forward_and_transpose():
    dom = ImageDomain((4, 3, 5), (-2.0, -1.5, -2.5), (2.0, 1.5, 2.5))
    T = TiltSeriesTransform(dom, TiltSeriesGeometry([-45.0, 0.0, 30.0], 6, tilt_axis="y", angle_unit="deg"))
    x = torch.randn(2, *dom.shape, dtype=torch.float64, requires_grad=True)
    y = torch.randn(2, *T.range_shape, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(T, (x,))
    assert torch.autograd.gradcheck(T.adjoint, (y,))
    assert torch.autograd.gradgradcheck(lambda v: (T(v) ** 2).sum(), (x,))


def test_batched_and_float32():
    T = transform("y")
    f = torch.randn(2, 3, *DOMAIN.shape, dtype=torch.float64)
    out = T(f)
    assert out.shape == (2, 3, *T.range_shape)
    torch.testing.assert_close(out[1, 2], T(f[1, 2]), rtol=1e-13, atol=1e-13)
    back = T.adjoint(out)
    torch.testing.assert_close(back[0, 1], T.adjoint(out[0, 1]), rtol=1e-13, atol=1e-13)
    out32 = T(f.float())
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), out, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_blocked_cpu_products_are_bit_for_bit(monkeypatch, dtype):
    """Large batches go through the sparse products in blocks of the slices (``CPU_BLOCK_BYTES``, one slice here, so
    that both products run slice by slice): the same sums in the same order, so the same bits."""
    from indreg.forward import ray_transform

    T = transform("y")
    f = torch.randn(*DOMAIN.shape, dtype=dtype)
    y = torch.randn(*T.range_shape, dtype=dtype)
    whole = T(f), T.transpose(y)
    slice_bytes = DOMAIN.shape[0] * DOMAIN.shape[2] * f.element_size()
    monkeypatch.setattr(ray_transform, "CPU_BLOCK_BYTES", slice_bytes)
    assert DOMAIN.shape[1] * slice_bytes > 4 * ray_transform.CPU_BLOCK_BYTES   # 6 slices: blocked
    blocked = T(f), T.transpose(y)
    assert torch.equal(whole[0], blocked[0]) and torch.equal(whole[1], blocked[1])


@pytest.mark.parametrize("width", [1, 7, 40, 10 ** 6])
def test_column_blocks_give_the_projection(width):
    """``matmul_columns`` over ``A``'s column blocks (the slabs' projector on a CPU) equals ``A`` applied whole, to
    float64 rounding, for blocks that do not divide the slice (7, 40), single pixels (1) and one block."""
    from indreg.forward.ray_transform import _matmul, matmul_columns

    T = transform("y")
    x = torch.randn(5, DOMAIN.shape[0] * DOMAIN.shape[2], dtype=torch.float64)
    A = T.system.get(torch.float64, torch.device("cpu"))[0]
    blocks = T.system.column_blocks(torch.float64, torch.device("cpu"), width)
    assert [b[0] for b in blocks] == list(range(0, x.shape[1], width)) and blocks[-1][1] == x.shape[1]
    assert sum(b[2]._nnz() for b in blocks) == A._nnz()
    torch.testing.assert_close(matmul_columns(blocks, x), _matmul(A, x), rtol=1e-13, atol=1e-13)
    assert T.system.column_blocks(torch.float64, torch.device("cpu"), width) is blocks   # cached


def test_protocol_and_geometry():
    T = transform("y")
    assert check_operator(T) is T and isinstance(T, LinearOperator)
    g = TiltSeriesGeometry.uniform(-60, 60, 2, det_count=64, det_min=-16.0, det_max=16.0)
    assert g.num_tilts == 61 and g.tilt_axis == "y" and g.slice_axes == (0, 2)
    torch.testing.assert_close(g.angle_weights, torch.full((61,), math.radians(2.0), dtype=torch.float64))
    r = g.resolve(ImageDomain.paper(16, 3))
    assert r.shape == (61, 16, 64) and r.data_weight == pytest.approx(math.pi / 61 * 0.5 * 2.0)
    assert not g.is_resolved   # resolve returns a copy
    rad = TiltSeriesGeometry([-1.0, 0.0, 1.0], 8, angle_unit="rad")
    torch.testing.assert_close(rad.angles, torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64))


def test_bad_input_one_line_errors():
    T = transform("y")
    with pytest.raises(ValueError, match=r"volume must have shape \(\.\.\., 9, 6, 7\)"):
        T(torch.zeros(9, 7, 6, dtype=torch.float64))
    with pytest.raises(ValueError, match="volume contains non-finite"):
        T(torch.full(DOMAIN.shape, float("nan"), dtype=torch.float64))
    with pytest.raises(ValueError, match="data must have shape"):
        T.adjoint(torch.zeros(8, 7, 11, dtype=torch.float64))
    with pytest.raises(TypeError, match="float32 or float64"):
        T(torch.zeros(DOMAIN.shape, dtype=torch.float16))
    with pytest.raises(ValueError, match="angle_unit must be 'deg' or 'rad'"):
        TiltSeriesGeometry(TILTS, 11, angle_unit="degree")
    with pytest.raises(TypeError, match="angle_unit"):
        TiltSeriesGeometry(TILTS, 11)
    with pytest.raises(ValueError, match="tilt_axis must be"):
        TiltSeriesGeometry(TILTS, 11, tilt_axis="w", angle_unit="deg")
    with pytest.raises(ValueError, match="angles must be finite"):
        TiltSeriesGeometry([0.0, float("inf")], 11, angle_unit="deg")
    with pytest.raises(ValueError, match="3D ImageDomain"):
        TiltSeriesTransform(ImageDomain.paper(8), TiltSeriesGeometry(TILTS, 11, angle_unit="deg"))
    with pytest.raises(ValueError, match="not resolved"):
        TiltSeriesGeometry(TILTS, 11, angle_unit="deg").shape
    with pytest.raises(ValueError, match="RayTransform needs a 2D domain"):
        RayTransform(DOMAIN, ParallelBeamGeometry(4, 8))


def test_tilt_axis_is_one_axis_name_or_number():
    # "xy" and "" are substrings of "xyz" and were taken as axis 0; numpy's True == 1 was axis 1
    for bad in ("xy", "", "Y", np.bool_(True), True, 1.0, 3, None):
        with pytest.raises(ValueError, match="^tilt_axis must be 'x', 'y', 'z' \\(or 0, 1, 2\\), got "):
            TiltSeriesGeometry(TILTS, 11, tilt_axis=bad, angle_unit="deg")
    for good, axis in (("z", 2), (0, 0), (np.int64(2), 2)):
        assert TiltSeriesGeometry(TILTS, 11, tilt_axis=good, angle_unit="deg").axis == axis
