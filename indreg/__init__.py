"""indreg: indirect image registration with large diffeomorphic deformations (LDDMM) in PyTorch.

The public names are imported on first use (PEP 562), so that importing a light submodule (e.g. the app's entry
point answering ``--help``) does not load torch; ``from indreg import register`` works as ever.
"""
from __future__ import annotations

from . import _lazy, _openmp

_lazy.install_deprecated()   # renamed modules: the old names that stay warn until they go (indreg._lazy)
_openmp.configure()  # before torch loads OpenMP: idle threads sleep instead of spinning (see indreg._openmp)

#: public name -> the submodule that defines it
_HOME = {
    "ImageDomain": "domain",
    **dict.fromkeys(("FanBeamGeometry", "LinearOperator", "ParallelBeamGeometry", "RayTransform",
                     "TiltSeriesGeometry", "TiltSeriesTransform", "ImageOperator", "compose", "stack", "restrict"),
                    "forward"),
    **dict.fromkeys(("CoarseVelocityDeformation", "GaussianKernel", "LDDMMDeformation", "MetamorphosisDeformation"),
                    "deform"),
    **dict.fromkeys(("IndirectRegistration", "Algorithm1", "TorchOptimSolver", "MultilevelSolver",
                     "RegistrationProblem", "SolverState", "StepControl", "MetamorphosisRegistration",
                     "MetamorphosisDescent", "MetamorphosisTorchOptim"), "solvers"),
    **dict.fromkeys(("GeodesicShooting", "ShootingResult"), "deform.shooting"),
    "IndirectShootingLoss": "learn.loss",
    **dict.fromkeys(("RegistrationResult", "register"), "registration.api"),
    **dict.fromkeys(("RegistrationInputs", "load"), "inputs"),
}

__all__ = ["ImageDomain", "ParallelBeamGeometry", "FanBeamGeometry", "RayTransform", "LinearOperator",
           "TiltSeriesGeometry", "TiltSeriesTransform", "ImageOperator", "compose", "stack", "restrict",
           "GaussianKernel", "LDDMMDeformation", "CoarseVelocityDeformation", "IndirectRegistration", "Algorithm1",
           "TorchOptimSolver", "MultilevelSolver", "RegistrationProblem", "SolverState", "StepControl",
           "MetamorphosisDeformation", "MetamorphosisRegistration", "MetamorphosisDescent", "MetamorphosisTorchOptim",
           "GeodesicShooting", "ShootingResult", "IndirectShootingLoss", "register", "RegistrationResult",
           "load", "RegistrationInputs",
           "metrics", "noise", "phantoms"]
__version__ = "0.1.0"

__getattr__, __dir__ = _lazy.attributes(__name__, _HOME, __all__)   # public names on first use
