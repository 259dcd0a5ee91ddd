"""The 2D ray transform ``T`` (parallel or fan beam) as a precomputed sparse system matrix (Joseph's method).

Discretisation: Joseph's method. For every ray the line is marched along its dominant image axis
(y when ``|cos theta| >= |sin theta|``, else x), one step per pixel row (column); at each step the image
is linearly interpolated between the two neighbouring cell centres along the other axis (zero outside the
image), and the step length ``h / |cos theta|`` (or ``h / |sin theta|``) is folded into the weights. This
is exact for the linear interpolant along each row, second-order accurate, gives two non-zeros per step
(fewer than exact pixel-intersection lengths for the same accuracy) and is built with a few vectorised
numpy operations per angle. The fan-beam matrix does the same per ray (source point -> bin centre), the
dominant axis chosen ray by ray.

System matrices are built by a projector registered per geometry type (``register_projector``, as ODL keys
its back-ends): ``ParallelBeamGeometry -> joseph_matrix``, ``FanBeamGeometry -> fan_joseph_matrix``.

The matrix ``A`` (rows ``k * det_count + d``, columns ``i * ny + j``) and its transpose ``A^T`` are kept as
two CSR matrices (float64 master copy on the CPU, converted copies cached per dtype and device), so the
forward and the adjoint are each one sparse-dense product (``torch.mv`` for one image, ``torch.mm`` for a
batch). A separate CSR for ``A^T`` is about as fast as ``A`` itself, while a transposed product over ``A``
is not. 32-bit indices are used when they fit (about 1.5x faster than 64-bit on CPU).
"""
from __future__ import annotations

import copy
import math
import warnings

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn

from .._checks import check_tensor
from ..domain import ImageDomain
from .geometry import FanBeamGeometry, ParallelBeamGeometry, domain_radius
from .algebra import WeightedDataMixin

_PROJECTORS = {}


def register_projector(geometry_type: type, matrix_builder) -> None:
    """Register ``matrix_builder(domain, geometry) -> scipy CSR`` (rows ``k * det_count + d``, columns
    ``i * ny + j``, float64, physical line-integral weights) for geometries of ``geometry_type``.

    The geometry must provide ``shape``, ``data_weight`` and ``resolve(domain)`` (see ``geometry._Geometry``).

    Parameters
    ----------
    geometry_type : type
        The geometry class (its subclasses too, unless they have their own projector).
    matrix_builder : callable
        ``(domain, geometry) -> scipy.sparse CSR`` system matrix.

    Raises
    ------
    TypeError
        ``geometry_type`` is not a class or ``matrix_builder`` not callable.
    """
    if not isinstance(geometry_type, type) or not callable(matrix_builder):
        raise TypeError("register_projector(geometry_type, matrix_builder) needs a class and a callable, got "
                        f"{geometry_type!r}, {matrix_builder!r}")
    _PROJECTORS[geometry_type] = matrix_builder


def _projector_for(geometry):
    for cls in type(geometry).__mro__:
        if cls in _PROJECTORS:
            return _PROJECTORS[cls]
    names = ", ".join(c.__name__ for c in _PROJECTORS)
    raise TypeError(f"geometry must be one of {names} (or a type registered with register_projector), "
                    f"got {type(geometry).__name__}")


