"""Parallel-beam acquisition geometry in 2D: projection angles and a flat detector."""
from __future__ import annotations

import math

import torch

from .._checks import check_int


class ParallelBeamGeometry:
    """Angles ``theta_k`` in radians and a detector line ``[det_min, det_max]`` split into ``det_count`` cells.

    Convention:
        - A datum ``p(theta_k, s_d)`` is the line integral over ``{s_d w + t w_perp : t in R}`` with
          ``w = (cos theta, sin theta)`` and ``w_perp = (-sin theta, cos theta)`` (see ``RayTransform``).
        - Detector bins are cell-centred: ``s_d = det_min + (d + 1/2) * det_cell``,
          ``det_cell = (det_max - det_min) / det_count``, in the image domain's physical units.
        - Data are tensors ``(..., num_angles, det_count)``.
        - The data-space inner product is ``<p, q> = data_weight * sum p q`` with
          ``data_weight = angle_cell * det_cell`` and ``angle_cell = pi / num_angles``, as ODL weights its
          data space (every angle gets the same weight, whatever the angles are).

    Args:
        num_angles: number of angles; the default angles are uniform ``k * pi / num_angles`` on ``[0, pi)``.
        det_count: number of detector bins (>= 1).
        det_min, det_max: detector extent (``det_min < det_max``), physical units.
        angles: explicit angles in radians (1D, finite); ``num_angles`` may then be ``None``.

    Example:
        >>> g = ParallelBeamGeometry.paper(num_angles=10, det_count=92)
        >>> round(float(g.angles[1]) * 180 / math.pi, 2), round(g.det_cell, 4)
        (18.95, 0.5217)
    """

    def __init__(self, num_angles: int | None = None, det_count: int = 1, det_min: float = -1.0,
                 det_max: float = 1.0, angles=None):
        if angles is None:
            if num_angles is None:
                raise ValueError("give num_angles (>= 1) or an explicit angles= list/tensor")
            n = check_int(num_angles, "num_angles", 1)
            angles = torch.arange(n, dtype=torch.float64) * (math.pi / n)
        else:
            angles = torch.as_tensor(angles, dtype=torch.float64).detach().cpu().reshape(-1)
            if angles.numel() == 0:
                raise ValueError("angles must contain at least one angle, got none")
            if not bool(torch.isfinite(angles).all()):
                raise ValueError(f"angles must be finite (radians), got {angles.tolist()}")
            if num_angles is not None and check_int(num_angles, "num_angles", 1) != angles.numel():
                raise ValueError(f"num_angles={num_angles} but {angles.numel()} angles were given")
        self.angles = angles
        self.det_count = check_int(det_count, "det_count", 1)
        self.det_min, self.det_max = float(det_min), float(det_max)
        if not (math.isfinite(self.det_min) and math.isfinite(self.det_max)):
            raise ValueError(f"det_min and det_max must be finite, got {det_min}, {det_max}")
        if not self.det_min < self.det_max:
            raise ValueError(f"det_min must be < det_max, got det_min={det_min} >= det_max={det_max}")

    @classmethod
    def paper(cls, num_angles: int, det_count: int, det_min: float = -24.0, det_max: float = 24.0):
        """The authors' geometry: ODL's ``uniform_partition(0, pi, n, nodes_on_bdry=(True, False))``.

        Angles ``k * pi / (n - 1/2)``, ``k = 0..n-1`` (for n = 10: 0, 18.95, ..., 170.53 degrees), and
        the detector ``uniform_partition(-24, 24, det_count)``.
        """
        n = check_int(num_angles, "num_angles", 1)
        angles = torch.arange(n, dtype=torch.float64) * (math.pi / (n - 0.5))
        return cls(det_count=det_count, det_min=det_min, det_max=det_max, angles=angles)

    @property
    def num_angles(self) -> int:
        return int(self.angles.numel())

    @property
    def det_cell(self) -> float:
        """Detector bin width."""
        return (self.det_max - self.det_min) / self.det_count

    @property
    def det_points(self) -> torch.Tensor:
        """Bin centres ``s_d`` (float64, length ``det_count``)."""
        return self.det_min + (torch.arange(self.det_count, dtype=torch.float64) + 0.5) * self.det_cell

    @property
    def angle_cell(self) -> float:
        """Quadrature weight of one angle, ``pi / num_angles``."""
        return math.pi / self.num_angles

    @property
    def data_weight(self) -> float:
        """Weight of the data-space inner product, ``angle_cell * det_cell``."""
        return self.angle_cell * self.det_cell

    @property
    def shape(self) -> tuple:
        """Data shape ``(num_angles, det_count)``."""
        return (self.num_angles, self.det_count)

    def __repr__(self) -> str:
        return (f"ParallelBeamGeometry(num_angles={self.num_angles}, det_count={self.det_count}, "
                f"det_min={self.det_min}, det_max={self.det_max})")
