"""indreg: indirect image registration with large diffeomorphic deformations (LDDMM) in PyTorch."""
from . import _openmp

_openmp.configure()  # before torch loads OpenMP: idle threads sleep instead of spinning (see indreg._openmp)

from .domain import ImageDomain
from .forward import (FanBeamGeometry, ImageOperator, LinearOperator, ParallelBeamGeometry, RayTransform,
                      TiltSeriesGeometry, TiltSeriesTransform, compose, restrict, stack)
from .deform import CoarseVelocityDeformation, GaussianKernel, LDDMMDeformation, MetamorphosisDeformation
from . import metrics, noise, phantoms
from .solvers import IndirectRegistration, Algorithm1, TorchOptimSolver, MultilevelSolver, RegistrationProblem
from .solvers import SolverState, StepControl
from .solvers import MetamorphosisRegistration, MetamorphosisDescent, MetamorphosisTorchOptim
from .deform.shooting import GeodesicShooting, ShootingResult
from .learn.loss import IndirectShootingLoss
from . import models
from .api import RegistrationResult, register
from .inputs import RegistrationInputs, load

__all__ = ["ImageDomain", "ParallelBeamGeometry", "FanBeamGeometry", "RayTransform", "LinearOperator",
           "TiltSeriesGeometry", "TiltSeriesTransform", "ImageOperator", "compose", "stack", "restrict",
           "GaussianKernel", "LDDMMDeformation", "CoarseVelocityDeformation", "IndirectRegistration", "Algorithm1", "TorchOptimSolver",
           "MultilevelSolver", "RegistrationProblem", "SolverState", "StepControl", "models",
           "MetamorphosisDeformation", "MetamorphosisRegistration", "MetamorphosisDescent", "MetamorphosisTorchOptim",
           "GeodesicShooting", "ShootingResult", "IndirectShootingLoss", "register", "RegistrationResult",
           "load", "RegistrationInputs",
           "metrics", "noise", "phantoms"]
__version__ = "0.1.0"
