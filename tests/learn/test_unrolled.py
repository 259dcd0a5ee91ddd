"""Tests of UnrolledMomentum (indreg/learn/unrolled.py): gradients in float64, the updates computed outside the
module, memory, errors."""
import pytest
import torch

from indreg.learn import MomentumUNet, UnrolledDescent, UnrolledMomentum, indirect_gradient

from unrolled_problems import small_problem


def _scheme(loss, gradient="detached", shared=False, initial=True, seed=1):
    torch.manual_seed(seed)
    init = MomentumUNet(2, width=2, levels=1, momentum_scale=0.01) if initial else None
    scheme = UnrolledMomentum(loss, num_updates=2, width=2, levels=1, shared=shared, initial=init,
                              momentum_scale=0.01, gradient=gradient).double()
    for p in scheme.parameters():               # away from the zero-initialised heads: every step does something
        torch.nn.init.normal_(p, std=0.3)
    return scheme


def _heads(scheme):
    return [p for net in scheme.updates for p in (net.head.weight, net.head.bias)]


def _with_heads(scheme, values, *args):
    names = [f"updates.{k}.head.{w}" for k in range(len(scheme.updates)) for w in ("weight", "bias")]
    return torch.func.functional_call(scheme, dict(zip(names, values)), args)


def _explicit(scheme, template, fbp, data, loss, frozen=None):
    """The ``K`` updates written out: m_{k+1} = m_k + U_k(m_k / s_m, grad_k / s_g, W(m_k, I), I, FBP), the gradient
    by autograd of the loss outside the module (or the given ``frozen`` gradients and deformed templates)."""
    m = scheme.initial(torch.stack([template, fbp], dim=1)).detach()
    for k, net in enumerate(scheme.updates if not scheme.shared else [scheme.updates[0]] * scheme.num_updates):
        if frozen is None:
            x = m.detach().requires_grad_(True)
            grad, = torch.autograd.grad(loss.terms(x, template, data)["loss"].sum(), x)
            deformed = loss.shooting(m.detach(), template)
        else:
            grad, deformed = frozen[k]
        x = torch.cat([m / scheme.momentum_scale, grad / scheme.gradient_scale,
                       torch.stack([deformed, template, fbp], dim=1)], dim=1)
        m = m + net(x)
    return m


