"""Input validation shared by every operator: errors name the problem and the expected value."""
from __future__ import annotations

import torch


FLOAT_DTYPES = (torch.float32, torch.float64)


def check_dtype(x: torch.Tensor, name: str) -> None:
    """Check that a tensor is float32 or float64 (the dtypes every operator supports)."""
    if not x.is_floating_point():
        raise TypeError(f"{name} must have a floating dtype (float32 or float64), got {x.dtype}")
    if x.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name} must be float32 or float64, got {x.dtype}")


def check_tensor(x, name: str, trailing_shape: tuple | None = None, min_dim: int | None = None) -> torch.Tensor:
    """Check that ``x`` is a float32 / float64 tensor with finite values and the given trailing shape."""
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
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains non-finite values (nan or inf)")
    return x


def check_same(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """Check that two tensors share dtype and device."""
    if a.dtype != b.dtype:
        raise TypeError(f"{name_a} has dtype {a.dtype} but {name_b} has dtype {b.dtype}; they must match")
    if a.device != b.device:
        raise ValueError(f"{name_a} is on {a.device} but {name_b} is on {b.device}; they must match")


def check_positive(value, name: str) -> float:
    """Check that a scalar parameter is a finite positive number."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a positive number, got {value!r}") from None
    if not (v > 0 and v < float("inf")):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def check_int(value, name: str, minimum: int) -> int:
    """Check that a parameter is an integer >= minimum (an integral float such as 4.0 is accepted)."""
    try:
        integral = not isinstance(value, bool) and int(value) == value
    except (TypeError, ValueError, OverflowError):  # None, "a", nan, inf, ...
        integral = False
    if not integral:
        raise TypeError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if int(value) < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)
