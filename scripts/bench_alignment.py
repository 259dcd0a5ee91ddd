"""Alignment in the fit on a simulated misaligned tilt series (docs/alignment.md).

``--projector indreg`` (default): the suite_et_3d data (3D Shepp-Logan -> the same bent and swirled on [-16, 16]^3,
tilt axis y, -60..60 degrees in 2-degree steps, detector as wide as the volume, white noise at 10 dB) with known
random shifts (uniform random, in the gauge of ``indreg.alignment.gauge``, scaled to at most ``max_shift`` px across
and along the axis) and, in a second series, the tilt axis also rotated by ``--angle`` degrees in the detector
plane, all made by indreg's own operators. Three registrations with the same settings: no alignment on the aligned
series, ``align="shifts"`` on the shifted one, ``align="shifts+axis"`` on the shifted and rotated one.

``--projector scipy``: data made outside indreg, as a microscope would: the Shepp-Logan phantom (``--blur`` voxels
of Gaussian blur: a band-limited specimen) turned about the tilt axis by ``scipy.ndimage.rotate`` (cubic splines)
and summed along the beam (``--projector astra``: projected by ASTRA's CPU projector slice by slice,
``scripts/astra_projections.py`` run by ``--astra-python``, a Python with ``astra-toolbox``), every tilt image then
turned about its centre by each angle of ``--angles`` and shifted (``scipy.ndimage.rotate`` and ``shift``, cubic),
Gaussian noise of ``--noise`` times the largest datum; the template is the swirled and bent phantom, turned about the
beam by ``--template-turn`` degrees. ``--phantom beads``: the specimen also carries ``--beads`` gold beads (the
fiducials of electron tomography, :func:`specimen`), which the template does not. One registration without
alignment on the unturned, unshifted stack, then ``align="shifts+axis"`` on every turned one.

Prints a table: the projector, the template's turn about the beam (deg), the series, the shifts' RMS error (px,
across / along the axis, in the gauge), the angle's error (deg), its standard error, where the angle came from
(``stack``: the moment conditions of the stack before the fit, then held; ``fit``: estimated in the fit, the stack
not determining it; ``indreg.alignment.stack_angle``) with the stack estimate's standard error, SSIM, relative
residual and seconds of each run.

    OMP_NUM_THREADS=1 python scripts/bench_alignment.py            # 64^3, 100 iterations, velocity_factor 2
    python scripts/bench_alignment.py --size 32 --iterations 30    # a quick look
    python scripts/bench_alignment.py --projector scipy --size 32 --angles 0.5 -0.5 3 -3 --template-turn 4
    OMP_NUM_THREADS=1 python scripts/bench_alignment.py --projector scipy --phantom beads --size 64 --step 3 \
        --max-shift 4 --iterations 60                                # issue #39's table (docs/alignment.md)
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

import indreg
from indreg import ImageDomain, noise, phantoms
from indreg.alignment import gauge
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.alignment.operator import AlignedOperator


def arguments():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=64, help="volume side (cells), 64: suite_et_3d")
    p.add_argument("--iterations", type=int, default=100, help="Algorithm 1 iterations of each run")
    p.add_argument("--velocity-factor", type=int, default=2, help="the velocity on a grid this many times coarser")
    p.add_argument("--max-shift", type=float, default=8.0, help="largest true shift (px)")
    p.add_argument("--angle", type=float, default=3.0, help="true tilt-axis angle (deg, --projector indreg)")
    p.add_argument("--snr", type=float, default=10.0, help="white noise (dB, --projector indreg); inf: exact data")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--projector", choices=("indreg", "scipy", "astra"), default="indreg",
                   help="what makes the data (astra: ASTRA's CPU projector slice by slice, then turned as scipy's)")
    p.add_argument("--astra-python", default=".venv/bin/python", help="a Python with astra-toolbox (--projector astra)")
    p.add_argument("--step", type=float, default=2.0, help="tilt step (deg)")
    p.add_argument("--angles", type=float, nargs="+", default=[0.5, -0.5, 1.0, -1.0, 3.0, -3.0, 5.0, -5.0],
                   help="true tilt-axis angles (deg, indreg's convention; --projector scipy)")
    p.add_argument("--template-turn", type=float, default=0.0, help="template turned about the beam (deg)")
    p.add_argument("--blur", type=float, default=1.0, help="Gaussian blur of the phantom (voxels; scipy)")
    p.add_argument("--noise", type=float, default=0.02, help="noise std / largest datum (scipy)")
    p.add_argument("--phantom", choices=("shepp-logan", "beads"), default="shepp-logan",
                   help="the specimen (scipy, astra): the Shepp-Logan alone, or with gold beads the template lacks")
    p.add_argument("--beads", type=int, default=20, help="gold beads in the specimen (--phantom beads)")
    p.add_argument("--undetermined", choices=("hold", "prior", "fit"), default=None,
                   help="the policy where the stack does not determine the angle (indreg.alignment.solver.UNDETERMINED)")
    p.add_argument("--holdout", type=int, default=None, help="hold out every k-th tilt (its residual in the table)")
    return p.parse_args()


def geometry(a):
    domain = ImageDomain.paper(a.size, ndim=3)
    return domain, TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, a.step, det_count=a.size,
                                                                          det_min=-16.0, det_max=16.0))


def random_shifts(T, a) -> torch.Tensor:
    gen = torch.Generator().manual_seed(a.seed)
    shifts = gauge(AlignedOperator(T), torch.rand(T.range_shape[0], 2, generator=gen, dtype=torch.float64) * 2 - 1)
    return shifts * (a.max_shift / shifts.abs().amax(dim=0))


def simulated(a) -> tuple:
    """indreg's operators make the data (``--projector indreg``)."""
    domain, T = geometry(a)
    template = phantoms.get("shepp_logan_3d", domain)
    target = phantoms.get("shepp_logan_3d_swirl", domain)
    shifts = random_shifts(T, a)
    angle = torch.tensor(math.radians(a.angle), dtype=torch.float64)
    series = [T(target), AlignedOperator(T, shifts)(target), AlignedOperator(T, shifts, angle)(target)]
    if math.isfinite(a.snr):
        series = [noise.add_white_noise(y, snr_db=a.snr, seed=a.seed)[0] for y in series]
    runs = [("aligned", series[0], "none", 0.0), ("shifted", series[1], "shifts", 0.0),
            ("shifted, axis rotated", series[2], "shifts+axis", a.angle)]
    return T, template, target, runs, shifts


