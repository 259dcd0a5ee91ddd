"""The per-voxel uncertainty (indreg.evaluation.uncertainty): exact on a linear-Gaussian problem, and on a registration
computed without touching the run's result."""
import math

import pytest
import torch

import indreg
from indreg import phantoms
from indreg.evaluation.uncertainty import coverage, data_correction, perturbed_solutions, registration_uncertainty


def _linear_gaussian(n=40, m=25, noise=0.1, seed=0):
    """``g = A x + n``, ``x ~ N(x0, C)`` with a smooth ``C`` (squared exponential, width 3 cells, plus 1 % nugget):
    the posterior covariance ``(A^T A / s^2 + C^-1)^-1`` and the solver of the perturbed problem (module
    docstring), exact."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(m, n, generator=gen, dtype=torch.float64) / math.sqrt(n)
    i = torch.arange(n, dtype=torch.float64)
    C = torch.exp(-(i[:, None] - i[None, :]) ** 2 / 18.0) + 0.01 * torch.eye(n, dtype=torch.float64)
    Ci, x0 = torch.linalg.inv(C), torch.ones(n, dtype=torch.float64)
    post = torch.linalg.inv(A.T @ A / noise ** 2 + Ci)
    L = torch.linalg.cholesky(C)

    def solve(g, p):
        return post @ (A.T @ g / noise ** 2 + Ci @ (x0 + (0 if p is None else p)))

    return A, L, x0, post, solve, noise, gen


def test_perturbed_solutions_sample_the_exact_posterior():
    A, L, x0, post, solve, noise, gen = _linear_gaussian()
    x = x0 + L @ torch.randn(40, generator=gen, dtype=torch.float64)
    g = A @ x + noise * torch.randn(25, generator=gen, dtype=torch.float64)
    mean, sd = perturbed_solutions(solve, g, noise, 4000, seed=1,
                                   prior_draw=lambda r: L @ torch.randn(40, generator=r, dtype=torch.float64))
    exact = post.diagonal().sqrt()
    assert float(((sd - exact) / exact).abs().max()) < 0.07          # 4000 samples: about 1.1 % each
    assert float(((mean - solve(g, None)) / exact).abs().max()) < 0.1
    without_prior = perturbed_solutions(solve, g, noise, 400, seed=1)[1]   # the data's spread only: too small
    assert float((without_prior / exact).max()) < 0.9


def test_the_coverage_is_exact_on_a_linear_gaussian_problem():
    """Truths drawn from the prior, data from them: the posterior mean +- the perturbed solutions' standard deviation
    covers 68.3 % / 95.4 % of the truths' values."""
    A, L, x0, post, solve, noise, gen = _linear_gaussian(seed=2)
    draw = lambda r: L @ torch.randn(40, generator=r, dtype=torch.float64)   # noqa: E731
    _, sd = perturbed_solutions(solve, torch.zeros(25, dtype=torch.float64), noise, 3000, seed=3, prior_draw=draw)
    errors = []
    for _ in range(300):
        x = x0 + draw(gen)
        g = A @ x + noise * torch.randn(25, generator=gen, dtype=torch.float64)
        errors.append(solve(g, None) - x)
    c = coverage(torch.stack(errors), sd.expand(300, 40))
    assert abs(c[1] - 0.683) < 0.02 and abs(c[2] - 0.954) < 0.01


@pytest.fixture(scope="module")
def small():
    d = indreg.ImageDomain.paper(32)
    T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(10, 46))
    target = phantoms.get("v", d).double()
    g = T(target) + 0.05 * torch.randn(T.range_shape, generator=torch.Generator().manual_seed(0),
                                       dtype=torch.float64)
    return phantoms.get("j", d).double(), g, T


def test_register_reports_the_uncertainty_without_changing_its_result(small):
    I, g, T = small
    kw = dict(sigma=4.0, max_iter=6, holdout=5)
    on = indreg.register(I, g, T, uncertainty_samples=2, **kw)
    off = indreg.register(I, g, T, uncertainty=False, **kw)
    assert torch.equal(on.deformed, off.deformed) and off.uncertainty is None
    sd = on.uncertainty
    assert sd.shape == I.shape and bool(torch.isfinite(sd).all()) and float(sd.min()) >= 0 < float(sd.max())
    e = on.evaluation
    assert e["uncertainty_samples"] == 2 and e["uncertainty_seconds"] > 0 and e["split_projection_difference"] < 2e-3
    assert torch.allclose(on.data_part + on.prior_part, on.deformed, atol=1e-12)
    plain = indreg.register(I, g, T, sigma=4.0, max_iter=2)   # "auto": no held-out angles, no uncertainty
    assert plain.uncertainty is None and plain.data_part is not None
    with pytest.raises(ValueError, match="uncertainty"):
        indreg.register(I, g, T, uncertainty="yes", max_iter=1)


