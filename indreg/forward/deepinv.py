"""deepinv interoperability: indreg operators as deepinv physics, deepinv physics as indreg operators.

``as_physics(T)`` hands an indreg linear operator (``RayTransform`` or any operator with ``domain``,
``range_shape``, ``__call__``, ``adjoint``, ``inner_data``) to deepinv's solvers, trainers and tests;
``as_operator(physics, domain)`` turns a deepinv ``LinearPhysics`` (``Tomography``, ``Blur``, ...) into an
indreg operator that ``IndirectRegistration`` accepts. deepinv is imported only when one of them is called
(install it with ``pip install "indreg[deepinv]"``).

Inner products. indreg's are weighted: images ``<f, g>_X = cell_volume * sum f g``, data
``<y1, y2>_Y = sum w y1 y2`` (``inner_data``; ``w = data_weight``, a constant for ``RayTransform``).
deepinv's are the plain Euclidean sums over all entries: its ``adjointness_test``, the gradient
``A^T (A x - y)`` of its L2 data fidelity, its least-squares solvers (``A_dagger``, ``prox_l2``) and autograd
all assume them, so deepinv's ``A_adjoint`` is the matrix transpose ``A^T``. With ``W_X = cell_volume * Id``
and ``W_Y = diag(w)`` the two adjoints are related by

    T^* = W_X^{-1} A^T W_Y      i.e.      A^T y = cell_volume * T^*(y / w),   T^* y = (w / cell_volume) * A^T y.

Shapes. deepinv images are ``(B, C, H, W)``; indreg images ``(..., nx, ny)``, so ``H`` is indreg's x axis
and ``W`` its y axis (no transposition either way). indreg operators act on any leading dims, so in
``as_physics`` every channel is projected independently: ``(B, C, nx, ny) -> (B, C, *range_shape)``.
``as_operator`` adds a channel dim of 1 before calling the physics and drops it afterwards.
"""
from __future__ import annotations

import copy
import math

import torch
from torch import nn

from .._checks import check_positive, check_tensor
from ..domain import ImageDomain
from .algebra import OperatorAlgebra
from .operator import check_data_pair

_INSTALL_HINT = 'deepinv is not installed; install the optional extra with: pip install "indreg[deepinv]"'
_PROTOCOL = ("domain", "range_shape", "adjoint", "inner_data")
_PHYSICS_CLASS = None


def _import_deepinv():
    """``import deepinv``, or an ImportError that says how to install it."""
    try:
        import deepinv
    except ImportError as err:
        raise ImportError(_INSTALL_HINT) from err
    return deepinv


def _physics_class():
    """``IndregPhysics``, a ``deepinv.physics.LinearPhysics`` subclass built on first use (deepinv is optional)."""
    global _PHYSICS_CLASS
    deepinv = _import_deepinv()
    if _PHYSICS_CLASS is None:
        class IndregPhysics(deepinv.physics.LinearPhysics):
            """An indreg linear operator ``T`` as deepinv physics: ``A = T``, ``A_adjoint = A^T`` (Euclidean).

            Notes
            -----
            - ``A``: images ``(B, C, nx, ny)`` (``H`` = x, ``W`` = y) -> measurements
              ``(B, C, *range_shape)``, channels projected independently; any leading dims work.
            - ``A_adjoint`` is the transpose for deepinv's plain sums, ``A^T y = cell_volume * T^*(y / w)``
              with ``T^*`` indreg's L2 adjoint and ``w`` the data weight of ``T.inner_data`` (module
              docstring). For ``RayTransform`` this is exactly ``T.transpose``.
            - Noise and sensor models, solver settings: deepinv's ``LinearPhysics`` keyword arguments.
            - ``clone()`` / ``copy.deepcopy`` copy the deepinv state and share the indreg operator.
            """

            def __init__(self, operator, data_weight, **kwargs):
                super().__init__(img_size=(1, *operator.domain.shape), **kwargs)
                self.operator = operator
                self.cell_volume = operator.domain.cell_volume
                self.data_weight = data_weight

            def A(self, x, **kwargs):
                """``T x``: ``(B, C, nx, ny) -> (B, C, *range_shape)``."""
                return self.operator(x)

            def A_adjoint(self, y, **kwargs):
                """``A^T y = cell_volume * T^*(y / w)``: the adjoint for deepinv's Euclidean inner products."""
                w = self.data_weight
                w = w.to(y.dtype).to(y.device) if isinstance(w, torch.Tensor) else w
                return self.cell_volume * self.operator.adjoint(y / w)

            def __deepcopy__(self, memo):
                """Copies (deepinv's ``clone``) share the indreg operator: it is immutable, and a used
                ``RayTransform`` holds cached sparse CSR tensors that ``copy.deepcopy`` cannot copy."""
                memo[id(self.operator)] = self.operator
                new = type(self).__new__(type(self))
                memo[id(self)] = new
                new.__dict__.update(copy.deepcopy(self.__dict__, memo))
                return new

        IndregPhysics.__module__, IndregPhysics.__qualname__ = __name__, "IndregPhysics"
        _PHYSICS_CLASS = IndregPhysics
    return _PHYSICS_CLASS


