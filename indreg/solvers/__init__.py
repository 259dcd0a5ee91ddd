"""Objective and solvers of indirect registration: Algorithm 1 and any torch.optim optimizer."""
from .algorithm1 import Algorithm1
from .multilevel import MultilevelSolver
from .metamorphosis import (MetamorphosisDescent, MetamorphosisRegistration, MetamorphosisState,
                            MetamorphosisTorchOptim)
from .objective import IndirectRegistration, total_variation
from .state import SolverState
from .torch_optim import TorchOptimSolver

__all__ = ["IndirectRegistration", "Algorithm1", "TorchOptimSolver", "MultilevelSolver", "SolverState", "total_variation",
           "MetamorphosisRegistration", "MetamorphosisDescent", "MetamorphosisTorchOptim", "MetamorphosisState"]
