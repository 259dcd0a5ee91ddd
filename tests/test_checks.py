"""The shared scalar / tensor checks (indreg/_checks.py) and the parameters that go through them (issue #19)."""
import math

import numpy as np
import pytest
import torch

from indreg import GaussianKernel, ImageDomain, LDDMMDeformation, ParallelBeamGeometry
from indreg._checks import (broadcast_shapes, check_bool, check_finite, check_finite_in, check_int, check_nonempty,
                            check_nonnegative, check_number, check_positive)

# numbers in every form a caller may hold them: python, numpy scalars, 0-dim arrays and tensors
NUMBERS = [6, 6.0, np.float32(6), np.float64(6), np.int64(6), np.array(6.0), torch.tensor(6.0),
           torch.tensor(6, dtype=torch.int32)]
# not numbers, although float() takes them (or takes them as something else)
NOT_NUMBERS = ["6", b"6", True, False, np.bool_(True), torch.tensor(True), None, 6 + 0j, np.complex64(6),
               [6.0], (6.0,), torch.tensor([6.0]), np.array([6.0]), object()]


@pytest.mark.parametrize("value", NUMBERS, ids=repr)
def test_numbers_in_every_form_are_accepted(value):
    for check in (check_positive, check_nonnegative, check_finite, check_number):
        v = check(value, "sigma")
        assert v == 6.0 and type(v) is float
    assert check_int(value, "num_steps", 1) == 6 and type(check_int(value, "num_steps", 1)) is int


def _id(value) -> str:
    """``repr``, but an ``object()`` by its type: the same id in every process (pytest-xdist compares them)."""
    return "object()" if type(value) is object else repr(value)


@pytest.mark.parametrize("value", NOT_NUMBERS, ids=_id)
def test_str_bool_none_complex_and_arrays_are_refused(value):
    for check, what in ((check_positive, "a positive number"), (check_nonnegative, "a finite number >= 0"),
                        (check_finite, "a finite number"), (check_number, "a real number")):
        with pytest.raises(TypeError, match=f"^sigma must be {what}, got "):
            check(value, "sigma")
    with pytest.raises(TypeError, match="^num_steps must be an integer >= 1, got "):
        check_int(value, "num_steps", 1)


def test_range_errors_name_the_parameter():
    for bad in (0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="^sigma must be a finite number > 0"):
            check_positive(bad, "sigma")
    for bad in (-1e-300, math.inf, math.nan):
        with pytest.raises(ValueError, match="^gamma must be a finite number >= 0"):
            check_nonnegative(bad, "gamma")
    assert check_nonnegative(0, "gamma") == 0.0
    for bad in (math.inf, -math.inf, math.nan):
        with pytest.raises(ValueError, match="^det_min must be a finite number"):
            check_finite(bad, "det_min")
    with pytest.raises(ValueError, match=r"^sigma must be a positive number, got 1000.* \(beyond float64\)"):
        check_positive(10 ** 400, "sigma")
    for bad in (2.5, math.inf, math.nan):
        with pytest.raises(TypeError, match="^num_iter must be an integer >= 0"):
            check_int(bad, "num_iter", 0)
    with pytest.raises(ValueError, match=r"^num_iter must be an integer <= 9223372036854775807 \(int64\)"):
        check_int(1e30, "num_iter", 0)
    with pytest.raises(ValueError, match="^num_iter must be an integer >= 1, got 0"):
        check_int(0, "num_iter", 1)


def test_values_must_be_representable_in_the_working_dtype():
    # step_size=1e39 is inf as float32 alpha (torch.add raises deep inside); 1e-50 is 0 (a step that does nothing)
    with pytest.raises(ValueError, match=r"^step_size must be representable in torch.float32 \(\|value\| <= 3.403e\+38\)"):
        check_positive(1e39, "step_size", torch.float32)
    with pytest.raises(ValueError, match="^step_size must be representable in torch.float32, got 1e-50, which rounds"):
        check_positive(1e-50, "step_size", torch.float32)
    with pytest.raises(ValueError, match="^gamma must be representable in torch.float32"):
        check_nonnegative(1e39, "gamma", torch.float32)
    assert check_positive(1e39, "step_size", torch.float64) == 1e39
    assert check_positive(1e-50, "step_size", torch.float64) == 1e-50
    assert check_positive(3e38, "step_size", torch.float32) == 3e38
    assert check_nonnegative(0.0, "gamma", torch.float32) == 0.0
    assert check_finite_in(1e39, "x", None) == 1e39
    with pytest.raises(TypeError, match="dtype must be a floating torch.dtype"):
        check_finite_in(1.0, "x", torch.int64)


def test_bool_flags_and_empty_batches():
    assert check_bool(np.bool_(False), "padding") is False
    for bad in ("no", None, 0, 1.0):
        with pytest.raises(TypeError, match="^padding must be True or False, got "):
            check_bool(bad, "padding")
    check_nonempty(torch.zeros(1, 4, 4), "template", 2)
    with pytest.raises(ValueError, match=r"^template is empty \(shape \(0, 4, 4\)\): give at least one item of "
                                         r"shape \(4, 4\)"):
        check_nonempty(torch.zeros(0, 4, 4), "template", 2)


def test_parameters_checked_through_check_positive_refuse_str_and_bool():
    # issue #19: GaussianKernel(D, '6') and GaussianKernel(D, True) were sigma 6.0 and 1.0
    dom = ImageDomain.paper(8)
    for bad in ("6", True, np.bool_(True)):
        with pytest.raises(TypeError, match="^sigma must be a positive number, got "):
            GaussianKernel(dom, bad)
    assert GaussianKernel(dom, np.float32(6)).sigma == 6.0 == GaussianKernel(dom, torch.tensor(6.0)).sigma
    with pytest.raises(TypeError, match="^num_steps must be an integer >= 1, got True"):
        LDDMMDeformation(dom, True)
    with pytest.raises(TypeError, match="^step_deg must be a positive number, got '2'"):
        ParallelBeamGeometry.tilt_series(-60, 60, "2", 16)


def test_broadcast_shapes_is_torchs():
    """The same shape as ``torch.broadcast_shapes``, or a ``RuntimeError`` where torch raises one (sizes 0 and 1)."""
    import itertools

    sizes = (0, 1, 2, 3)
    shapes = [()] + [(a,) for a in sizes] + [(a, b) for a in sizes for b in sizes] + [(2, 1, 3), (1, 0, 1)]
    for s1, s2, s3 in itertools.product(shapes, shapes, [(), (1,), (2, 1)]):
        try:
            expected = torch.broadcast_shapes(s1, s2, s3)
        except RuntimeError:
            with pytest.raises(RuntimeError, match="do not broadcast"):
                broadcast_shapes(torch.Size(s1), s2, s3)
        else:
            got = broadcast_shapes(torch.Size(s1), s2, s3)
            assert got == expected and isinstance(got, torch.Size)
    assert broadcast_shapes() == torch.Size([])
