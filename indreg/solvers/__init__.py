"""Solvers of indirect registration: Algorithm 1 with step control, any torch.optim optimizer, coarse to fine, the
models' own (metamorphosis, the intertwined spatiotemporal scheme). The problems they descend live in
``indreg.problems`` (re-exported here: ``indreg.solvers.IndirectRegistration`` is ``indreg.problems``')."""
from ..problems import (IndirectRegistration, MetamorphosisRegistration, RegistrationProblem,
                        SpatiotemporalRegistration, total_variation)
from .algorithm1 import Algorithm1
from .multilevel import MultilevelSolver
from .metamorphosis import MetamorphosisDescent, MetamorphosisState, MetamorphosisTorchOptim
from .state import SolverState, StepControl
from .torch_optim import TorchOptimSolver

__all__ = ["RegistrationProblem", "IndirectRegistration", "Algorithm1", "StepControl", "TorchOptimSolver",
           "MultilevelSolver", "SolverState", "total_variation", "MetamorphosisRegistration", "MetamorphosisDescent",
           "MetamorphosisTorchOptim", "MetamorphosisState", "SpatiotemporalRegistration"]
