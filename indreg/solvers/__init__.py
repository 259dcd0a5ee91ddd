"""Objectives and solvers of indirect registration: the registration-problem protocol, Algorithm 1 with step
control, any torch.optim optimizer, coarse to fine."""
from .problem import RegistrationProblem
from .algorithm1 import Algorithm1
from .multilevel import MultilevelSolver
from .metamorphosis import (MetamorphosisDescent, MetamorphosisRegistration, MetamorphosisState,
                            MetamorphosisTorchOptim)
from .objective import IndirectRegistration, total_variation
from .spatiotemporal import SpatiotemporalRegistration
from .state import SolverState, StepControl
from .torch_optim import TorchOptimSolver

__all__ = ["RegistrationProblem", "IndirectRegistration", "Algorithm1", "StepControl", "TorchOptimSolver",
           "MultilevelSolver", "SolverState", "total_variation", "MetamorphosisRegistration", "MetamorphosisDescent",
           "MetamorphosisTorchOptim", "MetamorphosisState", "SpatiotemporalRegistration"]
