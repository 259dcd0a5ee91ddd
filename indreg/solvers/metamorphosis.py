"""Indirect metamorphosis (eq:Metam:ODE / eq:DirectMatchingMetamorphosisPDE): objective and solvers.

In the scale of ``objective.IndirectRegistration`` (half the printed objective, so the paper's gammas and step
sizes work unchanged):

    E(nu, zeta) = (gamma/2) sum_{i=0..N} (1/N) ||nu_i||_V^2 + (tau/2) sum_{i=0..N} (1/N) ||zeta_i||_L2^2
                  + (1/2) ||T f(1) - g||^2_data  (+ tv_weight TV(f(1)))

with ``f(1) = M(nu, zeta, I)`` the metamorphosis image path (``indreg.deform.MetamorphosisDeformation``) and
``nu = K m``. Large ``tau`` forbids intensity changes (LDDMM); small ``tau`` lets the source reconstruct the
image freely (a reconstruction with an ``L2`` penalty on the intensity change).

Optionally (``source_kernel``, a Gaussian kernel ``K_s`` of width ``source_sigma``) the source lives in an RKHS
like the velocity: ``zeta = K_s s`` and ``||zeta_i||^2`` is replaced by the RKHS norm ``<s_i, K_s s_i>_L2``,
which penalises rough intensity changes (noise and streaks of sparse-view data) more than smooth ones; the
iterate is then the source momentum ``s`` (``h_s = tau s + (N / cell_volume) dL/dzeta``, update ``s <- s - beta
h_s``, i.e. ``zeta <- zeta - beta K_s h_s``). Without it (the paper's ``L2([0,1], X)`` norm) ``s = zeta``.
A ``source_mask`` ``chi`` (values in [0, 1]) confines the intensity changes: ``zeta = chi K_s s`` (or ``chi s``),
the penalty unchanged, ``h_s = tau s + chi (N / cell_volume) dL/dzeta`` (e.g. ``template_support``: no intensity
is created where the template and its surroundings are empty).

L2 gradients (``L`` = data fit + TV of ``f(1)``, ``dL/d.`` the deformation's backward, torch entries):
``h_nu = gamma m + (N / cell_volume) dL/dnu`` (the V-gradient is ``K h_nu``, as Algorithm 1) and
``h_zeta = tau zeta + (N / cell_volume) dL/dzeta``, i.e. ``h_zeta(t_i) = tau zeta_i + lambda_i / cell_volume``
with ``lambda_i ~ |D phi_{t_i,1}| (T^*(T f(1) - g) o phi_{t_i,1})`` (the data gradient carried back to
``t_i``).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch

from .._checks import check_int, check_positive, check_same, check_tensor
from ..deform.metamorphosis import MetamorphosisDeformation
from ..forward.operator import operator_norm
from .objective import IndirectRegistration, check_nonnegative
from .state import IterativeSolver, SolverState, make_info, problems
from .torch_optim import _DEFAULTS, setup_common


class MetamorphosisRegistration:
    """Indirect metamorphosis ``min_{m, zeta} E(K m, zeta)`` (eq:Metam:ODE in the code's scale, module docstring).

    Args:
        ray_transform, kernel, template, data, gamma, tv_weight, tv_smoothing: as ``IndirectRegistration``.
        deformation: a ``MetamorphosisDeformation``.
        tau: weight (>= 0) of the source term's ``L2([0,1], L2)`` norm (the paper's ``tau``).
        source_kernel: None (the paper's L2 norm) or a ``GaussianKernel`` ``K_s`` on the domain: RKHS source
            ``zeta = K_s s`` (module docstring).
        source_mask: None or a ``(nx, ny)`` tensor with values in [0, 1] (the template's dtype / device): the
            source is multiplied by it (module docstring; ``template_support`` builds one).

    ``lddmm`` is the LDDMM problem with the same data (``deformation.lddmm``, gamma, TV): ``lddmm.deformed(m)``
    is the pure-deformation part ``W(nu, I)``.

    Convention:
        momentum / velocity ``(N+1, 2, nx, ny)``, source ``(N+1, nx, ny)`` at ``t_i = i/N``; the discrete
        ``L2([0,1], X)`` inner products are ``sum_{i=0..N} (1/N) <u_i, v_i>_X`` (N+1 terms, as LDDMM's);
        ``zeta_0`` does not enter ``f(1)`` (right Riemann sum), so it only feels the penalty and stays 0.
    """

    def __init__(self, ray_transform, deformation, kernel, template, data, gamma, tau, tv_weight=0.0,
                 tv_smoothing=1e-3, source_kernel=None, source_mask=None):
        if not isinstance(deformation, MetamorphosisDeformation):
            raise TypeError(f"deformation must be a MetamorphosisDeformation, got {type(deformation).__name__}")
        self.lddmm = IndirectRegistration(ray_transform, deformation.lddmm, kernel, template, data, gamma,
                                          tv_weight, tv_smoothing)
        self.deformation = deformation
        self.tau = check_nonnegative(tau, "tau")
        for name in ("ray_transform", "kernel", "domain", "template", "data", "gamma", "tv_weight",
                     "tv_smoothing", "num_steps", "momentum_shape", "time_weight"):
            setattr(self, name, getattr(self.lddmm, name))
        if source_kernel is not None and getattr(source_kernel, "domain", None) != kernel.domain:
            raise ValueError(f"source_kernel must be a GaussianKernel on the kernel's domain {kernel.domain}, got "
                             f"{source_kernel!r}")
        self.source_kernel = source_kernel
        if source_mask is not None:
            check_tensor(source_mask, "source_mask", tuple(self.domain.shape))
            check_same(source_mask, template, "source_mask", "template")
            if bool((source_mask < 0).any() | (source_mask > 1).any()):
                raise ValueError("source_mask must have values in [0, 1]")
        self.source_mask = source_mask

    def __repr__(self):
        return (f"MetamorphosisRegistration(domain={self.domain}, N={self.num_steps}, gamma={self.gamma}, "
                f"tau={self.tau}, tv_weight={self.tv_weight}, source_kernel={self.source_kernel!r})")

    def with_deformation(self, deformation: MetamorphosisDeformation) -> "MetamorphosisRegistration":
        """The same problem with another metamorphosis operator (e.g. ``backward="autograd"``)."""
        return MetamorphosisRegistration(self.ray_transform, deformation, self.kernel, self.template, self.data,
                                         self.gamma, self.tau, self.tv_weight, self.tv_smoothing, self.source_kernel,
                                         self.source_mask)

    @property
    def source_shape(self) -> tuple:
        """``(N+1, nx, ny)``."""
        return (self.num_steps + 1, *self.domain.shape)

    def zero_momentum(self) -> torch.Tensor:
        return self.lddmm.zero_momentum()

    def zero_source(self) -> torch.Tensor:
        """``zeta = 0`` (no intensity change), ``(N+1, nx, ny)`` in the template's dtype/device."""
        return torch.zeros(self.source_shape, dtype=self.template.dtype, device=self.template.device)

    def check(self, m, zeta) -> None:
        """Validate a momentum ``(N+1, 2, nx, ny)`` and a source ``(N+1, nx, ny)`` (the template's dtype/device)."""
        self.lddmm.check_momentum(m)
        check_tensor(zeta, "source", self.source_shape)
        check_same(zeta, self.template, "source", "template")

    def velocity(self, m: torch.Tensor) -> torch.Tensor:
        """``nu = K m`` (differentiable)."""
        return self.kernel.apply(m)

    def unmasked_source(self, s: torch.Tensor) -> torch.Tensor:
        """``K_s s`` (RKHS source) or ``s`` (L2 source), differentiable: the field whose pairing with ``s`` is the
        source's squared norm."""
        return s if self.source_kernel is None else self.source_kernel.apply(s)

    def source(self, s: torch.Tensor) -> torch.Tensor:
        """``zeta = chi K_s s`` (``chi`` the ``source_mask``, ``K_s`` the source kernel; each 1 when not given)."""
        u = self.unmasked_source(s)
        return u if self.source_mask is None else u * self.source_mask

    def image(self, m: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """``f(1) = M(K m, zeta, I)``, ``(nx, ny)`` (``s``: the source iterate, ``zeta = source(s)``)."""
        with torch.no_grad():
            return self.deformation(self.velocity(m), self.source(s), self.template)

    def parts(self, m: torch.Tensor, s: torch.Tensor) -> tuple:
        """``(W(nu, I), f(1) - W(nu, I))``: the pure deformation of the template and the intensity part."""
        with torch.no_grad():
            return self.deformation.parts(self.velocity(m), self.source(s), self.template)

    def trajectory(self, m: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """``f(t_i)`` for ``i = 0..N``, ``(N+1, nx, ny)``."""
        with torch.no_grad():
            return self.deformation.trajectory(self.velocity(m), self.source(s), self.template)

    def source_regulariser(self, s: torch.Tensor, unmasked: torch.Tensor) -> torch.Tensor:
        """``(tau/2) sum_i (1/N) <s_i, u_i>_L2``, ``u = unmasked_source(s)``: ``||zeta||^2`` in ``L2([0,1], L2)``
        (``u = s = zeta``) or in the source RKHS (``u = K_s s``)."""
        return 0.5 * self.tau * self.time_weight * torch.dot(s.reshape(-1), unmasked.reshape(-1))

    def terms(self, m: torch.Tensor, s: torch.Tensor, nu: torch.Tensor | None = None,
              unmasked: torch.Tensor | None = None) -> dict:
        """All terms as 0-dim tensors (differentiable; ``nu = K m``, ``unmasked = unmasked_source(s)`` if not
        given): ``data_fit``, ``tv``, ``regulariser`` (velocity), ``source_regulariser`` and ``objective``."""
        nu = self.velocity(m) if nu is None else nu
        unmasked = self.unmasked_source(s) if unmasked is None else unmasked
        zeta = unmasked if self.source_mask is None else unmasked * self.source_mask
        out = self.lddmm.matching(self.deformation(nu, zeta, self.template))
        out["regulariser"] = self.lddmm.regulariser(m, nu)
        out["source_regulariser"] = self.source_regulariser(s, unmasked)
        out["objective"] = out["data_fit"] + out["tv"] + out["regulariser"] + out["source_regulariser"]
        return out

    def evaluate(self, m: torch.Tensor, s: torch.Tensor) -> dict:
        """All terms as python floats (no gradient)."""
        self.check(m, s)
        with torch.no_grad():
            return {k: float(v) for k, v in self.terms(m, s).items()}

    def l2_gradient(self, m: torch.Tensor, s: torch.Tensor) -> tuple:
        """Terms (python floats) and the L2 gradients ``(h_nu, h_s)`` at ``(m, s)``; one forward/backward.

        ``h_s = tau s + (N / cell_volume) dL/dzeta`` (the L2 gradient in ``zeta`` for the L2 source; ``K_s h_s`` is
        the RKHS gradient otherwise). Returns ``(terms, h_nu, h_s, nu)`` (detached tensors, ``nu = K m``);
        ``K h_nu`` is the V-gradient.
        """
        with torch.no_grad():
            nu, unmasked = self.velocity(m), self.unmasked_source(s)
            zeta = unmasked if self.source_mask is None else unmasked * self.source_mask
        with torch.enable_grad():
            nu_leaf, zeta_leaf = nu.detach().requires_grad_(True), zeta.detach().requires_grad_(True)
            match = self.lddmm.matching(self.deformation(nu_leaf, zeta_leaf, self.template))
            dl_dnu, dl_dzeta = torch.autograd.grad(match["data_fit"] + match["tv"], (nu_leaf, zeta_leaf))
        h_nu = dl_dnu.div_(self.time_weight).add_(m, alpha=self.gamma)
        if self.source_mask is not None:
            dl_dzeta.mul_(self.source_mask)
        h_zeta = dl_dzeta.div_(self.time_weight).add_(s, alpha=self.tau)
        terms = {"data_fit": float(match["data_fit"].detach()), "tv": float(match["tv"].detach()),
                 "regulariser": float(self.lddmm.regulariser(m, nu)),
                 "source_regulariser": float(self.source_regulariser(s, unmasked))}
        terms["objective"] = sum(terms.values())
        return terms, h_nu, h_zeta, nu

    def gradient_norm(self, h: torch.Tensor) -> float:
        """``||h||_{L2([0,1], L2)}`` (velocity or source gradient)."""
        return self.lddmm.gradient_norm(h)

    def min_jacobian(self, nu: torch.Tensor) -> float:
        return self.lddmm.min_jacobian(nu)

    def source_lipschitz(self, num_iter: int = 30) -> float:
        """``(tau + ||T||^2) ||K_s||``: the Lipschitz constant of the source update at ``nu = 0`` (``f(1)`` depends
        on ``zeta`` through the average ``(1/N) sum zeta_i``, of norm 1 in ``L2([0,1], L2)``; ``||K_s|| = 1``
        for the L2 source, else the kernel's largest eigenvalue, at most ``K_s`` applied to ones); the step
        ``1 / source_lipschitz()`` is the ``"auto"`` source step size."""
        norm_t = operator_norm(self.ray_transform, num_iter, self.template.dtype, self.template.device)
        return (self.tau + norm_t ** 2) * self.source_kernel_norm()

    def source_kernel_norm(self) -> float:
        """``||K_s||`` bounded by its largest row sum (1 for the L2 source)."""
        if self.source_kernel is None:
            return 1.0
        ones = torch.ones(self.domain.shape, dtype=self.template.dtype, device=self.template.device)
        return float(self.source_kernel.apply(ones).max())


def template_support(template: torch.Tensor, domain, margin: float = 1.0, threshold: float = 0.01) -> torch.Tensor:
    """A ``source_mask``: 1 where ``|I| > threshold max |I|`` or within ``margin`` (physical units, a square
    neighbourhood) of such a pixel, else 0; ``(nx, ny)`` in the template's dtype / device."""
    kx, ky = (2 * max(int(round(margin / h)), 0) + 1 for h in domain.cell_sides)
    inside = (template.abs() > threshold * template.abs().max()).to(template.dtype)[None, None]
    return torch.nn.functional.max_pool2d(inside, (kx, ky), stride=1, padding=(kx // 2, ky // 2))[0, 0]


@dataclass
class MetamorphosisState(SolverState):
    """The iterate of a metamorphosis solver: momentum ``m`` (``nu = K m``), source iterate ``s`` (``(N+1, nx, ny)``;
    ``zeta = problem.source(s)``: ``s`` itself for the L2 source), iteration count. Solvers replace both tensors
    at every accepted step (never in place)."""

    source: torch.Tensor | None = None

    def state_dict(self) -> dict:
        return dict(super().state_dict(), source=self.source.detach().clone())

    def load_state_dict(self, d: dict) -> None:
        super().load_state_dict(d)
        self.source = d["source"].detach().clone()

    @classmethod
    def zeros(cls, problem: MetamorphosisRegistration) -> "MetamorphosisState":
        return cls(problem.zero_momentum(), 0, problem.zero_source())


def _info(iteration, terms, h_nu, h_zeta, problem, min_jac, step_sizes, evaluations, rejected, warnings) -> dict:
    """``state.make_info`` plus the source's regulariser, gradient norm and step size."""
    info = make_info(iteration, terms, problem.gradient_norm(h_nu), min_jac, step_sizes[0], evaluations, rejected,
                     warnings)
    info.update(source_regulariser=terms["source_regulariser"], source_grad_norm=problem.gradient_norm(h_zeta),
                source_step_size=float(step_sizes[1]))
    info["grad_norm"] = math.hypot(info["grad_norm"], info["source_grad_norm"])
    info["velocity_grad_norm"] = problem.gradient_norm(h_nu)
    return info


def _check_problem(problem):
    if not isinstance(problem, MetamorphosisRegistration):
        raise TypeError(f"problem must be a MetamorphosisRegistration, got {type(problem).__name__}")


def _check_state(state):
    if not isinstance(state, MetamorphosisState) or state.source is None:
        raise TypeError(f"state must be a MetamorphosisState with a source, got {type(state).__name__}")


class MetamorphosisDescent(IterativeSolver):
    """Gradient descent in the spirit of Algorithm 1 with separate step sizes for ``nu`` and ``zeta``:

        m <- m - alpha h_nu        (nu = K m: nu <- nu - alpha grad_V E, as Algorithm 1)
        s <- s - beta h_s          (L2 gradient step on zeta = s; with ``source_kernel`` zeta <- zeta - beta K_s h_s)

    Args:
        problem: a ``MetamorphosisRegistration``.
        step_size: ``alpha > 0`` (the paper's Algorithm 1 step sizes work unchanged).
        source_step_size: ``beta > 0``, or ``"auto"``: ``1 / ((tau + ||T||^2) ||K_s||)`` (``problem.source_lipschitz``).
        max_iter, grad_tol: as ``Algorithm1``; ``grad_norm`` is ``sqrt(|h_nu|^2 + |h_zeta|^2)`` (both
            ``L2([0,1], L2)`` norms), also reported separately (``velocity_grad_norm``, ``source_grad_norm``).
        step_halving: reject a step whose objective is non-finite, larger than the current one, or folds;
            halve both step sizes and retry, at most ``max_halvings`` times (as ``Algorithm1``).
        source_start: the source is kept fixed for the first ``source_start`` iterations (Algorithm 1 on
            ``nu`` alone: the deformation first explains what it can, then the source the remainder); 0
            (default) updates both from the start.
        jacobian_every: compute ``min_jacobian`` every this many iterations (always with ``step_halving``).

    ``step(state)`` (a ``MetamorphosisState``) returns ``Algorithm1``'s report plus ``source_regulariser``,
    ``source_grad_norm``, ``velocity_grad_norm`` and ``source_step_size``; one evaluation per iteration.
    """

    def __init__(self, problem: MetamorphosisRegistration, step_size: float = 0.02, source_step_size="auto",
                 max_iter: int = 200, grad_tol: float = 0.0, step_halving: bool = False, max_halvings: int = 10,
                 jacobian_every: int = 1, source_start: int = 0):
        _check_problem(problem)
        self.problem = problem
        self.step_size = check_positive(step_size, "step_size")
        if source_step_size == "auto":
            source_step_size = 1.0 / problem.source_lipschitz()
        self.source_step_size = check_positive(source_step_size, "source_step_size")
        self.max_iter = check_int(max_iter, "max_iter", 0)
        self.grad_tol = check_nonnegative(grad_tol, "grad_tol")
        self.step_halving = bool(step_halving)
        self.max_halvings = check_int(max_halvings, "max_halvings", 0)
        self.jacobian_every = check_int(jacobian_every, "jacobian_every", 1)
        self.source_start = check_int(source_start, "source_start", 0)
        self.evaluations = 0
        self._current = None  # (momentum, source, their versions, terms, h_nu, h_zeta, nu) of the iterate

    def __repr__(self):
        return (f"MetamorphosisDescent(step_size={self.step_size}, source_step_size={self.source_step_size:.4g}, "
                f"max_iter={self.max_iter}, step_halving={self.step_halving}, source_start={self.source_start})")

    def _evaluate(self, m, zeta):
        self.evaluations += 1
        return self.problem.l2_gradient(m, zeta)

    def _at(self, state: MetamorphosisState):
        _check_state(state)
        m, z = state.momentum, state.source
        c = self._current
        if c is None or c[0] is not m or c[1] is not z or c[2] != (m._version, z._version):
            self.problem.check(m, z)
            self._current = (m, z, (m._version, z._version), *self._evaluate(m, z))
        return self._current[3:]

    def _min_jacobian(self, nu, iteration: int) -> float:
        if self.step_halving or iteration % self.jacobian_every == 0:
            return self.problem.min_jacobian(nu)
        return math.nan

    def report(self, state: MetamorphosisState) -> dict:
        """The report at the current iterate (no step; ``min_jacobian`` always computed)."""
        terms, h_nu, h_zeta, nu = self._at(state)
        min_jac = self.problem.min_jacobian(nu)
        return _info(state.iteration, terms, h_nu, h_zeta, self.problem, min_jac,
                     (self.step_size, self.source_step_size), self.evaluations, False,
                     problems(terms["objective"], min_jac))

    def step(self, state: MetamorphosisState) -> dict:
        """One iteration (with optional step halving); mutates ``state``; returns the report at the new iterate."""
        terms, h_nu, h_zeta, nu = self._at(state)
        for attempt in range(1 + (self.max_halvings if self.step_halving else 0)):
            alpha, beta = self.step_size, self.source_step_size
            m_new = torch.add(state.momentum, h_nu, alpha=-alpha)
            z_new = state.source if state.iteration < self.source_start else \
                torch.add(state.source, h_zeta, alpha=-beta)
            new = self._evaluate(m_new, z_new)
            min_jac = self._min_jacobian(new[3], state.iteration + 1)
            warnings = problems(new[0]["objective"], min_jac, terms["objective"])
            if not (self.step_halving and warnings):
                break
            if attempt < self.max_halvings:
                self.step_size, self.source_step_size = alpha / 2, beta / 2
        rejected = bool(self.step_halving and warnings)
        if rejected:
            warnings = [f"step rejected after {self.max_halvings} halvings (kept the iterate): " + "; ".join(warnings)]
            new = (terms, h_nu, h_zeta, nu)
        else:
            state.momentum, state.source = m_new, z_new
            self._current = (m_new, z_new, (m_new._version, z_new._version), *new)
        state.iteration += 1
        return _info(state.iteration, new[0], new[1], new[2], self.problem, min_jac, (alpha, beta),
                     self.evaluations, rejected, warnings)

    def state_dict(self) -> dict:
        return {"step_size": self.step_size, "source_step_size": self.source_step_size,
                "evaluations": self.evaluations}

    def load_state_dict(self, d: dict) -> None:
        self.step_size = check_positive(d["step_size"], "step_size")
        self.source_step_size = check_positive(d["source_step_size"], "source_step_size")
        self.evaluations = int(d["evaluations"])
        self._current = None


class MetamorphosisTorchOptim(IterativeSolver):
    """Any ``torch.optim`` optimizer on ``(p, q)``: ``nu = K(c p)``, source iterate ``c q``, ``c = N / cell_volume``.

    As ``TorchOptimSolver``: with this scaling autograd's gradients are ``dE/dp = K h_nu`` (the V-gradient)
    and ``dE/dq = K_s h_s`` (the source's L2 gradient, or its RKHS gradient with ``source_kernel``), so E is an
    honest function of the parameters and
    a line search (L-BFGS ``strong_wolfe``) sees consistent values. ``lr`` applies to ``p``, ``source_lr``
    (default ``lr``) to ``q`` (two parameter groups; L-BFGS takes a single group, so it needs ``source_lr``
    unset or equal to ``lr``). ``backward``: "adjoint" (default, the exact custom backward) or "autograd".
    Reports as ``MetamorphosisDescent``; ``step(state)`` takes a ``MetamorphosisState``.
    """

    def __init__(self, problem: MetamorphosisRegistration, optimizer="lbfgs", lr: float | None = None,
                 source_lr: float | None = None, max_iter: int = 100, grad_tol: float = 0.0,
                 backward: str = "adjoint", jacobian_every: int = 1, **optimizer_kwargs):
        _check_problem(problem)
        if backward != problem.deformation.backward:
            M = problem.deformation
            problem = problem.with_deformation(MetamorphosisDeformation(M.domain, M.num_steps, backward,
                                                                        M.interpolation))
        cls = setup_common(self, problem, optimizer, lr, max_iter, grad_tol, jacobian_every)
        self.source_lr = self.lr if source_lr is None else check_positive(source_lr, "source_lr")
        if cls is torch.optim.LBFGS and self.source_lr != self.lr:
            raise ValueError(f"source_lr must equal lr for LBFGS (one parameter group), got {source_lr} and {lr}")
        self.p = torch.nn.Parameter(problem.zero_momentum())
        self.q = torch.nn.Parameter(problem.zero_source())
        groups = [{"params": [self.p, self.q]}] if cls is torch.optim.LBFGS else \
            [{"params": [self.p], "lr": self.lr}, {"params": [self.q], "lr": self.source_lr}]
        self.optimizer = cls(groups, lr=self.lr, **{**_DEFAULTS.get(cls, {}), **optimizer_kwargs})
        self.evaluations = 0
        self._cache = None

    def __repr__(self):
        return f"MetamorphosisTorchOptim(optimizer={type(self.optimizer).__name__}, lr={self.lr}, " \
               f"source_lr={self.source_lr}, max_iter={self.max_iter})"

    def _evaluate(self):
        """Terms, parameter gradients, L2 gradients and ``nu`` at the current parameters (cached by value)."""
        c = self._cache
        if c is not None and torch.equal(c[0], self.p.detach()) and torch.equal(c[1], self.q.detach()):
            return c[2:]
        with torch.enable_grad():
            m, s = self.scale * self.p, self.scale * self.q
            nu, unmasked = self.problem.velocity(m), self.problem.unmasked_source(s)
            terms = self.problem.terms(m, s, nu, unmasked)
            grad_p, grad_q, dnu, du = torch.autograd.grad(terms["objective"], (self.p, self.q, nu, unmasked))
        # dE/dnu at fixed m (dE/du at fixed s) holds half the regulariser's gradient; dE/dq = K_s h_s (L2
        # source: u is s itself, and dE/dq = h_s)
        h_nu = dnu / self.problem.time_weight + 0.5 * self.problem.gamma * m.detach()
        h_s = grad_q if self.problem.source_kernel is None else \
            du / self.problem.time_weight + 0.5 * self.problem.tau * s.detach()
        self.evaluations += 1
        terms = {k: float(v.detach()) for k, v in terms.items()}
        self._cache = (self.p.detach().clone(), self.q.detach().clone(), terms, grad_p, grad_q, h_nu, h_s,
                       nu.detach())
        return self._cache[2:]

    def _closure(self):
        terms, grad_p, grad_q, *_ = self._evaluate()
        self.p.grad, self.q.grad = grad_p.clone(), grad_q.clone()
        return torch.tensor(terms["objective"], dtype=self.p.dtype)

    def _sync(self, state: MetamorphosisState) -> None:
        _check_state(state)
        self.problem.check(state.momentum, state.source)
        with torch.no_grad():
            if not torch.equal(self.scale * self.p, state.momentum):
                self.p.copy_(state.momentum / self.scale)
            if not torch.equal(self.scale * self.q, state.source):
                self.q.copy_(state.source / self.scale)

    def _report(self, iteration, previous=None, min_jac=None) -> dict:
        terms, _, _, h_nu, h_zeta, nu = self._evaluate()
        if min_jac is None:
            min_jac = self.problem.min_jacobian(nu)
        return _info(iteration, terms, h_nu, h_zeta, self.problem, min_jac, (self.lr, self.source_lr),
                     self.evaluations, False, problems(terms["objective"], min_jac, previous))

    def report(self, state: MetamorphosisState) -> dict:
        self._sync(state)
        return self._report(state.iteration)

    def step(self, state: MetamorphosisState) -> dict:
        """One ``optimizer.step``; mutates ``state``; returns the report at the new iterate."""
        self._sync(state)
        previous = self._evaluate()[0]["objective"]
        self.optimizer.step(self._closure)
        state.iteration += 1
        state.momentum, state.source = (self.scale * self.p).detach(), (self.scale * self.q).detach()
        min_jac = None if state.iteration % self.jacobian_every == 0 else math.nan
        return self._report(state.iteration, previous, min_jac)

    def state_dict(self) -> dict:
        return {"optimizer": copy.deepcopy(self.optimizer.state_dict()), "p": self.p.detach().clone(),
                "q": self.q.detach().clone(), "evaluations": self.evaluations}

    def load_state_dict(self, d: dict) -> None:
        with torch.no_grad():
            self.p.copy_(d["p"])
            self.q.copy_(d["q"])
        self.optimizer.load_state_dict(copy.deepcopy(d["optimizer"]))
        self.evaluations = int(d["evaluations"])
        self._cache = None
