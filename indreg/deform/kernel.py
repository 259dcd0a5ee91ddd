"""The Gaussian reproducing kernel of the velocity space V and its application to vector fields."""
from __future__ import annotations

import math
import sys

import scipy.fft
import torch

from .._checks import check_positive, check_same, check_tensor
from ..domain import ImageDomain

#: ``method="auto"`` uses the dense separable (Toeplitz matrix) form up to this many pixels per axis
#: and the zero-padded FFT above. Measured on the 2-core CPU (float32, 42 fields = 21 two-component,
#: median ms, ``scripts/bench_deform.py --kernel``; a busy machine, 1-2 threads), matrix vs fft:
#: 64^2 0.5-0.7 vs 4-4.4, 128^2 2.7-5.3 vs 20-35, 256^2 25-69 vs 175-475, 438^2 450-530 vs 710-2000,
#: 512^2 180-740 vs 750-2570, 768^2 600-2030 vs 3300-4060: BLAS beats the 2n-padded FFT by 1.5-7x at every
#: size measured; the FFT's n^2 log n only pays off beyond ~1000^2 (extrapolated, not measured).
MATRIX_MAX_CPU = 1024
MATRIX_MAX_CUDA = 1024
#: The smallest accepted ``sigma``: ``sqrt`` of the smallest normal float64. Below it ``sigma^2`` underflows and
#: ``exp(-d^2 / (2 sigma^2))`` is NaN at ``d = 0``; a ``sigma`` far below a cell side but above this bound gives
#: the (representable) discrete delta ``K m = cell_volume * m``.
SIGMA_MIN = math.sqrt(sys.float_info.min)


