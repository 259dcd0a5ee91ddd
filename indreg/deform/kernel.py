"""The Gaussian reproducing kernel of the velocity space V and its application to vector fields."""
from __future__ import annotations

import math
import numbers
import sys

import torch

from .._checks import check_positive, check_same, check_tensor
from ..domain import ImageDomain


def fast_length(n: int) -> int:
    """The least length ``>= n`` whose prime factors are among 2, 3, 5, 7 and 11, a fast length of an FFT (as
    ``scipy.fft.next_fast_len(n)``, without importing ``scipy.fft``: 0.1 s of a start-up)."""
    length = n
    while True:
        rest = length
        for p in (2, 3, 5, 7, 11):
            while rest % p == 0:
                rest //= p
        if rest == 1:
            return length
        length += 1


#: The methods; ``"auto"`` picks the cheapest exact one by :data:`COST_NS` (see :meth:`GaussianKernel.cost`).
METHODS = ("auto", "matrix", "lowrank", "fft")
#: ns per unit of :meth:`GaussianKernel.cost` (a multiply-add of the matrix products; for the FFT a point x
#: log2 of its padded length), measured on this 2-core CPU (float32, (11, d) fields, 1 thread, best of 5,
#: methods interleaved; ``scripts/bench_kernel.py``). Per unit, matrix 0.06-0.23 (BLAS with inner dimension n),
#: lowrank 0.09-0.33 (inner dimension r ~ 22: closer to memory bound, the more so the larger the field), FFT
#: 0.6-6.7, over 32^2..512^2 and 32^3..96^3 with sigma 0.25..3 (r 22..231). With these constants ``"auto"``
#: picked the faster of matrix / lowrank in 13 of 14 of those cases (the miss: 128^2, sigma 1, r = 60, matrix
#: 16 ms vs lowrank 12 ms) and never the FFT below ~2000 cells per axis (the FFT was 4-70x slower than the
#: faster of the two everywhere measured). Not measured on CUDA (the same constants are used).
COST_NS = {"matrix": 0.13, "lowrank": 0.25, "fft": 3.5}
#: The smallest accepted ``sigma``: ``sqrt`` of the smallest normal float64. Below it ``sigma^2`` underflows and
#: ``exp(-d^2 / (2 sigma^2))`` is NaN at ``d = 0``; a ``sigma`` far below a cell side but above this bound gives
#: the (representable) discrete delta ``K m = cell_volume * m``.
SIGMA_MIN = math.sqrt(sys.float_info.min)


def _along(t: torch.Tensor, M: torch.Tensor, dim: int) -> torch.Tensor:
    """``sum_j M[i, j] t[..., j, ...]`` over the axis ``dim`` (negative) of ``t``: one (batched) matrix product."""
    if dim == -1:
        return torch.matmul(t, M.T)
    shape = t.shape
    out = torch.matmul(M, t.reshape(-1, shape[dim], math.prod(shape[dim + 1:])))
    return out.reshape(*shape[:dim], M.shape[0], *shape[dim + 1:])


