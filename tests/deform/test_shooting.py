"""Tests of GeodesicShooting (indreg/deform/shooting.py): EPDiff shooting reusing LDDMMDeformation."""
import math

import pytest
import torch

from indreg import ImageDomain
from indreg.deform.kernel import GaussianKernel
from indreg.deform.shooting import GeodesicShooting, ShootingResult, coadjoint_transport, jacobian_matrix


def bump_momentum(domain, displacement, kernel, centre=(3.0, -2.0), width=4.0, direction=(1.0, 0.5),
                  dtype=torch.float64):
    """A smooth Gaussian momentum whose velocity peaks at ``displacement`` (physical units)."""
    x = domain.points(dtype)
    g = torch.exp(-((x[0] - centre[0]) ** 2 + (x[1] - centre[1]) ** 2) / (2 * width ** 2))
    m = torch.stack([direction[0] * g, direction[1] * g])
    return m * (displacement / kernel.apply(m).abs().max())


def disc(domain, radius=6.0, centre=(0.0, 0.0), dtype=torch.float64):
    """A smoothed disc (tanh edge of one cell), differentiable template."""
    x = domain.points(dtype)
    r = ((x[0] - centre[0]) ** 2 + (x[1] - centre[1]) ** 2).sqrt()
    return 0.5 * (1 - torch.tanh((r - radius) / domain.cell_sides[0]))


@pytest.fixture(scope="module")
def small():
    dom = ImageDomain.paper(16)
    return dom, GaussianKernel(dom, 5.0)


# ---------------------------------------------------------------- smoke / cardinality
def test_shapes_batch_and_return_all(small):
    dom, K = small
    shoot = GeodesicShooting(dom, K, num_steps=3)
    m0 = torch.randn(2, 3, 2, 16, 16, dtype=torch.float64) * 1e-3
    out = shoot(m0, disc(dom))
    assert out.shape == (2, 3, 16, 16)
    res = shoot(m0, disc(dom), return_all=True)
    assert isinstance(res, ShootingResult)
    assert res.deformed.shape == (2, 3, 16, 16)
    assert res.trajectory.shape == (2, 3, 4, 16, 16)
    assert res.deformation.shape == (2, 3, 2, 16, 16)
    assert res.velocity.shape == res.momentum.shape == (2, 3, 4, 2, 16, 16)
    torch.testing.assert_close(res.trajectory[..., -1, :, :], res.deformed)
    torch.testing.assert_close(res.momentum[..., 0, :, :, :], m0)
    torch.testing.assert_close(res.velocity, K.apply(res.momentum))
    # the returned velocities reproduce the deformed template through the deformation operator
    torch.testing.assert_close(shoot.deformation(res.velocity, disc(dom)), res.deformed)


def test_float32_runs_and_keeps_dtype(small):
    dom, K = small
    m0 = bump_momentum(dom, 2.0, K, dtype=torch.float32)
    out = GeodesicShooting(dom, K, 4)(m0, disc(dom, dtype=torch.float32))
    assert out.dtype == torch.float32 and torch.isfinite(out).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(small):
    dom, K = small
    m0, tmpl = bump_momentum(dom, 2.0, K), disc(dom)
    shoot = GeodesicShooting(dom, K, 4)
    torch.testing.assert_close(shoot(m0.cuda(), tmpl.cuda()).cpu(), shoot(m0, tmpl))


# ---------------------------------------------------------------- exceptions
def test_bad_input_errors(small):
    dom, K = small
    with pytest.raises(ValueError, match="num_steps"):
        GeodesicShooting(dom, K, 0)
    with pytest.raises(TypeError, match="kernel"):
        GeodesicShooting(dom, "gauss", 4)
    with pytest.raises(ValueError, match="kernel is defined on"):
        GeodesicShooting(dom, GaussianKernel(ImageDomain.paper(8), 5.0), 4)
    shoot = GeodesicShooting(dom, K, 2)
    with pytest.raises(ValueError, match=r"momentum must have shape \(\.\.\., 2, 16, 16\)"):
        shoot(torch.zeros(3, 16, 16, dtype=torch.float64), disc(dom))
    with pytest.raises(TypeError, match="dtype"):
        shoot(torch.zeros(2, 16, 16, dtype=torch.float32), disc(dom))
    with pytest.raises(ValueError, match="non-finite"):
        shoot(torch.full((2, 16, 16), math.nan, dtype=torch.float64), disc(dom))


