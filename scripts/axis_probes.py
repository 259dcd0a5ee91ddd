"""Template-free estimates of the tilt-axis angle on series made outside indreg (issue #39; docs/alignment.md,
"The angle on data made outside indreg"): measurements, not a method of indreg.

Two criteria, each scanned over trial angles ``alpha`` (indreg's convention, docs/alignment.md), the estimate at
the minimum refined by a parabola through it and its neighbours:

- ``common-lines``: in a parallel beam every tilt image projected onto the tilt axis gives the same profile (the
  mass of each slice), up to a shift along the axis and a scale. The profile of image ``k`` along the trial
  direction ``(-sin alpha, cos alpha)`` (across, along) is taken in Fourier space, ``F_k(rho) = sum_p I_k(p)
  w(tau_p - c_k) exp(-2 pi i rho tau_p)`` with ``tau_p`` the pixel's coordinate along the trial axis (an exact sum
  over the pixels: no interpolation of the data, so the noise's share of the criterion does not depend on
  ``alpha``), ``w`` a cos^2 window of half-width ``rows / 2 - max shift - margin`` placed at each tilt's shift
  ``c_k`` (content that leaves the detector along the axis stays out; ``c_k`` chosen for the least misfit),
  ``rho`` up to ``band`` cycles per pixel. The criterion is the relative misfit of ``F_k = a_k exp(-2 pi i rho c_k)
  M`` (a scale ``a_k``, a shift ``c_k`` per tilt, one profile ``M``), fitted by alternation.
- ``sirt``: the consistency of the stack with a reconstruction through the trial angle: ``rounds`` of nonnegative
  SIRT and a re-fit of the shifts (``indreg.alignment.estimate``, gauge ``"translation"``), each trial angle from
  the cross-correlation start; the criterion is the last SIRT's relative residual.

- ``moments``: ``indreg.alignment.moments.estimate_axis_angle`` (the Helgason-Ludwig conditions of every detector row,
  orders ``0 .. --orders``, exact sums over the pixels, the shifts fitted, a chi-square scanned over the angle), its
  estimate, standard error, chi-square per degree of freedom and the tilts it used.
- ``valley`` (not a scan): the data's least-squares misfit ``(1/2) ||S_{s, alpha} T(turn_beta f) - g||^2`` (shifts
  re-fitted by ``indreg.alignment.estimate``) against the object ``f`` turned about the beam by ``--reference-turn``
  (as a deformation that took up a turn), then by ``beta`` (``scipy.ndimage.rotate``, cubic), at the truth
  ``(alpha, -turn)``, along the valley ``alpha + beta = const`` where a turn of the axis and one of the object
  look alike, and across it.

The series: ``scripts/bench_alignment.py --projector scipy``'s (the Shepp-Logan blurred by one voxel, projected by
``scipy.ndimage.rotate``, every image turned by ``scipy.ndimage.rotate`` and shifted, Gaussian noise), with the
shifts left out, only along the axis, or both ways; ``--phantom blobs`` projects 40 Gaussian blobs in a slab
instead (:func:`blobs`), a specimen whose slices' centres of mass wander along the axis.

    OMP_NUM_THREADS=1 python scripts/axis_probes.py                     # common lines, 32^3, a few seconds a row
    OMP_NUM_THREADS=1 python scripts/axis_probes.py --probe sirt --series shifted --noise 0 0.02 --angles 3
    OMP_NUM_THREADS=1 python scripts/axis_probes.py --probe valley --angles 3 --noise 0.02
    OMP_NUM_THREADS=1 python scripts/axis_probes.py --phantom blobs --series shifted --noise 0.02 --trials -1.5 1.5 0.25
    OMP_NUM_THREADS=1 python scripts/axis_probes.py --probe moments --series shifted --noise 0.02 --size 64 --blur 0
"""
from __future__ import annotations

import argparse
import math
import time
import types

import numpy as np
import torch

import bench_alignment as bench

SERIES = ("turned", "turned, shifted along", "turned, shifted")