def __getattr__(name):
    """``IndregPhysics`` on demand (it needs deepinv), so that it can be named and checked with isinstance."""
    if name == "IndregPhysics":
        return _physics_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _diagonal_data_weight(operator):
    """The weights ``w`` of ``operator.inner_data(y1, y2) = sum w y1 y2``: a float if constant, else a tensor.

    ``w`` is the gradient of ``y -> inner_data(y, 1)``; a random pair then checks that ``inner_data`` is
    really this diagonal form (a non-diagonal weighting has no elementwise ``y / w``).
    """
    shape = tuple(operator.range_shape)
    y = torch.zeros(shape, dtype=torch.float64, requires_grad=True)
    (w,) = torch.autograd.grad(operator.inner_data(y, torch.ones(shape, dtype=torch.float64)), y)
    if not bool((w > 0).all()):
        raise ValueError("operator.inner_data must be a positively weighted sum, found weights <= 0")
    gen = torch.Generator().manual_seed(0)
    y1, y2 = (torch.randn(shape, generator=gen, dtype=torch.float64) for _ in range(2))
    expected, got = (w * y1 * y2).sum(), operator.inner_data(y1, y2)
    scale = math.sqrt(float((w * y1 * y1).sum() * (w * y2 * y2).sum()))
    if not math.isclose(float(got), float(expected), rel_tol=1e-10, abs_tol=1e-10 * scale):
        raise ValueError("operator.inner_data must be a weighted sum sum(w * y1 * y2) over the data axes; "
                         "as_physics cannot convert a non-diagonal data inner product")
    return float(w.flatten()[0]) if bool((w == w.flatten()[0]).all()) else w


def as_physics(operator, **kwargs):
    """deepinv ``LinearPhysics`` whose ``A`` is the indreg operator ``T`` and ``A_adjoint`` its transpose.

    Use it to run deepinv's solvers (``A_dagger``, ``prox_l2``, ``deepinv.optim``), its ``adjointness_test``
    and its trainers on indreg's projector.

    Parameters
    ----------
    operator : LinearOperator
        An indreg linear operator (``indreg.RayTransform`` or any object with ``domain``, ``range_shape``,
        ``__call__``, ``adjoint`` (L2 adjoint) and ``inner_data`` (a positively weighted sum)).
    **kwargs
        Passed to ``deepinv.physics.LinearPhysics`` (``noise_model``, ``max_iter``, ``tol``, ...).

    Returns
    -------
    IndregPhysics
        A ``deepinv.physics.LinearPhysics`` with ``A = T`` and ``A_adjoint = A^T``.

    Raises
    ------
    ImportError
        deepinv is not installed (the message says how).
    TypeError
        ``operator`` is no indreg linear operator.
    ValueError
        A data inner product that is not a positively weighted sum over the data entries.

    Notes
    -----
    - Images ``(B, C, nx, ny)`` (deepinv's ``H`` = indreg's x axis, ``W`` = y), measurements
      ``(B, C, *range_shape)``; each channel is projected independently.
    - ``A_adjoint`` is the adjoint for deepinv's plain Euclidean inner products, i.e. the matrix transpose
      ``A^T y = cell_volume * T^*(y / w)`` (``w`` the data weight of ``inner_data``), not indreg's weighted
      L2 adjoint ``T^*``: deepinv's adjointness test, data-fidelity gradients, least-squares solvers and
      autograd all use unweighted sums. For ``RayTransform``, ``A_adjoint == T.transpose``.

    Examples
    --------
    >>> import torch
    >>> from indreg import ImageDomain, ParallelBeamGeometry, RayTransform
    >>> phys = as_physics(RayTransform(ImageDomain.paper(64), ParallelBeamGeometry.paper(10, 92)))
    >>> bool(phys.adjointness_test(img_size=(1, 64, 64), dtype=torch.float64) < 1e-12)
    True
    """
    cls = _physics_class()
    missing = [name for name in _PROTOCOL if not hasattr(operator, name)]
    if missing or not callable(operator):
        raise TypeError(f"operator must be an indreg linear operator (callable, with {', '.join(_PROTOCOL)}); "
                        f"{type(operator).__name__} lacks {', '.join(missing) or '__call__'}")
    if not isinstance(operator.domain, ImageDomain):
        raise TypeError(f"operator.domain must be an ImageDomain, got {type(operator.domain).__name__}")
    return cls(operator, _diagonal_data_weight(operator), **kwargs)