# ---------------------------------------------------------------- features
def test_zero_momentum_is_identity(small):
    dom, K = small
    tmpl = torch.rand(16, 16, dtype=torch.float64)
    res = GeodesicShooting(dom, K, 5)(torch.zeros(2, 2, 16, 16, dtype=torch.float64), tmpl, return_all=True)
    assert torch.equal(res.deformed, tmpl.expand(2, 16, 16))
    assert torch.equal(res.deformation, dom.points().expand(2, 2, 16, 16))
    assert not res.velocity.any() and not res.momentum.any()


def test_coadjoint_action_of_a_translation_and_a_scaling():
    """Ad*: a translation moves the momentum; phi = c x multiplies it by c * c^2 (|D phi| (D phi)^T)."""
    dom = ImageDomain.paper(32)
    K = GaussianKernel(dom, 5.0)
    m = bump_momentum(dom, 1.0, K, centre=(0.0, 0.0))
    shift = torch.zeros(2, 32, 32, dtype=torch.float64)
    shift[0] = 2 * dom.cell_sides[0]              # phi = x + 2 cells: (m o phi)(x) = m(x + 2h)
    torch.testing.assert_close(coadjoint_transport(m, shift, dom)[:, :-2], m[:, 2:])
    c = 1.1
    scale = (c - 1) * dom.points()
    assert torch.allclose(jacobian_matrix(scale, dom)[:, :, 1:-1, 1:-1],
                          c * torch.eye(2, dtype=torch.float64)[:, :, None, None].expand(2, 2, 30, 30))
    centre = coadjoint_transport(m, scale, dom)[:, 16, 16]
    assert torch.allclose(centre, c ** 3 * m[:, 16, 16], rtol=1e-2)


def v_norm_drift(num_steps, n=64):
    dom = ImageDomain.paper(n)
    K = GaussianKernel(dom, 6.0)
    shoot = GeodesicShooting(dom, K, num_steps)
    _, momenta, u = shoot.shoot(bump_momentum(dom, 4.0, K))
    energy = shoot.energy(momenta)                # ||nu(t_i)||_V^2, i = 0..N
    assert u.abs().max() > 3.5                    # a large deformation (4 units = 8 pixels)
    return float((energy - energy[0]).abs().max() / energy[0])


def test_v_norm_conserved_along_the_geodesic():
    drift = {n: v_norm_drift(n) for n in (10, 20, 40)}
    assert drift[20] <= 0.01, drift
    assert drift[10] > drift[20] > drift[40], drift


def test_geodesic_energy_is_v_norm_of_initial_velocity(small):
    dom, K = small
    m0 = torch.randn(3, 2, 16, 16, dtype=torch.float64)
    shoot = GeodesicShooting(dom, K, 2)
    v0 = K.apply(m0)
    expected = dom.cell_volume * (m0 * v0).sum(dim=(-3, -2, -1))
    torch.testing.assert_close(shoot.energy(m0), expected)
    assert (shoot.energy(m0) > 0).all()


def test_batch_equals_single_calls(small):
    dom, K = small
    shoot = GeodesicShooting(dom, K, 4)
    m0 = torch.stack([bump_momentum(dom, 2.0, K, centre=(c, -c)) for c in (-2.0, 0.0, 3.0)])
    tmpl = torch.stack([disc(dom, radius=r) for r in (4.0, 5.0, 6.0)])
    batch = shoot(m0, tmpl, return_all=True)
    for b in range(3):
        single = shoot(m0[b], tmpl[b], return_all=True)
        for field in ShootingResult._fields:
            torch.testing.assert_close(getattr(batch, field)[b], getattr(single, field), rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------- gradients
def directional_check(fn, x, seed, eps=1e-6):
    """``<grad fn(x), d>`` against the central difference quotient along a random direction ``d``."""
    d = torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=x.dtype)
    x = x.detach().requires_grad_(True)
    (g,) = torch.autograd.grad(fn(x), x)
    with torch.no_grad():
        fd = (fn(x + eps * d) - fn(x - eps * d)) / (2 * eps)
    return float((g * d).sum()), float(fd)