class GaussianKernel:
    """Gaussian kernel ``K(x, y) = exp(-|x - y|^2 / (2 sigma^2)) Id`` of the RKHS V (eq:KernelEq, with the square).

    ``K(m)(x) = int_Omega K(x, y) m(y) dy`` is evaluated at the cell centres as a Riemann sum,
    ``cell_volume * sum_j K(x, y_j) m(y_j)``, with no wrap-around and no truncation. The Gaussian is
    separable, ``K(x, y) = k_x(x1 - y1) k_y(x2 - y2) [k_z(x3 - y3)]``, so the sum is computed either as

    - ``method="matrix"``: ``hx hy * Kx @ M @ Ky^T`` per component (3D: one more product along z), with the
      dense Toeplitz matrices ``Kx[i, j] = exp(-(x_i - x_j)^2 / (2 sigma^2))`` (cost ``O(n^(d+1))``, fast
      BLAS), or
    - ``method="fft"``: a linear convolution by FFT, each axis zero-padded to a fast FFT length
      ``L >= 2n - 1`` (``scipy.fft.next_fast_len``) so the circular convolution equals the linear one
      on the grid (cost ``O(n^d log n)``; the padded spectra of a batch take ``2^d`` times its memory),
    - ``method="auto"``: the matrix form up to ``MATRIX_MAX_CPU`` (CPU) / ``MATRIX_MAX_CUDA`` (CUDA)
      pixels on the longer axis, else the FFT (crossover measured, see ``MATRIX_MAX_CPU``).

    Both are exact to floating-point precision and agree with each other (tests/deform/test_kernel.py).

    Convention:
        vector fields ``(..., 2, nx, ny)`` on ``domain`` (component 0 = x, 1 = y), any batch dims;
        ``sigma`` in physical units (the paper's domain is ``[-16, 16]^2``); the output has the input's
        shape, dtype and device. The operator is L2-self-adjoint and positive definite:
        ``<K f, g>_L2 = <f, K g>_L2``, and for ``v = K m`` the V norm is ``<v, v>_V = <m, K m>_L2``
        (``inner_v``). 3D (a ``domain`` of shape ``(nx, ny, nz)``): vector fields ``(..., 3, nx, ny, nz)``
        (component 2 = z), the same methods with a third factor.

    Example:
        >>> K = GaussianKernel(ImageDomain.paper(64), sigma=6.0)
        >>> m = torch.zeros(21, 2, 64, 64)
        >>> m[:, 0, 32, 32] = 1.0                               # a point momentum along x at each time
        >>> v = K(m)                                            # a Gaussian bump of velocity around it
        >>> v.shape, bool(v[:, 1].eq(0).all())
        (torch.Size([21, 2, 64, 64]), True)
    """

    def __init__(self, domain: ImageDomain, sigma: float, method: str = "auto"):
        if not isinstance(domain, ImageDomain):
            raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
        if method not in ("auto", "fft", "matrix"):
            raise ValueError(f"method must be 'auto', 'fft' or 'matrix', got {method!r}")
        self.domain = domain
        self.sigma = check_positive(sigma, "sigma")
        if self.sigma < SIGMA_MIN:
            raise ValueError(f"sigma must be >= {SIGMA_MIN:.3g} (below, sigma^2 underflows and the kernel is NaN), "
                             f"got {sigma!r}")
        self._two_sigma2 = 2.0 * self.sigma * self.sigma  # a product: inf (a constant kernel) for huge sigma,
        # where sigma ** 2 raises OverflowError
        self.method = method
        self._cache = {}

    def __repr__(self):
        return f"GaussianKernel(domain={self.domain!r}, sigma={self.sigma}, method={self.method!r})"

    def resolved_method(self, device: torch.device) -> str:
        """The method ``"auto"`` picks on ``device`` ("matrix" or "fft")."""
        if self.method != "auto":
            return self.method
        limit = MATRIX_MAX_CUDA if torch.device(device).type == "cuda" else MATRIX_MAX_CPU
        return "matrix" if max(self.domain.shape) <= limit else "fft"

    def _gauss(self, d: torch.Tensor) -> torch.Tensor:
        return torch.exp(-d * d / self._two_sigma2)

    def toeplitz(self, axis: int, dtype=torch.float64, device=None) -> torch.Tensor:
        """The dense matrix ``exp(-(x_i - x_j)^2 / (2 sigma^2))`` on ``axis`` (0 = x, 1 = y, 2 = z)."""
        x = self.domain.axes(torch.float64, device)[axis]
        return self._gauss(x[:, None] - x[None, :]).to(dtype)

    def _matrices(self, dtype, device):
        """``(Kx, ..., K_last^T)``: the matrices of all axes, the last one transposed (it multiplies from the
        right); in 3D ``Kx`` carries the factor ``cell_volume`` (one pass less over the volumes)."""
        key = ("matrix", dtype, device)
        if key not in self._cache:
            d = self.domain.ndim
            first = self.toeplitz(0, torch.float64, device) * (self.domain.cell_volume if d == 3 else 1.0)
            self._cache[key] = (first.to(dtype), *(self.toeplitz(a, dtype, device) for a in range(1, d - 1)),
                                self.toeplitz(d - 1, dtype, device).T.contiguous())
        return self._cache[key]

    def _spectra(self, dtype, device):
        key = ("fft", dtype, device)
        if key not in self._cache:
            lengths, spectra = [], []
            for axis, (n, h) in enumerate(zip(self.domain.shape, self.domain.cell_sides)):
                length = scipy.fft.next_fast_len(2 * n - 1)
                offsets = torch.arange(length, dtype=torch.float64, device=device)
                offsets = torch.where(offsets < n, offsets, offsets - length)  # circular offsets -(L-n)..n-1
                kernel = torch.where(offsets.abs() < n, self._gauss(offsets * h), torch.zeros_like(offsets))
                last = axis == self.domain.ndim - 1
                spectra.append(torch.fft.rfft(kernel) if last else torch.fft.fft(kernel))
                lengths.append(length)
            ctype = torch.complex64 if dtype == torch.float32 else torch.complex128
            spectrum = spectra[0]
            for s in spectra[1:]:  # the outer product of the per-axis spectra
                spectrum = spectrum[..., None] * s
            self._cache[key] = (tuple(lengths), spectrum.to(ctype))
        return self._cache[key]

    def __call__(self, m: torch.Tensor) -> torch.Tensor:
        """``K(m)(x_i) = cell_volume * sum_j exp(-|x_i - x_j|^2 / (2 sigma^2)) m(x_j)`` for ``m (..., d, *shape)``."""
        check_tensor(m, "vector field", (self.domain.ndim, *self.domain.shape))
        return self.apply(m)

    def apply(self, f: torch.Tensor) -> torch.Tensor:
        """The kernel on any tensor ``(..., *shape)`` (no shape check on the component axis, no finiteness check).

        Linear in ``f`` and differentiable by autograd (matrix products / FFTs).
        """
        shape = self.domain.shape
        if self.resolved_method(f.device) == "matrix":
            matrices = self._matrices(f.dtype, f.device)
            if len(shape) == 2:
                out = torch.matmul(torch.matmul(matrices[0], f), matrices[1])
            else:  # z from the right; y: (ny, ny) @ (..., nx, ny, nz) acts on axis -2; x on (..., nx, ny * nz)
                out = torch.matmul(matrices[1], torch.matmul(f, matrices[2]))
                return torch.matmul(matrices[0], out.reshape(*out.shape[:-3], shape[0], -1)).reshape(out.shape)
        else:
            lengths, spectrum = self._spectra(f.dtype, f.device)
            dims = tuple(range(-len(shape), 0))
            out = torch.fft.irfftn(torch.fft.rfftn(f, s=lengths, dim=dims) * spectrum, s=lengths, dim=dims)
            out = out[(Ellipsis, *(slice(0, n) for n in shape))]
        return out * self.domain.cell_volume

    def inner_v(self, m1: torch.Tensor, m2: torch.Tensor) -> torch.Tensor:
        """``<m1, K m2>_L2`` over the last d + 1 dims (batch dims kept): the V inner product of ``K m1`` and ``K m2``."""
        d = self.domain.ndim
        check_tensor(m1, "m1", (d, *self.domain.shape))
        check_same(m1, m2, "m1", "m2")
        return self.domain.cell_volume * (m1 * self(m2)).sum(dim=tuple(range(-d - 1, 0)))