def _probe(physics, domain: ImageDomain):
    """Measurement shape ``(C, *rest)`` of one single-channel image, and the float dtypes the physics accepts."""
    holder = next(iter(physics.buffers()), None)
    device = holder.device if holder is not None else torch.device("cpu")
    shapes, errors = {}, []
    for dtype in (torch.float32, torch.float64):
        try:
            y = physics.A(torch.zeros(1, 1, *domain.shape, dtype=dtype, device=device))
        except Exception as err:   # deepinv's own error, reported below if no dtype works
            errors.append(f"{type(err).__name__}: {err}")
            continue
        if not isinstance(y, torch.Tensor):
            raise TypeError(f"physics must return a tensor, {type(physics).__name__} returned {type(y).__name__} "
                            "(stacked physics are not supported)")
        if y.is_complex():
            raise TypeError(f"physics {type(physics).__name__} returns complex measurements; "
                            "as_operator supports real-valued physics only")
        shapes[dtype] = tuple(y.shape[1:])
    if not shapes:
        raise ValueError(f"physics {type(physics).__name__} cannot be applied to a real single-channel image of "
                         f"shape (1, 1, {', '.join(map(str, domain.shape))}) for domain {domain}: {errors[0]}")
    shape = next(iter(shapes.values()))
    if len(shape) < 2 or shape[0] != 1:
        raise ValueError(f"physics {type(physics).__name__} maps a single-channel image to measurements of "
                         f"shape (1, {', '.join(map(str, shape))}); as_operator needs a single channel (1, ...)")
    return shape[1:], tuple(shapes)


class PhysicsOperator(OperatorAlgebra, nn.Module):
    """A deepinv ``LinearPhysics`` ``A`` as an indreg linear operator ``T`` on ``domain`` (made by
    :func:`as_operator`, which checks and infers the arguments).

    Parameters
    ----------
    physics : deepinv.physics.LinearPhysics
        ``A``.
    domain : ImageDomain
        The images' domain.
    range_shape : tuple of int
        The data shape (deepinv's measurement without batch and channel dims).
    dtypes : tuple of torch.dtype
        The float dtypes the physics accepts.
    data_weight : float
        Weight of the data inner product.

    Notes
    -----
    - Input images ``(..., nx, ny)`` (axis 0 = x = deepinv's ``H``), any leading batch dims, in a dtype
      the physics accepts (``dtypes``) and on its device; a channel dim of 1 is added for deepinv.
    - Output data ``(..., *range_shape)`` (deepinv's measurement without its channel dim; for
      ``deepinv.physics.Tomography`` that is ``(det_count, num_angles)``).
    - Image inner product ``cell_volume * sum``; data inner product ``data_weight * sum`` (``inner_data``).
    - ``transpose`` is deepinv's ``A_adjoint`` (Euclidean); the L2 adjoint for the weighted inner products
      is ``T^* = (data_weight / cell_volume) * A^T`` (``adjoint``).
    - Gradients are deepinv's (autograd through ``physics.A``).
    - Arithmetic and checks from ``OperatorAlgebra`` (``T * B``, ``c * T``, ``adjointness_test``, ...).
    """

    def __init__(self, physics, domain: ImageDomain, range_shape: tuple, dtypes: tuple, data_weight: float):
        super().__init__()
        self.physics = physics
        self.domain = domain
        self.range_shape = range_shape
        self.dtypes = dtypes
        self.data_weight = data_weight

    @property
    def adjoint_scale(self) -> float:
        """``data_weight / cell_volume``: the factor between ``adjoint`` and ``transpose``."""
        return self.data_weight / self.domain.cell_volume

    def _check(self, x: torch.Tensor, name: str) -> None:
        if x.dtype not in self.dtypes:
            raise TypeError(f"{name} has dtype {x.dtype} but the physics accepts only "
                            f"{', '.join(map(str, self.dtypes))}")
        holder = next(iter(self.physics.buffers()), None)
        if holder is not None and holder.device != x.device:
            raise ValueError(f"{name} is on {x.device} but the physics is on {holder.device}; they must match")

    def _apply(self, fn, x: torch.Tensor, in_shape: tuple, out_shape: tuple) -> torch.Tensor:
        """``fn`` on ``x (..., *in_shape)`` as deepinv's ``(B, 1, *in_shape)``; returns ``(..., *out_shape)``."""
        batch = x.shape[:x.dim() - len(in_shape)]
        out = fn(x.reshape(-1, 1, *in_shape))
        if tuple(out.shape[1:]) != (1, *out_shape):
            raise ValueError(f"physics returned shape {tuple(out.shape)}, expected (B, 1, "
                             f"{', '.join(map(str, out_shape))})")
        return out.reshape(*batch, *out_shape)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        """``T f = A f``: images ``(..., nx, ny)`` -> data ``(..., *range_shape)``."""
        f = self.domain.check_image(f, "image")
        self._check(f, "image")
        return self._apply(self.physics.A, f, self.domain.shape, self.range_shape)

    def transpose(self, y: torch.Tensor) -> torch.Tensor:
        """deepinv's ``A_adjoint`` (Euclidean transpose): data ``(..., *range_shape)`` -> images ``(..., nx, ny)``."""
        y = check_tensor(y, "data", self.range_shape)
        self._check(y, "data")
        return self._apply(self.physics.A_adjoint, y, self.range_shape, self.domain.shape)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """L2 adjoint ``T^* y = (data_weight / cell_volume) * A^T y``."""
        return self.adjoint_scale * self.transpose(y)

    def inner_data(self, y1: torch.Tensor, y2: torch.Tensor) -> torch.Tensor:
        """Weighted data inner product ``data_weight * sum(y1 * y2)`` over the data axes; batch dims kept."""
        dims = check_data_pair(y1, y2, self.range_shape)
        return self.data_weight * (y1 * y2).sum(dim=dims)

    def extra_repr(self) -> str:
        return f"domain={self.domain}, range_shape={self.range_shape}, data_weight={self.data_weight}"