def arguments():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--probe", choices=("common-lines", "sirt", "valley", "moments"), default="common-lines")
    p.add_argument("--size", type=int, default=32, help="volume side (cells)")
    p.add_argument("--angles", type=float, nargs="+", default=[3.0, -1.0], help="true tilt-axis angles (deg)")
    p.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.02], help="noise std / largest datum")
    p.add_argument("--series", choices=("all",) + tuple(s.split(", ")[-1].replace(" ", "-") for s in SERIES),
                   default="all", help="which shifts: none (turned), along, both (shifted)")
    p.add_argument("--trials", type=float, nargs=3, default=[-4.0, 4.0, 1.0], metavar=("FROM", "TO", "STEP"),
                   help="trial angles relative to the true one (deg)")
    p.add_argument("--band", type=float, default=0.15, help="common lines: highest frequency (cycles / px)")
    p.add_argument("--margin", type=float, default=3.0, help="common lines: window margin (px)")
    p.add_argument("--sirt-iters", type=int, default=100, help="sirt: SIRT iterations per round")
    p.add_argument("--reference-turn", type=float, default=2.0, help="valley: the reference's turn (deg)")
    p.add_argument("--phantom", choices=("shepp-logan", "blobs"), default="shepp-logan",
                   help="the specimen: bench_alignment's Shepp-Logan, or 40 Gaussian blobs in a slab (blobs)")
    p.add_argument("--blur", type=float, default=1.0, help="Gaussian blur of the Shepp-Logan (voxels; 0: sharp)")
    p.add_argument("--orders", type=int, default=2, help="moments: highest order of the conditions")
    p.add_argument("--projector", choices=("scipy", "astra"), default="scipy",
                   help="what projects the volume: scipy.ndimage.rotate (bench_alignment's), or ASTRA's CPU projector "
                        "slice by slice (scripts/astra_projections.py, run by --astra-python)")
    p.add_argument("--astra-python", default=".venv/bin/python", help="a Python with astra-toolbox and numpy")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


def blobs(T, seed: int) -> torch.Tensor:
    """40 Gaussian blobs (width 1.5 cells, heights 0.5 - 1) at random in a slab ``|x|, |y| < 0.7``, ``|z| < 0.35``
    of the half-extent: a specimen whose slices' centres of mass wander, as a real one's do."""
    gen = np.random.default_rng(seed)
    grid = torch.meshgrid(*T.domain.axes(), indexing="ij")
    half = [float(a.abs().max()) for a in T.domain.axes()]
    f = torch.zeros(T.domain.shape, dtype=torch.float64)
    cell = T.domain.cell_sides[0]
    for _ in range(40):
        c = gen.uniform(-1, 1, 3) * np.array([0.7, 0.7, 0.35]) * half
        r2 = sum((g - float(x)) ** 2 for g, x in zip(grid, c))
        f += gen.uniform(0.5, 1) * torch.exp(-r2 / (2 * (1.5 * cell) ** 2))
    return f


# ---------------------------------------------------------------------------------------------------- common lines
def along_axis(shape: tuple, alpha_deg: float) -> np.ndarray:
    """Every pixel's coordinate along the trial axis ``(-sin alpha, cos alpha)`` (across, along), pixels from the
    image's centre, flattened: ``(rows * columns,)``."""
    R, C = shape
    a = math.radians(alpha_deg)
    t, s = np.arange(R) - (R - 1) / 2, np.arange(C) - (C - 1) / 2
    return (-math.sin(a) * s[None, :] + math.cos(a) * t[:, None]).reshape(-1)


def profiles(stack: np.ndarray, alpha_deg: float, freqs: np.ndarray) -> np.ndarray:
    """``F_k(rho)`` ``(tilts, freqs)`` of every whole image along the trial axis (module docstring)."""
    tau = along_axis(stack.shape[1:], alpha_deg)
    return stack.reshape(len(stack), -1) @ np.exp(-2j * np.pi * freqs[:, None] * tau[None, :]).T


def common_profile_fit(F: np.ndarray, freqs: np.ndarray, rounds: int = 10) -> tuple:
    """Fit ``F_k = a_k exp(-2 pi i rho c_k) M`` by alternation (the shifts ``c_k`` first on a grid, then by
    Newton steps); returns ``(relative misfit, c)``."""
    w = 2j * np.pi * freqs[None, :]
    M, c = F.mean(0), np.zeros(len(F))
    grid = np.arange(-8, 8.01, 0.25)
    for r in range(rounds):
        if r == 0:
            phase = np.exp(2j * np.pi * freqs[None, :] * grid[:, None])
            c = grid[np.real(np.einsum("kf,gf,f->kg", F, phase, np.conj(M))).argmax(1)]
        for _ in range(3):
            z = F * np.exp(w * c[:, None]) * np.conj(M)[None]
            d1, d2 = np.real(w * z).sum(1), np.real(w ** 2 * z).sum(1)
            c = c - np.clip(d1 / np.where(d2 < 0, d2, -1e30), -0.5, 0.5)
        G = F * np.exp(w * c[:, None])
        a = np.real((G * np.conj(M)[None]).sum(1)) / np.real((M * np.conj(M)).sum())
        M = (a[:, None] * G).sum(0) / (a ** 2).sum()
    misfit = F * np.exp(w * c[:, None]) - a[:, None] * M[None]
    return float((np.abs(misfit) ** 2).sum() / (np.abs(F) ** 2).sum()), c


