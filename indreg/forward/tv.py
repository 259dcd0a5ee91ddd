"""Total-variation (TV) reconstruction, the paper's direct-reconstruction baseline (eq:VarReg, section
"Reconstruction protocol"), solved by the primal-dual method of Chambolle & Pock (2011) with steps balanced
between the data and the TV blocks (Pock & Chambolle 2011), so that the iterates do not depend on the units.

Notes
-----
- ``T`` is any ``LinearOperator`` (``indreg.forward.operator``): a ``RayTransform`` or a user's operator.
- ``T`` may also be a ``TiltSeriesTransform`` (3D): everything below holds with d = 3.
- Images ``(..., nx, ny)`` or volumes ``(..., nx, ny, nz)`` (axis 0 = x) on ``T.domain``; data
  ``(..., *T.range_shape)`` (for a ray transform ``(..., num_angles, det_count)``); any leading batch
  dims (shared by ``y`` and ``x0``); dtype and device follow ``y``.
- Objective, as the paper's eq:VarReg with ODL's ``L2NormSquared`` data term (no factor 1/2, the
  authors' ODL set-up, so the paper's ``mu`` means the same here):
      ``E(x) = ||T x - y||^2 + mu * TV(x)``,  ``TV(x) = int |grad x| dx``  (isotropic),
  with ``||.||`` the weighted data norm (``T.inner_data``) and the integral a cell-volume Riemann sum.
  Equivalently ``(1/2)||T x - y||^2 + (mu/2) TV(x)``. Measured on suite 1 (V, 64^2, 10 x 92 angles x bins,
  4.87 dB code convention, seed 0, 1000 iterations, balanced steps): ``mu = 3.0`` gives SSIM 0.62 (0.73 in
  the paper's convention) against FBP's 0.39 (0.45); ``mu = 1.5`` (the paper's 3.0 read with a halved data
  term) gives 0.49, ``mu = 6`` 0.63. (The equal steps, 1000 iterations: 0.55, 0.49, 0.48, further from the
  minimum: objective 0.8 % above it at ``mu = 3`` against 0.04 %.)
- ``grad``: forward differences divided by the cell sides, zero padding beyond the last pixel (ODL's
  ``Gradient`` default, ``pad_mode="constant"``): ``(grad f)_x[i] = (f[i+1] - f[i]) / hx`` with
  ``f[nx] = 0``. ``div = -grad^*`` (L2 adjoint; the cell volumes cancel, so it is the matrix transpose):
  ``(div p)[i] = (p_x[i] - p_x[i-1]) / hx + (same in y[, z])`` with ``p_x[-1] = 0``. In 3D the same
  with a third component (z); the vector field is ``(..., d, *shape)``.
- Over ranks (``indreg.forward.split``): ``T`` a ``SlabTransform``, ``y`` its rows; its domain's inner products,
  the data's and the objective are summed over the ranks, the differences read the neighbours' slices across
  the split (``beyond``), and the power iteration starts from the rows of the whole volume's random draw, so
  that every rank's rows equal one process's to rounding.
"""
from __future__ import annotations

import math

import torch

from .._checks import check_bool, check_int, check_nonnegative, check_positive, check_tensor
from ..domain import ImageDomain
from .operator import check_operator
from .sirt import start_image
from .split import beyond, maximum, own_rows, total, whole_domain