def test_a_known_noise_level_replaces_the_estimate(small):
    """``uncertainty_noise``: the re-drawn noise and the correction's stopping level are the given one."""
    I, g, T = small
    from indreg.units import noise_std

    kw = dict(sigma=4.0, max_iter=4, holdout=5, uncertainty_samples=2)
    estimated = indreg.register(I, g, T, **kw)
    given = indreg.register(I, g, T, uncertainty_noise=0.05, **kw)
    kept = [i for i in range(g.shape[0]) if i not in range(2, g.shape[0], 5)]
    assert estimated.evaluation["uncertainty_noise_sd"] == pytest.approx(noise_std(g[kept]))
    assert given.evaluation["uncertainty_noise_sd"] == 0.05
    assert not torch.equal(given.uncertainty, estimated.uncertainty)
    assert torch.equal(given.deformed, estimated.deformed)
    for bad in (-1.0, 0.0, float("nan"), "0.05"):
        with pytest.raises((ValueError, TypeError), match="uncertainty_noise"):
            indreg.register(I, g, T, uncertainty_noise=bad, **kw)


def test_the_samples_are_seeded_and_leave_the_problem_alone(small):
    I, g, T = small
    from indreg.registration.run import initial_state, setup

    s = setup(I, g, T, sigma=4.0, model="residual", residual_finish_iter=8)
    x = s.problem.finish(initial_state(s.problem).iterate, None)   # as build_result: the finish first
    data = s.problem.data.clone()
    a = registration_uncertainty(s.problem, x, samples=2, iterations=1, seed=5)
    b = registration_uncertainty(s.problem, x, samples=2, iterations=1, seed=5)
    assert torch.equal(a.sd, b.sd) and torch.equal(s.problem.data, data) and s.problem.mu_candidates
    with pytest.raises(TypeError, match="registration problem"):
        registration_uncertainty(object(), x)


def test_a_nonnegative_result_takes_no_correction_below_zero(small):
    """The residual model's finish makes ``f >= 0`` (``nonnegative``): the data's correction counts only as far as
    ``f + d >= 0``; where the result is 0 a correction that asks for less adds nothing to the samples' spread."""
    I, g, T = small
    from indreg.registration.run import initial_state, setup

    s = setup(I, g, T, sigma=4.0, model="residual", residual_finish_iter=8)
    x = s.problem.finish(initial_state(s.problem).iterate, None)
    assert s.problem.nonnegative
    f = s.problem.reconstruction(x).double()
    assert float(f.min()) >= 0
    d = data_correction(s.problem.ray_transform, f, s.problem.data, 0.02).double()
    below = (f + d < 0)
    assert int(below.sum()) > 10
    kept = registration_uncertainty(s.problem, x, samples=2, iterations=1, noise_sd=0.02)
    spread = registration_uncertainty(s.problem, x, samples=2, iterations=1, noise_sd=0.02, correction=False)
    assert torch.allclose(kept.sd.double().pow(2), spread.sd.double().pow(2) + torch.maximum(d, -f).pow(2))
    zero = below & (f == 0)
    assert int(zero.sum()) > 0 and torch.equal(kept.sd[zero], spread.sd[zero])
    s.problem.nonnegative = False   # as a result the loop kept (not the finish's): the whole correction
    whole = registration_uncertainty(s.problem, x, samples=2, iterations=1, noise_sd=0.02)
    assert bool((whole.sd[zero] > kept.sd[zero]).all())


def test_the_data_correction_stops_at_the_noise(small):
    I, g, T = small
    d = data_correction(T, I, g, 0.0, max_iter=60)
    r = T(I + d) - g
    assert float(T.inner_data(r, r)) < 0.05 * float(T.inner_data(g - T(I), g - T(I)))
    assert float(data_correction(T, I, g, 1e6).abs().max()) == 0.0   # all within the noise: nothing