def windowed_misfits(stack: np.ndarray, alpha_deg: float, freqs: np.ndarray, M: np.ndarray, grid: np.ndarray,
                     half: float) -> tuple:
    """For every tilt and every window position ``c`` of ``grid``: the misfit of the profile windowed at ``c`` and
    moved back by ``c`` against ``a M`` (``a`` fitted), and its squared norm: ``(tilts, grid)`` each."""
    tau = along_axis(stack.shape[1:], alpha_deg)
    x = (tau[None, :] - grid[:, None]) / half
    w = np.where(np.abs(x) < 1, np.cos(np.pi * x / 2) ** 2, 0.0)                       # (grid, pixels)
    E = np.exp(-2j * np.pi * freqs[:, None] * tau[None, :]).T                         # (pixels, freqs)
    back = np.exp(2j * np.pi * freqs[None, :] * grid[:, None])                        # (grid, freqs)
    G = np.einsum("kp,gp,pf->kgf", stack.reshape(len(stack), -1), w, E, optimize=True) * back[None]
    norm = (np.abs(G) ** 2).sum(-1)
    return norm - np.real((G * np.conj(M)).sum(-1)) ** 2 / float((np.abs(M) ** 2).sum()), norm, G


def common_lines(stack: np.ndarray, alpha_deg: float, a) -> float:
    """The common-lines criterion at the trial angle (module docstring): the shifts and the profile from the whole
    images, then 4 rounds of every tilt's window position chosen on a 0.1 px grid for the least misfit against the
    common profile (the window moves with the shift) and the profile re-fitted."""
    R = stack.shape[1]
    freqs = np.arange(0, int(a.band * R) + 1) / R
    _, c = common_profile_fit(profiles(stack, alpha_deg, freqs), freqs)
    c = c - np.median(c)
    half = R / 2 - np.abs(c).max() - a.margin
    grid = np.arange(np.floor(c.min()) - 1, np.ceil(c.max()) + 1.01, 0.1)
    idx = np.abs(grid[None, :] - c[:, None]).argmin(1)
    k = np.arange(len(c))
    for _ in range(4):
        G = windowed_misfits(stack, alpha_deg, freqs, np.ones(len(freqs)), grid, half)[2][k, idx]
        scale = np.real((G * np.conj(G.mean(0))).sum(1))
        M = (scale[:, None] * G).sum(0) / (scale ** 2).sum()
        misfit, norm, _ = windowed_misfits(stack, alpha_deg, freqs, M, grid, half)
        idx = misfit.argmin(1)
    return float(misfit[k, idx].sum() / norm[k, idx].sum())


# ---------------------------------------------------------------------------------------------------- SIRT
def sirt_consistency(T, stack: np.ndarray, alpha_deg: float, a, rounds: int = 3) -> float:
    """The SIRT-consistency criterion at the trial angle (module docstring)."""
    from indreg.alignment import aligned, estimate, first_start
    from indreg.forward.sirt import sirt

    data = torch.from_numpy(stack)
    op, state = aligned(T, "shifts", "probe", "translation")
    op.angle = torch.tensor(math.radians(alpha_deg), dtype=torch.float64)
    for r in range(rounds + 1):
        x, history = sirt(op, data, num_iter=a.sirt_iters, nonneg=True)
        if r == rounds:
            return float(history["data_residual"][-1] / op.inner_data(data, data).sqrt())
        P = op.operator(x)
        start = first_start(op, state, P, data) if r == 0 else op.shifts
        op.shifts, _, _ = estimate(op, P, data, start, op.angle, False, kind=state.gauge)


# ---------------------------------------------------------------------------------------------------- the valley
def valley(T, f: torch.Tensor, stack: np.ndarray, angle: float, true: torch.Tensor, a) -> None:
    """Print the misfit at ``(alpha, beta)`` pairs along and across the valley (module docstring)."""
    from scipy import ndimage

    from indreg.alignment import aligned, estimate

    def turned(x: np.ndarray, beta: float) -> np.ndarray:
        return ndimage.rotate(x, beta, axes=(0, 1), reshape=False, order=3, mode="nearest")

    g, (op, _) = torch.from_numpy(stack), aligned(T, "shifts+axis", "probe")
    reference = turned(f.numpy(), a.reference_turn)
    print("| alpha (deg) | beta (deg) | where | misfit |")
    print("|---|---|---|---|")
    t = -a.reference_turn
    pairs = [(angle - d, t + d, "truth" if d == 0 else "along the valley") for d in (0.0, 1.0, 2.0, 3.0, 4.0)]
    pairs += [(angle, 0.0, "across"), (angle - 2.0, t, "across")]
    for alpha, beta, where in pairs:
        P = T(torch.from_numpy(turned(reference, beta))).double()
        s, an, _ = estimate(op, P, g, true, torch.tensor(math.radians(alpha), dtype=torch.float64), False, 20)
        print(f"| {alpha:+.2f} | {beta:+.2f} | {where} | {0.5 * float(((op.warp(P, s, an) - g) ** 2).sum()):.1f} |",
              flush=True)


