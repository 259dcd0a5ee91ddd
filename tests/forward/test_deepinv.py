"""deepinv interop: as_physics passes deepinv's adjointness test, round trips, registration through deepinv physics.

Every test but the first needs deepinv (``pytest.importorskip``); see docs/deepinv.md for the second venv.
"""
import math
import sys

import pytest
import torch
from torch import nn

import indreg
from indreg import ImageDomain, ParallelBeamGeometry, RayTransform, phantoms
from indreg.forward.deepinv import as_operator, as_physics

SMALL_DOMAIN = ImageDomain((7, 5), (-3.0, -2.0), (4.0, 3.0))
ODD_DOMAIN = ImageDomain((6, 6), (-1.0, -2.0), (2.0, 1.6))              # cell volume 0.5 * 0.6
SMALL_GEOMETRY = ParallelBeamGeometry(angles=[0.0, 0.4, 1.3, 2.0, 2.9], det_count=9, det_min=-5.0, det_max=5.0)


@pytest.fixture(scope="module")
def dinv():
    return pytest.importorskip("deepinv")


@pytest.fixture(scope="module")
def small():
    return RayTransform(ODD_DOMAIN, SMALL_GEOMETRY)


class DiagonalWeighted(nn.Module):
    """A dense operator ``f -> M f`` with per-entry data weights ``w``: ``T^* = W_X^-1 M^T W_Y``."""

    def __init__(self, domain, weights, seed=0):
        super().__init__()
        self.domain, self.weights, self.range_shape = domain, weights, tuple(weights.shape)
        n = domain.shape[0] * domain.shape[1]
        self.matrix = torch.randn(weights.numel(), n, generator=torch.Generator().manual_seed(seed),
                                  dtype=torch.float64)

    def forward(self, f):
        return (f.reshape(*f.shape[:-2], -1) @ self.matrix.T.to(f)).reshape(*f.shape[:-2], *self.range_shape)

    def adjoint(self, y):
        wy = (self.weights.to(y) * y).reshape(*y.shape[:-2], -1)
        return (wy @ self.matrix.to(y)).reshape(*y.shape[:-2], *self.domain.shape) / self.domain.cell_volume

    def inner_data(self, y1, y2):
        return (self.weights.to(y1) * y1 * y2).sum(dim=(-2, -1))


def test_clear_import_error_without_deepinv(monkeypatch, small):
    """No deepinv needed: importing the module works; using it says how to install deepinv."""
    monkeypatch.setitem(sys.modules, "deepinv", None)   # makes `import deepinv` raise ImportError
    with pytest.raises(ImportError, match=r'pip install "indreg\[deepinv\]"'):
        as_physics(small)
    with pytest.raises(ImportError, match=r'pip install "indreg\[deepinv\]"'):
        as_operator(object(), ODD_DOMAIN)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_as_physics_passes_deepinv_adjointness_test(dinv, small, dtype, tol):
    phys = as_physics(small)
    assert isinstance(phys, dinv.physics.LinearPhysics)
    assert float(phys.adjointness_test(img_size=(1, *ODD_DOMAIN.shape), dtype=dtype, num_samples=4)) < tol
    assert float(phys.adjointness_test(img_size=(3, *ODD_DOMAIN.shape), dtype=dtype)) < tol   # 3 channels
    # indreg's weighted adjoint would fail deepinv's (Euclidean) test: the scaling matters
    assert small.adjoint_scale != pytest.approx(1.0)


def test_as_physics_is_transpose_per_channel(dinv, small):
    phys = as_physics(small)
    x = torch.randn(2, 3, *ODD_DOMAIN.shape, dtype=torch.float64)
    y = torch.randn(2, 3, *small.range_shape, dtype=torch.float64)
    torch.testing.assert_close(phys.A(x), small(x))
    torch.testing.assert_close(phys(x), small(x))               # zero noise by default
    torch.testing.assert_close(phys.A_adjoint(y), small.transpose(y))
    assert isinstance(phys, indreg.forward.deepinv.IndregPhysics)


