"""Spatiotemporal indirect registration: one flow explains data taken at several times (docs/spatiotemporal.md).

Data ``g_k`` are measured at times ``0 <= t_1 < ... < t_K <= 1``, each with its own operator ``T_k``
(``indreg.forward.TimeSeriesOperator``). The object at time ``t`` is the template ``I`` carried by the flow of one
velocity field ``nu`` on ``[0, 1]``: ``f_t = W(phi_{0,t}, I) = I o phi_{t,0}`` (geometric action; mass-preserving
likewise). In the scale of ``objective.IndirectRegistration`` (half the printed objective):

    E(nu [, I]) = (gamma/2) sum_{i=0..N} (1/N) ||nu_i||_V^2 + (1/2) sum_k ||T_k f_{t_k} - g_k||^2_k
                  (+ tv_weight sum_k TV(f_{t_k})) (+ template_tv_weight TV(I), template unknown)

with ``nu = K m`` and the same time grid ``t_i = i/N`` as a registration: every ``t_k`` must be a grid point
``j_k / N`` (``time_indices``), and ``f_{t_k}`` is the deformation's trajectory at ``i = j_k``. With ``K = 1``,
``t_1 = 1`` this is ``IndirectRegistration``; with ``nu = 0`` it is a static reconstruction from all the data.

Gradients (torch entries, ``L`` = the matching terms):

- ``backward="autograd"`` (default): plain autograd through the deformation's trajectory, one forward of ``N``
  steps and its reverse for all frames (the exact derivative of the discrete map; keeps the graph of the time
  loop). A velocity with an all-zero step (``m = 0``: the start) takes the ``"exact"`` path below, whose backward
  uses central differences where every point sits on a node (autograd's one-sided slopes there are no descent
  direction);
- ``"exact"``: frame ``k`` is ``W(nu 1_{i <= j_k}, I)`` (the velocity zeroed after ``t_k``: those steps are the
  identity), all frames in one batched call of the deformation with its hand-written exact backward (memory
  ``O(N n^2)`` per frame, ``K`` forwards of ``N`` steps). The paper's gradient formula is not offered: on masked
  velocities it drifts far from the derivative (cosine 0.58 against it on a 16^2, N = 4, K = 2 test problem).

``h_nu = gamma m + (N / cell_volume) dL/dnu`` (as LDDMM; the V-gradient is ``K h_nu``) and, template unknown,
``h_I = dE/dI / cell_volume``, the L2 gradient ``sum_k (D W_k)^* T_k^*(T_k f_{t_k} - g_k)`` (+ TV): the
frames' residuals back-projected and pulled back to ``t = 0`` through the current deformations.
"""
from __future__ import annotations

import math
import numbers

import numpy as np
import torch

from .._checks import check_nonnegative, check_same, check_tensor
from ..deform.kernel import GaussianKernel
from ..deform.lddmm import LDDMMDeformation
from ..forward.time_series import TimeSeriesOperator
from ..forward.tv import total_variation
from .problem import RegistrationProblem

#: ``t_k N`` must be an integer to this tolerance.
GRID_TOLERANCE = 1e-6


def time_indices(times, num_steps: int, count: int) -> list:
    """The grid indices ``j_k = t_k N`` of ``times`` (None: ``t_k = k / K``, ``k = 1..K``); one-line ValueError
    when they are not ``count`` increasing numbers in ``[0, 1]`` on the grid ``j / N``."""
    if times is None:
        times = [(k + 1) / count for k in range(count)]
    if hasattr(times, "tolist") and not isinstance(times, (str, bytes)):
        times = times.tolist()
    if not isinstance(times, (list, tuple)) or not all(
            isinstance(t, numbers.Real) and not isinstance(t, (bool, np.bool_)) for t in times):
        raise ValueError(f"times must be a list of {count} numbers in [0, 1], got {times!r}")
    times = [float(t) for t in times]   # numpy scalars (a list of np.float32) as the same array's tolist()
    if len(times) != count:
        raise ValueError(f"times has {len(times)} entries but the data {count} frames: give one time per frame")
    if not all(math.isfinite(t) and 0 <= t <= 1 for t in times):
        raise ValueError(f"times must lie in [0, 1], got {list(times)}")
    if any(b <= a for a, b in zip(times, times[1:])):
        raise ValueError(f"times must be strictly increasing, got {list(times)}")
    out = []
    for t in times:
        j = round(t * num_steps)
        if abs(t * num_steps - j) > GRID_TOLERANCE:
            raise ValueError(f"times must lie on the time grid j / num_steps (num_steps={num_steps}): {t} is not "
                             f"(nearest {j / num_steps:g}); choose num_steps a multiple of the frame spacing")
        out.append(j)
    return out


