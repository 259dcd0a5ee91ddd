"""The LDDMM deformation with a band-limited velocity: the velocity and the flow on a coarser grid of the image's
box (``register(velocity_factor=f)``)."""
from __future__ import annotations

import torch

from ..domain import ImageDomain
from . import functional as Fd
from .lddmm import LDDMMDeformation, _broadcast, _Config, _ExactDeformation

BACKWARDS = ("exact", "autograd")


def coarse_domain(domain: ImageDomain, factor: int) -> ImageDomain:
    """The grid of ``domain``'s box coarsened ``factor`` times per axis.

    Parameters
    ----------
    domain : ImageDomain
        The image's grid.
    factor : int
        The coarsening (``velocity_factor``, >= 1), dividing every axis.

    Returns
    -------
    ImageDomain
        The same box with ``shape // factor`` cells.

    Raises
    ------
    ValueError
        A factor that is no integer >= 1 or does not divide every axis.
    """
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise ValueError(f"velocity_factor must be an integer >= 1, got {factor!r}")
    if any(n % factor for n in domain.shape):
        raise ValueError(f"velocity_factor must divide every axis of the grid {domain.shape}, got {factor}")
    return ImageDomain(tuple(n // factor for n in domain.shape), domain.min_pt, domain.max_pt)


class CoarseVelocityDeformation(LDDMMDeformation):
    """``W(nu, I)`` of LDDMM for a velocity on ``velocity_domain``, a coarser grid of the image's box ``domain``.

    The Gaussian velocities of V are smooth on the scale ``sigma``, so they are sampled on a grid ``f`` times
    coarser than the image (``velocity_factor``): the momentum, ``nu = K m``, the kernel and the flow live there,
    the template and the operator on ``domain``. The flow's displacement ``u_N = phi_{1,0} - Id`` is composed on
    the coarse grid by eq:ODEflow1b (as ``interpolation="compose"``), interpolated bi/trilinearly from the coarse
    cell centres to the image's (``P``, ``functional.upsample``: ``align_corners=False``, continued constantly
    beyond the outer coarse centres) and the template is sampled once:

    - geometric: ``W(nu, I) = I o (Id + P u_N)`` (eq:DeforOpGeom with ``phi_{1,0}`` interpolated);
    - mass-preserving: ``W(nu, I) = (P J_N) I o (Id + P u_N)``, ``J_N`` the first-order product of
      ``LDDMMDeformation.jacobian`` on the coarse grid.

    What it approximates: ``phi_{1,0}`` of the velocity ``P nu`` by the coarse composition interpolated (the
    error of interpolating a field that is smooth on the scale sigma: small where the coarse cell side is well
    below sigma), so the map is a smooth one on the image's grid with the cost of the flow and the kernel cut by
    ``f^d`` (memory: the momentum, the velocity and the record ``f^d`` times smaller; only the template's warp
    and its adjoint run on the image's grid). With ``velocity_domain == domain`` it is the ``"compose"``
    ``LDDMMDeformation`` with ``backward="exact"`` bit for bit (tests).

    - ``backward="exact"`` (default): the exact derivative of this discrete map without a graph
      (``functional.coarse_gradient``: the fine warp's adjoint, ``P^T``, then the exact reverse sweep on the coarse
      grid; the record is the coarse displacements). ``"autograd"``: plain autograd through the same forward.
      The paper's gradient formula has no coarse-grid form (it needs ``I o phi_{t_i,0}`` on the image's grid).
    - ``interpolation``: ``"compose"`` only (the template is sampled once at the interpolated map).
    - ``jacobian_determinant`` / ``deformation``: of ``Id + P u_N`` on the image's grid; ``min_jacobian`` (the
      folding check of every step): of the coarse map ``Id + u_N`` on the velocity grid, whose interpolation is
      applied (``f^d`` times cheaper: at 256^3 with ``f = 4`` the fine determinant cost more than half a gradient).

    Parameters
    ----------
    domain : ImageDomain
        The template's and the operator's grid.
    velocity_domain : ImageDomain
        The velocity's grid: the box of ``domain`` with at most its cells per axis.
    num_steps : int
        Time steps N (>= 1).
    action : {"geometric", "mass_preserving"}
        The group action.
    backward : {"exact", "autograd"}
        The backward (above).
    interpolation : {"compose"}
        The only one on a coarser grid.
    scheme : {"central", "forward"}
        The finite differences.

    Raises
    ------
    TypeError
        ``domain`` or ``velocity_domain`` is no ``ImageDomain``.
    ValueError
        Another ``backward`` or ``interpolation``, a ``velocity_domain`` of another box or dimension or finer
        than ``domain``, and the errors of ``LDDMMDeformation``.

    Notes
    -----
    ``velocity (..., N+1, d, *velocity_domain.shape)`` (component 0 = x; physical units per unit time),
    ``template (..., *domain.shape)``, output ``(..., *domain.shape)``; 2D and 3D, float32 / float64, any
    device. ``velocity_domain`` has the box (``min_pt``, ``max_pt``) of ``domain`` and at most its cells per
    axis (any ratio; ``coarse_domain(domain, f)`` is the grid of ``velocity_factor=f``).

    Examples
    --------
    >>> from indreg import phantoms
    >>> dom = ImageDomain.paper(32)
    >>> W = CoarseVelocityDeformation(dom, coarse_domain(dom, 2), num_steps=10)
    >>> v = torch.zeros(11, 2, 16, 16, dtype=torch.float64, requires_grad=True)
    >>> template = phantoms.get("j", dom)
    >>> bool(torch.equal(W(v, template), template)), W.deformation(v).shape
    (True, torch.Size([2, 32, 32]))
    """

    def __init__(self, domain: ImageDomain, velocity_domain: ImageDomain, num_steps: int = 20,
                 action: str = "geometric", backward: str = "exact", interpolation: str = "compose",
                 scheme: str = "central"):
        if backward not in BACKWARDS:
            raise ValueError(f"backward must be one of {BACKWARDS} with a coarser velocity grid, got {backward!r}")
        if interpolation != "compose":
            raise ValueError(f"interpolation must be 'compose' with a coarser velocity grid (the template is sampled "
                             f"once at the interpolated phi_{{1,0}}), got {interpolation!r}")
        super().__init__(domain, num_steps, action, backward, interpolation, scheme)
        if not isinstance(velocity_domain, ImageDomain):
            raise TypeError(f"velocity_domain must be an ImageDomain, got {type(velocity_domain).__name__}")
        if velocity_domain.ndim != domain.ndim or velocity_domain.min_pt != domain.min_pt \
                or velocity_domain.max_pt != domain.max_pt \
                or any(a > b for a, b in zip(velocity_domain.shape, domain.shape)):
            raise ValueError(f"velocity_domain must be a grid of the box of domain {domain} with at most its cells "
                             f"per axis, got {velocity_domain}")
        self.velocity_domain = velocity_domain
        self._config = _Config(domain, action, interpolation, scheme, velocity_domain)

    def extra_repr(self) -> str:
        return f"velocity_shape={self.velocity_domain.shape}, " + super().extra_repr()

    def arguments(self) -> dict:
        return {**super().arguments(), "velocity_domain": self.velocity_domain}

    def forward(self, velocity: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
        """The deformed template ``W(nu, I)``, ``(..., *shape)``."""
        moving = self._check(velocity, template)
        if self.backward == "exact" and torch.is_grad_enabled() and (velocity.requires_grad
                                                                     or template.requires_grad):
            return _ExactDeformation.apply(velocity, template, self._config, moving)
        return self._coarse_trajectory(velocity, template, moving, last=True)

    def _trajectory(self, velocity: torch.Tensor, template: torch.Tensor, moving: list) -> torch.Tensor:
        return self._coarse_trajectory(velocity, template, moving, last=False)

    def _coarse_trajectory(self, velocity, template, moving, last: bool) -> torch.Tensor:
        template, velocity = _broadcast(velocity, template, self.domain.ndim)
        return Fd.coarse_trajectory(template, velocity, self.velocity_domain, self.domain, self.action, self.scheme,
                                    moving, last)

    def jacobian(self, velocity: torch.Tensor) -> torch.Tensor:
        """``P J_N``: the first-order product of ``LDDMMDeformation.jacobian`` on the coarse grid, interpolated."""
        moving, c = self._check_velocity(velocity), -self.domain.ndim - 1
        jac = Fd.jacobian_trajectory(velocity, self.velocity_domain, self.scheme, moving).select(c, -1)
        return Fd.upsample(jac.unsqueeze(c), self.domain.shape).squeeze(c)

    def min_jacobian(self, velocity: torch.Tensor) -> torch.Tensor:
        """Minimum of ``det D phi_{1,0}`` on the velocity grid, ``(...)``: the coarse map ``Id + u_N`` (finite
        differences as ``LDDMMDeformation.jacobian_determinant``), which ``P`` interpolates to the image's grid.
        Inside, the fine map's derivatives are blends of the coarse differences and the two agree to the
        interpolation's error of a field smooth on the scale sigma (``tests/deform/test_coarse.py``: minima within
        0.035 on swirls of scale 4 at coarse cells of 1, down to 0.3; both <= 0 where it folds); within a coarse
        cell of the border, where ``P`` continues constantly and the differences are one-sided, the fine map reads
        lower (0.78 vs 0.88 for the swirl of amplitude 2)."""
        moving = self._check_velocity(velocity)
        with torch.no_grad():
            u = Fd.displacement_10(velocity, self.velocity_domain, moving)
            return Fd.displacement_determinant(u, self.velocity_domain).amin(dim=self.velocity_domain.dims)

    def _displacement_10(self, velocity: torch.Tensor, moving: list) -> torch.Tensor:
        """``P u_N``: the coarse ``phi_{1,0} - Id`` (physical units) interpolated to the image's grid."""
        return Fd.upsample(Fd.displacement_10(velocity, self.velocity_domain, moving), self.domain.shape)
