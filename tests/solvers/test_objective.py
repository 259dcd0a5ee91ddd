"""IndirectRegistration: the objective's parts, the L2 / V gradients, bad input."""
import math

import numpy as np
import pytest
import torch

from indreg.deform import functional as Fn
from indreg.solvers import IndirectRegistration, total_variation

from solver_problems import make_problem, smooth_momentum


def test_parts_equal_direct_computation(problem):
    m = smooth_momentum(problem)
    p, K, T, W = problem, problem.kernel, problem.ray_transform, problem.deformation
    terms = p.evaluate(m)
    nu = K(m)
    f = W(nu, p.template)
    data_fit = 0.5 * float(T.norm_data(T(f) - p.data)) ** 2
    reg = 0.5 * p.gamma * sum(float(K.inner_v(m[i], m[i])) / p.num_steps for i in range(p.num_steps + 1))
    assert terms["data_fit"] == pytest.approx(data_fit, rel=1e-12)
    assert terms["regulariser"] == pytest.approx(reg, rel=1e-12)
    assert terms["regulariser"] > 0 and terms["tv"] == 0.0
    assert terms["objective"] == pytest.approx(data_fit + reg, rel=1e-12)
    # weighted data norm: sum of squares times angle cell * detector cell
    w = T.geometry.data_weight
    assert data_fit == pytest.approx(0.5 * w * float(((T(f) - p.data) ** 2).sum()), rel=1e-6)
    assert torch.equal(p.deformed(m), f)
    assert p.trajectory(m).shape == (p.num_steps + 1, *p.domain.shape)


def test_tv_term_and_its_value():
    p = make_problem(tv_weight=0.3)
    m = smooth_momentum(p)
    f = p.deformed(m).numpy()
    hx, hy = p.domain.cell_sides
    padded = np.pad(f, ((0, 1), (0, 1)))                     # the image is 0 outside the domain
    gx = (padded[1:, :-1] - f) / hx
    gy = (padded[:-1, 1:] - f) / hy
    eps = p.tv_smoothing
    tv = p.domain.cell_volume * np.sqrt(gx ** 2 + gy ** 2 + eps ** 2).sum()
    # forward differences, zero padding (as the TV baseline, indreg.forward.tv)
    assert float(total_variation(torch.from_numpy(f), p.domain, eps)) == pytest.approx(tv, rel=1e-10)
    assert p.evaluate(m)["tv"] == pytest.approx(0.3 * tv, rel=1e-10)
    plain = total_variation(torch.zeros(p.domain.shape, dtype=torch.float64, requires_grad=True), p.domain, 0.0)
    plain.backward()  # plain TV at a constant image: value 0, subgradient 0, no nan
    assert float(plain.detach()) == 0.0


def _paper_update(p, nu, alpha):
    """Algorithm 1, lines 7-11, assembled independently from indreg.deform.functional pieces."""
    N, dom, K, T, scheme = p.num_steps, p.domain, p.kernel, p.ray_transform, p.deformation.scheme
    x = dom.points(dtype=nu.dtype)
    images = [p.template]                                      # line 7: I o phi_{t_i,0}
    for i in range(1, N + 1):
        images.append(Fn.warp(images[-1], x - nu[i] / N, dom))
    f = images[-1]
    grad_data = T.adjoint(T(f) - p.data)                        # T^*(T f - g)
    rho = [None] * (N + 1)                                      # lines 8-9 fused: |D phi_{t_i,1}| G o phi_{t_i,1}
    rho[N] = grad_data
    for i in range(N - 1, -1, -1):
        rho[i] = (1 + Fn.divergence(nu[i], dom, scheme) / N) * Fn.warp(rho[i + 1], x + nu[i] / N, dom)
    data_grad = torch.stack([rho[i] * Fn.gradient(images[i], dom, scheme) for i in range(N + 1)])
    grad_v = p.gamma * nu - K(data_grad)                        # line 10 (code's scale, no factor 2)
    return nu - alpha * grad_v                                  # line 11


@pytest.mark.parametrize("scale", [0.0, 1.5])
def test_algorithm1_update_equals_paper_formula(problem, scale):
    from indreg.solvers import Algorithm1, SolverState
    m = smooth_momentum(problem, scale=scale, seed=1) if scale else problem.zero_momentum()
    state = SolverState(m)
    Algorithm1(problem, step_size=0.02).step(state)
    expected = _paper_update(problem, problem.velocity(m), 0.02)
    got = problem.velocity(state.momentum)
    assert float((got - expected).abs().max()) <= 1e-10 * float(expected.abs().max())
    assert float((got - problem.velocity(m)).abs().max()) > 1e-6   # the step moved the field