def scipy_projections(volume: np.ndarray, tilts_deg, cell: float) -> np.ndarray:
    """``(tilts, y, x)``: the ``(x, y, z)`` volume turned about y by each tilt (cubic splines) and summed along z,
    in indreg's tilt convention (checked against ``TiltSeriesTransform``: 1.5 % apart on a 32^3 phantom)."""
    from scipy import ndimage

    return np.stack([ndimage.rotate(volume, -t, axes=(0, 2), reshape=False, order=3).sum(axis=2).T * cell
                     for t in tilts_deg])


def astra_projections(volume: np.ndarray, tilts_deg, cell: float, python: str) -> np.ndarray:
    """``(tilts, y, x)`` by ASTRA's CPU projector slice by slice (``scripts/astra_projections.py``, run by ``python``,
    a Python that has ``astra-toolbox``), in indreg's tilt convention: ASTRA's angle ``-theta`` (matched
    ``TiltSeriesTransform`` to 6e-7 relative on the 32^3 phantom)."""
    import subprocess
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        files = [str(Path(tmp) / name) for name in ("volume.npy", "tilts.npy", "out.npy")]
        np.save(files[0], volume)
        np.save(files[1], -np.asarray(tilts_deg, dtype=np.float64))
        script = Path(__file__).with_name("astra_projections.py")
        subprocess.run([python, str(script), files[0], files[1], str(cell), files[2]], check=True)
        return np.load(files[2])


def microscope(stack: np.ndarray, axis_deg: float, shifts: np.ndarray, level: float, seed: int) -> np.ndarray:
    """Every image turned about its centre so that the tilt axis lies at ``axis_deg`` (indreg's angle:
    ``scipy.ndimage.rotate`` by ``-axis_deg``), then shifted by ``shifts`` ``(tilts, [across, along])`` px (cubic),
    plus Gaussian noise of ``level`` times the largest datum."""
    from scipy import ndimage

    out = np.stack([ndimage.shift(ndimage.rotate(img, -axis_deg, reshape=False, order=3), (s[1], s[0]), order=3)
                    for img, s in zip(stack, shifts)])
    rng = np.random.default_rng(seed)
    return out + level * np.abs(out).max() * rng.standard_normal(out.shape)


#: A gold bead (``--phantom beads``): its value (the skull's is 1) and radius (normalised frame: 1.6 voxels at 64^3).
BEAD_VALUE, BEAD_RADIUS = 4.0, 0.05


def specimen(a) -> tuple:
    """The ellipsoids of the target: the 3D Shepp-Logan, with ``--phantom beads`` also ``--beads`` gold beads (the
    fiducial markers of electron tomography, dense against the specimen) at random (seeded) within ``|x| < 0.5``,
    ``|y| < 0.7``, ``|z| < 0.5`` of the half-extent, so every bead stays on the detector at every tilt."""
    if a.phantom == "shepp-logan":
        return phantoms.SHEPP_LOGAN_3D_ELLIPSOIDS
    gen = np.random.default_rng(a.seed + 1)
    beads = [(BEAD_VALUE, BEAD_RADIUS, BEAD_RADIUS, BEAD_RADIUS, *(gen.uniform(-1, 1, 3) * [0.5, 0.7, 0.5]), 0, 0, 0)
             for _ in range(a.beads)]
    return phantoms.SHEPP_LOGAN_3D_ELLIPSOIDS + tuple(beads)