def as_operator(physics, domain: ImageDomain, range_shape=None, data_weight: float = 1.0) -> PhysicsOperator:
    """An indreg linear operator (``PhysicsOperator``) wrapping a deepinv ``LinearPhysics`` on ``domain``.

    Parameters
    ----------
    physics : deepinv.physics.LinearPhysics
        Real-valued, taking single-channel images ``(B, 1, nx, ny)`` (``Tomography``, ``Blur``, ...).
        Complex-valued physics (``MRI``, whose images are 2-channel real/imaginary pairs) are refused.
    domain : ImageDomain
        The images' domain; its cell volume weights the image inner product.
    range_shape : tuple of int, optional
        The data shape (deepinv's measurement shape without batch and channel dims); inferred by applying the
        physics to a zero image when None, checked against it otherwise.
    data_weight : float
        Weight ``w > 0`` of the data inner product ``w * sum(y1 * y2)`` (e.g. angle step times detector step for
        a tomography sinogram, as ``RayTransform``); 1 gives deepinv's plain sum.

    Returns
    -------
    PhysicsOperator
        ``T = A``, ``T^* = (data_weight / cell_volume) * A^T`` (deepinv's ``A_adjoint`` is the Euclidean
        transpose, so this scaling makes ``T^*`` the adjoint for indreg's inner products).

    Raises
    ------
    ImportError
        deepinv is not installed.
    TypeError
        No ``LinearPhysics``, a complex-valued one, no ``ImageDomain``, or physics that return no tensor or
        complex measurements.
    ValueError
        Physics that cannot be applied to a single-channel image of the domain's shape, a ``range_shape`` that
        disagrees, ``data_weight <= 0``.

    Examples
    --------
    >>> import math
    >>> import deepinv
    >>> from indreg import ImageDomain
    >>> phys = deepinv.physics.Tomography(angles=10, img_width=64, normalize=False)
    >>> T = as_operator(phys, ImageDomain.paper(64), data_weight=math.pi / 10 * 0.5)
    >>> T.range_shape      # deepinv's sinogram axes: (detector, angle)
    (91, 10)
    """
    deepinv = _import_deepinv()
    if not isinstance(physics, deepinv.physics.LinearPhysics):
        raise TypeError(f"physics must be a deepinv.physics.LinearPhysics, got {type(physics).__name__}")
    if isinstance(physics, deepinv.utils.mixins.MRIMixin):
        raise TypeError(f"physics {type(physics).__name__} is complex-valued (MRI); as_operator supports "
                        "real-valued physics only")
    if not isinstance(domain, ImageDomain):
        raise TypeError(f"domain must be an ImageDomain, got {type(domain).__name__}")
    data_weight = check_positive(data_weight, "data_weight")
    probed, dtypes = _probe(physics, domain)
    if range_shape is not None and tuple(range_shape) != probed:
        raise ValueError(f"range_shape {tuple(range_shape)} differs from the physics' measurement shape "
                         f"{probed} (without batch and channel dims)")
    return PhysicsOperator(physics, domain, probed, dtypes, data_weight)
