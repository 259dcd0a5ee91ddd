"""What a solver, the run loop and the result builder need from a registration problem (a model's objective).

A *registration problem* is an objective ``E(x)`` over an iterate ``x = (x_0, x_1, ...)``, a tuple of tensors whose
first entry is the momentum ``m`` of the velocity field ``nu = K m``. LDDMM (``IndirectRegistration``) has
``x = (m,)``; metamorphosis (``MetamorphosisRegistration``) has ``x = (m, s)``, ``s`` the source iterate. Solvers
(``Algorithm1``, ``TorchOptimSolver``), step control (``StepControl``), the run loop and the result builder
(``indreg.registration.run``) only use the members below, so a new model is a new subclass and one registry entry
(``indreg.registration.models``), with no change to any of them.

Members a subclass implements:

- ``iterate_names``: names of the iterate's entries (``("momentum",)``, ``("momentum", "source")``);
- ``zero_iterate()``: the starting iterate (the identity deformation: all zeros);
- ``check_iterate(x)``: one-line errors for a wrong shape / dtype / device;
- ``differentiable(x) -> (terms, aux, l2)``: the terms as 0-dim tensors differentiable through ``x`` (for autograd
  and torch.optim), tensors ``aux`` (``aux[0] = nu``) and ``l2(x, dx, daux) -> h`` turning autograd's gradients
  into the descent directions ``h = (h_0, h_1, ...)``; ``dx`` are the gradients with respect to the parameters
  ``p_k = x_k / s``, ``s = N / cell_volume`` (the torch.optim solvers' parametrisation: ``dE/dp_0 = K h_0``);
- ``gradient(x) -> (terms, h, nu)``: the objective's terms (python floats: ``objective`` and its parts), ``h``
  (Algorithm 1 descends ``x_k <- x_k - alpha_k h_k``) and ``nu = K m``: by default autograd through
  ``differentiable``; LDDMM and metamorphosis hand-write it (one forward / backward, in place);
- ``reconstruction(x)`` (the image the iterate implies, ``f(1)``), ``image_trajectory(x)`` (``f(t_i)``),
  ``image_frames(x)`` (the same ``f(t_i)`` one at a time: by default from ``image_trajectory``; the slab-wise
  problem computes each frame alone),
  ``evaluate_iterate(x)`` (the terms, python floats), ``outputs(x)`` (model-specific results by name),
  ``scored`` (which of those are images to score against a target), ``hparams()``, ``relative_residual(x)``
  (``||T f - g|| / ||g||``; by default of ``reconstruction(x)``);
- ``with_backward(backward)`` / ``for_line_search()``: the problem with another deformation backward (a line
  search needs the exact gradient of the discrete map);
- optionally ``default_step(name)`` for entries after the momentum, ``coarsened(shape, num_steps,
  backward)`` (the same problem on a coarser grid, for ``MultilevelSolver``) and ``at_iteration(k)`` (Algorithm 1
  calls it before each step; a problem whose objective is staged by the iteration switches there and returns True).

Grids: ``domain`` is the momentum's and the velocity's (its ``cell_volume`` weighs the iterate's ``L2`` inner
product: ``time_weight``, ``gradient_norm``, the torch.optim scale); the template, the operator and the images
live on ``image_domain`` where a problem has one (``IndirectRegistration`` with ``velocity_factor > 1``), else on
``domain`` too.

Shared here: the velocity ``nu = K m``, the discrete ``L2([0,1], L2)`` norm of a gradient, the minimum Jacobian
determinant of ``phi_{1,0}``.
"""
from __future__ import annotations

from typing import Optional

import math

import torch

from ..forward.operator import relative_residual


