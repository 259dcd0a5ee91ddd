"""Tests of UnrolledDescent (indreg/learn/descent.py): the batched gradient against IndirectRegistration, the
untrained scheme against Algorithm 1, the trained map against K explicit updates, gradcheck of the map as trained."""
import math

import pytest
import torch

from indreg.deform.lddmm import LDDMMDeformation
from indreg.learn import MomentumUNet, UnrolledDescent, descent_gradient, descent_terms
from indreg.solvers import Algorithm1, IndirectRegistration, SolverState

from unrolled_problems import small_problem


def _registration(loss, template, data):
    s = loss.shooting
    return IndirectRegistration(loss.transforms[0], LDDMMDeformation(s.domain, s.num_steps), s.kernel, template, data,
                                gamma=loss.gamma)


def _scheme(loss, shared=True, correction=True, num_updates=3, seed=1, std=0.3, heavy_ball=True):
    torch.manual_seed(seed)
    init = MomentumUNet(2, width=2, levels=1, momentum_scale=0.01)
    scheme = UnrolledDescent(loss, num_updates=num_updates, step_size=0.05, width=2, levels=1, shared=shared,
                             correction=correction, initial=init, momentum_scale=0.01, heavy_ball=heavy_ball).double()
    for p in scheme.parameters():               # away from the zero-initialised heads: every step does something
        torch.nn.init.normal_(p, std=std)
    return scheme


def test_batched_gradient_is_the_problems_l2_gradient():
    loss, template, fbp, data = small_problem(n=16, angles=4, num_steps=3)
    m = 0.01 * torch.randn(2, 4, 2, 16, 16, dtype=torch.float64)
    h, deformed, residual = descent_gradient(loss, m, template, data)
    terms = descent_terms(loss, m, template, data)
    for b in range(2):
        problem = _registration(loss, template[b], data[b])
        p_terms, p_h, _ = problem.l2_gradient(m[b])
        torch.testing.assert_close(h[b], p_h)
        torch.testing.assert_close(deformed[b], problem.deformed(m[b]))
        assert float(terms["loss"][b]) == pytest.approx(2 * p_terms["objective"], rel=1e-12)
        r = loss.transforms[0](deformed[b]) - data[b]        # dL/df = T^* W (T f - g) in torch's scale
        expected = loss.transforms[0].transpose(r * loss.transforms[0].geometry.data_weight)
        torch.testing.assert_close(residual[b], expected)


@pytest.mark.parametrize("heavy_ball", [False, True])
def test_untrained_scheme_is_algorithm1_from_the_oneshot_geodesic(heavy_ball):
    """Zero correction heads, a_k = 0 and beta_k = 0: K steps are K Algorithm 1 iterations from the shot one-shot
    momentum."""
    loss, template, fbp, data = small_problem(n=16, angles=4, num_steps=3)
    torch.manual_seed(0)
    scheme = UnrolledDescent(loss, num_updates=4, step_size=0.05, width=4, levels=2, heavy_ball=heavy_ball,
                             initial=MomentumUNet(2, 4, 2, momentum_scale=0.01), momentum_scale=0.01).double()
    torch.nn.init.normal_(scheme.initial.head.weight, std=0.5)
    with torch.no_grad():
        out = scheme(template, fbp, data)
    m0 = scheme.oneshot(template, fbp).detach()
    for b in range(2):
        problem = _registration(loss, template[b], data[b])
        state = SolverState(momentum=loss.shooting(m0[b:b + 1], template[b], return_all=True).momentum[0])
        Algorithm1(problem, step_size=0.05, max_iter=4).run(state)
        torch.testing.assert_close(out[b], state.momentum)


def _residual(loss, deformed, data):
    """``T^* W (T f - g)`` in torch's scale (``W`` the data weight)."""
    T = loss.transforms[0]
    return T.transpose((T(deformed) - data) * T.geometry.data_weight)


def _explicit(scheme, template, fbp, data, frozen=None):
    """The K updates written out from their definition, per sample through IndirectRegistration (or with the given
    frozen (h, f, r) per step)."""
    loss, s = scheme.loss, scheme.loss.shooting
    m = s(scheme.oneshot(template, fbp).detach(), template, return_all=True).momentum
    alphas = 0.05 * torch.nn.functional.softplus(scheme.step_logits) / math.log(2.0)
    previous = m
    for k in range(scheme.num_updates):
        if frozen is None:
            problems = [_registration(loss, template[b], data[b]) for b in range(len(m))]
            h = torch.stack([p.l2_gradient(m[b].detach())[1] for b, p in enumerate(problems)])
            deformed = torch.stack([p.deformed(m[b].detach()) for b, p in enumerate(problems)])
            residual = _residual(loss, deformed, data)
        else:
            h, deformed, residual = frozen[k]
        net = scheme.updates[0 if scheme.shared else k]
        beta = torch.tanh(scheme.inertia_logits[k - 1]) if scheme.heavy_ball and k else 0.0
        inertia = beta * (m - previous)                                     # beta_k (m_k - m_{k-1})
        previous, m = m, (m - alphas[k] * h + inertia
                          + net(torch.stack([deformed, residual / scheme.residual_scale, template], 1))[:, None])
    return m


