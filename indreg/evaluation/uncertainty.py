"""A per-voxel standard deviation of a reconstruction by perturbed re-optimisation (randomise, then optimise).

For a linear-Gaussian problem, ``g = A x + n`` with ``n ~ N(0, s^2 I)`` and the prior ``x ~ N(x0, C)``, the
minimiser of ``||A x - (g + n_b)||^2 / s^2 + ||x - (x0 + p_b)||^2_{C^-1}`` with fresh draws ``n_b ~ N(0, s^2 I)``,
``p_b ~ N(0, C)`` is an exact sample of the posterior (randomised maximum likelihood; Oliver, He and Reynolds 1996;
Bardsley, Solonen, Haario and Laine 2014): :func:`perturbed_solutions` draws them and returns their mean and
standard deviation, which tend to the posterior's.

A registration is not linear and its regulariser is not a calibrated prior (indreg's relative ``gamma`` makes the
regulariser about 2e-6 of the objective on the HAADF walk-through: a Laplace approximation would take its spread
from that weight alone). :func:`registration_uncertainty` therefore re-optimises from the run's result, ``samples``
times, with warm starts: the data re-drawn with white noise of the level the data show
(``indreg.units.noise_std``; the option ``uncertainty_noise`` gives a known level instead: the estimate runs 30 %
high on a 32-pixel detector, docs/evaluation.md), the momentum moved by a smooth random field whose velocity has
``prior`` times the result's own root-mean-square velocity (an empirical-Bayes scale: the deformation the data
asked for measures how far the template was from them), then ``iterations`` steps of Algorithm 1 (and the residual
model's finish). Directions the data pin down relax back within those steps; those they do not (a missing wedge, a
flat region) keep the random move. The samples' root-mean-square deviation from the result is reported (their
spread, and their common drift where the run had not settled; the result is not estimated from the samples, so the
mean square is over ``samples``, not ``samples - 1``), and to its square is added the square of the data's own
correction (:func:`data_correction`): the change of the result that the data ask for beyond their noise, by CGLS on
the fitted data stopped at the noise level (the discrepancy principle) or later where the held-out data confirm the
later iterate beyond their own noise (cross-validation: the noise level estimated from the data runs high on a
small detector and stops the discrepancy principle early); where the result is constrained to ``f >= 0`` (the
problem's ``nonnegative``: the residual model's finish) only the part ``max(d, -f)`` that keeps it there. Where
the data disagree with the result by more than their noise, the disagreement is an error the re-optimisations,
started from the result, need not show. Nothing is scaled afterwards: held-out angles cannot calibrate a scale where
the noise dominates their residual (measured: the held-out residual of the paper's suite 1 at 10 dB lies below the
noise's estimate). Its calibration against the
truth is measured in docs/evaluation.md (the fraction of voxels whose error lies within one and two standard
deviations).

Convention: images ``problem.image_domain.shape``; the noise standard deviation per datum in the data's units.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from typing import Callable, Optional

import torch

__all__ = ["Uncertainty", "perturbed_solutions", "registration_uncertainty", "data_correction", "coverage", "SAMPLES",
           "ITERATIONS", "PRIOR"]

#: Defaults of :func:`registration_uncertainty` (chosen in docs/evaluation.md by their calibration and cost).
SAMPLES, ITERATIONS, PRIOR = 6, 5, 0.25


@dataclass
class Uncertainty:
    """:func:`registration_uncertainty`'s result.

    Attributes
    ----------
    sd : torch.Tensor
        The per-voxel standard deviation (the reconstruction's shape).
    mean : torch.Tensor
        The mean of the samples (the reconstruction's shape).
    samples : int
        The number of re-optimisations.
    iterations : int
        Algorithm 1 steps in each.
    noise_sd : float
        The data's noise standard deviation per datum.
    prior : float
        The momentum's draw relative to the result's velocity.
    seconds : float
        Wall time.
    """
    sd: torch.Tensor
    mean: torch.Tensor
    samples: int
    iterations: int
    noise_sd: float
    prior: float
    seconds: float

    def summary(self) -> dict:
        """The numbers, for ``metrics.json`` (keys ``uncertainty_*``)."""
        sd = self.sd.detach().double()
        return {"uncertainty_samples": self.samples, "uncertainty_iterations": self.iterations,
                "uncertainty_noise_sd": self.noise_sd, "uncertainty_prior": self.prior,
                "uncertainty_seconds": self.seconds, "uncertainty_mean_sd": float(sd.mean()),
                "uncertainty_max_sd": float(sd.max())}


class _Moments:
    """Welford's running mean and sum of squared deviations (no stack of samples is kept)."""

    def __init__(self):
        self.n, self.mean, self.m2 = 0, None, None

    def add(self, x: torch.Tensor) -> None:
        x = x.detach().double()
        self.n += 1
        if self.mean is None:
            self.mean, self.m2 = x.clone(), torch.zeros_like(x)
            return
        delta = x - self.mean
        self.mean.add_(delta / self.n)
        self.m2.add_(delta * (x - self.mean))

    def sd(self) -> torch.Tensor:
        return (self.m2 / max(self.n - 1, 1)).sqrt()


def perturbed_solutions(solve: Callable, data: torch.Tensor, noise_sd: float, samples: int, seed: int = 0,
                        prior_draw: Optional[Callable] = None) -> tuple:
    """Randomise, then optimise: ``solve(data + noise_sd n_b, p_b)`` for ``b < samples`` (module docstring).

    Parameters
    ----------
    solve : callable
        ``solve(g, p) -> x``: the estimate from data ``g`` with the prior's mean moved by ``p`` (None without a
        ``prior_draw``).
    data : torch.Tensor
        The data ``g``.
    noise_sd : float
        The noise's standard deviation per datum (>= 0).
    samples : int
        How many (>= 2).
    seed : int
        Seeds a private generator (the global one is left alone).
    prior_draw : callable, optional
        ``prior_draw(generator) -> p``: a draw of the prior's perturbation.

    Returns
    -------
    tuple
        ``(mean, sd)`` of the solutions, float64 (``sd`` with the ``samples - 1`` divisor).

    Raises
    ------
    ValueError
        ``samples < 2`` or a negative or non-finite ``noise_sd``.
    """
    if int(samples) < 2 or not (noise_sd >= 0 and math.isfinite(noise_sd)):
        raise ValueError(f"samples must be >= 2 and noise_sd finite and >= 0, got {samples}, {noise_sd}")
    gen = torch.Generator(device=data.device).manual_seed(int(seed))
    moments = _Moments()
    for _ in range(int(samples)):
        noise = torch.randn(data.shape, generator=gen, dtype=data.dtype, device=data.device)
        p = prior_draw(gen) if prior_draw is not None else None
        moments.add(solve(data + noise_sd * noise, p))
    return moments.mean, moments.sd()


def _momentum_draw(problem, m: torch.Tensor, prior: float) -> Callable:
    """``gen -> dm``: white noise in space, constant in time, scaled so that its velocity ``K dm`` has ``prior``
    times the root-mean-square of the result's velocity ``K m`` (0 when the result did not move)."""
    with torch.no_grad():
        target = float(problem.velocity(m).pow(2).mean().sqrt()) * prior

    def draw(gen: torch.Generator) -> torch.Tensor:
        xi = torch.randn(m.shape[1:], generator=gen, dtype=m.dtype, device=m.device).expand_as(m)
        if target == 0:
            return torch.zeros_like(m)
        with torch.no_grad():
            rms = float(problem.velocity(xi.contiguous()).pow(2).mean().sqrt())
        return xi * (target / rms) if rms > 0 else torch.zeros_like(m)

    return draw


def registration_uncertainty(problem, iterate: tuple, steps: Optional[list] = None, samples: int = SAMPLES,
                             iterations: int = ITERATIONS, prior: float = PRIOR, noise_sd: Optional[float] = None,
                             seed: int = 0, correction: bool = True, held_out: Optional[tuple] = None) -> Uncertainty:
    """The per-voxel standard deviation of a registration's reconstruction (module docstring).

    Parameters
    ----------
    problem : RegistrationProblem
        The run's problem (its operator and data are the fitted ones).
    iterate : tuple
        The run's final iterate (after the model's finish).
    steps : list, optional
        Algorithm 1's step sizes, one per entry of the iterate (the run's last ones; None: Algorithm 1's defaults).
    samples, iterations : int
        Re-optimisations, and Algorithm 1 steps in each (each costs about one iteration of the run).
    prior : float
        The momentum's random move relative to the result's velocity (0: the data's noise alone).
    noise_sd : float, optional
        The data's noise per datum (default ``indreg.units.noise_std(problem.data)``).
    seed : int
        Seeds the draws.
    correction : bool
        Add the data's correction beyond their noise (:func:`data_correction`) in quadrature (``max(d, -f)`` where
        ``problem.nonnegative``).
    held_out : tuple, optional
        ``(T_H, g_H)``: the run's held-out operator and data, which may take the correction past the discrepancy
        principle's stop (:func:`data_correction`; None: that stop alone).

    Returns
    -------
    Uncertainty

    Raises
    ------
    TypeError
        A problem without the protocol's ``data``, ``reconstruction`` and ``velocity``.
    """
    from ..solvers import Algorithm1, SolverState
    from ..units import noise_std

    for member in ("data", "reconstruction", "velocity", "iterate_names"):
        if not hasattr(problem, member):
            raise TypeError(f"registration_uncertainty needs a registration problem with {member}, got "
                            f"{type(problem).__name__}")
    t0 = time.perf_counter()
    data = problem.data
    sigma = noise_std(data) if noise_sd is None else float(noise_sd)
    sigma = 0.0 if not math.isfinite(sigma) else sigma
    names = tuple(problem.iterate_names)
    draw = _momentum_draw(problem, iterate[0], prior) if prior > 0 else None
    finish = getattr(problem, "finish", None)

    def solve(g: torch.Tensor, dm) -> torch.Tensor:
        replica = copy.copy(problem)
        replica.data = g
        start = [t.detach().clone() for t in iterate]
        if dm is not None:
            start[0] = start[0] + dm
        state = SolverState(start[0], 0, **dict(zip(names[1:], start[1:])))
        frozen = {"residual": iterations} if "residual" in names[1:] else None   # the finish re-solves it
        solver = Algorithm1(replica, step_size=None if steps is None else steps[0], max_iter=iterations,
                            steps=None if steps is None else dict(zip(names[1:], steps[1:])), frozen=frozen)
        solver.run(state)
        x = state.iterate
        if finish is not None:
            x = _finished(replica, x)
        return replica.reconstruction(x)

    mean, sd = perturbed_solutions(solve, data, sigma, samples, seed, draw)
    result = problem.reconstruction(iterate).detach().double()
    sd = _rms_about(mean, sd, int(samples), result)
    if correction:
        d = data_correction(problem.ray_transform, result.to(data.dtype), data, sigma, held_out=held_out).double()
        if getattr(problem, "nonnegative", False):   # a result constrained to f >= 0: no error takes it below 0
            d = torch.maximum(d, -result)
        sd = (sd.pow(2) + d.pow(2)).sqrt()
    return Uncertainty(sd.to(data.dtype), mean.to(data.dtype), int(samples), int(iterations), sigma, float(prior),
                       time.perf_counter() - t0)


def _rms_about(mean: torch.Tensor, sd: torch.Tensor, samples: int, centre: torch.Tensor) -> torch.Tensor:
    """The samples' root-mean-square deviation from ``centre`` from their ``mean`` and ``sd`` (divisor
    ``samples - 1``): ``sqrt(mean_b (x_b - centre)^2)``, a drift of every sample included; the divisor is
    ``samples`` because the centre is not estimated from them."""
    return (sd.pow(2) * ((samples - 1) / samples) + (mean - centre).pow(2)).sqrt()


def data_correction(operator, image: torch.Tensor, data: torch.Tensor, noise_sd: float, max_iter: int = 100,
                    held_out: Optional[tuple] = None, z: float = 2.0, patience: int = 10) -> torch.Tensor:
    """The change ``d`` of the image ``f`` that the data ask for beyond their noise: CGLS for ``T d = g - T f`` from 0.

    CGLS stops when the residual falls to the noise's norm ``noise_sd sqrt(#data)`` (the discrepancy principle; 0
    where the residual is already within the noise). With ``held_out = (T_H, g_H)``, data of angles ``T`` does not
    see, a later CGLS iterate is taken where the held-out data confirm it: the iterate that lowers the held-out
    squared residual most, counted only where that decrease ``D = 2 <r_H, T_H d> - ||T_H d||^2``
    (``r_H = g_H - T_H f``) exceeds ``z`` times its standard deviation under noise alone,
    ``2 noise_sd sqrt(w) ||T_H d||`` (``w`` the data weight), so that the held-out data's noise does not choose it.
    The later of the two iterates is returned: an overestimated noise level stops the discrepancy principle early,
    and a correction the fitted data ask for is kept where too few held-out angles can confirm it. The held-out
    search stops ``patience`` iterations after its last confirmed iterate, or at ``max_iter``.

    Parameters
    ----------
    operator : LinearOperator
        ``T``, the fitted data's operator.
    image : torch.Tensor
        ``f``, the result.
    data : torch.Tensor
        ``g``, the fitted data.
    noise_sd : float
        The noise's standard deviation per datum.
    max_iter : int
        CGLS iterations at most.
    held_out : tuple, optional
        ``(T_H, g_H)``.
    z : float
        The held-out decrease's significance, in standard deviations.
    patience : int
        Iterations without a better held-out iterate before CGLS stops.

    Returns
    -------
    torch.Tensor
        ``d``, the image's shape.
    """
    from .parts import cgls

    with torch.no_grad():
        b = data - operator(image)
        ones = torch.ones_like(b)
        bound = noise_sd * math.sqrt(max(float(operator.inner_data(ones, ones).sum()), 0.0))
        if held_out is None:
            return cgls(operator, b, bound, max_iter)[0]
        choose = _HeldOutChoice(operator, *held_out, image, b, noise_sd, bound, z, patience)
        d, _ = cgls(operator, b, 0.0, max_iter, callback=choose)
        return choose.result(d)


class _HeldOutChoice:
    """:func:`data_correction`'s choice among the CGLS iterates (a ``cgls`` callback on one run without a bound):
    the discrepancy principle's iterate (the first whose residual is within ``bound``) and the held-out data's
    (searched until ``patience`` iterations after the last confirmed one); the run goes on until both are known."""

    def __init__(self, T, T_H, g_H, image: torch.Tensor, b: torch.Tensor, noise_sd: float, bound: float, z: float,
                 patience: int):
        from .parts import _dnorm

        self.T, self.bound, self.dnorm = T, bound, _dnorm
        self.T_H, self.r_H, self.patience = T_H, g_H - T_H(image), patience
        ones = torch.ones_like(g_H)
        weight = float(T_H.inner_data(ones, ones).sum()) / max(g_H.numel(), 1)
        self.noise = 2.0 * z * noise_sd * math.sqrt(max(weight, 0.0))
        self.best, self.decrease, self.iteration, self.calls = torch.zeros_like(image), 0.0, 0, 0
        within = _dnorm(T, b) <= bound   # the residual already within the noise: the discrepancy principle's is 0
        self.discrepancy, self.discrepancy_at = (torch.zeros_like(image), 0) if within else (None, None)

    def __call__(self, d: torch.Tensor, r: torch.Tensor) -> bool:
        self.calls += 1
        if self.discrepancy is None and self.dnorm(self.T, r) <= self.bound:
            self.discrepancy, self.discrepancy_at = d.clone(), self.calls
        if self.calls - 1 - self.iteration < self.patience:   # the search had not stopped at the previous call
            q = self.T_H(d)
            qq = float(self.T_H.inner_data(q, q).sum())
            decrease = 2.0 * float(self.T_H.inner_data(self.r_H, q).sum()) - qq
            if decrease > self.decrease and decrease > self.noise * math.sqrt(max(qq, 0.0)):
                self.best, self.decrease, self.iteration = d.clone(), decrease, self.calls
        return self.discrepancy is not None and self.calls - self.iteration >= self.patience

    def result(self, last: torch.Tensor) -> torch.Tensor:
        """The later of the two iterates (``last``, the run's final one, where the bound was never reached)."""
        if self.discrepancy is None:
            self.discrepancy, self.discrepancy_at = last, self.calls
        return self.best if self.iteration > self.discrepancy_at else self.discrepancy


#: The residual model's finish in a sample: this fraction of the run's Chambolle-Pock iterations, warm-started, at
#: the weight the run chose (0.1 and 6 samples: docs/evaluation.md, "Cost").
FINISH_FRACTION = 0.1


def _finished(replica, x: tuple) -> tuple:
    """The model's finish on a sample at the run's chosen weight (``finish_info``), with fewer iterations."""
    info = getattr(replica, "finish_info", {}) or {}
    if "residual_tv" in info:
        replica.residual_tv = info["residual_tv"]
    replica.mu_candidates = ()
    replica.finish_iter = max(1, int(round(FINISH_FRACTION * getattr(replica, "finish_iter", 0))))
    return replica.finish(x, None)


def coverage(error: torch.Tensor, sd: torch.Tensor, mask: Optional[torch.Tensor] = None, k=(1.0, 2.0)) -> dict:
    """The fraction of voxels (of ``mask`` when given) whose ``|error|`` is at most ``k`` reported standard
    deviations, ``{k: fraction}`` (a Gaussian error: 0.683 at 1, 0.954 at 2).

    Parameters
    ----------
    error : torch.Tensor
        The reconstruction's error (e.g. reconstruction minus the truth).
    sd : torch.Tensor
        The reported per-voxel standard deviation, of ``error``'s shape.
    mask : torch.Tensor, optional
        The voxels counted (taken as boolean; default all).
    k : iterable of float
        The multiples of ``sd``.

    Returns
    -------
    dict
        ``{k: fraction}``, one entry per multiple (floats in [0, 1]).
    """
    e, s = error.detach().double().abs(), sd.detach().double()
    if mask is not None:
        e, s = e[mask.bool()], s[mask.bool()]
    return {kk: float((e <= kk * s).double().mean()) for kk in k}
