"""How the example data of ``indreg-register experiment=own_data_example`` (``indreg/data/own_data_*``) were made.

A limited-angle tomography problem with a known answer, written in the file formats a user would bring:

1. template: indreg's "compressed" Shepp-Logan template (``indreg.phantoms``, the suite-3 template) on 64 x 64
   cells of [-16, 16]^2, scaled to grey levels 0..255 and saved as an 8-bit picture ``own_data_template.png``
   (shown upright: x to the right, y up). Its grey levels are the intensity unit of everything below.
2. target (ground truth): the template as read back from the picture, deformed by a known smooth
   diffeomorphism: the flow (N = 20 steps, ``indreg.LDDMMDeformation``, the template interpolated once) of a
   stationary velocity field, a swirl about (2, -1) of peak speed 3 plus a shift of 1 along x, both under a
   Gaussian envelope of width 8 (physical units). Saved as ``own_data_target.npy`` (indreg's (x, y) layout).
3. data: 61 parallel-beam projections at -60, -58, ..., 60 degrees (a limited-angle tilt series), 92 detector
   bins on [-24, 24], computed with ``indreg.RayTransform`` from the target in float64, plus white Gaussian noise
   at an SNR of 15 dB (``indreg.noise``, "code" convention: 10 log10 of a ratio of norms), seed 0. Saved as
   ``own_data_sinogram.npy`` (rows = angles, columns = bins) and the angles, one per line in degrees, as
   ``own_data_angles.tlt`` (IMOD's tilt-angle format).

Run from the repository root: ``python examples/make_own_data_example.py [out_dir]`` (default ``indreg/data``).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

import indreg
from indreg import io, noise, phantoms

N_PIXELS, HALF_WIDTH = 64, 16.0
TILTS_DEG = np.arange(-60.0, 60.0 + 1e-9, 2.0)          # 61 tilts
DET_COUNT, DET_MIN, DET_MAX = 92, -24.0, 24.0
SNR_DB, SEED = 15.0, 0


def known_velocity(domain: indreg.ImageDomain, num_steps: int) -> torch.Tensor:
    """Stationary smooth velocity ``(N+1, 2, nx, ny)``: swirl about (2, -1), peak speed 3, plus a shift of 1
    along x, under a Gaussian envelope of width 8."""
    x, y = domain.points()                                   # (nx, ny) each, physical units
    dx, dy = x - 2.0, y + 1.0
    envelope = torch.exp(-(dx ** 2 + dy ** 2) / (2 * 8.0 ** 2))
    swirl = 3.0 * envelope / 8.0 * torch.stack([-dy, dx]) * np.exp(0.5)   # peak speed 3 at radius 8
    shift = torch.stack([envelope, torch.zeros_like(envelope)])
    return (swirl + shift).expand(num_steps + 1, 2, *domain.shape).contiguous()


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    domain = indreg.ImageDomain.paper(N_PIXELS)
    template = phantoms.get("shepp_logan_template", domain).numpy()
    grey = np.round(255 * (template - template.min()) / (template.max() - template.min())).astype(np.uint8)
    import imageio.v3 as iio
    iio.imwrite(out / "own_data_template.png", np.rot90(grey))                      # displayed upright
    template_f = torch.from_numpy(io.read_image(out / "own_data_template.png", integer_scale="raw"))  # 0..255

    W = indreg.LDDMMDeformation(domain, num_steps=20, interpolation="compose")   # one interpolation: no blur
    velocity = known_velocity(domain, 20)
    target = W(velocity, template_f)
    print(f"known deformation: min Jacobian {float(W.min_jacobian(velocity)):.3f}")

    geometry = indreg.ParallelBeamGeometry(det_count=DET_COUNT, det_min=DET_MIN, det_max=DET_MAX,
                                           angles=torch.from_numpy(np.deg2rad(TILTS_DEG)))
    T = indreg.RayTransform(domain, geometry)
    sinogram, _ = noise.add_white_noise(T(target), snr_db=SNR_DB, seed=SEED)
    np.save(out / "own_data_target.npy", target.numpy())
    np.save(out / "own_data_sinogram.npy", sinogram.numpy())
    (out / "own_data_angles.tlt").write_text("".join(f"{a:.2f}\n" for a in TILTS_DEG))
    print(f"wrote {out}/own_data_{{template.png,target.npy,sinogram.npy,angles.tlt}}: template {template_f.shape}, "
          f"sinogram {tuple(sinogram.shape)}, SNR {SNR_DB} dB")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "indreg" / "data")