@pytest.mark.parametrize("action", ["geometric", "mass_preserving"])
def test_gradients_match_finite_differences(action):
    dom = ImageDomain.paper(20)
    K = GaussianKernel(dom, 5.0)
    shoot = GeodesicShooting(dom, K, 4, action=action, backward="autograd")
    m0, tmpl = bump_momentum(dom, 3.0, K), disc(dom)
    w = torch.randn(20, 20, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def loss_m(m):
        return (w * shoot(m, tmpl)).sum() + 10.0 * shoot.energy(m)

    def loss_t(t):
        return (w * shoot(m0, t)).sum()

    for seed in range(3):
        analytic, fd = directional_check(loss_m, m0, seed)
        assert analytic == pytest.approx(fd, rel=1e-5, abs=1e-8)
        analytic, fd = directional_check(loss_t, tmpl, seed)
        assert analytic == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_checkpointing_gives_the_same_gradient(small):
    dom, K = small
    m0 = bump_momentum(dom, 2.0, K).requires_grad_(True)
    grads = []
    for ckpt in (True, False):
        shoot = GeodesicShooting(dom, K, 4, checkpoint=ckpt)
        (g,) = torch.autograd.grad(shoot(m0, disc(dom)).square().sum(), m0)
        grads.append(g)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------- Algorithm 1 warm start
@pytest.mark.slow
def test_shooting_initial_momentum_of_an_algorithm1_solution():
    """A converged Algorithm 1 solution is (numerically) a geodesic: shooting its m(t=0) reproduces it.

    Measured (32^2, N = 10, gamma 0.1): ||shot - solution|| / ||solution - template|| = 0.062 / 0.050 / 0.040 /
    0.037 after 250 / 500 / 1000 / 2000 iterations (gradient norm 0.040 / 0.014 / 0.0043 / 0.0006); with gamma
    0.01 (slower convergence) 0.093 after 500 and 0.078 after 2000 iterations.
    """
    solvers = pytest.importorskip("indreg.solvers")
    from indreg.deform.lddmm import LDDMMDeformation
    from indreg.forward import ParallelBeamGeometry, RayTransform

    dom = ImageDomain.paper(32)
    K = GaussianKernel(dom, 6.0)
    N = 10
    tmpl = disc(dom, radius=6.0)
    target = GeodesicShooting(dom, K, N)(bump_momentum(dom, 3.0, K, centre=(2.0, 0.0)), tmpl)
    T = RayTransform(dom, ParallelBeamGeometry.paper(10, 46))
    problem = solvers.IndirectRegistration(T, LDDMMDeformation(dom, N), K, tmpl, T(target), gamma=0.1)
    state = solvers.SolverState(momentum=problem.zero_momentum(), iteration=0)
    solvers.Algorithm1(problem, step_size=0.02, max_iter=500).run(state)
    solution = problem.deformed(state.momentum)
    shot = GeodesicShooting(dom, K, N, backward="paper")(state.momentum[0], tmpl)
    moved = (solution - tmpl).norm()
    assert moved > 0.9 * (target - tmpl).norm()          # the solver did deform the template
    assert (shot - solution).norm() <= 0.06 * moved, float((shot - solution).norm() / moved)


def saved_vector_fields(shoot, m0, template):
    """Size of the tensors autograd saves for the backward pass, in units of one vector field (2, nx, ny)."""
    seen = {}

    def pack(t):
        seen[(t.data_ptr(), t.dtype, tuple(t.shape))] = t.numel() * t.element_size()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        shoot(m0, template)
    return sum(seen.values()) / (m0.numel() * m0.element_size())


def test_checkpointing_bounds_the_saved_memory():
    """Measured at 32^2: 30.5 / 58.5 fields (N = 8 / 16) with checkpointing, 167.5 / 331.6 without."""
    dom = ImageDomain.paper(16)
    K = GaussianKernel(dom, 5.0)
    m0 = bump_momentum(dom, 2.0, K).requires_grad_(True)
    saved = {(ckpt, n): saved_vector_fields(GeodesicShooting(dom, K, n, checkpoint=ckpt), m0, disc(dom))
             for ckpt in (True, False) for n in (4, 8)}
    assert saved[True, 8] - saved[True, 4] <= 4 * 4         # <= 4 fields per time step (velocity, displacement, ...)
    assert saved[True, 8] < 0.25 * saved[False, 8]


def test_empty_batch_and_flag_types_are_refused(small):
    dom, K = small
    shoot = GeodesicShooting(dom, K, 2)
    m0 = torch.zeros(1, 2, 16, 16, dtype=torch.float64)
    for call in (lambda m: shoot(m, disc(dom)), shoot.shoot, shoot.velocity):
        with pytest.raises(ValueError, match=r"^momentum is empty \(shape \(0, 2, 16, 16\)\)"):
            call(m0[:0])
    with pytest.raises(ValueError, match=r"^template is empty \(shape \(0, 16, 16\)\)"):
        shoot(m0, disc(dom)[None][:0])
    for bad in ("no", None, 1):
        with pytest.raises(TypeError, match="^checkpoint must be True or False, got "):
            GeodesicShooting(dom, K, 2, checkpoint=bad)
    with pytest.raises(TypeError, match="^corrector_steps must be an integer >= 0, got True"):
        GeodesicShooting(dom, K, 2, corrector_steps=True)
