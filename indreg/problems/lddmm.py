"""The indirect registration objective (eq:OptimV / eq:RegOptim, optional TV term of eq:VarRegExactShape).

Scale conventions follow the authors' code (see docs/paper_notes.md, "Objective scale") so that the paper's
step sizes and gammas work unchanged:

    E(nu) = (gamma / 2) sum_{i=0..N} (1/N) ||nu_i||_V^2  +  (1/2) ||T W(nu, I) - g||^2_data  (+ mu TV(W(nu, I)))

The paper prints ``gamma ||nu||^2 + ||T f - g||^2`` (gradient ``2 gamma nu - ...``, eq:GradGoalFunctionalVRHKS);
the code descends half of that, so its update is ``nu <- nu - alpha (gamma nu - K(...))`` with no factor 2 on
either term. Our ``gamma`` is the code's ``lamb`` (= the paper's printed ``gamma``; only the overall factor 2,
which rescales the step size, differs from the printed objective).

The velocity field is parametrised by the momentum ``m``: ``nu = K m`` (``K`` the Gaussian kernel of V), so
``||nu_i||_V^2 = <m_i, K m_i>_L2 = <m_i, nu_i>_L2`` is exact.
"""
from __future__ import annotations

import math

import torch

from .._checks import check_nonnegative, check_same, check_tensor
from ..deform.kernel import GaussianKernel
from ..deform.lddmm import LDDMMDeformation
from ..domain import ImageDomain
from ..forward.operator import check_operator
from ..forward.tv import total_variation
from .problem import RegistrationProblem


def _check_parts(ray_transform, deformation, kernel) -> tuple:
    """Check the operators of the problem (one line naming the argument); returns ``(image_domain,
    velocity_domain)``: the operator's and the deformation's, and the kernel's and the velocity's."""
    if not isinstance(deformation, LDDMMDeformation):
        raise TypeError(f"deformation must be an LDDMMDeformation, got {type(deformation).__name__}")
    if not isinstance(kernel, GaussianKernel):
        raise TypeError(f"kernel must be a GaussianKernel, got {type(kernel).__name__}")
    check_operator(ray_transform, "ray_transform")
    image_domain, velocity_domain = deformation.domain, deformation.velocity_domain
    if kernel.domain != velocity_domain:
        raise ValueError(f"kernel.domain {kernel.domain} differs from the deformation's velocity_domain "
                         f"{velocity_domain}")
    if ray_transform.domain != image_domain:
        raise ValueError(f"ray_transform.domain {ray_transform.domain} differs from deformation.domain "
                         f"{image_domain}")
    return image_domain, velocity_domain