def test_as_physics_clone_after_use(dinv, small):
    """deepinv's clone (used by its dataset generator and losses) works on a used RayTransform and shares it."""
    phys = as_physics(small, noise_model=dinv.physics.GaussianNoise(0.1))
    x = torch.randn(2, 1, *ODD_DOMAIN.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    y = phys.A(x)                                                  # fills the operator's sparse-matrix cache
    copy = phys.clone()
    assert copy is not phys and copy.operator is small and copy.noise_model is not phys.noise_model
    torch.testing.assert_close(copy.A(x), y)
    torch.manual_seed(0)
    assert float((copy(x) - y).std()) == pytest.approx(0.1, rel=0.3)


def test_as_physics_l2_fidelity_gradient_equals_autograd(dinv, small):
    """deepinv's L2 data-fidelity gradient A^T(Ax - y) equals autograd of (1/2)||Ax - y||^2 (Euclidean)."""
    phys = as_physics(small)
    x = torch.randn(2, 1, *ODD_DOMAIN.shape, dtype=torch.float64, requires_grad=True)
    y = torch.randn(2, 1, *small.range_shape, dtype=torch.float64)
    (auto,) = torch.autograd.grad(0.5 * (phys.A(x) - y).pow(2).sum(), x)
    torch.testing.assert_close(dinv.optim.data_fidelity.L2().grad(x.detach(), y, phys), auto)


def test_as_physics_non_constant_data_weight(dinv):
    weights = torch.rand(4, 5, generator=torch.Generator().manual_seed(3), dtype=torch.float64) + 0.5
    op = DiagonalWeighted(ODD_DOMAIN, weights)
    x = torch.randn(1, *ODD_DOMAIN.shape, dtype=torch.float64)
    y = torch.randn(1, 4, 5, dtype=torch.float64)
    # the test operator's own adjoint is right for its weighted inner products ...
    torch.testing.assert_close(op.inner_data(op(x), y), ODD_DOMAIN.inner(x, op.adjoint(y)))
    # ... and as_physics turns it into the Euclidean transpose M^T
    phys = as_physics(op)
    assert float(phys.adjointness_test(img_size=(1, *ODD_DOMAIN.shape), dtype=torch.float64)) < 1e-12
    torch.testing.assert_close(phys.A_adjoint(y).reshape(-1), op.matrix.T @ y.reshape(-1))


def test_as_physics_bad_operator(dinv):
    with pytest.raises(TypeError, match="linear operator.*Linear lacks domain, range_shape, adjoint, inner_data"):
        as_physics(nn.Linear(2, 2))
    with pytest.raises(ValueError, match="positively weighted sum, found weights <= 0"):
        as_physics(DiagonalWeighted(ODD_DOMAIN, torch.zeros(4, 5, dtype=torch.float64)))
    op = DiagonalWeighted(ODD_DOMAIN, torch.ones(4, 5, dtype=torch.float64))
    op.inner_data = lambda y1, y2: (y1.sum(dim=(-2, -1)) * y2.sum(dim=(-2, -1)))   # not diagonal
    with pytest.raises(ValueError, match="non-diagonal data inner product"):
        as_physics(op)


def test_round_trip_equals_ray_transform(dinv, small):
    op = as_operator(as_physics(small), ODD_DOMAIN, data_weight=SMALL_GEOMETRY.data_weight)
    assert op.range_shape == small.range_shape and op.domain == ODD_DOMAIN
    f = torch.randn(2, 3, *ODD_DOMAIN.shape, dtype=torch.float64)
    y = torch.randn(2, 3, *small.range_shape, dtype=torch.float64)
    torch.testing.assert_close(op(f), small(f), rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(op.adjoint(y), small.adjoint(y), rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(op.inner_data(y, y), small.inner_data(y, y))
    assert op(f[0, 0]).shape == small.range_shape                 # no batch dims
    assert op.dtypes == (torch.float32, torch.float64)


def tomography(dinv, n, angles, dtype=torch.float64):
    return dinv.physics.Tomography(angles=angles, img_width=n, normalize=False, dtype=dtype)


@pytest.mark.parametrize("kind", ["tomography", "blur"])
def test_as_operator_adjoint_weighted_inner_products(dinv, kind):
    """<T x, y>_data = <x, T^* y>_L2 with cell volume 0.3 and data weight 0.7: T^* = (w / cell_volume) A^T."""
    if kind == "tomography":
        phys = tomography(dinv, 6, 5)
    else:
        kernel = torch.rand(1, 1, 3, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)  # asymmetric
        phys = dinv.physics.Blur(filter=kernel, padding="circular")
    op = as_operator(phys, ODD_DOMAIN, data_weight=0.7)
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(3, *ODD_DOMAIN.shape, generator=gen, dtype=torch.float64)
    y = torch.randn(3, *op.range_shape, generator=gen, dtype=torch.float64)
    lhs, rhs = op.inner_data(op(x), y), ODD_DOMAIN.inner(x, op.adjoint(y))
    assert lhs.shape == (3,)
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(op.transpose(y), phys.A_adjoint(y[:, None])[:, 0])
    torch.testing.assert_close(op.adjoint(y), 0.7 / 0.3 * op.transpose(y))
    assert op.adjoint(y[0]).shape == ODD_DOMAIN.shape


def test_as_operator_gradcheck(dinv):
    """Gradients are autograd's through deepinv (float64 gradcheck of T and T^*)."""
    op = as_operator(tomography(dinv, 6, 3), ODD_DOMAIN, data_weight=0.7)
    f = torch.randn(*ODD_DOMAIN.shape, dtype=torch.float64, requires_grad=True)
    y = torch.randn(*op.range_shape, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(op, (f,))
    assert torch.autograd.gradcheck(op.adjoint, (y,))


def test_as_operator_infers_and_checks_range_shape(dinv):
    phys = tomography(dinv, 6, 5)
    op = as_operator(phys, ODD_DOMAIN)
    assert op.range_shape == tuple(phys.A(torch.zeros(1, 1, 6, 6, dtype=torch.float64)).shape[2:])
    assert op.range_shape[1] == 5                                  # deepinv: (detector, angle)
    assert as_operator(phys, ODD_DOMAIN, range_shape=op.range_shape).range_shape == op.range_shape
    with pytest.raises(ValueError, match="range_shape .* differs from the physics' measurement shape"):
        as_operator(phys, ODD_DOMAIN, range_shape=(5, 9))


def test_as_operator_bad_input(dinv):
    phys = tomography(dinv, 6, 5)
    op = as_operator(phys, ODD_DOMAIN)
    assert op.dtypes == (torch.float64,)
    with pytest.raises(TypeError, match="must be a deepinv.physics.LinearPhysics"):
        as_operator(RayTransform(ODD_DOMAIN, SMALL_GEOMETRY), ODD_DOMAIN)
    with pytest.raises(TypeError, match="domain must be an ImageDomain"):
        as_operator(phys, (6, 6))
    with pytest.raises(ValueError, match="data_weight must be a finite number > 0"):
        as_operator(phys, ODD_DOMAIN, data_weight=0.0)
    with pytest.raises(ValueError, match=r"cannot be applied to a real single-channel image of shape \(1, 1, 7, 5\)"):
        as_operator(phys, SMALL_DOMAIN)                             # the physics is 6 x 6
    with pytest.raises(TypeError, match="complex-valued .*MRI"):
        as_operator(dinv.physics.MRI(img_size=(6, 6)), ODD_DOMAIN)
    with pytest.raises(ValueError, match=r"image must have shape \(\.\.\., 6, 6\)"):
        op(torch.zeros(7, 5, dtype=torch.float64))
    with pytest.raises(TypeError, match="image has dtype torch.float32 but the physics accepts only torch.float64"):
        op(torch.zeros(6, 6))
    with pytest.raises(ValueError, match="data contains non-finite values"):
        op.adjoint(torch.full(op.range_shape, math.nan, dtype=torch.float64))


def test_registration_through_deepinv_tomography_decreases_objective(dinv):
    """IndirectRegistration + Algorithm1 with deepinv's Tomography as T: the objective decreases at every step."""
    domain = ImageDomain.paper(32)                                 # cell side 1: deepinv's pixel units are physical
    op = as_operator(tomography(dinv, 32, 10), domain, data_weight=math.pi / 10)
    template = phantoms.get("j", domain)
    data = op(phantoms.get("v", domain))
    problem = indreg.IndirectRegistration(op, indreg.LDDMMDeformation(domain, 10),
                                          indreg.GaussianKernel(domain, 6.0), template, data, gamma=1e-6)
    state = indreg.solvers.SolverState(problem.zero_momentum())
    solver = indreg.Algorithm1(problem, step_size=0.02, max_iter=1)
    objectives = [problem.evaluate(state.momentum)["objective"]]
    for _ in range(5):
        objectives.append(solver.step(state)["objective"])
    assert all(b < a for a, b in zip(objectives, objectives[1:])), objectives
    assert objectives[-1] < 0.8 * objectives[0], objectives
