"""Pure functions of the LDDMM time discretisation: interpolation, finite differences, the flow recursions.

Everything here is plain torch and device / dtype agnostic, so the deformation operator (``lddmm.py``) and
later layers (geodesic shooting) share one implementation. The recursions are differentiable by autograd;
without a graph to record they run in place (reused buffers, ``out=``), and ``gradient_record`` /
``paper_gradient`` are the two halves of the paper's gradient (Algorithm 1, lines 7-10) without autograd;
``exact_record`` / ``exact_gradient`` those of the exact derivative of the discrete map (its discrete adjoint,
hand-written). Modules: ``sampling`` (grids, interpolation and its transposes), ``differences`` (finite
differences, divergence, their transposes, determinants), ``flows`` (the time-stepping recursions),
``backward`` (the paper's gradient and the exact one), ``coarse`` (a velocity on a coarser grid than the image:
the flow there, ``phi_{1,0}`` interpolated to the image's grid, and its exact derivative); every name is
re-exported here.

Notes
-----
- Images ``(..., nx, ny)``, vector fields ``(..., 2, nx, ny)`` (component 0 = x, 1 = y), velocity
  fields ``(..., N+1, 2, nx, ny)`` at ``t_i = i / N``; physical units of ``ImageDomain``.
- 3D: every function takes the same arguments on an ``ImageDomain`` of shape ``(nx, ny, nz)``, with
  images ``(..., nx, ny, nz)``, vector fields ``(..., 3, nx, ny, nz)`` (component 2 = z) and velocities
  ``(..., N+1, 3, nx, ny, nz)``: one code path, the number of image axes d read from ``domain.ndim`` (in
  the docstrings ``(..., nx, ny)`` then reads ``(..., nx, ny, nz)`` and ``2`` components read 3).
  Interpolation is trilinear, finite differences and divergences run over three axes, and
  ``jacobian_determinant`` is the 3x3 determinant (``determinant``).
- Interpolation and padding: ``sampling``; finite-difference schemes: ``differences``.
"""
from .backward import ExactRecord, exact_gradient, exact_record, gradient_record, paper_gradient
from .coarse import coarse_gradient, coarse_record, coarse_trajectory, upsample, upsample_adjoint
from .differences import (SCHEMES, _growth_into, determinant, displacement_determinant, divergence,
                          divergence_adjoint, gradient, jacobian_determinant)
from .flows import (ACTIONS, INTERPOLATIONS, _check_interpolation, _Steps, deformation, deformed_trajectory,
                    displacement_10, displacements_t0, jacobian_trajectory, step_flags, template_trajectory)
from .sampling import (_bands, _grid_units, _sample_displaced, displaced_grid, identity_grid, sample,
                       to_grid_units, warp)

__all__ = ["ACTIONS", "INTERPOLATIONS", "SCHEMES", "ExactRecord", "coarse_gradient", "coarse_record",
           "coarse_trajectory", "deformation", "deformed_trajectory",
           "determinant", "displaced_grid", "displacement_10", "displacement_determinant", "displacements_t0",
           "divergence", "divergence_adjoint", "exact_gradient", "exact_record", "gradient", "gradient_record",
           "identity_grid", "jacobian_determinant", "jacobian_trajectory", "paper_gradient", "sample",
           "step_flags", "template_trajectory", "to_grid_units", "upsample", "upsample_adjoint", "warp"]