@pytest.mark.slow   # ~25 s idle: the full gradcheck of every head's entries through double backward
def test_gradcheck_of_the_exact_scheme():
    """gradient="exact": the derivative of the whole map (double backward through shooting and projector)."""
    loss, template, fbp, data = small_problem()
    scheme = _scheme(loss, "exact")
    scheme.train_initial = True                 # the template's path through m_0 too
    heads = [p.detach().clone().requires_grad_(True) for p in _heads(scheme)]
    assert torch.autograd.gradcheck(lambda *v: _with_heads(scheme, v, template, fbp, data), tuple(heads),
                                    eps=1e-6, atol=1e-6, rtol=1e-5)
    tmpl = template.clone().requires_grad_(True)    # and the template, through m_0 and every step (projections)
    assert torch.autograd.gradcheck(lambda *v: _with_heads(scheme, v[:-1], v[-1], fbp, data), (*heads, tmpl),
                                    eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_detached_scheme_is_the_map_with_frozen_gradients():
    """gradient="detached" (as trained): its backward is the derivative of the K updates with grad_k and
    W(m_k, I) held at their values, a map gradcheck verifies."""
    loss, template, fbp, data = small_problem()
    scheme = _scheme(loss)
    with torch.no_grad():
        momenta = scheme.trajectory(template, fbp, data)
    frozen = []
    for m in momenta[:-1]:
        x = m.clone().requires_grad_(True)
        grad, = torch.autograd.grad(loss.terms(x, template, data)["loss"].sum(), x)
        frozen.append((grad, loss.shooting(m, template)))
    weights = torch.randn(2, 2, 8, 8, dtype=torch.float64)
    (scheme(template, fbp, data) * weights).sum().backward()
    heads = [p.detach().clone().requires_grad_(True) for p in _heads(scheme)]

    def frozen_map(*values):
        names = [f"{k}.head.{w}" for k in range(2) for w in ("weight", "bias")]
        nets = torch.nn.ModuleList(scheme.updates)
        params = dict(nets.named_parameters())
        params.update(dict(zip(names, values)))
        with torch.nn.utils.stateless._reparametrize_module(nets, params):
            return _explicit(scheme, template, fbp, data, loss, frozen)

    assert torch.autograd.gradcheck(frozen_map, tuple(heads), eps=1e-6, atol=1e-6, rtol=1e-5)
    expected = torch.autograd.grad((frozen_map(*heads) * weights).sum(), heads)
    for p, g in zip(_heads(scheme), expected):
        torch.testing.assert_close(p.grad, g)
    assert all(p.grad is None for p in scheme.initial.parameters())    # the one-shot network stays fixed


def test_trained_scheme_equals_explicit_updates():
    loss, template, fbp, data = small_problem(n=16, angles=4, num_steps=3, batch=3)
    scheme = _scheme(loss)
    scheme.calibrate(template, fbp, data)
    optimizer = torch.optim.Adam(scheme.parameters(), lr=1e-2)
    for _ in range(3):                          # a few steps of the training the app does
        optimizer.zero_grad()
        loss(scheme(template, fbp, data), template, data).backward()
        optimizer.step()
    with torch.no_grad():
        out = scheme(template, fbp, data)
    torch.testing.assert_close(out, _explicit(scheme, template, fbp, data, loss), rtol=1e-10, atol=1e-12)
    shared = _scheme(loss, shared=True)
    assert len(shared.updates) == 1
    torch.testing.assert_close(shared(template, fbp, data), _explicit(shared, template, fbp, data, loss))


def test_start_stop_and_calibration():
    loss, template, fbp, data = small_problem(n=16, angles=4)
    scheme = UnrolledMomentum(loss, num_updates=3, width=4, levels=2).double()
    m = scheme.trajectory(template, fbp, data)
    assert len(m) == 4 and not any(x.any() for x in m)     # from zero, zero-initialised heads: m_k = 0
    x = torch.zeros_like(m[0]).requires_grad_(True)
    grad, = torch.autograd.grad(loss.terms(x, template, data)["loss"].sum(), x)
    assert scheme.calibrate(template, fbp, data) == pytest.approx(float(grad.square().mean((1, 2, 3)).sqrt().mean()))
    assert "gradient_scale" in scheme.state_dict()
    small, t8, f8, d8 = small_problem()
    one_shot = _scheme(small)
    torch.testing.assert_close(one_shot(t8, f8, d8, num_updates=0), one_shot.initial(torch.stack([t8, f8], 1)))


def test_checkpointed_updates_keep_less_for_backward():
    """Memory: a checkpointed update keeps its inputs only; a detached gradient keeps no graph at all."""
    loss, template, fbp, data = small_problem(n=16, angles=4)
    m = torch.zeros(2, 2, 16, 16, dtype=torch.float64, requires_grad=True)
    grad, deformed = indirect_gradient(loss, m, template, data)
    assert grad.grad_fn is None and deformed.grad_fn is None and loss.shooting.checkpoint

    def saved(checkpoint):
        torch.manual_seed(0)
        scheme = UnrolledMomentum(loss, num_updates=3, width=8, levels=2, checkpoint=checkpoint).double()
        total = []
        with torch.autograd.graph.saved_tensors_hooks(lambda t: total.append(t.numel()) or t, lambda t: t):
            scheme.update(0, m, grad, deformed, template, fbp)
        return sum(total)

    assert saved(True) * 4 < saved(False)


@pytest.mark.parametrize("scheme_class", [UnrolledMomentum, UnrolledDescent])
def test_errors(scheme_class):
    """The input errors both unrolled schemes share (the descent's own: test_descent.py)."""
    loss, template, fbp, data = small_problem()
    with pytest.raises(TypeError, match="loss must be an IndirectShootingLoss"):
        scheme_class(loss.shooting)
    with pytest.raises(ValueError, match="num_updates"):
        scheme_class(loss, num_updates=0)
    with pytest.raises(TypeError, match="initial must be an nn.Module"):
        scheme_class(loss, initial=lambda x: x)
    scheme = scheme_class(loss, num_updates=2, width=2, levels=1).double()
    with pytest.raises(ValueError, match=r"num_updates must be an integer in \[0, 2\], got 3"):
        scheme(template, fbp, data, num_updates=3)
    with pytest.raises(ValueError, match=r"data must have shape \(B=2, 3, 12\)"):
        scheme(template, fbp, data[:, :2])


def test_gradient_mode_error():
    with pytest.raises(ValueError, match="gradient must be one of detached, exact, got 'double'"):
        UnrolledMomentum(small_problem()[0], gradient="double")
