"""Input validation shared by every operator: errors name the problem and the expected value.

Scalars: a number is a python ``int`` / ``float``, a numpy real scalar or a 0-dim real numpy array / torch
tensor; ``str``, ``bool`` (python or numpy), ``None``, complex numbers and arrays with more than one entry are
refused with a ``TypeError`` (``float("6")`` and ``float(True)`` would otherwise pass as 6.0 and 1.0).
"""
from __future__ import annotations

import math
import numbers
import sys
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:   # imported where used: the app's preflight checks numbers without loading torch
    import torch


def _float_dtypes() -> tuple:
    """``(torch.float32, torch.float64)``: the dtypes every operator supports."""
    import torch

    return torch.float32, torch.float64


def __getattr__(name: str):
    """``FLOAT_DTYPES`` (:func:`_float_dtypes`), made on first use: importing this module loads no torch."""
    if name == "FLOAT_DTYPES":
        return _float_dtypes()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _arrays() -> tuple:
    """The array types a 0-dim value may come in: numpy arrays, and torch tensors once torch is loaded (none can
    exist before)."""
    torch = sys.modules.get("torch")
    return (np.ndarray,) if torch is None else (torch.Tensor, np.ndarray)


#: Largest integer parameter accepted (torch's index type, int64).
INT_MAX = 2 ** 63 - 1


class StepOverflowError(ValueError):
    """A step found only in the run to overflow the iterate's dtype (step halving off); :meth:`message` names the
    options by ``label`` (the keywords, or the app's config keys)."""

    def __init__(self, value: float, dtype: torch.dtype, detail: str):
        self.value, self.dtype, self.detail = value, str(dtype).replace("torch.", ""), detail
        super().__init__(self.message(lambda name: name))

    def message(self, label) -> str:
        return (f"{label('step_size')}={self.value:.4g} makes the iterate non-finite in {self.dtype} ({self.detail}): "
                f"give a smaller {label('step_size')} (or {label('step_rel')})")


def check_dtype(x: torch.Tensor, name: str) -> None:
    """Check that a tensor is float32 or float64 (the dtypes every operator supports)."""
    if not x.is_floating_point():
        raise TypeError(f"{name} must have a floating dtype (float32 or float64), got {x.dtype}")
    if x.dtype not in _float_dtypes():
        raise TypeError(f"{name} must be float32 or float64, got {x.dtype}")


def check_tensor(x, name: str, trailing_shape: tuple | None = None, min_dim: int | None = None,
                 finite: bool = True) -> torch.Tensor:
    """Check that ``x`` is a float32 / float64 tensor with the given trailing shape and (``finite``) finite values.

    ``finite=False`` skips the pass over the values, for intermediate results (residuals, deformed images)
    whose non-finite values the caller reports itself (a solver rejects a step with a non-finite objective)."""
    import torch

    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    check_dtype(x, name)
    if trailing_shape is not None:
        k = len(trailing_shape)
        if x.dim() < k or tuple(x.shape[x.dim() - k:]) != tuple(trailing_shape):
            raise ValueError(
                f"{name} must have shape (..., {', '.join(map(str, trailing_shape))}), got {tuple(x.shape)}")
    if min_dim is not None and x.dim() < min_dim:
        raise ValueError(f"{name} must have at least {min_dim} dims, got shape {tuple(x.shape)}")
    if finite and not all_finite(x):
        raise ValueError(f"{name} contains non-finite values (nan or inf)")
    return x


def check_nonempty(x: torch.Tensor, name: str, event_dims: int) -> None:
    """Check that a batch ``(..., *event)`` (``event`` its last ``event_dims`` axes) holds at least one item."""
    if x.numel() == 0:
        raise ValueError(f"{name} is empty (shape {tuple(x.shape)}): give at least one item of "
                         f"shape {tuple(x.shape[x.dim() - event_dims:])}")


