"""Forward model of indirect registration: geometries, ray transform ``T``, FBP and TV baselines.

The data model is ``g = T(W(nu, I)) + noise`` (``eq:OptimV``); ``T`` is any ``LinearOperator`` (protocol in
``operator``), by default the 2D ray transform for a parallel-beam or fan-beam geometry, or in 3D the
single-axis tilt series of electron tomography (``tilt_series``); data at several time points: one operator per
frame (``time_series``). Operators combine (``algebra``, ``stacking``): ``R * B`` (a blur ``B = ImageOperator(...)``,
then ``R``),
``A + B``, ``c * A``, ``stack(T_1, ..., T_K)``, ``restrict(T, rows)``. Baselines: FBP, SIRT and TV (2D and 3D).
"""
from .geometry import FanBeamGeometry, ParallelBeamGeometry
from .operator import LinearOperator, adjointness, check_operator
from .algebra import ComposedOperator, ImageOperator, OperatorAlgebra, ScaledOperator, SumOperator, add, compose, scale
from .stacking import RestrictedOperator, StackedOperator, restrict, stack
from .ray_transform import RayTransform, register_projector
from .tilt_series import TiltSeriesGeometry, TiltSeriesTransform
from .time_series import TimeSeriesOperator
from .fbp import fbp
from .sirt import sirt
from .tv import intensity_scale, tv_reconstruction, tv_weight_unit
from .wide_box import WideBox, wide_box

#: The forward operator of each geometry type (``operator_for``); a new geometry adds its entry here.
OPERATORS = {ParallelBeamGeometry: RayTransform, FanBeamGeometry: RayTransform, TiltSeriesGeometry: TiltSeriesTransform}


def operator_for(domain, geometry):
    """The forward operator of ``geometry`` on ``domain`` (``OPERATORS``: ``RayTransform`` for the 2D beams,
    ``TiltSeriesTransform`` for a tilt series).

    Parameters
    ----------
    domain : ImageDomain
        The image domain.
    geometry : object
        A geometry of a type in ``OPERATORS`` (or a subclass of one).

    Returns
    -------
    LinearOperator
        ``OPERATORS[type](domain, geometry)``.

    Raises
    ------
    TypeError
        No operator is registered for the geometry's type.
    """
    for cls in type(geometry).__mro__:
        if cls in OPERATORS:
            return OPERATORS[cls](domain, geometry)
    raise TypeError(f"no forward operator is registered for a {type(geometry).__name__} "
                    f"(indreg.forward.OPERATORS: {', '.join(c.__name__ for c in OPERATORS)})")


__all__ = ["ParallelBeamGeometry", "FanBeamGeometry", "RayTransform", "register_projector", "LinearOperator",
           "check_operator", "adjointness", "fbp", "sirt", "tv_reconstruction", "intensity_scale", "TiltSeriesGeometry",
           "TiltSeriesTransform", "TimeSeriesOperator", "OPERATORS", "operator_for", "OperatorAlgebra", "ImageOperator",
           "ComposedOperator", "SumOperator", "ScaledOperator", "StackedOperator", "RestrictedOperator", "compose",
           "add", "scale", "stack", "restrict", "tv_weight_unit", "WideBox", "wide_box"]