def external(a) -> tuple:
    """Data made outside indreg (``--projector scipy`` or ``astra``): the target the specimen's ellipsoids, the
    template the Shepp-Logan's deformed by suite ET-3D's swirl and bend, both blurred (an atlas has no gold: the
    beads are in the data only)."""
    from scipy import ndimage

    domain, T = geometry(a)
    rows = specimen(a)
    target = torch.from_numpy(ndimage.gaussian_filter(phantoms.ellipsoid_phantom(domain, rows).double().numpy(),
                                                      a.blur))
    template = ndimage.gaussian_filter(phantoms.get("shepp_logan_3d_swirl", domain).double().numpy(), a.blur)
    if a.template_turn:
        template = ndimage.rotate(template, a.template_turn, axes=(0, 1), reshape=False, order=3)
    shifts = random_shifts(T, a)
    tilts = np.degrees(T.geometry.angles.numpy())
    clean = (astra_projections(target.numpy(), tilts, domain.cell_sides[2], a.astra_python) if a.projector == "astra"
             else scipy_projections(target.numpy(), tilts, domain.cell_sides[2]))
    runs = [("unturned, unshifted", microscope(clean, 0.0, 0 * shifts.numpy(), a.noise, a.seed), "none", 0.0)]
    runs += [(f"turned {angle:+g} deg, shifted", microscope(clean, angle, shifts.numpy(), a.noise, a.seed),
              "shifts+axis", angle) for angle in a.angles]
    return T, torch.from_numpy(template), target, [(n, torch.from_numpy(d), al, an) for n, d, al, an in runs], shifts


def main():
    a = arguments()
    if a.undetermined:
        from indreg.alignment import solver

        solver.UNDETERMINED = a.undetermined
    T, template, target, runs, true = (simulated if a.projector == "indreg" else external)(a)
    options = dict(sigma=3.0, num_steps=10, gamma=1e-6, step_size=0.1, max_iter=a.iterations,
                   velocity_factor=a.velocity_factor, interpolation="compose", target=target, holdout=a.holdout)
    specimen_name = "" if a.projector == "indreg" else f"{a.phantom}{f' ({a.beads})' if a.phantom == 'beads' else ''}, "
    print(f"{a.size}^3, {specimen_name}{T.range_shape[0]} tilts, shifts up to {a.max_shift} px, projector {a.projector}, "
          f"template turned {a.template_turn} deg, {a.iterations} iterations, velocity_factor {a.velocity_factor}, "
          f"{torch.get_num_threads()} thread(s)")
    print(f"policy where the stack does not determine the angle: {a.undetermined or 'default'}; held out: every "
          f"{a.holdout}-th tilt" if a.holdout else "")
    print("| projector | template turned (deg) | series | align | shifts RMS error across / along (px) | "
          "axis angle error (deg) | angle s.e. (deg) | angle from (stack s.e., deg) | SSIM | residual | held-out "
          "residual | warnings | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, data, align, angle in runs:
        t0 = time.perf_counter()
        r = indreg.register(template, data, T, align=align, **options)
        seconds = time.perf_counter() - t0
        errors = "- | - | - | -"
        if r.alignment:
            rms = (torch.tensor(r.alignment["shifts_px"], dtype=torch.float64) - true).pow(2).mean(0).sqrt()
            se = r.alignment.get("axis_angle_se_deg")
            errors = (f"{rms[0]:.3f} / {rms[1]:.3f} | "
                      + (f"{r.alignment['axis_angle_deg'] - angle:+.3f} | " if align == "shifts+axis" else "- | ")
                      + (f"{se:.3f}" if se is not None else ("-" if align != "shifts+axis" else "inf"))
                      + f" | {source(r.alignment)}")
        held = r.holdout.get("holdout_residual")
        print(f"| {a.projector} | {a.template_turn:g} | {name} | {align} | {errors} | {r.ssim:.4f} | "
              f"{r.residual:.4f} | {'-' if held is None else f'{held:.4f}'} | {r.warnings} | {seconds:.0f} |",
              flush=True)


def source(alignment: dict) -> str:
    """Where the angle came from, with the stack estimate's standard error (``inf``: flat; ``-``: not run)."""
    if "axis_angle_source" not in alignment:
        return "-"
    se = alignment.get("axis_angle_stack_se_deg", "-")
    return f"{alignment['axis_angle_source']} ({se if se in ('-', None) else f'{se:.3f}'})".replace("None", "inf")


if __name__ == "__main__":
    main()
