"""model="residual" (indreg.problems.residual): LDDMM plus an intensity residual regularised by TV. Its gradient
(float64 gradcheck and finite differences), that it is LDDMM with the residual frozen, and a template that lacks an
intensity the data have: the residual recovers it, LDDMM cannot."""
import pytest
import torch

import indreg
from indreg import phantoms
from indreg.deform import GaussianKernel, LDDMMDeformation
from indreg.problems.residual import ResidualRegistration


def small(n=8, dtype=torch.float64):
    domain = indreg.ImageDomain.paper(n)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(6, 12))
    template = phantoms.get("j", domain).to(dtype)
    data = T(phantoms.get("v", domain).to(dtype))
    return domain, T, template, data


def problem(backward="exact", mu=0.3):
    domain, T, template, data = small()
    W = LDDMMDeformation(domain, num_steps=2, backward=backward, interpolation="compose")
    return ResidualRegistration(T, W, GaussianKernel(domain, 6.0), template, data, 1e-3, mu, 0.05)


def random_iterate(p, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = 0.05 * torch.randn(p.momentum_shape, generator=g, dtype=torch.float64)
    r = 0.1 * torch.randn(p.image_domain.shape, generator=g, dtype=torch.float64)
    return m, r


@pytest.mark.slow
def test_objective_gradcheck_float64():
    p = problem()
    m, r = random_iterate(p)
    m.requires_grad_(True), r.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda m, r: p.residual_terms(m, r)["objective"], (m, r), eps=1e-6, atol=1e-5)


def test_l2_gradients_match_finite_differences():
    """``E(x + e d) - E(x - e d) = 2 e (<h_nu, K d_m>-pairing) ...``: checked per entry, the residual's in L2
    (cell volume), the momentum's through autograd of E in m (``h_nu = dE/dnu / time_weight + gamma m``)."""
    p = problem()
    m, r = random_iterate(p)
    _, (h_m, h_r), nu = p.gradient((m, r))
    d = torch.randn(r.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    e = 1e-6
    fd = (p.evaluate_iterate((m, r + e * d))["objective"] - p.evaluate_iterate((m, r - e * d))["objective"]) / (2 * e)
    assert fd == pytest.approx(p.image_domain.cell_volume * float((h_r * d).sum()), rel=1e-5)
    with torch.enable_grad():     # h_nu: dE/dnu at fixed m over the time weight, plus gamma m
        nu_leaf = nu.clone().requires_grad_(True)
        t = p.residual_terms(m, r, nu_leaf)
        (d_nu,) = torch.autograd.grad(t["data_fit"] + t["residual_tv"], nu_leaf)
    assert torch.allclose(h_m, d_nu / p.time_weight + p.gamma * m, rtol=1e-10, atol=1e-12)


def test_at_zero_residual_the_objective_and_momentum_gradient_are_lddmm():
    p = problem()
    m, _ = random_iterate(p)
    lddmm = indreg.IndirectRegistration(p.ray_transform, p.deformation, p.kernel, p.template, p.data, p.gamma)
    terms, (h_m, _), _ = p.gradient((m, p.zero_residual()))
    ref_terms, (ref_h,), _ = lddmm.gradient((m,))
    # TV_eps(0) = eps |Omega| is a constant: the rest is LDDMM's objective
    assert terms["residual_tv"] == pytest.approx(p.residual_tv * p.smoothing * p.image_domain.cell_volume * 64)
    assert terms["objective"] - terms["residual_tv"] == pytest.approx(ref_terms["objective"], rel=1e-12)
    assert torch.allclose(h_m, ref_h, rtol=1e-12, atol=1e-14)


def test_with_the_residual_frozen_it_is_lddmm():
    _, T, template, data = small(16)
    options = dict(max_iter=6, num_steps=3, sigma=4.0)
    ref = indreg.register(template, data, T, **options)
    off = indreg.register(template, data, T, model="residual", residual_start_fraction=1.0, residual_finish_iter=0,
                          **options)
    assert torch.equal(off.momentum, ref.momentum) and torch.equal(off.deformed, ref.deformed)


def lacking(n=16, holdout=None, **options):
    """V plus a block of +0.5 that J lacks, registered from J by the residual model (12 iterations)."""
    domain = indreg.ImageDomain.paper(n)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(12, 24))
    template, target = phantoms.get("j", domain), phantoms.get("v", domain).clone()
    target[3:6, 3:6] += 0.5
    return indreg.register(template, T(target), T, model="residual", max_iter=12, num_steps=3, holdout=holdout,
                           **options)


def test_the_finish_minimises_the_anchored_tv_with_the_deformation_fixed():
    """The finish keeps the momentum and lowers ``(1/2)||T f - g||^2 + mu TV(f - W)`` (W fixed) from the loop's
    iterate; its f is nonnegative."""
    before, after = (lacking(residual_tv=1e-4, residual_finish_iter=k) for k in (0, 100))
    assert torch.equal(after.momentum, before.momentum)
    p = after.problem
    assert p.finish_info["residual_tv"] == p.residual_tv and after.intensity_part.abs().max() > 0
    assert float(after.deformed.min()) >= 0
    e = {k: p.evaluate_iterate((r.momentum, r.intensity_part))
         for k, r in (("before", before), ("after", after))}
    total = {k: v["data_fit"] + v["residual_tv"] for k, v in e.items()}   # smoothed TV: eps 1 % of the unit
    assert total["after"] < 0.5 * total["before"]


