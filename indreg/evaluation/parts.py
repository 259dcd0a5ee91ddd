"""The part of a volume the data determine and the part the prior fills.

For a linear operator ``T`` (the fitted tilts or angles) every image splits orthogonally, ``f = P f + (f - P f)``,
with ``P`` the projection onto the range of the adjoint ``T^*`` (the orthogonal complement of ``T``'s null space):
``T (f - P f) = 0``, so the second part is invisible in the data, whatever it holds, and ``T P f = T f``.

- :func:`data_split` computes ``P f`` for any operator by conjugate gradients on the normal equations (CGLS, Hestenes
  and Stiefel 1952; Paige and Saunders 1982) for ``T x = T f`` from ``x = 0``: the iterates stay in the range of
  ``T^*`` and tend to its minimum-norm solution, ``P f``; it stops when ``||T x - T f|| <= tol ||T f||``, so the
  prior-filled part projects to at most ``tol`` of the volume's projections. Directions with tiny singular values
  that the iterations have not reached stay in the prior-filled part: the data barely see them either.
- :func:`wedge_split` is the Fourier picture of a parallel tilt series (or a parallel sinogram): by the Fourier slice
  theorem the projection at angle ``theta`` samples the slice's Fourier transform along the detector direction
  ``(cos theta, sin theta)``, so the measured wedge is the set of frequencies whose direction lies within the tilt
  range (widened by half a tilt step at each end). Sparse tilts inside the range count as measured, so its
  prior-filled part is the missing wedge only, and it projects to zero on the tilts up to the discretisation
  (reported: ``projection_difference``).

Convention: images ``operator.domain.shape`` (2D ``(nx, ny)`` or 3D ``(nx, ny, nz)``); inner products are the
domain's and ``operator.inner_data`` (weighted L2), so ``P`` is orthogonal in L2; the two parts sum to the volume.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["Split", "data_split", "wedge_split", "wedge_mask", "parallel_angles", "cgls", "DEFAULT_TOL"]

#: The projections of the prior-filled part relative to the volume's at which :func:`data_split` stops.
DEFAULT_TOL = 1e-3


@dataclass
class Split:
    """``volume = data + prior``: the data-determined and the prior-filled parts of a volume ``f``
    (:func:`data_split`, :func:`wedge_split`).

    Attributes
    ----------
    data : torch.Tensor
        The data-determined part (the volume's shape).
    prior : torch.Tensor
        The prior-filled part (the volume's shape), ``f - data``.
    method : str
        ``"range"`` or ``"wedge"``.
    iterations : int
        CGLS iterations (0 for the wedge).
    projection_difference : float
        ``||T data - T f|| / ||T f||`` (= ``||T prior|| / ||T f||``; 0 when ``T f`` is 0).
    prior_fraction : float
        ``||prior|| / ||f||`` (0 for an all-zero ``f``).
    """
    data: torch.Tensor
    prior: torch.Tensor
    method: str
    iterations: int
    projection_difference: float
    prior_fraction: float

    def summary(self) -> dict:
        """The numbers, for ``metrics.json`` (keys ``split_*``)."""
        return {"split_method": self.method, "split_iterations": self.iterations,
                "split_projection_difference": self.projection_difference,
                "split_prior_fraction": self.prior_fraction}


def _dnorm(T, y: torch.Tensor) -> float:
    return math.sqrt(max(float(T.inner_data(y, y).sum()), 0.0))


def _finish(f, data, T, Tf, method, iterations) -> Split:
    prior = f - data
    Tf_norm, f_norm = _dnorm(T, Tf), float(T.domain.norm(f))
    diff = _dnorm(T, T(prior)) / Tf_norm if Tf_norm > 0 else 0.0
    return Split(data, prior, method, iterations, diff, float(T.domain.norm(prior)) / f_norm if f_norm > 0 else 0.0)


@torch.no_grad()
def data_split(volume: torch.Tensor, operator, tol: float = DEFAULT_TOL, max_iter: int = 300) -> Split:
    """``volume = P f + (f - P f)`` with ``P`` the projection onto the range of ``operator``'s adjoint (module
    docstring), by CGLS from 0 until ``||T x - T f|| <= tol ||T f||`` or ``max_iter`` iterations.

    Parameters
    ----------
    volume : torch.Tensor
        ``f``, ``operator.domain.shape``.
    operator : LinearOperator
        ``T``: the fitted tilts or angles (any ``indreg.forward.LinearOperator``, alignment included).
    tol : float
        The relative projection of the prior-filled part at which to stop (> 0).
    max_iter : int
        At most this many iterations (each one ``T`` and one ``T^*``).

    Returns
    -------
    Split
        The two parts, ``method="range"``.

    Raises
    ------
    ValueError
        ``volume`` not of the domain's shape, ``tol`` not in (0, 1), ``max_iter`` < 1.
    """
    T = operator
    f = T.domain.check_image(volume, "volume")
    if tuple(f.shape) != tuple(T.domain.shape):
        raise ValueError(f"volume must have shape {tuple(T.domain.shape)} (the operator's domain), got "
                         f"{tuple(f.shape)}")
    if not 0 < tol < 1 or int(max_iter) < 1:
        raise ValueError(f"tol must be in (0, 1) and max_iter >= 1, got tol={tol}, max_iter={max_iter}")
    b = T(f)
    x, k = cgls(T, b, tol * _dnorm(T, b), max_iter)
    return _finish(f, x, T, b, "range", k)


@torch.no_grad()
def cgls(T, b: torch.Tensor, bound: float, max_iter: int, callback=None) -> tuple:
    """``(x, iterations)``: conjugate gradients on the normal equations of ``T x = b`` from ``x = 0`` (CGLS, in
    the domain's and the data's inner products), stopped when ``||T x - b|| <= bound``, after ``max_iter``
    iterations or when ``callback(x, r)``, called after each iteration with the iterate and its residual
    ``r = b - T x``, returns True; ``x`` lies in the range of ``T^*``."""
    inner = T.domain.inner
    x, r = T.domain.zeros(dtype=b.dtype, device=b.device), b.clone()
    s = T.adjoint(r)
    p, gamma = s.clone(), float(inner(s, s))
    k = 0
    while k < max_iter and _dnorm(T, r) > bound and gamma > 0:
        q = T(p)
        qq = float(T.inner_data(q, q).sum())
        if qq <= 0:
            break
        alpha = gamma / qq
        x.add_(p, alpha=alpha)
        r.sub_(q, alpha=alpha)
        s = T.adjoint(r)
        gamma_new = float(inner(s, s))
        p = s.add_(p, alpha=gamma_new / gamma)
        gamma, k = gamma_new, k + 1
        if callback is not None and callback(x, r):
            break
    return x, k


def parallel_angles(operator) -> tuple:
    """``(angles in radians, slice axes (u, v))`` of a parallel-beam ``RayTransform`` (2D, axes ``(0, 1)``) or a
    ``TiltSeriesTransform`` (its slice axes), also inside an ``AlignedOperator`` (its in-plane shifts do not move
    the measured frequencies) or a ``RestrictedOperator`` (its rows); a one-line TypeError for any other."""
    from ..forward.geometry import ParallelBeamGeometry
    from ..forward.ray_transform import RayTransform
    from ..forward.stacking import RestrictedOperator
    from ..forward.tilt_series import TiltSeriesTransform

    op, rows = operator, None
    while True:
        if isinstance(op, RestrictedOperator):
            rows = op.rows if rows is None else op.rows[rows]
            op = op.operator
        elif hasattr(op, "operator") and hasattr(op, "shifts"):   # an AlignedOperator
            op = op.operator
        else:
            break
    if isinstance(op, TiltSeriesTransform):
        angles, axes = op.geometry.angles, op.geometry.slice_axes
    elif isinstance(op, RayTransform) and isinstance(op.geometry, ParallelBeamGeometry):
        angles, axes = op.geometry.angles, (0, 1)
    else:
        raise TypeError(f"the measured wedge needs a parallel-beam RayTransform or a TiltSeriesTransform, got "
                        f"{type(op).__name__}: use data_split (any operator)")
    angles = torch.as_tensor(angles, dtype=torch.float64).cpu()
    return (angles if rows is None else angles[rows.cpu()]), tuple(axes)


def wedge_mask(shape: tuple, cells: tuple, angles: torch.Tensor) -> torch.Tensor:
    """A boolean ``shape`` (``(n_u, n_v)``) mask of the FFT frequencies (``torch.fft.fftfreq`` order) whose
    direction ``(k_u, k_v)`` lies, up to sign, within the tilt range of ``angles`` (radians) widened by half the
    median step at each end; the zero frequency is measured. All of them when the widened range covers pi.

    Parameters
    ----------
    shape : tuple
        ``(n_u, n_v)``: the slice's sizes along its two axes.
    cells : tuple
        ``(cell_u, cell_v)``: the voxel sides along those axes (the sample spacings of ``torch.fft.fftfreq``).
    angles : torch.Tensor
        The tilts or projection angles in radians (any order; taken modulo pi into ``[-pi/2, pi/2)``).

    Returns
    -------
    torch.Tensor
        Boolean, of ``shape``: True where the frequency is measured.
    """
    a = torch.sort(torch.remainder(torch.as_tensor(angles, dtype=torch.float64) + math.pi / 2, math.pi)
                   - math.pi / 2).values
    step = float(torch.diff(a).median()) if a.numel() > 1 else 0.0
    lo, hi = float(a[0]) - step / 2, float(a[-1]) + step / 2
    ku = torch.fft.fftfreq(shape[0], d=cells[0], dtype=torch.float64).view(-1, 1)
    kv = torch.fft.fftfreq(shape[1], d=cells[1], dtype=torch.float64).view(1, -1)
    if hi - lo >= math.pi:
        return torch.ones(shape, dtype=torch.bool)
    phi = torch.atan2(kv.expand(shape), ku.expand(shape))
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    d = torch.abs(torch.remainder(phi - centre + math.pi / 2, math.pi) - math.pi / 2)
    return (d <= half + 1e-12) | ((ku == 0) & (kv == 0))


@torch.no_grad()
def wedge_split(volume: torch.Tensor, operator) -> Split:
    """``volume`` split by the measured wedge of a parallel tilt series or sinogram (module docstring): the data
    part keeps the Fourier coefficients of every slice (orthogonal to the tilt axis) inside the wedge of
    ``operator``'s angles (:func:`wedge_mask`), the prior part the rest (the missing wedge).

    Parameters
    ----------
    volume : torch.Tensor
        ``operator.domain.shape``.
    operator : LinearOperator
        A parallel-beam ``RayTransform`` or ``TiltSeriesTransform`` (:func:`parallel_angles`).

    Returns
    -------
    Split
        ``method="wedge"``; ``projection_difference`` measures how nearly the missing wedge projects to zero.

    Raises
    ------
    TypeError
        Another operator (fan beam, a user operator).
    """
    angles, (u, v) = parallel_angles(operator)
    T = operator
    f = T.domain.check_image(volume, "volume")
    cells = T.domain.cell_sides
    mask = wedge_mask((f.shape[u], f.shape[v]), (cells[u], cells[v]), angles).to(f.device)
    if f.dim() == 3:   # (u, v) last, the tilt axis in front
        t = ({0, 1, 2} - {u, v}).pop()
        g = f.permute(t, u, v)
        data = torch.fft.ifft2(torch.fft.fft2(g) * mask).real.permute(*torch.argsort(torch.tensor([t, u, v])).tolist())
    else:
        data = torch.fft.ifft2(torch.fft.fft2(f) * mask).real
    return _finish(f, data.contiguous().to(f.dtype), T, T(f), "wedge", 0)