def gradient(f: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """Forward-difference gradient with zero padding: ``(..., *shape) -> (..., d, *shape)`` (component 0 = x).

    ``(grad f)_a[i] = (f[i + e_a] - f[i]) / h_a`` with ``f = 0`` beyond the last cell, for every axis ``a``
    of the d-dimensional domain (d = 2 or 3)."""
    parts = []
    for dim, h in zip(domain.dims, domain.cell_sides):
        parts.append(torch.diff(f, dim=dim, append=beyond(f, domain, dim, 1)) / h)
    return torch.stack(parts, dim=-domain.ndim - 1)


def divergence(p: torch.Tensor, domain: ImageDomain) -> torch.Tensor:
    """Backward-difference divergence ``-grad^*``: ``(..., d, *shape) -> (..., *shape)``;
    ``<grad f, p> = -<f, div p>``: ``(div p)[i] = sum_a (p_a[i] - p_a[i - e_a]) / h_a`` with ``p_a = 0``
    before the first cell."""
    out = None
    for a, (dim, h) in enumerate(zip(domain.dims, domain.cell_sides)):
        pa = p.select(-domain.ndim - 1, a)
        term = torch.diff(pa, dim=dim, prepend=beyond(pa, domain, dim, -1)) / h
        out = term if out is None else out + term
    return out


def total_variation(f: torch.Tensor, domain: ImageDomain, smoothing: float = 0.0) -> torch.Tensor:
    """Isotropic total variation ``TV(f) = int sqrt(|grad f|^2 + eps^2) dx`` (eps = ``smoothing``).

    ``grad f`` by forward differences in physical units with zero padding (``gradient``, ODL's default); the
    integral is the Riemann sum with the cell volume.

    Parameters
    ----------
    f : torch.Tensor
        Images ``(..., *domain.shape)`` (non-finite values show in the sum).
    domain : ImageDomain
        A 2D or 3D domain.
    smoothing : float
        ``eps >= 0``. 0 gives plain TV, whose autograd gradient is taken as 0 where ``grad f = 0`` (a
        subgradient); ``eps > 0`` the smooth approximation (``TV_eps >= TV``, ``TV_eps - TV <= eps |Omega|``),
        differentiable everywhere.

    Returns
    -------
    torch.Tensor
        ``TV(f)``, the batch dims kept.

    Raises
    ------
    TypeError
        ``domain`` is no ``ImageDomain``.
    ValueError
        ``f`` of the wrong shape, ``smoothing < 0``.
    """
    if not isinstance(domain, ImageDomain):
        raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
    check_tensor(f, "f", domain.shape, finite=False)  # a deformed template: non-finite values show in the sum
    smoothing = check_nonnegative(smoothing, "smoothing")
    sq = (gradient(f, domain) ** 2).sum(dim=-domain.ndim - 1)
    if smoothing > 0:
        mag = (sq + smoothing ** 2).sqrt()
    else:
        zero = sq == 0  # not "sq > 0": a nan must stay nan (a non-finite image has no TV of 0)
        mag = torch.where(zero, torch.zeros_like(sq), torch.where(zero, torch.ones_like(sq), sq).sqrt())
    return domain.cell_volume * mag.sum(dim=domain.dims)


def _power_norm(normal, domain: ImageDomain, dtype, device, num_iter: int) -> float:
    """``||A||`` by power iteration on ``A^* A`` (``normal``: image -> image) in the domain's weighted L2 norm; a
    lower estimate (the steps keep a margin of 1.1)."""
    x = own_rows(torch.randn(whole_domain(domain).shape, generator=torch.Generator().manual_seed(0),
                             dtype=torch.float64), domain).to(dtype=dtype, device=device)   # the same start over ranks
    x = x / domain.norm(x)
    lam = torch.zeros((), dtype=dtype, device=device)
    for _ in range(num_iter):
        ax = normal(x)
        lam = domain.inner(x, ax)
        x = ax / domain.norm(ax).clamp_min(torch.finfo(dtype).tiny)   # A = 0: x = 0, ||A|| = 0 (not nan)
    return float(lam.sqrt())


def intensity_scale(T, y: torch.Tensor) -> float:
    """The data's intensity unit: ``max |T^* y| / max T^* T 1``, the intensity of a uniform image on the domain
    whose backprojection peaks as high as the data's (``1`` image of ones). It scales with the data (``y -> c y``
    gives ``c`` times it) and not with the geometry's sampling; times a length squared it is the unit of a TV weight
    (``tv_weight_unit``, the app's ``baseline.tv_mu``).

    Parameters
    ----------
    T : LinearOperator
        The forward operator.
    y : torch.Tensor
        Data ``T.range_shape`` (finite).

    Returns
    -------
    float
        The intensity unit (its maximum over the ranks of a split operator).

    Raises
    ------
    TypeError
        ``T`` is no operator.
    ValueError
        Data of another shape or non-finite.
    """
    check_operator(T, "T")
    check_tensor(y, "y", tuple(T.range_shape))
    with torch.no_grad():
        ones = torch.ones(T.domain.shape, dtype=y.dtype, device=y.device)
        peak = float(maximum(T.adjoint(T(ones)).abs().max(), T.domain))   # maxima over the ranks of a split
        return float(maximum(T.adjoint(y).abs().max(), T.domain)) / peak


def tv_weight_unit(T, y: torch.Tensor) -> float:
    """The unit of a TV weight: ``intensity_scale(T, y) * L^2``, ``L`` the largest side of ``T.domain``'s box
    (physical units), so that ``mu = mu_rel * tv_weight_unit(T, y)`` means the same in any intensity and length unit.

    Why ``L^2``: with lengths times ``s`` (the box, the detector) an image of intensity ``u`` gives line integrals
    times ``s`` on a detector measure times ``s^(d-1)``, so ``||T x - y||^2`` grows by ``s^(d+1)``, while ``TV(x) = int
    |grad x| dx`` grows by ``s^(d-1)``: the two balance when ``mu`` grows by ``s^2`` times the intensity's factor, that
    is ``mu / u`` is a length squared in 2D and 3D. The box side ``L`` (not the cell side) keeps ``mu_rel`` for the
    same object sampled finer.

    Parameters
    ----------
    T : LinearOperator
        The forward operator (a slab's: the whole box counts).
    y : torch.Tensor
        Data ``T.range_shape``.

    Returns
    -------
    float
        ``intensity_scale(T, y) * L^2``.

    Raises
    ------
    TypeError, ValueError
        As :func:`intensity_scale`.
    """
    return intensity_scale(T, y) * max(whole_domain(T.domain).extent) ** 2   # a slab's: the whole box


def _magnitude(v: torch.Tensor, dim: int, keepdim: bool = False) -> torch.Tensor:
    """``|v|`` over the components' axis ``dim``: the square root of the sum of squares (torch's ``norm`` over an
    outer axis runs 7x slower on the CPU: 1.9 s vs 0.27 s for a 3 x 256^3 field)."""
    return v.square().sum(dim=dim, keepdim=keepdim).sqrt()


STEP_MARGIN = 1.1                                     # steps 1 / 1.1 of the bound
#: The data dual's step ``sigma_p`` of the balanced steps: a pure number (the data term ``||T x - y||^2`` has no
#: unit of its own), so the iterates are the same in any length or intensity unit (``tv_reconstruction``). Its best
#: value depends on the problem; 0.3 is never far off in what was measured (objective above the lowest of 0.03 ...
#: 10 and the equal steps, at the app's iteration counts): suite 3 (256^2, 1000 iterations) 1.0 % (0.1: 3.9 %, the
#: equal steps 1.4 %), the own-data example (500) 1.8 % (0.1: 0.3 %, 1: 6.5 %), the HAADF tilt series (200, mu =
#: 3 u) 16 % (1: 2.6x), suite 1 (1000) 0.04 %.
DATA_DUAL_STEP = 0.3


def _steps(T, dtype, device, num_iter: int, balanced: bool, norms: tuple | None = None) -> tuple:
    """``(tau, sigma_p, sigma_q, norms)`` of ``tv_reconstruction`` (its docstring): balanced from ``norms = (||T||,
    ||grad||)``, equal from ``norms = (||[T; grad]||,)``, by power iteration unless ``norms`` are given (an earlier
    run's ``history["norms"]`` with the same operator, dtype and options)."""
    dom = T.domain

    def laplacian(x):                                 # grad^* grad = -div grad
        return -divergence(gradient(x, dom), dom)

    if not balanced:
        opnorm, = norms or (_power_norm(lambda x: T.adjoint(T(x)) + laplacian(x), dom, dtype, device, num_iter),)
        step = 1.0 / (STEP_MARGIN * opnorm)
        return step, step, step, (opnorm,)
    t_norm = norms[0] if norms else _power_norm(lambda x: T.adjoint(T(x)), dom, dtype, device, num_iter)
    if not (t_norm > 0 and math.isfinite(t_norm)):
        raise ValueError(f"T must not map every image to 0 (||T|| = {t_norm:.4g} by power iteration): the balanced "
                         "steps are 1 / ||T||^2; check the operator")
    g_norm = norms[1] if norms else _power_norm(laplacian, dom, dtype, device, num_iter)
    sigma_p = DATA_DUAL_STEP
    tau = 1.0 / (2.0 * STEP_MARGIN * sigma_p * t_norm ** 2)
    return tau, sigma_p, sigma_p * (t_norm / g_norm) ** 2, (t_norm, g_norm)


def _check_norms(norms, balanced: bool):
    """``norms`` (``tv_reconstruction``): None, or positive finite numbers, two for the balanced steps, one for the
    equal ones."""
    if norms is None:
        return None
    count = 2 if balanced else 1
    try:
        values = tuple(float(v) for v in norms)
    except (TypeError, ValueError):
        values = ()
    if len(values) != count or not all(v > 0 and math.isfinite(v) for v in values):
        which = "(||T||, ||grad||)" if balanced else "(||[T; grad]||,)"
        raise ValueError(f"norms must be {count} positive finite number(s) {which}: an earlier run's "
                         f"history['norms'], got {norms!r}")
    return values


def tv_reconstruction(T, y: torch.Tensor, mu: float, num_iter: int = 1000, x0: torch.Tensor | None = None,
                      callback=None, nonneg: bool = False, opnorm_iter: int = 100, balanced: bool = True,
                      anchor: torch.Tensor | None = None, norms: tuple | None = None) -> tuple:
    """Minimise ``||T x - y||^2 + mu TV(x - a)`` (module docstring; ``a`` = ``anchor``, default 0) by Chambolle-Pock
    with ``K = [T; grad]``.

    Splitting: ``E(x) = F1(T x) + F2(grad x) + G(x)`` with ``F1(z) = ||z - y||^2``, ``F2(w) = mu int |w|``,
    ``G`` = 0 (or the indicator of ``x >= 0`` when ``nonneg``); an anchor moves ``F2`` to ``mu int |w - grad a|``,
    whose conjugate's prox is ``P_mu(. - sigma_q grad a)``. Each iteration, for duals ``p`` (data) and ``q``
    (vector field), a primal step ``tau``, dual steps ``sigma_p``, ``sigma_q`` and ``x_bar`` the extrapolated primal:

    - ``p <- (p + sigma_p (T x_bar - y)) / (1 + sigma_p / 2)`` (prox of sigma_p F1^*)
    - ``q <- P_mu(q + sigma_q (grad x_bar - grad a))`` (projection on ``|q(x)| <= mu``)
    - ``x_new <- prox_G(x - tau (T^* p - div q))``,  ``x_bar = 2 x_new - x``.

    ``K x_bar`` is formed as ``2 K x_new - K x`` (linearity), so an iteration costs one ``T`` and one ``T^*``.

    Steps. Balanced (default; Pock & Chambolle's block-diagonal preconditioning, 2011): ``sigma_p = 0.3``
    (``DATA_DUAL_STEP``), ``tau = 1 / (2.2 sigma_p ||T||^2)``, ``sigma_q = sigma_p (||T|| / ||grad||)^2``: both
    blocks of ``Sigma^(1/2) K`` have the norm ``sqrt(sigma_p) ||T||``, so ``tau ||Sigma^(1/2) K||^2 <= tau 2
    sigma_p ||T||^2 = 1 / 1.1 < 1`` (convergence). Equivalently the plain method on ``K' = [T; c grad]``,
    ``c = ||T|| / ||grad||``, with ``F2'(w) = (mu / c) int |w|`` (dual bound ``mu / c``) and the dual ``q' = q / c``.
    Under other length units (sides and detector times ``s``: ``||T||^2`` times ``s``, ``||grad||`` over ``s``) and
    intensity units these steps carry the iterates over exactly (``mu`` times ``s^2`` and the intensity factor,
    docs/units.md), so the TV dual reaches its bound ``mu`` in the same number of iterations in any units.
    Equal (``balanced=False``, the method before): ``tau = sigma_p = sigma_q = 1 / (1.1 ||K||)``; where ``||T||``
    and ``||grad||`` differ by orders of magnitude (e.g. nm units: 53 against 0.26 / nm) ``q`` then moves too
    slowly to reach ``mu`` in hundreds of iterations and ``mu`` does not act.

    Parameters
    ----------
    T : LinearOperator
        ``T(x)``, ``T.adjoint(y)`` (L2 adjoint), ``T.inner_data``, ``T.domain``, ``T.range_shape``; the norms are
        estimated by power iteration, so no operator norm is needed.
    y : torch.Tensor
        Data ``(..., *T.range_shape)``.
    mu : float
        TV weight (> 0); the paper uses 3.0 (suite 1) and 1.0 (suite 2).
    num_iter : int
        Iterations (the paper: 1000).
    x0 : torch.Tensor, optional
        Start (default zeros), shape ``(..., *T.domain.shape)`` with the data's batch dims.
    callback : callable, optional
        Called as ``callback(i, x)`` after iteration ``i`` (0-based).
    nonneg : bool
        Constrain ``x >= 0``.
    opnorm_iter : int
        Power iterations for each norm.
    balanced : bool
        The balanced steps (default) or the equal ones (above).
    anchor : torch.Tensor, optional
        ``a``, shape ``T.domain.shape`` (a template-anchored TV: ``indreg.problems.residual``).
    norms : tuple of float, optional
        The norms that set the steps, ``history["norms"]`` of an earlier run with the same ``T``, dtype and
        ``balanced``: the power iterations are skipped (a parameter scan: the same iterates, bit for bit, at a
        third less cost per run of 200 iterations).

    Returns
    -------
    x : torch.Tensor
        The reconstruction ``(..., *T.domain.shape)``.
    history : dict
        ``"objective"``: float64 CPU tensor ``(num_iter, ...)`` with ``E`` of each iterate; ``"step"``: ``tau``;
        ``"dual_steps"``: ``(sigma_p, sigma_q)``; ``"opnorm"``: the estimated ``||T||`` (balanced) or ``||K||``
        (equal); ``"norms"``: ``(||T||, ||grad||)`` (balanced) or ``(||K||,)`` (equal).

    Raises
    ------
    TypeError
        ``T`` is no operator, or an argument of the wrong type.
    ValueError
        Data, ``x0`` or ``anchor`` of the wrong shape or non-finite, ``mu <= 0``, ``num_iter < 1``, ``norms`` of
        the wrong count, an operator that maps every image to 0.
    """
    check_operator(T, "T")
    check_tensor(y, "y", tuple(T.range_shape))
    mu = check_positive(mu, "mu")
    num_iter = check_int(num_iter, "num_iter", 1)
    nonneg = check_bool(nonneg, "nonneg")
    balanced = check_bool(balanced, "balanced")
    dom = T.domain
    batch = y.shape[:y.dim() - len(T.range_shape)]
    x = dom.zeros(*batch, dtype=y.dtype, device=y.device) if x0 is None else start_image(x0, batch, dom, y)
    tau, sigma_p, sigma_q, norms = _steps(T, y.dtype, y.device, check_int(opnorm_iter, "opnorm_iter", 1), balanced,
                                          _check_norms(norms, balanced))
    vec = -dom.ndim - 1                               # the axis of the gradient's components
    ga = 0.0 if anchor is None else gradient(check_tensor(anchor, "anchor", tuple(dom.shape)).to(y), dom)

    def energy(tx, gx):
        r = tx - y
        return T.inner_data(r, r) + mu * dom.cell_volume * total(_magnitude(gx - ga, vec).sum(dim=dom.dims), dom)

    tx, gx = T(x), gradient(x, dom)
    p, q = torch.zeros_like(tx), torch.zeros_like(gx)
    tx_bar, gx_bar = tx, gx
    objective = torch.empty((num_iter,) + tuple(batch), dtype=torch.float64, device=y.device)
    for i in range(num_iter):
        p = (p + sigma_p * (tx_bar - y)) / (1.0 + sigma_p / 2.0)
        q = q + sigma_q * (gx_bar - ga)
        q = q / torch.clamp(_magnitude(q, vec, keepdim=True) / mu, min=1.0)
        x_new = x - tau * (T.adjoint(p) - divergence(q, dom))
        if nonneg:
            x_new = x_new.clamp(min=0.0)
        tx_new, gx_new = T(x_new), gradient(x_new, dom)
        tx_bar, gx_bar = 2.0 * tx_new - tx, 2.0 * gx_new - gx
        x, tx, gx = x_new, tx_new, gx_new
        objective[i] = energy(tx, gx)
        if callback is not None:
            callback(i, x)
    return x, {"objective": objective.cpu(), "step": tau, "dual_steps": (sigma_p, sigma_q), "opnorm": norms[0],
               "norms": norms}