def joseph_matrix(domain: ImageDomain, geometry: ParallelBeamGeometry) -> sp.csr_matrix:
    """The Joseph system matrix ``A`` as a scipy CSR matrix (float64, sorted column indices).

    Row ``k * det_count + d`` holds the weights of the line integral ``p(theta_k, s_d)``; column
    ``i * ny + j`` is pixel ``(i, j)``. For a ray marched along y (``|cos theta| >= |sin theta|``) the
    point at height ``y_j`` is ``x = (s_d - y_j sin theta) / cos theta``, weight ``hy / |cos theta|``; along x,
    ``y = (s_d - x_i cos theta) / sin theta``, weight ``hx / |sin theta|``. Entries are generated ray by ray
    (one vectorised block per angle), so the CSR structure needs no global sort.
    """
    nx, ny = domain.shape
    hx, hy = domain.cell_sides
    xc, yc = (a.numpy() for a in domain.axes())
    sd = geometry.det_points.numpy()
    itype = np.int32 if nx * ny < 2**31 - 1 else np.int64
    counts, cols, vals = [], [], []
    for theta in geometry.angles.tolist():
        c, s = math.cos(theta), math.sin(theta)
        along_y = abs(c) >= abs(s)
        if along_y:   # march over rows y_j, interpolate in x
            u = ((sd[:, None] - yc[None, :] * s) / c - xc[0]) / hx
            step, n_march = hy / abs(c), ny
        else:         # march over columns x_i, interpolate in y
            u = ((sd[:, None] - xc[None, :] * c) / s - yc[0]) / hy
            step, n_march = hx / abs(s), nx
        rays = len(sd)
        cnt, col, val = _joseph_entries(u, np.full(rays, step), np.full(rays, along_y), np.full(rays, n_march),
                                        (nx, ny), itype)
        counts.append(cnt)
        cols.append(col)
        vals.append(val)
    return _csr(counts, cols, vals, (geometry.num_angles * geometry.det_count, nx * ny))


def _csr(counts, cols, vals, shape) -> sp.csr_matrix:
    """The system matrix from per-angle blocks of row counts, column indices and values (rays in row order)."""
    indptr = np.concatenate([[0], np.cumsum(np.concatenate(counts))])
    mat = sp.csr_matrix((np.concatenate(vals), np.concatenate(cols), indptr), shape=shape)
    mat.sort_indices()
    return mat


def _joseph_entries(u, step, along_y, n_march, shape, itype):
    """Joseph entries of a block of rays: ``u`` (rays, M) interpolation coordinates in cells along the
    non-marching axis at march positions ``0..M-1``, ``step`` (rays,) length per step, ``along_y`` (rays,)
    marching direction, ``n_march`` (rays,) valid positions. Returns (counts per ray, columns, values)."""
    nx, ny = shape
    n_interp = np.where(along_y, nx, ny)[:, None]
    lower = np.floor(np.clip(u, -2, max(nx, ny) + 1))   # out-of-image points are dropped below
    frac = u - lower
    lo = lower.astype(itype)
    march = np.arange(u.shape[1], dtype=itype)[None, :]
    ay = along_y[:, None]
    base = np.where(ay, lo * ny + march, march * ny + lo)                 # column of the lower neighbour
    col = np.stack([base, base + np.where(ay, ny, 1)], axis=-1)
    w = np.stack([1.0 - frac, frac], axis=-1) * step[:, None, None]
    inside = march < n_march[:, None]
    keep = np.stack([inside & (lo >= 0) & (lo < n_interp),
                     inside & (lo >= -1) & (lo < n_interp - 1) & (frac > 0)], axis=-1)
    return keep.sum(axis=(1, 2)), col[keep], w[keep]