@pytest.mark.parametrize("backward", ["paper", "autograd"])
def test_autograd_gradient_of_parametrisation_is_v_gradient(backward):
    """nu = K(s p), s = N / cell_volume: dE/dp (autograd) equals grad_V E = K h."""
    p = make_problem(backward=backward, gamma=0.05)
    m = smooth_momentum(p, seed=2)
    s = p.num_steps / p.domain.cell_volume
    param = (m / s).requires_grad_(True)
    p.terms(s * param)["objective"].backward()
    v_grad = p.v_gradient(m)
    assert float((param.grad - v_grad).abs().max()) <= 1e-11 * float(v_grad.abs().max())


def test_exact_gradient_matches_finite_difference():
    p = make_problem(backward="autograd", gamma=0.05, tv_weight=0.1)
    m = smooth_momentum(p, seed=3)
    terms, h, _ = p.l2_gradient(m)
    direction = smooth_momentum(p, seed=4)
    eps = 1e-5
    fd = (p.evaluate(m + eps * direction)["objective"] - p.evaluate(m - eps * direction)["objective"]) / (2 * eps)
    # dE along m-direction dm = <h, K dm>_{L2([0,1], L2)}
    analytic = p.time_weight * float((h * p.velocity(direction)).sum())
    assert analytic == pytest.approx(fd, rel=1e-6)
    assert terms["objective"] == pytest.approx(p.evaluate(m)["objective"], rel=1e-14)


def test_gradient_norm(problem):
    h = torch.ones(problem.momentum_shape, dtype=torch.float64)
    expected = math.sqrt((problem.num_steps + 1) * 2 * 32 * 32 * problem.domain.cell_volume / problem.num_steps)
    assert problem.gradient_norm(h) == pytest.approx(expected, rel=1e-14)


def test_bad_input(problem):
    T, W, K, I, g = problem.ray_transform, problem.deformation, problem.kernel, problem.template, problem.data
    with pytest.raises(ValueError, match="gamma"):
        IndirectRegistration(T, W, K, I, g, gamma=-1.0)
    with pytest.raises(ValueError, match="tv_weight"):
        IndirectRegistration(T, W, K, I, g, gamma=1.0, tv_weight=-0.1)
    with pytest.raises(ValueError, match="template must have shape"):
        IndirectRegistration(T, W, K, I[:-1], g, gamma=1.0)
    with pytest.raises(ValueError, match="data must have shape"):
        IndirectRegistration(T, W, K, I, g[:, :-1], gamma=1.0)
    with pytest.raises(TypeError, match="dtype"):
        IndirectRegistration(T, W, K, I, g.float(), gamma=1.0)
    with pytest.raises(ValueError, match="non-finite"):
        IndirectRegistration(T, W, K, I, g * float("nan"), gamma=1.0)
    with pytest.raises(ValueError, match="momentum must have shape"):
        problem.evaluate(torch.zeros(3, 2, 32, 32, dtype=torch.float64))


def test_constructor_arguments_are_type_checked(problem):
    # issue #19: gamma='1e-3' was accepted as 0.001 and kernel=None ended in an AttributeError traceback
    T, W, K, I, g = problem.ray_transform, problem.deformation, problem.kernel, problem.template, problem.data
    for bad in ("1e-3", True, None, 1e-3 + 0j):
        with pytest.raises(TypeError, match="^gamma must be a finite number >= 0, got "):
            IndirectRegistration(T, W, K, I, g, gamma=bad)
    with pytest.raises(TypeError, match="^tv_smoothing must be a finite number >= 0, got '0'"):
        IndirectRegistration(T, W, K, I, g, gamma=1.0, tv_smoothing="0")
    with pytest.raises(TypeError, match="^kernel must be a GaussianKernel, got NoneType"):
        IndirectRegistration(T, W, None, I, g, gamma=1.0)
    with pytest.raises(TypeError, match="^deformation must be an LDDMMDeformation, got GaussianKernel"):
        IndirectRegistration(T, K, K, I, g, gamma=1.0)
    with pytest.raises(TypeError, match="^ray_transform must be a linear operator .*NoneType lacks domain"):
        IndirectRegistration(None, W, K, I, g, gamma=1.0)
    with pytest.raises(TypeError, match="^template must be a torch.Tensor, got ndarray"):
        IndirectRegistration(T, W, K, I.numpy(), g, gamma=1.0)
    with pytest.raises(TypeError, match="^data must be a torch.Tensor, got list"):
        IndirectRegistration(T, W, K, I, g.tolist(), gamma=1.0)
    with pytest.raises(TypeError, match="^template must have a floating dtype"):
        IndirectRegistration(T, W, K, I.long(), g, gamma=1.0)
    # a weight must survive the cast to the problem's dtype (alpha of the float32 update)
    with pytest.raises(ValueError, match="^gamma must be representable in torch.float32"):
        IndirectRegistration(T, W, K, I.float(), g.float(), gamma=1e39)
    assert IndirectRegistration(T, W, K, I, g, gamma=1e39).gamma == 1e39