def check_same(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """Check that two tensors share dtype and device."""
    if a.dtype != b.dtype:
        raise TypeError(f"{name_a} has dtype {a.dtype} but {name_b} has dtype {b.dtype}; they must match")
    if a.device != b.device:
        raise ValueError(f"{name_a} is on {a.device} but {name_b} is on {b.device}; they must match")


def broadcast_shapes(*shapes) -> torch.Size:
    """``torch.broadcast_shapes`` (the same result, ``RuntimeError`` when the shapes do not broadcast) without its
    first call's import of sympy (torch 2.13: about a second of CPU at every start of a process)."""
    import torch

    out = [1] * max((len(s) for s in shapes), default=0)
    for shape in shapes:
        for i, n in enumerate(shape, len(out) - len(shape)):
            if n != 1 and out[i] not in (1, n):
                raise RuntimeError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
            out[i] = n if n != 1 else out[i]
    return torch.Size(out)


def _shown(value) -> str:
    """A short description of a refused value (arrays by shape and dtype, not by their entries)."""
    if isinstance(value, _arrays()):
        return f"a {type(value).__name__} of shape {tuple(value.shape)} and dtype {value.dtype}"
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def is_finite_number(v) -> bool:
    """A finite real number (bools and strings are not numbers): a config value's range checks start from it."""
    try:
        return v is not None and math.isfinite(check_number(v, "value"))
    except (TypeError, ValueError):
        return False


def check_number(value, name: str, expected: str = "a real number") -> float:
    """``value`` as a python float if it is a real number (module docstring), else a ``TypeError``.

    Any real number is accepted, nan and inf included (callers check the range)."""
    scalar = value
    if isinstance(value, _arrays()) and value.ndim == 0:
        scalar = value.item()
    if isinstance(scalar, (bool, np.bool_)) or not isinstance(scalar, numbers.Real):
        raise TypeError(f"{name} must be {expected}, got {_shown(value)}")
    try:
        return float(scalar)
    except OverflowError:  # an int beyond float64
        raise ValueError(f"{name} must be {expected}, got {_shown(value)} (beyond float64)") from None


def check_finite_in(value, name: str, dtype: torch.dtype | None) -> float:
    """Check that a finite number stays finite, and nonzero if nonzero, when cast to the float ``dtype`` (e.g. a
    step size used as ``alpha`` of a float32 ``torch.add``: ``1e39`` overflows to inf, ``1e-50`` underflows to
    0). ``dtype=None`` checks nothing. Returns the float."""
    import torch

    v = check_number(value, name)
    if dtype is None or not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        if dtype is None:
            return v
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype!r}")
    cast = float(torch.tensor(v, dtype=torch.float64).to(dtype))
    if math.isfinite(v) and not math.isfinite(cast):
        raise ValueError(f"{name} must be representable in {dtype} (|value| <= {torch.finfo(dtype).max:.4g}), "
                         f"got {value!r}")
    if v != 0 and cast == 0:
        raise ValueError(f"{name} must be representable in {dtype}, got {value!r}, which rounds to 0 there")
    return v


def check_positive(value, name: str, dtype: torch.dtype | None = None) -> float:
    """Check that a scalar parameter is a finite number > 0 (representable in ``dtype`` if given)."""
    v = check_number(value, name, "a positive number")
    if not (v > 0 and math.isfinite(v)):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return check_finite_in(v, name, dtype)


def check_nonnegative(value, name: str, dtype: torch.dtype | None = None) -> float:
    """Check that a scalar parameter is a finite number >= 0 (representable in ``dtype`` if given)."""
    v = check_number(value, name, "a finite number >= 0")
    if not (v >= 0 and math.isfinite(v)):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return check_finite_in(v, name, dtype)


def check_finite(value, name: str) -> float:
    """Check that a scalar parameter is a finite real number (any sign)."""
    v = check_number(value, name, "a finite number")
    if not math.isfinite(v):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return v


def check_bool(value, name: str) -> bool:
    """Check that a flag is a bool (python or numpy): ``"no"`` or ``None`` would otherwise pass by truthiness."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {_shown(value)}")
    return bool(value)


def check_int(value, name: str, minimum: int) -> int:
    """Check that a parameter is an integer >= minimum (an integral float such as 4.0 is accepted)."""
    scalar = value.item() if isinstance(value, _arrays()) and value.ndim == 0 else value
    integral = (isinstance(scalar, numbers.Real) and not isinstance(scalar, (bool, np.bool_))
                and math.isfinite(scalar) and int(scalar) == scalar)
    if not integral:
        raise TypeError(f"{name} must be an integer >= {minimum}, got {_shown(value)}")
    if int(scalar) < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if int(scalar) > INT_MAX:
        raise ValueError(f"{name} must be an integer <= {INT_MAX} (int64), got {value!r}")
    return int(scalar)


def as_tensor(x, name: str, shape: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``x`` (tensor or array-like) as a real, finite tensor of ``shape`` in ``dtype`` / ``device``;
    errors name the argument."""
    import torch

    if isinstance(x, torch.Tensor):
        t = x.detach()
    else:
        a = np.asarray(x)
        if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
            raise TypeError(f"{name} must be a numeric array or torch tensor, got {type(x).__name__} of {a.dtype}")
        t = torch.from_numpy(np.ascontiguousarray(a))
    if t.is_complex():
        raise TypeError(f"{name} must be real, got the complex dtype {t.dtype}")
    if tuple(t.shape) != tuple(shape):
        raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {tuple(shape)}")
    t = t.to(device=device, dtype=dtype)
    if not all_finite(t):
        raise ValueError(f"{name} contains non-finite values (nan or inf)")
    return t


#: :func:`all_finite` checks this many values at a time (its mask: 4 MiB, not one byte per value of a volume).
FINITE_CHUNK = 2 ** 22


def all_finite(t) -> bool:
    """Whether every value of the tensor ``t`` is finite, checked in chunks of :data:`FINITE_CHUNK` values."""
    import torch

    if t.dim() == 0 or t.numel() <= FINITE_CHUNK:
        return bool(torch.isfinite(t).all())
    if t.is_contiguous():
        flat = t.view(-1)
        return all(bool(torch.isfinite(flat[i:i + FINITE_CHUNK]).all()) for i in range(0, flat.numel(), FINITE_CHUNK))
    rows = FINITE_CHUNK // max(1, t[0].numel())
    if rows < 2:   # one sub-array at a time, itself in chunks
        return all(all_finite(part) for part in t)
    return all(bool(torch.isfinite(t[i:i + rows]).all()) for i in range(0, t.shape[0], rows))