def fan_joseph_matrix(domain: ImageDomain, geometry: FanBeamGeometry) -> sp.csr_matrix:
    """The fan-beam Joseph system matrix (flat detector), layout as ``joseph_matrix``.

    Ray ``(k, d)`` is the line from the source ``S`` to the bin centre ``D = C + u_d e`` (``FanBeamGeometry``),
    direction ``v = D - S``. If ``|v_y| >= |v_x|`` it is marched over rows: at ``y_j`` the point is
    ``x = S_x + (y_j - S_y) v_x / v_y``, weight ``hy |v| / |v_y|``; else over columns (x and y swapped). The
    dominant axis is chosen per ray, so one vectorised block per angle holds both kinds.
    """
    nx, ny = domain.shape
    hx, hy = domain.cell_sides
    xc, yc = (a.numpy() for a in domain.axes())
    ud = geometry.det_points.numpy()
    if geometry.src_radius <= domain_radius(domain):
        raise ValueError(f"src_radius={geometry.src_radius} must exceed the domain radius "
                         f"{domain_radius(domain):g} (the source must lie outside the domain)")
    itype = np.int32 if nx * ny < 2**31 - 1 else np.int64
    m = max(nx, ny)
    t = np.arange(m, dtype=np.float64)
    ys, xs = yc[0] + t * hy, xc[0] + t * hx                               # march positions (padded to m)
    counts, cols, vals = [], [], []
    for beta in geometry.angles.tolist():
        c, s = math.cos(beta), math.sin(beta)
        src = np.array([geometry.src_radius * s, -geometry.src_radius * c])
        vx = -geometry.det_radius * s + ud * c - src[0]
        vy = geometry.det_radius * c + ud * s - src[1]
        along_y = np.abs(vy) >= np.abs(vx)
        length = np.hypot(vx, vy)
        slope_y = np.where(along_y, vx / np.where(along_y, vy, 1.0), 0.0)     # dx/dy on rows
        slope_x = np.where(along_y, 0.0, vy / np.where(along_y, 1.0, vx))     # dy/dx on columns
        u_rows = (src[0] + (ys[None, :] - src[1]) * slope_y[:, None] - xc[0]) / hx
        u_cols = (src[1] + (xs[None, :] - src[0]) * slope_x[:, None] - yc[0]) / hy
        u = np.where(along_y[:, None], u_rows, u_cols)
        step = np.where(along_y, hy * length / np.abs(np.where(along_y, vy, 1.0)),
                        hx * length / np.abs(np.where(along_y, 1.0, vx)))
        cnt, col, val = _joseph_entries(u, step, along_y, np.where(along_y, ny, nx), (nx, ny), itype)
        counts.append(cnt)
        cols.append(col)
        vals.append(val)
    return _csr(counts, cols, vals, (geometry.num_angles * geometry.det_count, nx * ny))


register_projector(ParallelBeamGeometry, joseph_matrix)
register_projector(FanBeamGeometry, fan_joseph_matrix)


#: Elements of spare memory behind the end of every CSR array handed to torch. MKL's CPU kernels behind ``torch.mv``
#: and ``torch.mm`` (AVX-512; torch 2.13.0 and 2.15.0) load 64 bytes at a time and read up to 60 bytes past the end
#: of the column indices: where the array ended 32 bytes before an unmapped page, ``torch.mv`` of a 7240 x 65536
#: float32 matrix crashed the process (segmentation fault). The extra reads land in this spare memory, never used.
SPARE = 16


def _spare(t: torch.Tensor) -> torch.Tensor:
    """``t`` (1D, contiguous) itself where its storage holds ``SPARE`` more elements behind its end, else a copy in
    a buffer that does (the view of its first ``t.numel()`` elements)."""
    if t.untyped_storage().nbytes() >= (t.storage_offset() + t.numel() + SPARE) * t.element_size():
        return t
    buf = t.new_zeros(t.numel() + SPARE)
    buf[:t.numel()] = t
    return buf[:t.numel()]


def _torch_csr(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape) -> torch.Tensor:
    """A torch CSR tensor of these arrays, each with spare memory behind its end (``SPARE``)."""
    with warnings.catch_warnings():   # "Sparse CSR tensor support is in beta state"
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(_spare(crow), _spare(col), _spare(val), shape, check_invariants=False)