class RegistrationProblem:
    """Base class of the registration objectives (module docstring: the protocol). Subclasses set ``kernel``,
    ``deformation``, ``domain``, ``template``, ``data``, ``ray_transform``, ``num_steps``."""

    iterate_names: tuple = ("momentum",)
    #: names in ``outputs(x)`` that are images to compare with a target (SSIM / PSNR)
    scored: tuple = ()
    #: the kind of each output of ``outputs(x)`` that reports dispatch on (others are saved only): ``"parts"`` (a
    #: split of the reconstruction into summands, in order), ``"frames"`` (images over time, a leading axis whose
    #: times are ``frame_times()``)
    output_kinds: dict = {}
    #: whether the problem splits its work into slabs of rows along the tilt axis (``slab_size`` fine slices each),
    #: shared over the ranks of a process group (``indreg.ranks``) or taken one after another in one process
    splits_over_ranks: bool = False

    @property
    def time_weight(self) -> float:
        """Weight ``cell_volume / N`` of a torch entry in the discrete ``L2([0,1], L2)`` inner product."""
        return self.domain.cell_volume / self.num_steps

    def velocity(self, m: torch.Tensor) -> torch.Tensor:
        """``nu = K m`` (differentiable)."""
        return self.kernel.apply(m)

    def gradient_norm(self, h: torch.Tensor) -> float:
        """``||h||_{L2([0,1], L2)} = sqrt(sum_i (1/N) ||h_i||^2_L2)``."""
        flat = h.reshape(-1)
        return math.sqrt(self.time_weight * float(torch.dot(flat, flat)))

    def min_jacobian(self, nu: torch.Tensor) -> float:
        """Minimum Jacobian determinant of ``phi_{1,0}`` for velocity ``nu`` (folding when <= 0)."""
        with torch.no_grad():
            return float(self.deformation.min_jacobian(nu))

    def deformation_field(self, nu: torch.Tensor) -> torch.Tensor:
        """``phi_{1,0}`` of ``nu``, ``(d, *shape)`` (points, physical units)."""
        with torch.no_grad():
            return self.deformation.deformation(nu)

    def gradient(self, x: tuple) -> tuple:
        """``(terms, h, nu)`` by autograd through ``differentiable(x)`` (module docstring)."""
        s = self.num_steps / self.domain.cell_volume
        k = len(x)
        with torch.enable_grad():
            leaves = tuple(t.detach().requires_grad_(True) for t in x)
            terms, aux, l2 = self.differentiable(leaves)
            grads = torch.autograd.grad(terms["objective"], (*leaves, *aux))
        h = l2(tuple(t.detach() for t in x), tuple(s * g for g in grads[:k]), grads[k:])
        return {key: float(v.detach()) for key, v in terms.items()}, h, aux[0].detach()

    def check_iterate(self, x: tuple) -> None:
        if not isinstance(x, tuple) or len(x) != len(self.iterate_names):
            raise ValueError(f"the iterate must be a tuple of {len(self.iterate_names)} tensors "
                             f"{self.iterate_names}, got {type(x).__name__} of length {len(x)}")

    def default_step(self, name: str) -> float:
        """Algorithm 1's step for the iterate's entry ``name`` when none is given (entries after the momentum)."""
        raise TypeError(f"{type(self).__name__} has no default step for {name!r}: give one")

    def at_iteration(self, iteration: int) -> bool:
        """Before Algorithm 1's step ``iteration``: True when the objective changed there (none does by default)."""
        return False

    def for_line_search(self) -> "RegistrationProblem":
        """The problem with a deformation backward that is the exact gradient of the discrete map."""
        return self

    def hparams(self) -> dict:
        """The model's own hyperparameters for reports (TensorBoard's HParams, metrics.json)."""
        return {}

    def frame_times(self) -> Optional[list]:
        """The times of the ``"frames"`` outputs (None: no frames)."""
        return None

    def image_frames(self, x: tuple):
        """``f(t_i)`` for ``i = 0..N``, one frame at a time (an iterator of ``image_trajectory(x)[i]``); a problem
        that can evaluate a frame alone overrides it, so that a caller holds one frame, not ``N + 1``."""
        yield from self.image_trajectory(x)

    def outputs(self, x: tuple) -> dict:
        """Model-specific results at ``x`` by name (tensors), besides the reconstruction and the deformation."""
        return {}

    def relative_residual(self, x: tuple) -> float:
        """``||T f - g|| / ||g||`` of ``f = reconstruction(x)`` in the data norm (a model whose data are not
        ``T f`` of its reconstruction, e.g. several frames, overrides it)."""
        return relative_residual(self.ray_transform, self.reconstruction(x), self.data)