@pytest.mark.parametrize("shared, heavy_ball", [(True, True), (False, True), (True, False)])
def test_trained_scheme_equals_explicit_updates(shared, heavy_ball):
    loss, template, fbp, data = small_problem(n=16, angles=4, num_steps=3, batch=3)
    scheme = _scheme(loss, shared=shared, heavy_ball=heavy_ball)
    assert len(scheme.updates) == (1 if shared else 3)
    scheme.calibrate(template, fbp, data)
    optimizer = torch.optim.Adam(scheme.parameters(), lr=1e-2)
    for _ in range(3):                          # a few steps of the training the app does
        optimizer.zero_grad()
        descent_terms(loss, scheme(template, fbp, data), template, data)["loss"].mean().backward()
        optimizer.step()
    assert all(p.grad is None for p in scheme.initial.parameters())    # the one-shot network stays fixed
    assert scheme.step_logits.grad.abs().min() > 0
    assert not heavy_ball or (scheme.inertias.shape == (2,) and scheme.inertia_logits.grad.abs().min() > 0)
    with torch.no_grad():
        out = scheme(template, fbp, data)
    torch.testing.assert_close(out, _explicit(scheme, template, fbp, data), rtol=1e-10, atol=1e-12)


def test_gradcheck_of_the_map_as_trained():
    """Detached h_k, W(K m_k, I), r_k: the backward is the derivative of the K updates with those held at their
    values; gradcheck of that map in the step logits, the heavy-ball coefficients and the correction's head, and the
    scheme's gradient equals it."""
    loss, template, fbp, data = small_problem()
    scheme = _scheme(loss)
    scheme.calibrate(template, fbp, data)
    with torch.no_grad():
        momenta = scheme.trajectory(template, fbp, data)
    frozen = [descent_gradient(loss, m, template, data) for m in momenta[:-1]]
    weights = torch.randn_like(momenta[-1])
    (scheme(template, fbp, data) * weights).sum().backward()
    names = ["step_logits", "inertia_logits", "updates.0.head.weight", "updates.0.head.bias"]
    params = dict(scheme.named_parameters())
    leaves = tuple(params[n].detach().clone().requires_grad_(True) for n in names)

    def frozen_map(*values):
        with torch.nn.utils.stateless._reparametrize_module(scheme, dict(zip(names, values))):
            return _explicit(scheme, template, fbp, data, frozen)

    assert torch.autograd.gradcheck(frozen_map, leaves, eps=1e-6, atol=1e-6, rtol=1e-5)
    expected = torch.autograd.grad((frozen_map(*leaves) * weights).sum(), leaves)
    for n, g in zip(names, expected):
        torch.testing.assert_close(params[n].grad, g)


def test_step_sizes_only_and_start_from_zero():
    loss, template, fbp, data = small_problem(n=16, angles=4)
    scheme = UnrolledDescent(loss, num_updates=2, step_size=0.05, correction=False, heavy_ball=False).double()
    assert len(scheme.updates) == 0 and torch.allclose(scheme.step_sizes, torch.full((2,), 0.05, dtype=torch.float64))
    assert not hasattr(scheme, "inertia_logits") and "inertia_logits" not in scheme.state_dict()
    m = scheme.trajectory(template, fbp, data)
    assert len(m) == 3 and not m[0].any() and m[1].any()
    problem = _registration(loss, template[0], data[0])
    torch.testing.assert_close(m[1][0], -0.05 * problem.l2_gradient(problem.zero_momentum())[1])
    assert scheme.calibrate(template, fbp, data) > 0 and "residual_scale" in scheme.state_dict()


def test_errors():
    loss, template, fbp, data = small_problem()
    with pytest.raises(ValueError, match="step_size"):    # the errors both schemes share: test_unrolled.py
        UnrolledDescent(loss, step_size=-1.0)
    with pytest.raises(ValueError, match=r"momentum must have shape \(B, 3, 2, 8, 8\)"):
        descent_terms(loss, torch.zeros(2, 2, 8, 8, dtype=torch.float64), template, data)