class IndirectRegistration(RegistrationProblem):
    """Indirect registration problem ``min_nu E(nu)`` (eq:RegOptim), with ``nu = K m``.

    ``E(nu) = (gamma/2) sum_{i=0..N} (1/N) ||nu_i||_V^2 + (1/2) ||T W(nu, I) - g||^2_data + tv_weight TV(W(nu, I))``

    Parameters
    ----------
    ray_transform : LinearOperator
        The forward operator ``T``: ``indreg.RayTransform`` or any ``indreg.forward.LinearOperator`` (``domain``,
        ``range_shape``, ``__call__``, ``adjoint``, weighted data norm ``inner_data``).
    deformation : LDDMMDeformation
        ``W`` (geometric or mass-preserving action, eq:DeforOpX), or ``indreg.CoarseVelocityDeformation`` (the
        velocity on a coarser grid of the box); its ``domain`` is ``T``'s.
    kernel : GaussianKernel
        ``K`` of V, on the velocity's grid ``deformation.velocity_domain``.
    template : torch.Tensor
        The template ``I``, ``T.domain.shape``.
    data : torch.Tensor
        The data ``g``, shape ``T.range_shape`` (``(num_angles, det_count)`` for a ray transform), same
        dtype / device as ``template``.
    gamma : float
        Regularisation weight (>= 0), the code's ``lamb`` (see the module docstring for the factor 2).
    tv_weight : float
        Weight (>= 0) of the TV term on the deformed template (eq:VarRegExactShape). E is half the paper's
        printed objective, so the paper's ``mu`` is ``tv_weight = mu / 2`` (the TV baseline
        ``indreg.forward.tv_reconstruction`` uses ``||T x - y||^2 + mu TV``, no 1/2).
    tv_smoothing : float
        ``eps`` (>= 0) of the smoothed isotropic TV (``total_variation``); 0 is plain TV.

    Raises
    ------
    TypeError
        A deformation, kernel or operator of the wrong kind, tensors that are not real floating tensors.
    ValueError
        Parts on different grids, a template or data of the wrong shape, non-finite values, dtypes or devices
        that differ, a negative weight.

    Notes
    -----
    momentum / velocity ``(N+1, 2, nx, ny)`` at ``t_i = i/N`` (component 0 = x; 3D: ``(N+1, 3, nx, ny, nz)``,
    template ``(nx, ny, nz)``, any operator whose ``domain`` is 3D); the discrete
    ``L2([0,1], X)`` inner product is ``sum_{i=0..N} (1/N) <u_i, v_i>_X`` (the code's convention, N+1
    terms). The L2 gradient of E with respect to ``nu`` (``l2_gradient``) is
    ``h = gamma m + (N / cell_volume) dL/dnu`` with ``L`` the matching term (data fit + TV) and
    ``dL/dnu`` the torch gradient of the deformation's backward (``LDDMMDeformation``, "Gradient scale"); the
    V-gradient (eq:GradGoalFunctionalVRHKS(_mp), halved) is ``K h``.

    Two grids of one box: ``image_domain`` (the template's, the operator's, the TV term's) and ``domain`` (the
    momentum's, the velocity's, the kernel's: ``cell_volume`` above is its own). They are one grid unless the
    deformation is a ``CoarseVelocityDeformation`` (``velocity_factor``).
    """

    def __init__(self, ray_transform, deformation, kernel, template, data, gamma, tv_weight=0.0,
                 tv_smoothing=1e-3):
        image_domain, domain = _check_parts(ray_transform, deformation, kernel)
        check_tensor(template, "template")
        if tuple(template.shape) != tuple(image_domain.shape):
            raise ValueError(f"template must have shape {tuple(image_domain.shape)} (the domain's), "
                             f"got {tuple(template.shape)}")
        check_tensor(data, "data")
        if tuple(data.shape) != tuple(ray_transform.range_shape):
            raise ValueError(f"data must have shape {tuple(ray_transform.range_shape)} (the operator's range_shape), "
                             f"got {tuple(data.shape)}")
        check_same(template, data, "template", "data")
        self.ray_transform = ray_transform
        self.deformation = deformation
        self.kernel = kernel
        self.domain, self.image_domain = domain, image_domain
        self.template = template
        self.data = data
        self.gamma = check_nonnegative(gamma, "gamma", template.dtype)
        self.tv_weight = check_nonnegative(tv_weight, "tv_weight", template.dtype)
        self.tv_smoothing = check_nonnegative(tv_smoothing, "tv_smoothing", template.dtype)
        self.num_steps = int(deformation.num_steps)

    def __repr__(self):
        grids = f"domain={self.domain}" if self.image_domain == self.domain else \
            f"image_domain={self.image_domain}, velocity on domain={self.domain}"
        return (f"IndirectRegistration({grids}, N={self.num_steps}, gamma={self.gamma}, "
                f"tv_weight={self.tv_weight}, action={getattr(self.deformation, 'action', '?')!r})")

    def with_deformation(self, deformation) -> "IndirectRegistration":
        """The same problem with another deformation operator (e.g. ``backward="autograd"``)."""
        return IndirectRegistration(self.ray_transform, deformation, self.kernel, self.template, self.data,
                                    self.gamma, self.tv_weight, self.tv_smoothing)

    @property
    def momentum_shape(self) -> tuple:
        """``(N+1, d, *shape)``: ``(N+1, 2, nx, ny)`` or ``(N+1, 3, nx, ny, nz)``."""
        return (self.num_steps + 1, self.domain.ndim, *self.domain.shape)

    def check_momentum(self, m) -> torch.Tensor:
        """Validate a momentum ``(N+1, 2, nx, ny)`` in the template's dtype/device."""
        check_tensor(m, "momentum", self.momentum_shape)
        check_same(m, self.template, "momentum", "template")
        return m

    def zero_momentum(self) -> torch.Tensor:
        """``m = 0`` (identity deformation), ``(N+1, 2, nx, ny)`` in the template's dtype/device."""
        return torch.zeros(self.momentum_shape, dtype=self.template.dtype, device=self.template.device)

    def deformed(self, m: torch.Tensor) -> torch.Tensor:
        """``W(K m, I)`` (nx, ny)."""
        with torch.no_grad():
            return self.deformation(self.velocity(m), self.template)

    def trajectory(self, m: torch.Tensor) -> torch.Tensor:
        """``W(K m, I)(t_i)`` for i = 0..N, ``(N+1, nx, ny)``."""
        with torch.no_grad():
            return self.deformation.trajectory(self.velocity(m), self.template)

    def regulariser(self, m: torch.Tensor, nu: torch.Tensor) -> torch.Tensor:
        """``(gamma/2) sum_i (1/N) ||nu_i||_V^2 = (gamma/2) (cell_volume/N) sum m * nu`` for ``nu = K m``."""
        return 0.5 * self.gamma * self.time_weight * torch.dot(m.reshape(-1), nu.reshape(-1))

    def matching(self, f: torch.Tensor) -> dict:
        """Matching terms of a deformed template ``f``: ``data_fit = (1/2)||T f - g||^2_data`` and ``tv``."""
        residual = self.ray_transform(f) - self.data
        data_fit = 0.5 * self.ray_transform.inner_data(residual, residual).sum()
        if self.tv_weight > 0:
            tv = self.tv_weight * total_variation(f, self.image_domain, self.tv_smoothing).sum()
        else:
            tv = torch.zeros((), dtype=f.dtype, device=f.device)
        return {"data_fit": data_fit, "tv": tv}

    def terms(self, m: torch.Tensor, nu: torch.Tensor | None = None) -> dict:
        """All terms as 0-dim tensors (differentiable through ``m`` and ``nu``; ``nu = K m`` if not given)."""
        nu = self.velocity(m) if nu is None else nu
        out = self.matching(self.deformation(nu, self.template))
        out["regulariser"] = self.regulariser(m, nu)
        out["objective"] = out["data_fit"] + out["tv"] + out["regulariser"]
        return out

    def evaluate(self, m: torch.Tensor) -> dict:
        """``objective, data_fit, regulariser, tv`` at momentum ``m`` as python floats (no gradient)."""
        self.check_momentum(m)
        with torch.no_grad():
            return {k: float(v) for k, v in self.terms(m).items()}

    def l2_gradient(self, m: torch.Tensor) -> tuple:
        """Objective terms and the L2 gradient ``h`` at ``m``; one forward/backward of ``W`` and ``T``.

        ``h_i = gamma m_i + (N / cell_volume) dL/dnu_i`` with ``L`` = data fit + TV of ``W(nu, I)`` and
        ``dL/dnu`` from the deformation's backward (geometric action, ``backward="paper"``:
        ``h_i = gamma m_i - |D phi_{t_i,1}| (grad_data o phi_{t_i,1}) grad(I o phi_{t_i,0})``,
        ``grad_data = T^*(T f - g)``). ``K h`` is the V-gradient of E at ``nu = K m``.

        Returns ``(terms, h, nu)``: terms as python floats, ``h`` and ``nu = K m`` detached tensors.
        """
        with torch.no_grad():
            nu = self.velocity(m)
        with torch.enable_grad():
            nu_leaf = nu.detach().requires_grad_(True)
            match = self.matching(self.deformation(nu_leaf, self.template))
            (dl_dnu,) = torch.autograd.grad(match["data_fit"] + match["tv"], nu_leaf)
        h = dl_dnu.div_(self.time_weight).add_(m, alpha=self.gamma)  # in place: one pass over the field
        terms = {"data_fit": float(match["data_fit"].detach()), "tv": float(match["tv"].detach()),
                 "regulariser": float(self.regulariser(m, nu))}
        terms["objective"] = terms["data_fit"] + terms["tv"] + terms["regulariser"]
        return terms, h, nu

    def v_gradient(self, m: torch.Tensor) -> torch.Tensor:
        """The V-gradient ``K h`` of E at ``nu = K m`` (eq:GradGoalFunctionalVRHKS(_mp) in the code's scale)."""
        return self.kernel.apply(self.l2_gradient(m)[1])

    # the registration-problem protocol (indreg.problems.problem): the iterate is x = (m,)
    def zero_iterate(self) -> tuple:
        return (self.zero_momentum(),)

    def check_iterate(self, x: tuple) -> None:
        super().check_iterate(x)
        self.check_momentum(x[0])

    def gradient(self, x: tuple) -> tuple:
        """``(terms, (h,), nu)``: ``l2_gradient`` at ``x = (m,)``."""
        terms, h, nu = self.l2_gradient(x[0])
        return terms, (h,), nu

    def differentiable(self, x: tuple) -> tuple:
        """Terms differentiable through ``m``, ``aux = (nu,)``, and ``h = dE/dnu / time_weight + gamma m / 2``
        (``dE/dnu`` at fixed ``m`` holds half the regulariser's gradient)."""
        (m,) = x
        nu = self.velocity(m)
        return self.terms(m, nu), (nu,), lambda x, dx, daux: (daux[0] / self.time_weight + 0.5 * self.gamma * x[0],)

    def reconstruction(self, x: tuple) -> torch.Tensor:
        return self.deformed(x[0])

    def image_trajectory(self, x: tuple) -> torch.Tensor:
        return self.trajectory(x[0])

    def evaluate_iterate(self, x: tuple) -> dict:
        return self.evaluate(x[0])

    def with_backward(self, backward: str) -> "IndirectRegistration":
        return self.with_deformation(self.deformation.replace(backward=backward))

    def for_line_search(self) -> "IndirectRegistration":
        """The paper's backward is replaced by ``"exact"`` (a line search needs the gradient of what it evaluates)."""
        return self.with_backward("exact") if self.deformation.backward == "paper" else self

    def coarsened(self, shape: tuple, num_steps: int, backward: str) -> "IndirectRegistration":
        """The problem with the velocity on a ``shape`` grid of the same box and ``num_steps`` time steps
        (``MultilevelSolver``): the image's grid coarsened as much (the same grid unless the velocity lives on a
        coarser one: ``velocity_factor`` is kept), the template's cell averages, the operator rebuilt by
        ``T.on_domain(coarse)`` (the data cell-averaged to its range where that changes: a tilt series' detector
        rows, one per slice along the tilt axis, since a coarse slice projects to the average of its fine slices'
        rows), the same kernel width, gamma and TV weight; the deformation's action, interpolation and scheme with
        ``backward``."""
        from ..deform import GaussianKernel
        from ..domain import ImageDomain
        from .grids import restrict

        d, e, W, T = self.domain, self.image_domain, self.deformation, self.ray_transform
        if tuple(shape) == tuple(d.shape):
            domain, image_domain, T_level, template, K = d, e, T, self.template, self.kernel
        else:
            domain = ImageDomain(tuple(shape), d.min_pt, d.max_pt)
            image_domain = domain if e == d else \
                ImageDomain(tuple(s * n // m for s, n, m in zip(shape, e.shape, d.shape)), e.min_pt, e.max_pt)
            T_level = T.on_domain(image_domain)
            template = restrict(self.template, image_domain.shape)
            K = GaussianKernel(domain, self.kernel.sigma)
        data = self.data
        if tuple(T_level.range_shape) != tuple(data.shape):  # e.g. a tilt series: one detector row per slice
            data = restrict(data, tuple(T_level.range_shape)[-2:])
        grids = {"domain": image_domain}
        if "velocity_domain" in W.arguments():
            grids["velocity_domain"] = domain
        W_level = W.replace(num_steps=num_steps, backward=backward, **grids)
        return IndirectRegistration(T_level, W_level, K, template, data, self.gamma, self.tv_weight,
                                    self.tv_smoothing)
