"""Forward model of indirect registration: parallel-beam geometry, ray transform ``T``, FBP and TV baselines.

The data model is ``g = T(W(nu, I)) + noise`` (``eq:OptimV``); ``T`` is the 2D parallel-beam ray transform.
"""
from .geometry import ParallelBeamGeometry
from .ray_transform import RayTransform
from .fbp import fbp
from .tv import tv_reconstruction

__all__ = ["ParallelBeamGeometry", "RayTransform", "fbp", "tv_reconstruction"]
