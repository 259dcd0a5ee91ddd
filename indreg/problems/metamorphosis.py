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
is created where the template and its surroundings are empty; ``data_support``: the data's visual hull, where every
ray through a point carries mass). A ``uniform_region`` ``U`` (0 / 1, where the data show mass the template lacks:
a specimen's surroundings) holds a uniform source, its mean over ``U`` at each time: ``zeta = B K_s s`` with the
projection ``B u = chi (1 - U) u + U mean_U(u)`` (self-adjoint, so ``h_s = tau s + B (N / cell_volume) dL/dzeta``);
before ``source_start`` (Algorithm 1 calls ``at_iteration``) only its uniform part ``U mean_U(u)`` is on.

``tau`` relative to the data term (``tau_rel``, docs/metamorphosis.md "Relative tau"): ``tau = tau_rel * ||T||^2
||K_s||`` (``tau_scale``; ``||K_s|| = 1`` for the L2 source). At ``nu = 0`` the source update is ``zeta <- zeta -
beta (tau + K_s T^* T) zeta + ...``; on the smoothest source (the top eigenvector of ``T^* T``, eigenvalue
``||T||^2``, where ``K_s`` acts as ``||K_s||``) the source penalty is ``tau_rel`` times the data term's curvature,
so the source alone explains the fraction ``1 / (1 + tau_rel)`` of that component of the residual, whatever the
number of angles, detector sampling, domain size or source width.

L2 gradients (``L`` = data fit + TV of ``f(1)``, ``dL/d.`` the deformation's backward, torch entries):
``h_nu = gamma m + (N / cell_volume) dL/dnu`` (the V-gradient is ``K h_nu``, as Algorithm 1) and
``h_zeta = tau zeta + (N / cell_volume) dL/dzeta``, i.e. ``h_zeta(t_i) = tau zeta_i + lambda_i / cell_volume``
with ``lambda_i ~ |D phi_{t_i,1}| (T^*(T f(1) - g) o phi_{t_i,1})`` (the data gradient carried back to
``t_i``).
"""
from __future__ import annotations

import functools

import torch

from .._checks import check_int, check_same, check_tensor
from ..deform.metamorphosis import MetamorphosisDeformation
from ..forward.operator import operator_norm
from .lddmm import IndirectRegistration, check_nonnegative
from .problem import RegistrationProblem

__all__ = ["MetamorphosisRegistration", "template_support", "data_support", "noise_std", "opened"]


class MetamorphosisRegistration(RegistrationProblem):
    """Indirect metamorphosis ``min_{m, zeta} E(K m, zeta)`` (eq:Metam:ODE in the code's scale, module docstring).

    Parameters
    ----------
    ray_transform, kernel, template, data, gamma, tv_weight, tv_smoothing
        As ``IndirectRegistration``.
    deformation : MetamorphosisDeformation
        The image path ``M(nu, zeta, I)``.
    tau : float or None
        Weight (>= 0) of the source term's ``L2([0,1], L2)`` norm (the paper's ``tau``), or None with
        ``tau_rel``.
    source_kernel : GaussianKernel, optional
        None (the paper's L2 norm) or ``K_s`` on the kernel's domain: RKHS source ``zeta = K_s s`` (module
        docstring).
    source_mask : torch.Tensor, optional
        A ``domain.shape`` tensor with values in [0, 1] (the template's dtype / device): the source is multiplied
        by it (module docstring; ``template_support`` builds one).
    tau_rel : float, optional
        ``tau`` relative to the data term: ``tau = tau_rel * tau_scale`` (module docstring); exactly one of
        ``tau`` and ``tau_rel`` is given.
    uniform_region : torch.Tensor, optional
        A 0 / 1 ``domain.shape`` tensor (the template's dtype / device), where the source is uniform (its mean
        over the region at each time) and on from the first iteration (module docstring).
    source_start : int
        With ``uniform_region``, the iterations (Algorithm 1's, ``at_iteration``) during which only the uniform
        part of the source is on; the rest of it stays 0 until then.

    Raises
    ------
    TypeError
        A deformation that is no ``MetamorphosisDeformation``, and the errors of ``IndirectRegistration``.
    ValueError
        Both or neither of ``tau`` and ``tau_rel``, a negative weight, a source kernel on another domain, a mask
        of the wrong shape or outside [0, 1], a region not 0 / 1 or all 0, and the errors of
        ``IndirectRegistration``.

    ``lddmm`` is the LDDMM problem with the same data (``deformation.lddmm``, gamma, TV): ``lddmm.deformed(m)``
    is the pure-deformation part ``W(nu, I)``.

    Notes
    -----
    momentum / velocity ``(N+1, 2, nx, ny)``, source ``(N+1, nx, ny)`` at ``t_i = i/N`` (3D: ``(N+1, 3, nx,
    ny, nz)`` and ``(N+1, nx, ny, nz)``, template ``(nx, ny, nz)``: the same code); the discrete
    ``L2([0,1], X)`` inner products are ``sum_{i=0..N} (1/N) <u_i, v_i>_X`` (N+1 terms, as LDDMM's);
    ``zeta_0`` does not enter ``f(1)`` (right Riemann sum), so it only feels the penalty and stays 0.
    """

    def __init__(self, ray_transform, deformation, kernel, template, data, gamma, tau, tv_weight=0.0,
                 tv_smoothing=1e-3, source_kernel=None, source_mask=None, tau_rel=None, uniform_region=None,
                 source_start: int = 0):
        if not isinstance(deformation, MetamorphosisDeformation):
            raise TypeError(f"deformation must be a MetamorphosisDeformation, got {type(deformation).__name__}")
        self.lddmm = IndirectRegistration(ray_transform, deformation.lddmm, kernel, template, data, gamma,
                                          tv_weight, tv_smoothing)
        self.deformation = deformation
        for name in ("ray_transform", "kernel", "domain", "template", "data", "gamma", "tv_weight",
                     "tv_smoothing", "num_steps", "momentum_shape"):
            setattr(self, name, getattr(self.lddmm, name))
        if source_kernel is not None and getattr(source_kernel, "domain", None) != kernel.domain:
            raise ValueError(f"source_kernel must be a GaussianKernel on the kernel's domain {kernel.domain}, got "
                             f"{source_kernel!r}")
        self.source_kernel = source_kernel
        if (tau is None) == (tau_rel is None):
            raise ValueError(f"give exactly one of tau and tau_rel, got tau={tau!r}, tau_rel={tau_rel!r}")
        self.tau = check_nonnegative(tau, "tau") if tau_rel is None else \
            check_nonnegative(tau_rel, "tau_rel") * self.tau_scale
        if source_mask is not None:
            check_tensor(source_mask, "source_mask", tuple(self.domain.shape))
            check_same(source_mask, template, "source_mask", "template")
            if bool((source_mask < 0).any() | (source_mask > 1).any()):
                raise ValueError("source_mask must have values in [0, 1]")
        self.source_mask = source_mask
        if uniform_region is not None:
            check_tensor(uniform_region, "uniform_region", tuple(self.domain.shape))
            check_same(uniform_region, template, "uniform_region", "template")
            if bool(((uniform_region != 0) & (uniform_region != 1)).any()) or not bool(uniform_region.any()):
                raise ValueError("uniform_region must have values 0 or 1, some of them 1")
        self.uniform_region = uniform_region
        self.source_start = check_int(source_start, "source_start", 0)
        self.early = False   # before source_start: only the uniform part of the source is on (at_iteration)

    def __repr__(self):
        return (f"MetamorphosisRegistration(domain={self.domain}, N={self.num_steps}, gamma={self.gamma}, "
                f"tau={self.tau}, tv_weight={self.tv_weight}, source_kernel={self.source_kernel!r})")

    def with_deformation(self, deformation: MetamorphosisDeformation) -> "MetamorphosisRegistration":
        """The same problem with another metamorphosis operator (e.g. ``backward="autograd"``)."""
        return MetamorphosisRegistration(self.ray_transform, deformation, self.kernel, self.template, self.data,
                                         self.gamma, self.tau, self.tv_weight, self.tv_smoothing, self.source_kernel,
                                         self.source_mask, None, self.uniform_region, self.source_start)

    @property
    def source_shape(self) -> tuple:
        """``(N+1, *shape)``."""
        return (self.num_steps + 1, *self.domain.shape)

    def zero_momentum(self) -> torch.Tensor:
        return self.lddmm.zero_momentum()

    def zero_source(self) -> torch.Tensor:
        """``zeta = 0`` (no intensity change), ``(N+1, *shape)`` in the template's dtype/device."""
        return torch.zeros(self.source_shape, dtype=self.template.dtype, device=self.template.device)

    def check(self, m, zeta) -> None:
        """Validate a momentum ``(N+1, d, *shape)`` and a source ``(N+1, *shape)`` (the template's dtype/device)."""
        self.lddmm.check_momentum(m)
        check_tensor(zeta, "source", self.source_shape)
        check_same(zeta, self.template, "source", "template")

    def unmasked_source(self, s: torch.Tensor) -> torch.Tensor:
        """``K_s s`` (RKHS source) or ``s`` (L2 source), differentiable: the field whose pairing with ``s`` is the
        source's squared norm."""
        return s if self.source_kernel is None else self.source_kernel.apply(s)

    def source(self, s: torch.Tensor) -> torch.Tensor:
        """``zeta = B K_s s`` (``B = chi``, the ``source_mask``, or the projection with a ``uniform_region``:
        ``restricted``; ``K_s`` the source kernel; each the identity when not given)."""
        return self.restricted(self.unmasked_source(s))

    def restricted(self, u: torch.Tensor) -> torch.Tensor:
        """``B u`` for fields ``u`` ``(N+1, *shape)``: ``chi u``, or with a ``uniform_region`` ``U``: ``chi (1 - U) u
        + U mean_U(u_i)`` (before ``source_start`` the second term only); an orthogonal projection (0 / 1 masks)."""
        if self.uniform_region is None:
            return u if self.source_mask is None else u * self.source_mask
        region, axes = self.uniform_region, tuple(range(1, u.ndim))
        uniform = (u * region).sum(axes, keepdim=True) * (region / region.sum())
        if self.early:
            return uniform
        return uniform + u * (1 - region) * (1 if self.source_mask is None else self.source_mask)

    def at_iteration(self, iteration: int) -> bool:
        """Algorithm 1 calls it before each step: before ``source_start`` (with a ``uniform_region``) only the
        uniform part of the source is on. True when that changed (the objective did)."""
        early = self.uniform_region is not None and iteration < self.source_start
        changed, self.early = early != self.early, early
        return changed

    def image(self, m: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """``f(1) = M(K m, zeta, I)``, ``(*shape)`` (``s``: the source iterate, ``zeta = source(s)``)."""
        with torch.no_grad():
            return self.deformation(self.velocity(m), self.source(s), self.template)

    def parts(self, m: torch.Tensor, s: torch.Tensor) -> tuple:
        """``(W(nu, I), f(1) - W(nu, I))``: the pure deformation of the template and the intensity part."""
        with torch.no_grad():
            return self.deformation.parts(self.velocity(m), self.source(s), self.template)

    def trajectory(self, m: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """``f(t_i)`` for ``i = 0..N``, ``(N+1, *shape)``."""
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
        zeta = self.restricted(unmasked)
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
            zeta = self.restricted(unmasked)
        with torch.enable_grad():
            nu_leaf, zeta_leaf = nu.detach().requires_grad_(True), zeta.detach().requires_grad_(True)
            match = self.lddmm.matching(self.deformation(nu_leaf, zeta_leaf, self.template))
            dl_dnu, dl_dzeta = torch.autograd.grad(match["data_fit"] + match["tv"], (nu_leaf, zeta_leaf))
        h_nu = dl_dnu.div_(self.time_weight).add_(m, alpha=self.gamma)
        h_zeta = self.restricted(dl_dzeta).div_(self.time_weight).add_(s, alpha=self.tau)
        terms = {"data_fit": float(match["data_fit"].detach()), "tv": float(match["tv"].detach()),
                 "regulariser": float(self.lddmm.regulariser(m, nu)),
                 "source_regulariser": float(self.source_regulariser(s, unmasked))}
        terms["objective"] = sum(terms.values())
        return terms, h_nu, h_zeta, nu

    def source_lipschitz(self) -> float:
        """``(tau + ||T||^2) ||K_s||``: the Lipschitz constant of the source update at ``nu = 0`` (``f(1)`` depends
        on ``zeta`` through the average ``(1/N) sum zeta_i``, of norm 1 in ``L2([0,1], L2)``; ``||K_s|| = 1``
        for the L2 source, else the kernel's largest eigenvalue, at most ``K_s`` applied to ones); the step
        ``1 / source_lipschitz()`` is the ``"auto"`` source step size."""
        return (self.tau + self.operator_norm ** 2) * self.source_kernel_norm()

    @functools.cached_property
    def operator_norm(self) -> float:
        """``||T||`` by 30 power iterations on ``T^* T`` (``indreg.forward.operator_norm``, seed 0; computed once)."""
        return operator_norm(self.ray_transform, 30, self.template.dtype, self.template.device)

    @property
    def tau_scale(self) -> float:
        """``||T||^2 ||K_s||``: the data term's curvature on the smoothest source (module docstring); ``tau =
        tau_rel * tau_scale``."""
        return self.operator_norm ** 2 * self.source_kernel_norm()

    def source_kernel_norm(self) -> float:
        """``||K_s||`` bounded by its largest row sum (1 for the L2 source)."""
        if self.source_kernel is None:
            return 1.0
        ones = torch.ones(self.domain.shape, dtype=self.template.dtype, device=self.template.device)
        return float(self.source_kernel.apply(ones).max())


    # the registration-problem protocol (indreg.problems.problem): the iterate is x = (m, s)
    iterate_names = ("momentum", "source")
    scored = ("deformation_part",)
    output_kinds = {"deformation_part": "parts", "intensity_part": "parts"}

    def zero_iterate(self) -> tuple:
        return self.zero_momentum(), self.zero_source()

    def check_iterate(self, x: tuple) -> None:
        super().check_iterate(x)
        self.check(*x)

    def gradient(self, x: tuple) -> tuple:
        """``(terms, (h_nu, h_s), nu)``: ``l2_gradient`` at ``x = (m, s)``."""
        terms, h_nu, h_s, nu = self.l2_gradient(*x)
        return terms, (h_nu, h_s), nu

    def differentiable(self, x: tuple) -> tuple:
        """Terms differentiable through ``(m, s)``, ``aux = (nu, K_s s)``; ``h_nu = dE/dnu / time_weight + gamma m / 2``
        and ``h_s = dE/ds`` (L2 source) or ``dE/d(K_s s) / time_weight + tau s / 2`` (RKHS source)."""
        m, s = x
        nu, unmasked = self.velocity(m), self.unmasked_source(s)

        def l2(x, dx, daux):
            h_s = dx[1] if self.source_kernel is None else daux[1] / self.time_weight + 0.5 * self.tau * x[1]
            return daux[0] / self.time_weight + 0.5 * self.gamma * x[0], h_s
        return self.terms(m, s, nu, unmasked), (nu, unmasked), l2

    def reconstruction(self, x: tuple) -> torch.Tensor:
        return self.image(*x)

    def image_trajectory(self, x: tuple) -> torch.Tensor:
        return self.trajectory(*x)

    def evaluate_iterate(self, x: tuple) -> dict:
        return self.evaluate(*x)

    def outputs(self, x: tuple) -> dict:
        """The source ``s`` and the parts of ``f(1)``: ``deformation_part = W(nu, I)``, ``intensity_part = f(1) -
        W(nu, I)``."""
        deformation_part, intensity_part = self.parts(*x)
        return {"source": x[1], "deformation_part": deformation_part, "intensity_part": intensity_part}

    def default_step(self, name: str) -> float:
        """The source's step ``1 / source_lipschitz()``."""
        if name != "source":
            return super().default_step(name)
        return 1.0 / self.source_lipschitz()

    def with_backward(self, backward: str) -> "MetamorphosisRegistration":
        M = self.deformation
        return self.with_deformation(MetamorphosisDeformation(M.domain, M.num_steps, backward, M.interpolation))

    def hparams(self) -> dict:
        """``tau`` and ``tau_rel = tau / tau_scale`` (either way it was given), the source kernel's width (0: the
        L2 source)."""
        return {"tau": self.tau, "tau_rel": self.tau / self.tau_scale,
                "source_sigma": 0.0 if self.source_kernel is None else float(self.source_kernel.sigma)}


def template_support(template: torch.Tensor, domain, margin: float = 1.0, threshold: float = 0.01) -> torch.Tensor:
    """A ``source_mask``: 1 where ``|I| > threshold max |I|`` or within ``margin`` (physical units, a square /
    cubic neighbourhood) of such a pixel, else 0; ``domain.shape`` (2D or 3D) in the template's dtype / device."""
    return _dilated((template.abs() > threshold * template.abs().max()).to(template.dtype), domain, margin)


def data_support(data: torch.Tensor, operator, domain, margin: float = 0.0, smoothing: float = 2.0,
                 level: float = 3.0, fraction: float = 0.0, noise: float | None = None) -> torch.Tensor:
    """A ``source_mask`` from the data: 1 where the rays through a point carry mass (the data's visual hull).

    A data cell is *empty* when the data, smoothed along their last (detector) axis by a Gaussian of std
    ``smoothing`` cells, are within ``level`` times the smoothed noise's std of 0 (``noise``: the data's noise std,
    None: ``noise_std(data)``; the threshold at least 1e-3 of the largest smoothed value). A point is inside when at
    most ``fraction`` of the rays through it are empty (``T^* empty <= fraction T^* 1``: the operator's own
    back-projection, any geometry, 2D or 3D), then dilated by ``margin`` (physical units, as ``template_support``);
    points that no ray meets are outside. ``domain.shape`` in the data's dtype / device."""
    weights = _gaussian_weights(smoothing, data)
    smooth = torch.nn.functional.conv1d(
        torch.nn.functional.pad(data.reshape(-1, 1, data.shape[-1]), (len(weights) // 2,) * 2, mode="replicate"),
        weights[None, None]).reshape(data.shape)
    noise = (noise_std(data) if noise is None else noise) * float(weights.norm())
    empty = (smooth.abs() <= max(level * noise, 1e-3 * float(smooth.abs().max()))).to(data.dtype)
    hits, rays = operator.adjoint(empty), operator.adjoint(torch.ones_like(data))
    return _dilated(((hits <= fraction * rays) & (rays > 1e-6 * float(rays.max()))).to(data.dtype), domain, margin)


def noise_std(data: torch.Tensor) -> float:
    """The std of white noise in ``data`` from the median absolute deviation of the differences of neighbouring
    detector cells (last axis): robust to the (smooth) signal."""
    diff = (data[..., 1:] - data[..., :-1]).reshape(-1)
    return 1.4826 * float((diff - diff.median()).abs().median()) / 2 ** 0.5


def _gaussian_weights(std: float, like: torch.Tensor) -> torch.Tensor:
    """Normalised Gaussian weights of std ``std`` cells, truncated at 3 std (``[1.0]`` for ``std`` 0)."""
    x = torch.arange(-int(3 * std), int(3 * std) + 1, dtype=like.dtype, device=like.device)
    w = torch.exp(-0.5 * (x / max(std, 1e-12)) ** 2)
    return w / w.sum()


def opened(mask: torch.Tensor, domain, radius: float) -> torch.Tensor:
    """The morphological opening of a 0 / 1 ``mask`` by a square / cubic neighbourhood of half-width ``radius``
    (physical units): what remains of it when parts thinner than about ``2 radius`` are removed."""
    return _dilated(1 - _dilated(1 - mask, domain, radius), domain, radius)


def _dilated(inside: torch.Tensor, domain, margin: float) -> torch.Tensor:
    """``inside`` (0 / 1, ``domain.shape``) dilated by a square / cubic neighbourhood of half-width ``margin``."""
    sizes = tuple(2 * max(int(round(margin / h)), 0) + 1 for h in domain.cell_sides)
    pool = torch.nn.functional.max_pool2d if domain.ndim == 2 else torch.nn.functional.max_pool3d
    return pool(inside[None, None], sizes, stride=1, padding=tuple(k // 2 for k in sizes))[0, 0]