class _SystemMatrix:
    """``A`` and ``A^T`` as CSR, float64 on the CPU, with converted copies cached per (dtype, device)."""

    def __init__(self, domain: ImageDomain, geometry):
        mat = _projector_for(geometry)(domain, geometry)
        self.shape = mat.shape
        self.nnz = int(mat.nnz)
        self.index_dtype = torch.int32 if max(self.shape + (self.nnz,)) < 2**31 - 1 else torch.int64
        mat_t = mat.tocsc()   # CSC of A = CSR of A^T (linear-time conversion, sorted indices)
        self.master = tuple(tuple(_spare(torch.from_numpy(a)) for a in (m.indptr, m.indices, m.data))
                            for m in (mat, mat_t))
        self._cache = {}

    def get(self, dtype: torch.dtype, device: torch.device) -> tuple:
        """``(A, A^T)`` as torch CSR tensors of this dtype on this device (float64 CPU shares the master)."""
        key = (dtype, torch.device(device))
        if key not in self._cache:
            self._cache[key] = tuple(
                _torch_csr(crow.to(device, self.index_dtype), col.to(device, self.index_dtype), val.to(device, dtype),
                           shape)
                for (crow, col, val), shape in zip(self.master, (self.shape, self.shape[::-1])))
        return self._cache[key]

    def column_blocks(self, dtype: torch.dtype, device: torch.device, width: int) -> tuple:
        """``A``'s columns (pixels) in blocks of ``width``: ``((start, stop, A[:, start:stop]), ...)`` as CSR,
        cached per (dtype, device, width) (one more copy of the nonzeros), for ``matmul_columns``."""
        key = (dtype, torch.device(device), int(width))
        if key not in self._cache:
            crow, col, val = (t.to(device) for t in self.master[1])   # A^T's rows are A's columns
            blocks = []
            for a in range(0, self.shape[1], width):
                b = min(a + width, self.shape[1])
                lo, hi = int(crow[a]), int(crow[b])
                rows = _torch_csr((crow[a:b + 1] - lo).to(self.index_dtype), col[lo:hi].to(self.index_dtype),
                                  val[lo:hi].to(dtype), (b - a, self.shape[0]))
                block = rows.t().to_sparse_csr()
                blocks.append((a, b, _torch_csr(block.crow_indices(), block.col_indices(), block.values(),
                                                block.shape)))
            self._cache[key] = tuple(blocks)
        return self._cache[key]

    def __deepcopy__(self, memo):
        """Copies share the immutable master arrays and start with an empty cache (sparse CSR tensors cannot be
        deep-copied; the cached copies are rebuilt on first use)."""
        new = copy.copy(self)
        new._cache = {}
        return new

    def __getstate__(self):
        return dict(self.__dict__, _cache={})  # pickling: the cache is rebuilt on first use

    def nbytes(self, dtype: torch.dtype = torch.float64) -> int:
        """Memory of one cached ``(A, A^T)`` pair in bytes."""
        isz = torch.empty(0, dtype=self.index_dtype).element_size()
        vsz = torch.empty(0, dtype=dtype).element_size()
        return 2 * self.nnz * (isz + vsz) + (sum(self.shape) + 2) * isz

    def working_bytes(self, dtype: torch.dtype, device) -> int:
        """What a run in ``dtype`` on ``device`` holds of the matrix: the float64 master (scipy's int32 or int64
        indices), its ``(A, A^T)`` in ``dtype`` (unless float64 on the CPU, which shares the master) and, on a CPU, the
        column blocks of ``A`` (``column_blocks``, slab-wise projections)."""
        master = sum(t.numel() * t.element_size() for m in self.master for t in m)
        cpu = torch.device(device).type == "cpu"
        pair = 0 if (cpu and dtype == torch.float64) else self.nbytes(dtype)
        return master + pair + (self.nbytes(dtype) // 2 if cpu else 0)


#: On the CPU a sparse-dense product reads a row of the dense operand (``B`` values) per nonzero; when the operand
#: outgrows the cache (``4 x CPU_BLOCK_BYTES``) the batch is taken in blocks of about ``CPU_BLOCK_BYTES``: the same
#: sums in the same order (bit for bit), the matrix streamed once per block. A 256^3 tilt series (61 tilts):
#: forward 1.17 s -> 0.37 s in float32, 1.81 s -> 0.90 s in float64 (one thread, 32 MiB L3).
CPU_BLOCK_BYTES = 4 * 2 ** 20


def _matmul(mat: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``x @ mat^T`` for a CSR ``mat`` and a dense batch ``x`` of shape ``(B, n)`` (in blocks of the batch on the
    CPU when ``x`` is large: ``CPU_BLOCK_BYTES``)."""
    if x.shape[0] == 1:
        return torch.mv(mat, x[0]).unsqueeze(0)
    row = x.shape[1] * x.element_size()
    if x.device.type != "cpu" or x.shape[0] * row <= 4 * CPU_BLOCK_BYTES:
        return torch.mm(mat, x.t()).t()
    block = max(1, CPU_BLOCK_BYTES // row)
    return torch.cat([torch.mm(mat, x[i:i + block].t()).t() for i in range(0, x.shape[0], block)])


def matmul_columns(blocks: tuple, x: torch.Tensor) -> torch.Tensor:
    """``x @ A^T`` for ``x (B, n)`` from ``A``'s column blocks (``_SystemMatrix.column_blocks``): the sum over
    blocks of ``x[:, block] @ A[:, block]^T``, so that the dense rows a block reads stay in the cache (the same
    sums as ``_matmul`` in another order). A 1024 x 256 slice, 61 tilts, 16 slices at a time, float32, one thread:
    26 -> 7.2 ms a slice with blocks of 32768 pixels (the 16 MiB operand read per nonzero missed the cache)."""
    out = None
    for a, b, mat in blocks:
        part = torch.mm(mat, x[:, a:b].t())
        out = part if out is None else out.add_(part)
    return out.t()


class _Project(torch.autograd.Function):
    """``x -> x A^T`` on flattened images ``(B, nx*ny)``; backward is the exact transpose."""

    @staticmethod
    def forward(x, system):
        return _matmul(system.get(x.dtype, x.device)[0], x)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.system = inputs[1]

    @staticmethod
    def backward(ctx, grad):
        return _Backproject.apply(grad, ctx.system), None


class _Backproject(torch.autograd.Function):
    """``y -> y A`` on flattened data ``(B, num_angles*det_count)``; backward is the forward projection."""

    @staticmethod
    def forward(y, system):
        return _matmul(system.get(y.dtype, y.device)[1], y)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.system = inputs[1]

    @staticmethod
    def backward(ctx, grad):
        return _Project.apply(grad, ctx.system), None


class RayTransform(WeightedDataMixin, nn.Module):
    """Ray transform ``T: L2(domain) -> L2(angles x detector)`` (a ``LinearOperator``; deepinv-style names).

    Parallel beam: ``(T f)(theta, s) = integral over t of f(s w + t w_perp)``, ``w = (cos theta, sin theta)``,
    ``w_perp = (-sin theta, cos theta)``; fan beam: integrals along the lines from the source to the bin
    centres (``FanBeamGeometry``). The forward operator of the paper's indirect registration problem
    (``eq:OptimV``, data ``g = T(W(nu, I)) + noise``), discretised with Joseph's method (module docstring);
    the matrix comes from the projector registered for the geometry's type (``register_projector``).

    Parameters
    ----------
    domain : ImageDomain
        The 2D image domain.
    geometry : ParallelBeamGeometry or FanBeamGeometry
        The acquisition geometry (or one of a type registered with ``register_projector``).

    Raises
    ------
    TypeError
        ``domain`` is no ``ImageDomain``, or a geometry type without a projector.
    ValueError
        A 3D domain (use ``TiltSeriesTransform``), or a fan-beam source inside the domain.

    Notes
    -----
    - Input images ``(..., nx, ny)`` on ``domain`` (axis 0 = x, axis 1 = y, physical units), any
      leading batch dims, float32 or float64, on any device (the operator follows the input).
    - Output data ``(..., num_angles, det_count)``: line integrals in physical length units
      (a unit-valued disk of radius r gives ``2 r`` through its centre).
    - Image inner product ``cell_volume * sum``; data inner product ``data_weight * sum`` with
      ``data_weight = geometry.data_weight`` (as ODL).
    - ``transpose`` is the exact matrix transpose ``A^T``; the L2 adjoint for the weighted inner
      products is ``T^* = (data_weight / cell_volume) * A^T`` (``adjoint``), and
      ``T^* q (x) ~ sum_k angle_cell * q(theta_k, x . w_k)``, the discrete backprojection.
    - Gradients: the forward is an autograd Function whose backward is ``A^T`` and vice versa, so the
      backward of ``A`` is exact and twice differentiable.
    - A geometry without detector extent (``det_min = det_max = None``) is fitted to the domain
      (``geometry.resolve(domain)``); ``self.geometry`` is the resolved one.

    Examples
    --------
    >>> dom = ImageDomain.paper(64)
    >>> T = RayTransform(dom, ParallelBeamGeometry.paper(10, 92))
    >>> T(dom.zeros(3)).shape
    torch.Size([3, 10, 92])
    """

    def __init__(self, domain: ImageDomain, geometry):
        super().__init__()
        if not isinstance(domain, ImageDomain):
            raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
        if domain.ndim != 2:
            raise ValueError(f"RayTransform needs a 2D domain, got shape {domain.shape}; for a 3D volume use "
                             "TiltSeriesTransform (indreg.forward.tilt_series)")
        _projector_for(geometry)
        geometry = geometry.resolve(domain)
        self.domain = domain
        self.geometry = geometry
        self.system = _SystemMatrix(domain, geometry)

    def on_domain(self, domain: ImageDomain) -> "RayTransform":
        """The same geometry (detector extent included) on another grid of the plane, e.g. a coarser one for
        coarse-to-fine solvers; the data space is unchanged."""
        return RayTransform(domain, self.geometry)

    def _check_dtype(self, x: torch.Tensor, name: str) -> None:
        if x.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{name} must be float32 or float64, got {x.dtype}")

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        """``T f``: images ``(..., nx, ny)`` -> data ``(..., num_angles, det_count)``."""
        f = self.domain.check_image(f, "image")
        self._check_dtype(f, "image")
        batch = f.shape[:-2]
        out = _Project.apply(f.reshape(-1, f.shape[-2] * f.shape[-1]), self.system)
        return out.reshape(*batch, *self.range_shape)

    def A(self, f: torch.Tensor) -> torch.Tensor:
        """The forward operator ``T f`` (same as calling the module)."""
        return self(f)

    def transpose(self, y: torch.Tensor) -> torch.Tensor:
        """Exact matrix transpose ``A^T y``: data ``(..., num_angles, det_count)`` -> images ``(..., nx, ny)``."""
        y = check_tensor(y, "data", self.range_shape)
        self._check_dtype(y, "data")
        batch = y.shape[:-2]
        out = _Backproject.apply(y.reshape(-1, y.shape[-2] * y.shape[-1]), self.system)
        return out.reshape(*batch, *self.domain.shape)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """L2 adjoint ``T^* y = (data_weight / cell_volume) * A^T y`` (backprojection)."""
        return self.adjoint_scale * self.transpose(y)

    def A_adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """deepinv's ``A_adjoint``: the adjoint for plain (unweighted) sums, i.e. the transpose ``A^T y``.
        For the L2 adjoint of the weighted inner products use ``adjoint``; to hand the operator to deepinv use
        ``indreg.forward.deepinv.as_physics``."""
        return self.transpose(y)

    def extra_repr(self) -> str:
        return f"domain={self.domain}, geometry={self.geometry}, nnz={self.system.nnz}"
