"""Registration problems: the objectives a solver descends (the registration-problem protocol, ``problem.py``),
LDDMM's (``lddmm.py``: eq:OptimV / eq:RegOptim), metamorphosis' (``metamorphosis.py``) and the spatiotemporal
model's (``spatiotemporal.py``); LDDMM's data term slab by slab along a tilt axis, over processes (``slabs.py``). The
solvers (``indreg.solvers``) use them only through the protocol."""
from .problem import RegistrationProblem
from .lddmm import IndirectRegistration, total_variation
from .metamorphosis import MetamorphosisRegistration
from .spatiotemporal import SpatiotemporalRegistration
from .slabs import SlabwiseRegistration

__all__ = ["RegistrationProblem", "IndirectRegistration", "total_variation", "MetamorphosisRegistration",
           "SpatiotemporalRegistration", "SlabwiseRegistration"]