def series_stacks(clean: np.ndarray, shifts: dict, a):
    """``(series, noise level, true angle, stack)`` for every chosen series, noise level and angle: ``clean``'s
    images turned by the angle and shifted as the series says (``bench.microscope``)."""
    chosen = [s for s in SERIES if a.series == "all" or s.split(", ")[-1].replace(" ", "-") == a.series]
    for name in chosen:
        for level in a.noise:
            for angle in a.angles:
                yield name, level, angle, bench.microscope(clean, angle, shifts[name], level, a.seed)


# ---------------------------------------------------------------------------------------------------- moments
def moments_table(T, clean: np.ndarray, shifts: dict, a) -> None:
    """The Helgason-Ludwig estimate (``indreg.alignment.moments.estimate_axis_angle``, its own scan: every degree over
    +-10, then every quarter around the least) on every chosen series, noise level and angle."""
    from indreg.alignment.moments import estimate_axis_angle

    theta = T.geometry.angles.numpy()
    print(f"moments (orders 0-{a.orders}, band {a.band}), {a.phantom}" + (f" blurred {a.blur:g}" if a.phantom ==
          "shepp-logan" else "") + f", {a.size}^3, projector {a.projector}, {len(theta)} tilts over +-60 deg, shifts "
          "up to 4 px")
    print("| series | noise | true angle (deg) | estimate (deg) | error (deg) | s.e. (deg) | chi2 / dof | tilts | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, level, angle, stack in series_stacks(clean, shifts, a):
        t0 = time.perf_counter()
        e = estimate_axis_angle(stack, theta, band=a.band, orders=a.orders)
        print(f"| {name} | {level:g} | {angle:+g} | {e.angle_deg:+.3f} | {e.angle_deg - angle:+.3f} | "
              f"{e.se_deg:.3f} | {e.chi2_per_dof:.2f} | {int(e.tilts_used.sum())} | "
              f"{time.perf_counter() - t0:.0f} |", flush=True)


# ---------------------------------------------------------------------------------------------------- the table
def minimum(trials: np.ndarray, values: list) -> float:
    """The trial angle at the criterion's minimum, refined by a parabola through its neighbours."""
    i = min(max(int(np.argmin(values)), 1), len(values) - 2)
    lo, mid, hi = values[i - 1], values[i], values[i + 1]
    curvature = lo - 2 * mid + hi
    return float(trials[i] + (0.5 * (lo - hi) / curvature if curvature > 0 else 0.0))


def main():
    a = arguments()
    setup = types.SimpleNamespace(size=a.size, step=3.0, max_shift=4.0, seed=a.seed, blur=a.blur, noise=0.0,
                                  projector="scipy", template_turn=0.0, angles=[])
    T, _, target, _, true = bench.external(setup)
    if a.phantom == "blobs":
        target = blobs(T, a.seed)
    tilts = np.degrees(T.geometry.angles.numpy())
    clean = (bench.scipy_projections(target.numpy(), tilts, T.domain.cell_sides[2]) if a.projector == "scipy" else
             bench.astra_projections(target.numpy(), tilts, T.domain.cell_sides[2], a.astra_python))
    along = true.numpy().copy()
    along[:, 0] = 0
    shifts = {SERIES[0]: 0 * along, SERIES[1]: along, SERIES[2]: true.numpy()}
    if a.probe == "valley":
        print(f"valley, {a.size}^3, {T.range_shape[0]} tilts, turned {a.angles[0]:+g} deg and shifted, noise "
              f"{a.noise[-1]:g}, reference turned {a.reference_turn:+g} deg")
        valley(T, target, bench.microscope(clean, a.angles[0], true.numpy(), a.noise[-1], a.seed), a.angles[0], true, a)
        return
    if a.probe == "moments":
        moments_table(T, clean, shifts, a)
        return
    print(f"{a.probe}, {a.phantom}, {a.size}^3, {T.range_shape[0]} tilts over +-60 deg, shifts up to 4 px, "
          f"trials {a.trials}")
    print("| series | noise | true angle (deg) | estimate (deg) | criterion at the true angle / at its minimum | s |")
    print("|---|---|---|---|---|---|")
    for name, level, angle, stack in series_stacks(clean, shifts, a):
        trials = angle + np.arange(a.trials[0], a.trials[1] + 1e-9, a.trials[2])
        t0 = time.perf_counter()
        values = [common_lines(stack, x, a) if a.probe == "common-lines" else sirt_consistency(T, stack, x, a)
                  for x in trials]
        at_true = values[int(np.argmin(np.abs(trials - angle)))]
        print(f"| {name} | {level:g} | {angle:+g} | {minimum(trials, values):+.3f} | "
              f"{at_true:.3e} / {min(values):.3e} | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