def test_the_spread_is_taken_about_the_result():
    from indreg.evaluation.uncertainty import _Moments, _rms_about

    x = torch.randn(6, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    centre, m = torch.full((5,), 0.3, dtype=torch.float64), _Moments()
    for xb in x:
        m.add(xb)
    assert torch.allclose(_rms_about(m.mean, m.sd(), 6, centre), (x - centre).pow(2).mean(0).sqrt(), atol=1e-12)


@pytest.fixture(scope="module")
def split_angles():
    """20 angles, the odd ones held out; the truth ``V`` and its data with noise 0.05."""
    from indreg.evaluation.validation import split

    d = indreg.ImageDomain.paper(32)
    T = indreg.RayTransform(d, indreg.ParallelBeamGeometry.paper(20, 46))
    V = phantoms.get("v", d).double()
    g = T(V) + 0.05 * torch.randn(T.range_shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    TF, gF, held = split(T, g, list(range(1, 20, 2)))
    return V, TF, gF, (held.operator, held.data)


def test_the_held_out_data_confirm_a_later_correction(split_angles):
    """The noise level given 1.5 times too high (as the estimate runs on a 32-pixel detector) stops the discrepancy
    principle before a faint error: the held-out angles confirm a later CGLS iterate, which corrects it; an error
    too faint for them to confirm beyond their noise (a held-out decrease below 2 of its standard deviations) is
    not, nor is anything where the result is the truth."""
    V, TF, gF, held = split_angles
    x = indreg.ImageDomain.paper(32).points()
    blob = torch.exp(-((x[0] - 3.0) ** 2 + (x[1] + 4.0) ** 2) / 18.0).double()
    high = 0.075
    for size, within in ((0.02, 0.85), (0.3, 0.2)):
        f = V + size * blob
        assert size > 0.1 or float(data_correction(TF, f, gF, high).abs().max()) == 0.0
        d = data_correction(TF, f, gF, high, held_out=held)
        assert float((f + d - V).norm()) < within * float((size * blob).norm())
    assert float(data_correction(TF, V, gF, high, held_out=held).abs().max()) == 0.0
    faint = V + 0.005 * blob
    assert float(data_correction(TF, faint, gF, high, held_out=held).abs().max()) == 0.0
    assert float(data_correction(TF, faint, gF, high, held_out=held, z=0.0).abs().max()) > 0   # the test decides
    plain = data_correction(TF, faint, gF, 0.05)   # the noise level right: the discrepancy principle's stop is kept
    assert float(plain.abs().max()) > 0 and torch.equal(data_correction(TF, faint, gF, 0.05, held_out=held), plain)


class _Counted:
    """An operator that counts its forward and adjoint applications."""

    def __init__(self, T):
        self.T, self.calls = T, 0

    def __getattr__(self, name):
        return getattr(self.T, name)

    def __call__(self, x):
        self.calls += 1
        return self.T(x)

    def adjoint(self, y):
        self.calls += 1
        return self.T.adjoint(y)


def test_the_held_out_choice_takes_one_cgls_run(split_angles):
    """With held-out data the correction is a CGLS iterate later than the discrepancy principle's, found in one run
    (1 + 1 + 2 applications of the fitted operator per iteration, up to ``patience`` past the confirmed one): the
    discrepancy principle's first iterations are not computed twice."""
    from indreg.evaluation.parts import cgls

    V, TF, gF, held = split_angles
    x = indreg.ImageDomain.paper(32).points()
    f = V + 0.3 * torch.exp(-((x[0] - 3.0) ** 2 + (x[1] + 4.0) ** 2) / 18.0).double()
    counted = _Counted(TF)
    d = data_correction(counted, f, gF, 0.075, held_out=held, patience=4)
    b = gF - TF(f)
    bound = 0.075 * math.sqrt(float(TF.inner_data(torch.ones_like(b), torch.ones_like(b)).sum()))
    k = cgls(TF, b, bound, 100)[1]
    later = [j for j in range(k + 1, 60) if torch.equal(cgls(TF, b, 0.0, j)[0], d)]
    assert k >= 1 and len(later) == 1
    assert counted.calls <= 2 + 2 * (later[0] + 4)


def test_one_default_number_of_samples():
    # the option table (torch-free, read by the CLI) and the module give the same default (docs/evaluation.md, "Cost")
    from indreg import options
    from indreg.evaluation.uncertainty import SAMPLES

    assert next(o for o in options.CORE if o.name == "uncertainty_samples").default == SAMPLES