class SpatiotemporalRegistration(RegistrationProblem):
    """``min_{m [, I]} E`` (module docstring) over data at ``K`` time points.

    Parameters
    ----------
    operator : TimeSeriesOperator
        One ``T_k`` per time point (``indreg.forward.TimeSeriesOperator``).
    deformation : LDDMMDeformation
        ``W`` on the image's grid, ``backward`` ``"autograd"`` or ``"exact"`` (module docstring).
    kernel : GaussianKernel
        ``K`` of V on the deformation's domain.
    template : torch.Tensor or None
        The template ``I``, ``domain.shape``; None: unknown, reconstructed jointly (the iterate becomes
        ``(m, I)``, starting from ``initial_template``).
    data : torch.Tensor
        ``(K, *R)``, ``operator.range_shape``, the template's dtype / device.
    times : sequence of float, optional
        ``K`` strictly increasing times in ``[0, 1]`` on the grid ``j / N`` (None: ``k / K``, ``k = 1..K``).
    gamma, tv_weight, tv_smoothing : float
        As ``IndirectRegistration`` (``tv_weight`` on every frame).
    template_tv_weight : float
        Weight of ``TV(I)`` when the template is unknown.
    initial_template : torch.Tensor, optional
        The unknown template's start (default zeros in the data's dtype and device).

    Raises
    ------
    TypeError
        An operator that is no ``TimeSeriesOperator``, a deformation not on the image's grid.
    ValueError
        Another backward, a kernel or operator on another domain, data or template of the wrong shape, times
        not increasing, outside [0, 1] or off the time grid, a negative weight.

    Notes
    -----
    Momentum / velocity ``(N+1, d, *shape)`` at ``t_i = i / N``; frames ``(K, *shape)`` at ``t_k``;
    ``reconstruction`` is the last frame ``f_{t_K}``; ``outputs``: ``frames`` and, template unknown, ``template``.
    """

    def __init__(self, operator, deformation, kernel, template, data, times=None, gamma=1e-6, tv_weight=0.0,
                 tv_smoothing=1e-3, template_tv_weight=0.0, initial_template=None):
        if not isinstance(operator, TimeSeriesOperator):
            raise TypeError(f"operator must be an indreg.forward.TimeSeriesOperator (or a list of operators, one per "
                            f"time point), got {type(operator).__name__}")
        if not isinstance(deformation, LDDMMDeformation) or deformation.velocity_domain != deformation.domain:
            raise TypeError(f"deformation must be an LDDMMDeformation on the image's grid, got {deformation!r}")
        if deformation.backward not in ("autograd", "exact"):
            raise ValueError(f"deformation.backward must be 'autograd' or 'exact', got {deformation.backward!r}")
        if not isinstance(kernel, GaussianKernel) or kernel.domain != deformation.domain:
            raise ValueError("kernel must be a GaussianKernel on the deformation's domain")
        if operator.domain != deformation.domain:
            raise ValueError(f"operator.domain {operator.domain} differs from deformation.domain {deformation.domain}")
        check_tensor(data, "data")
        if tuple(data.shape) != tuple(operator.range_shape):
            raise ValueError(f"data must have shape {tuple(operator.range_shape)} (K frames of the operators' "
                             f"range_shape), got {tuple(data.shape)}")
        self.known = template is not None
        if self.known:
            check_tensor(template, "template")
            if tuple(template.shape) != tuple(operator.domain.shape):
                raise ValueError(f"template must have shape {tuple(operator.domain.shape)}, got "
                                 f"{tuple(template.shape)}")
            check_same(template, data, "template", "data")
        else:
            template = torch.zeros(operator.domain.shape, dtype=data.dtype, device=data.device) \
                if initial_template is None else initial_template
            self.iterate_names = ("momentum", "template")
        self.ray_transform, self.deformation, self.kernel = operator, deformation, kernel
        self.domain = self.image_domain = deformation.domain
        self.template, self.data = template, data
        self.num_steps = int(deformation.num_steps)
        self.times = times
        self.indices = time_indices(times, self.num_steps, len(operator))
        self.gamma = check_nonnegative(gamma, "gamma", data.dtype)
        self.tv_weight = check_nonnegative(tv_weight, "tv_weight", data.dtype)
        self.tv_smoothing = check_nonnegative(tv_smoothing, "tv_smoothing", data.dtype)
        self.template_tv_weight = check_nonnegative(template_tv_weight, "template_tv_weight", data.dtype)
        self._norm = None

    def __repr__(self):
        t = "known template" if self.known else "unknown template"
        return (f"SpatiotemporalRegistration(domain={self.domain}, K={len(self.indices)} frames at t = "
                f"{[j / self.num_steps for j in self.indices]}, N={self.num_steps}, gamma={self.gamma}, {t}, "
                f"backward={self.deformation.backward!r})")

    def _replace(self, deformation) -> "SpatiotemporalRegistration":
        return SpatiotemporalRegistration(self.ray_transform, deformation, self.kernel,
                                          self.template if self.known else None, self.data, self.times, self.gamma,
                                          self.tv_weight, self.tv_smoothing, self.template_tv_weight,
                                          None if self.known else self.template)

    def with_backward(self, backward: str) -> "SpatiotemporalRegistration":
        return self._replace(self.deformation.replace(backward=backward))

    # ------------------------------------------------------------------------------------------------ the model
    @property
    def momentum_shape(self) -> tuple:
        return (self.num_steps + 1, self.domain.ndim, *self.domain.shape)

    def zero_iterate(self) -> tuple:
        m = torch.zeros(self.momentum_shape, dtype=self.data.dtype, device=self.data.device)
        return (m,) if self.known else (m, self.template.clone())

    def check_iterate(self, x: tuple) -> None:
        super().check_iterate(x)
        check_tensor(x[0], "momentum", self.momentum_shape)
        check_same(x[0], self.data, "momentum", "data")
        if not self.known:
            check_tensor(x[1], "template", self.domain.shape)
            check_same(x[1], self.data, "template", "data")

    def _template(self, x: tuple) -> torch.Tensor:
        return self.template if self.known else x[1]

    def frames(self, nu: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
        """``f_{t_k} = W(phi_{0,t_k}, I)``, ``(K, *shape)`` (differentiable; module docstring for the modes)."""
        W, idx = self.deformation, self.indices
        if W.backward == "autograd" and self._all_steps_move(nu):
            trajectory = W.trajectory(nu, template)
            return trajectory.index_select(0, torch.tensor(idx, device=nu.device))
        steps = torch.arange(self.num_steps + 1, device=nu.device)
        mask = (steps[None, :] <= torch.tensor(idx, device=nu.device)[:, None]).to(nu.dtype)
        velocities = torch.stack([nu if j == self.num_steps else nu * mask[k].reshape(-1, *(1,) * (nu.dim() - 1))
                                  for k, j in enumerate(idx)])
        return W(velocities, template)

    def _all_steps_move(self, nu: torch.Tensor) -> bool:
        """Whether no step ``i = 1..N`` has an all-zero velocity. At such a step bilinear interpolation sits on its
        kinks (every point on a node) and autograd returns one-sided slopes, not a descent direction (the template
        steps of the intertwined scheme start at ``m = 0``); the exact path's backward takes their mean there."""
        return bool((nu[1:].detach().flatten(1).abs().amax(dim=1) > 0).all())

    def regulariser(self, m: torch.Tensor, nu: torch.Tensor) -> torch.Tensor:
        """``(gamma/2) (cell_volume/N) sum m * nu`` (``IndirectRegistration.regulariser``)."""
        return 0.5 * self.gamma * self.time_weight * torch.dot(m.reshape(-1), nu.reshape(-1))

    def matching(self, nu: torch.Tensor, template: torch.Tensor) -> dict:
        """``data_fit = (1/2) sum_k ||T_k f_{t_k} - g_k||^2_k``, ``tv`` (of the frames) and ``template_tv``."""
        frames = self.frames(nu, template)
        residual = self.ray_transform.frames(frames) - self.data
        out = {"data_fit": 0.5 * self.ray_transform.inner_data(residual, residual)}
        zero = torch.zeros((), dtype=frames.dtype, device=frames.device)
        out["tv"] = self.tv_weight * total_variation(frames, self.domain, self.tv_smoothing).sum() \
            if self.tv_weight > 0 else zero
        out["template_tv"] = self.template_tv_weight * total_variation(template, self.domain, self.tv_smoothing) \
            if self.template_tv_weight > 0 and not self.known else zero
        return out

    def terms(self, x: tuple, nu: torch.Tensor | None = None) -> dict:
        nu = self.velocity(x[0]) if nu is None else nu
        out = self.matching(nu, self._template(x))
        out["regulariser"] = self.regulariser(x[0], nu)
        out["objective"] = out["data_fit"] + out["tv"] + out["template_tv"] + out["regulariser"]
        return out

    # ------------------------------------------------------------------------------------------------ protocol
    def gradient(self, x: tuple) -> tuple:
        """``(terms, h, nu)``: ``h_nu = gamma m + (N / cell_volume) dL/dnu`` and (template unknown) ``h_I = dE/dI /
        cell_volume``, one forward / backward of all frames."""
        m = x[0]
        with torch.no_grad():
            nu = self.velocity(m)
        with torch.enable_grad():
            leaves = [nu.detach().requires_grad_(True)]
            if not self.known:
                leaves.append(x[1].detach().requires_grad_(True))
            match = self.matching(leaves[0], leaves[1] if not self.known else self.template)
            grads = torch.autograd.grad(match["data_fit"] + match["tv"] + match["template_tv"], leaves)
        h = (grads[0].div_(self.time_weight).add_(m, alpha=self.gamma),)
        if not self.known:
            h += (grads[1].div_(self.domain.cell_volume),)
        terms = {k: float(v.detach()) for k, v in match.items()}
        terms["regulariser"] = float(self.regulariser(m, nu))
        terms["objective"] = terms["data_fit"] + terms["tv"] + terms["template_tv"] + terms["regulariser"]
        return terms, h, nu

    def differentiable(self, x: tuple) -> tuple:
        """Terms differentiable through ``x``, ``aux = (nu,)`` and the L2 gradients (``dx``: per ``p = x / s``)."""
        nu = self.velocity(x[0])
        n = self.num_steps

        def l2(x, dx, daux):
            h = (daux[0] / self.time_weight + 0.5 * self.gamma * x[0],)
            return h if self.known else h + (dx[1] / n,)
        return self.terms(x, nu), (nu,), l2

    def evaluate_iterate(self, x: tuple) -> dict:
        self.check_iterate(x)
        with torch.no_grad():
            return {k: float(v) for k, v in self.terms(x).items()}

    def all_frames(self, x: tuple) -> torch.Tensor:
        """The frames ``f_{t_k}`` at ``x``, ``(K, *shape)``."""
        with torch.no_grad():
            return self.frames(self.velocity(x[0]), self._template(x))

    def reconstruction(self, x: tuple) -> torch.Tensor:
        """The last frame ``f_{t_K}`` (``f(1)`` when ``t_K = 1``)."""
        return self.all_frames(x)[-1]

    def image_trajectory(self, x: tuple) -> torch.Tensor:
        """``f(t_i)`` for ``i = 0..N``, ``(N+1, *shape)``."""
        with torch.no_grad():
            return self.deformation.trajectory(self.velocity(x[0]), self._template(x))

    def relative_residual(self, x: tuple) -> float:
        """``(sum_k ||T_k f_{t_k} - g_k||^2 / sum_k ||g_k||^2)^(1/2)``."""
        T, g = self.ray_transform, self.data
        with torch.no_grad():
            r = T.frames(self.all_frames(x)) - g
            return math.sqrt(float(T.inner_data(r, r)) / float(T.inner_data(g, g)))

    output_kinds = {"frames": "frames"}

    def frame_times(self) -> list:
        """``t_k = j_k / N``: the frames' times on the time grid."""
        return [j / self.num_steps for j in self.indices]

    def outputs(self, x: tuple) -> dict:
        out = {"frames": self.all_frames(x)}
        if not self.known:
            out["template"] = x[1]
        return out

    def default_step(self, name: str) -> float:
        """The template's step ``1 / ||T||^2`` (``||T||^2 = ||sum_k T_k^* T_k||``: the data term's curvature in ``I``
        near the identity deformation)."""
        if name != "template":
            return super().default_step(name)
        if self._norm is None:
            self._norm = self.ray_transform.operator_norm(30, self.data.dtype, self.data.device)
        return 1.0 / self._norm ** 2

    def hparams(self) -> dict:
        return {"frames": len(self.indices), "template_known": self.known}


class FramesOfTemplate:
    """``A I = (T_k W(phi_{0,t_k}, I))_k`` at a fixed velocity: linear in ``I`` (the linear-operator protocol of
    ``indreg.forward.operator``), so a reconstruction of the template from all frames pulled back through the
    current deformations is ``tv_reconstruction(A, g, mu)``. ``adjoint`` by autograd: ``A^* y = d<A I, y>/dI /
    cell_volume`` (the L2 adjoint). Convention: ``I`` ``domain.shape``, data ``(K, *R)``."""

    def __init__(self, problem: SpatiotemporalRegistration, nu: torch.Tensor):
        self.problem, self.nu = problem, nu.detach()
        self.domain, self.range_shape = problem.domain, problem.ray_transform.range_shape
        self.inner_data = problem.ray_transform.inner_data

    def _apply(self, template: torch.Tensor) -> torch.Tensor:
        return self.problem.ray_transform.frames(self.problem.frames(self.nu, template))

    def __call__(self, template: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self._apply(template)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        with torch.enable_grad():
            leaf = torch.zeros(self.domain.shape, dtype=y.dtype, device=y.device, requires_grad=True)
            (g,) = torch.autograd.grad(self.inner_data(self._apply(leaf), y), leaf)
        return g / self.domain.cell_volume