def test_auto_weight_is_chosen_by_the_held_out_angles():
    """``residual_tv="auto"`` with held-out angles: the finish tries the grid and keeps the weight with the least
    held-out residual, which is the run's reported one; without held-out angles it uses the fallback."""
    from indreg.registration.models import RESIDUAL_TV_FALLBACK, RESIDUAL_TV_GRID

    run = lacking(holdout=4, residual_finish_iter=60)
    info = run.problem.finish_info
    tried = info["holdout_by_weight"]
    assert len(tried) == len(RESIDUAL_TV_GRID) + len(info["widened"]) and len(set(tried.values())) == len(tried)
    best = min(tried, key=tried.get)
    assert info["residual_tv"] == best and info["chosen"] == ("loop" if info["holdout_loop"] <= tried[best]
                                                              else "finish")
    assert run.holdout["holdout_residual"] == pytest.approx(min(tried[best], info["holdout_loop"]), rel=1e-12)
    plain = lacking(residual_finish_iter=1)
    unit = plain.problem.mu_unit
    assert plain.problem.residual_tv == pytest.approx(RESIDUAL_TV_FALLBACK * unit)
    assert list(plain.problem.finish_info["holdout_by_weight"]) == [pytest.approx(RESIDUAL_TV_FALLBACK * unit)]


@pytest.mark.slow
def test_recovers_an_intensity_the_template_lacks():
    """The target is V plus a block of +0.5 that J has nowhere: LDDMM can only move J's intensities, the
    residual adds the block."""
    domain = indreg.ImageDomain.paper(24)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(10, 36))
    template, target = phantoms.get("j", domain), phantoms.get("v", domain).clone()
    target[4:8, 4:8] += 0.5
    options = dict(max_iter=60, num_steps=5, target=target)
    runs = {m: indreg.register(template, T(target), T, model=m, **options) for m in ("lddmm", "residual")}
    block = {m: float(r.deformed[4:8, 4:8].mean()) for m, r in runs.items()}
    truth = float(target[4:8, 4:8].mean())
    assert abs(block["residual"] - truth) < 0.5 * abs(block["lddmm"] - truth)
    assert runs["residual"].ssim > runs["lddmm"].ssim + 0.03
    assert runs["residual"].residual < 0.5 * runs["lddmm"].residual


def test_fast_solver_is_refused_in_one_line():
    _, T, template, data = small(16)
    with pytest.raises(ValueError, match="solver"):
        indreg.register(template, data, T, model="residual", solver="fast")


class _Scored:
    """A stand-in of ``indreg.evaluation.validation.Validation``: the held-out residual of ``f`` is ``score(f)``."""

    def __init__(self, score):
        self.residual = score


def _finished(score, candidates=(1e-3, 1e-2)):
    p = problem()
    p.finish_iter, p.mu_candidates = 20, tuple(candidates)
    m, r = random_iterate(p)
    return p, (m, r), p.finish((m, r), _Scored(score))


def test_the_finish_keeps_the_loops_result_where_it_is_better_held_out():
    """Every finish weight worse than the loop's own result on the held-out angles (as on a measured slice, 0.0843
    -> 0.0951 through the finish): the loop's result is kept, and the record says so."""
    loop = {}

    def score(f):   # the loop's reconstruction scores 0, anything else more
        return float((f - loop["f"]).norm())

    p = problem()
    m, r = random_iterate(p)
    loop["f"] = p.reconstruction((m, r))
    p.finish_iter, p.mu_candidates = 20, (1e-3, 1e-2)
    out = p.finish((m, r), _Scored(score))
    assert out[0] is m and out[1] is r
    assert p.finish_info["chosen"] == "loop" and p.finish_info["holdout_loop"] == 0.0
    assert min(p.finish_info["holdout_by_weight"].values()) > 0


def test_the_weight_grid_widens_while_the_best_sits_at_its_edge():
    """A held-out residual that falls with the weight (the distance to the anchor W; the loop's result scored worse
    than any): the best is the grid's top, so the grid grows by decades, at most MAX_WIDEN of them; the finish
    wins."""
    from indreg.problems.residual import MAX_WIDEN

    p = problem()
    m, r = random_iterate(p)
    W, loop = p.deformed(m), p.reconstruction((m, r))
    p.finish_iter, p.mu_candidates = 20, (1e-4, 1e-3)
    out = p.finish((m, r), _Scored(lambda f: float((f - W).norm()) + 100.0 * bool(torch.equal(f, loop))))
    info = p.finish_info
    assert info["widened"] == pytest.approx([1e-2, 1e-1, 1.0][:MAX_WIDEN])
    assert info["residual_tv"] == pytest.approx(max(info["widened"])) and info["chosen"] == "finish"
    assert torch.allclose(out[1] + W, p.reconstruction(out)) and not torch.equal(out[1], r)
