"""A tilt series projected by ASTRA's CPU projector, slice by slice (issue #39: data made outside indreg).

Runs with any Python that has ``astra-toolbox`` and numpy (not indreg), e.g. a venv of its own:

    python3 -m venv .venv && .venv/bin/pip install astra-toolbox numpy
    .venv/bin/python scripts/astra_projections.py volume.npy tilts_deg.npy cell out.npy

``volume.npy``: ``(x, y, z)``, the tilt axis y; ``tilts_deg.npy``: the tilt angles (deg); ``cell``: the voxel side (the
line integrals' unit); writes ``(tilts, y, x)``: every slice ``volume[:, j, :]`` projected by ASTRA's 2D parallel
beam, ``linear`` CPU projector, detector as wide as the slice with square cells. ASTRA's angle and detector directions
are its own: what the moment conditions use (the sinogram of each row) does not depend on them.
"""
import sys

import astra
import numpy as np


def project(volume: np.ndarray, tilts_deg: np.ndarray, cell: float) -> np.ndarray:
    nx, ny, nz = volume.shape
    vol_geom = astra.create_vol_geom(nz, nx)                    # rows z, columns x
    proj_geom = astra.create_proj_geom("parallel", 1.0, nx, np.radians(tilts_deg))
    projector = astra.create_projector("linear", proj_geom, vol_geom)
    out = np.zeros((len(tilts_deg), ny, nx))
    for j in range(ny):
        sino_id, sino = astra.create_sino(np.ascontiguousarray(volume[:, j, :].T), projector)
        out[:, j, :] = sino * cell
        astra.data2d.delete(sino_id)
    astra.projector.delete(projector)
    return out


if __name__ == "__main__":
    volume, tilts, cell, target = np.load(sys.argv[1]), np.load(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
    np.save(target, project(volume.astype(np.float64), tilts, cell))