class GaussianKernel:
    """Gaussian kernel ``K(x, y) = exp(-|x - y|^2 / (2 sigma^2)) Id`` of the RKHS V (eq:KernelEq, with the square).

    ``K(m)(x) = int_Omega K(x, y) m(y) dy`` is evaluated at the cell centres as a Riemann sum,
    ``cell_volume * sum_j K(x, y_j) m(y_j)``, with no wrap-around and no truncation. The Gaussian is
    separable, ``K(x, y) = k_x(x1 - y1) k_y(x2 - y2) [k_z(x3 - y3)]``: the sum is the product of one dense
    Toeplitz matrix ``Kx[i, j] = exp(-(x_i - x_j)^2 / (2 sigma^2))`` per axis (``toeplitz``), computed as

    - ``method="matrix"``: the dense matrices, one product per axis (``O(n^(d+1))``, fast BLAS);
    - ``method="lowrank"``: each matrix by its eigendecomposition ``Kx = V diag(lambda) V^T`` (float64, once),
      keeping the ``r`` eigenpairs with ``lambda_k > eps(dtype) lambda_max`` (``rank``): the field is projected
      onto the tensor basis axis by axis (``n -> r``, last axis first), scaled by the outer product of the
      eigenvalues and expanded back (first axis first). The eigenvalues of a Gaussian decay like
      ``exp(-(pi sigma k / extent)^2 / 2)``, so ``r ~ extent / sigma * sqrt(2 ln(1 / eps)) / pi`` does not
      grow with the resolution (22 in float32, 36 in float64 for sigma 3 on [-16, 16]) and the cost is
      ``~ 2 r n^d`` (``O(n^d)``) instead of ``d n^(d+1)``;
    - ``method="fft"``: a linear convolution by FFT, each axis zero-padded to a fast FFT length
      ``L >= 2n - 1`` (:func:`fast_length`) so the circular convolution equals the linear one
      on the grid (cost ``O(n^d log n)``; the padded spectra of a batch take ``2^d`` times its memory);
    - ``method="auto"`` (default): the cheapest by ``cost`` (multiply-adds per field times the measured
      ``COST_NS`` of each method): the dense form for small grids or sigma near a cell (``r`` close to ``n``),
      the low-rank form from ~64 cells per axis at sigma of a few cells, the FFT only beyond ~2000 cells.

    Measured (``scripts/bench_kernel.py``, (11, d) float32 fields, sigma 3 on cubic cells of ``[-16, 16]``,
    1 thread on the shared 2-core CPU, median ms, matrix -> lowrank): 64^2 0.7 -> 0.8, 256^2 60 -> 41,
    64^3 712 -> 273, 128^3 1949 -> 525, 256 x 256 x 96 ~5700 -> 1434, 256^3 ~22000 -> 3700-5300 (the last
    two: the dense form timed on one step x 11). At 256^3 the low-rank form is bound by memory traffic (2.2 GB
    in, 2.2 GB out, the output's fresh pages); the zero-padded FFT is 5-50x slower than either.

    ``"matrix"`` and ``"fft"`` are exact to rounding; ``"lowrank"`` drops only eigenpairs below
    ``eps(dtype)`` relative to the largest one, so they agree with ``"matrix"`` to the dense form's own
    rounding level (float32: max relative difference ~6e-7, float64 ~1e-14; tests/deform/test_kernel.py).

    Parameters
    ----------
    domain : ImageDomain
        The grid of the fields (2D or 3D).
    sigma : float
        The kernel's width (physical units, > 0, at least ``SIGMA_MIN``).
    method : {"auto", "matrix", "lowrank", "fft"}
        How the sum is computed (above).

    Raises
    ------
    TypeError
        ``domain`` is no ``ImageDomain``, or ``sigma`` is no number (a string, a bool).
    ValueError
        An unknown ``method``, ``sigma`` not positive and finite or below ``SIGMA_MIN``.

    Notes
    -----
    vector fields ``(..., 2, nx, ny)`` on ``domain`` (component 0 = x, 1 = y), any batch dims;
    ``sigma`` in physical units (the paper's domain is ``[-16, 16]^2``); the output has the input's
    shape, dtype and device. The operator is L2-self-adjoint and positive definite:
    ``<K f, g>_L2 = <f, K g>_L2``, and for ``v = K m`` the V norm is ``<v, v>_V = <m, K m>_L2``
    (``inner_v``). 3D (a ``domain`` of shape ``(nx, ny, nz)``): vector fields ``(..., 3, nx, ny, nz)``
    (component 2 = z), the same methods with a third factor.

    Examples
    --------
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
        if method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}")
        if isinstance(sigma, bool) or not isinstance(sigma, (numbers.Real, torch.Tensor)):  # not '6', not True
            raise TypeError(f"sigma must be a positive number, got {sigma!r}")
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

    def resolved_method(self, device: torch.device, dtype=torch.float32) -> str:
        """The method ``"auto"`` picks for ``dtype`` on ``device``: the smallest ``cost`` (CPU measurements)."""
        if self.method != "auto":
            return self.method
        key = ("auto", dtype)  # the cost model is the same on every device (measured on the CPU)
        if key not in self._cache:
            self._cache[key] = min(METHODS[1:], key=lambda method: self.cost(method, dtype))
        return self._cache[key]

    def cost(self, method: str, dtype=torch.float32) -> float:
        """Estimated ns per field of ``method``: its multiply-adds (FFT: points x log2 length) x ``COST_NS``.

        matrix ``N sum_a n_a``; lowrank ``2 sum_a`` (the tensor size when axis a is projected, ``... x n_a``)
        ``x r_a``; fft ``P sum_a log2 L_a`` with ``P = prod_a L_a``
        (``N = prod_a n_a``).
        """
        shape, d = self.domain.shape, self.domain.ndim
        if method == "matrix":
            units = math.prod(shape) * sum(shape)
        elif method == "lowrank":
            size, units = math.prod(shape), 0
            for axis in reversed(range(d)):
                size = size // shape[axis] * self.rank(axis, dtype)
                units += 2 * size * shape[axis]
        else:
            lengths = [fast_length(2 * n - 1) for n in shape]
            units = math.prod(lengths) * sum(math.log2(n) for n in lengths)
        return COST_NS[method] * units

    def _gauss(self, d: torch.Tensor) -> torch.Tensor:
        return torch.exp(-d * d / self._two_sigma2)

    def toeplitz(self, axis: int, dtype=torch.float64, device=None) -> torch.Tensor:
        """The dense matrix ``exp(-(x_i - x_j)^2 / (2 sigma^2))`` on ``axis`` (0 = x, 1 = y, 2 = z)."""
        x = self.domain.axes(torch.float64, device)[axis]
        return self._gauss(x[:, None] - x[None, :]).to(dtype)

    def eigenpairs(self, axis: int) -> tuple:
        """``(lambda, V)`` with ``toeplitz(axis) = V diag(lambda) V^T``, float64 on the CPU, ``lambda`` descending."""
        key = ("eigh", axis)
        if key not in self._cache:
            lam, V = torch.linalg.eigh(self.toeplitz(axis))
            self._cache[key] = (lam.flip(0), V.flip(1))
        return self._cache[key]

    def rank(self, axis: int, dtype=torch.float32) -> int:
        """The eigenpairs of ``toeplitz(axis)`` that ``"lowrank"`` keeps for ``dtype``: ``lambda_k > eps lambda_max``."""
        lam = self.eigenpairs(axis)[0]
        return max(1, int((lam > torch.finfo(dtype).eps * lam[0]).sum()))

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

    def _lowrank_factors(self, dtype, device):
        """``(V_x, ...), scale``: the kept eigenvectors ``(n_a, r_a)`` per axis and ``cell_volume`` times the outer
        product of the kept eigenvalues ``(r_x, r_y[, r_z])``."""
        key = ("lowrank", dtype, device)
        if key not in self._cache:
            bases, scale = [], torch.tensor(self.domain.cell_volume, dtype=torch.float64)
            for axis in range(self.domain.ndim):
                lam, V = self.eigenpairs(axis)
                r = self.rank(axis, dtype)
                bases.append(V[:, :r].to(dtype=dtype, device=device).contiguous())
                scale = scale[..., None] * lam[:r]
            self._cache[key] = (tuple(bases), scale.to(dtype=dtype, device=device))
        return self._cache[key]

    def _spectra(self, dtype, device):
        key = ("fft", dtype, device)
        if key not in self._cache:
            lengths, spectra = [], []
            for axis, (n, h) in enumerate(zip(self.domain.shape, self.domain.cell_sides)):
                length = fast_length(2 * n - 1)
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
        """The kernel on any tensor ``(..., *shape)`` (no check of the component axis, dtype or finiteness).

        Linear in ``f`` and differentiable by autograd (matrix products / FFTs).
        """
        shape = self.domain.shape
        if not isinstance(f, torch.Tensor):
            raise TypeError(f"f must be a torch.Tensor, got {type(f).__name__}")
        if tuple(f.shape[max(f.dim() - len(shape), 0):]) != shape:
            raise ValueError(f"f must have shape (..., {', '.join(map(str, shape))}), got {tuple(f.shape)}")
        method = self.resolved_method(f.device, f.dtype)
        if method == "lowrank":
            return self._apply_lowrank(f)
        if method == "matrix":
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

    def _apply_lowrank(self, f: torch.Tensor) -> torch.Tensor:
        """``V diag(lambda) V^T`` per axis: project ``n_a -> r_a`` (last axis first: one large product on the
        contiguous axis), scale, expand ``r_a -> n_a`` (first axis first, the last product writes the output)."""
        bases, scale = self._lowrank_factors(f.dtype, f.device)
        d = self.domain.ndim
        t = f
        for axis in reversed(range(d)):
            t = _along(t, bases[axis].T, axis - d)
        t = t * scale
        for axis in range(d):
            t = _along(t, bases[axis], axis - d)
        return t

    def inner_v(self, m1: torch.Tensor, m2: torch.Tensor) -> torch.Tensor:
        """``<m1, K m2>_L2`` over the last d + 1 dims (batch dims kept): the V inner product of ``K m1`` and ``K m2``."""
        d = self.domain.ndim
        check_tensor(m1, "m1", (d, *self.domain.shape))
        check_same(m1, m2, "m1", "m2")
        return self.domain.cell_volume * (m1 * self(m2)).sum(dim=tuple(range(-d - 1, 0)))
