"""A real tilt series, from the raw stack to the registered volume (docs/real_data.md).

The data: a HAADF-STEM tilt series of a rod-shaped specimen (77 tilts, -76..76 degrees in steps of 2, 256 x 256
pixels of 3.36 nm) that NIST ships as test data in the wheel of ``etspy`` 1.3.0 (NIST Public License: US federal
work, no copyright in the US; the licence text is in the wheel). Without ``--data`` it is fetched once with
``pip download etspy==1.3.0 --no-deps`` (66 MB) and its ``etspy/tests/test_data/HAADF*`` files are unpacked into
``--cache`` (nothing is installed); with ``--data DIR`` (a folder holding ``HAADF.mrc``, ``HAADF.rawtlt`` and
optionally ``HAADF_Aligned.hspy``) it runs offline.

Steps (each prints what it found): read the raw stack and its angles; check the tilt axis (which way it runs, how
consistent the stack is), raw vs aligned stack; the background (the raw int16 stack's offset); bin ``--stack``
(``raw``, the default, or etspy's ``aligned``) to ``--size`` detector pixels; a template "from an earlier scan" (a
smoothed, segmented SIRT reconstruction from the even tilts, reconstructed in voxel units as other programs do, so
not in the data's units, and turned by ``--misalign`` degrees; from the raw stack the even tilts are aligned first
by ``indreg.alignment.projection_matching``, whose shifts keep the tilt axis' offset); the data: a sparse subset of
the odd tilts within ``--max-angle`` (every ``--fit-every``-th), the odd tilts between them held out for validation;
registration (``--model``, default ``residual``: LDDMM plus a TV-regularised intensity residual whose weight the
validation tilts choose) with ``template_scale="auto"``, ``background="auto"``, ``holdout``, the default (relative) ``gamma``
and step, and from the raw stack ``align=--align``, ``align_gauge=--align-gauge`` (default ``none``: the template
fixes the frame, the shifts carry the axis' offset and the data's translation against it) and
``align_interpolation=--align-interpolation`` (default ``cubic``, also for projection matching); the estimated
shifts compared with etspy's recorded ones; FBP / SIRT / TV from the same sparse tilts (through the registration's
shifts); all scored by the relative residual on the odd tilts that none of them used (there is no ground truth).

    python examples/real_data_haadf.py [--data DIR] [--out DIR] [--stack raw|aligned] [--size 64] [--iters 100]

Outputs in ``--out``: ``metrics.json``, ``figure.png`` (central slices), ``alignment.png`` (the shifts against
etspy's; from the raw stack), the volumes as ``.npy`` and ``.mrc`` (voxel size in Angstrom).

Convention: the stack as stored is ``(tilt, row, column)`` with the tilt axis along the columns' index (the
image's X; the acquisition log says "Tilt Axis Angle: 90"); indreg's layout has it along the rows
(``tilt_axis_angle=90`` turns it, ``indreg.alignment.tilt_axis``). Volumes ``(nx, ny, nz)``: y the tilt axis (the rod's
length), z the beam at tilt 0; the domain is in nm.
"""
from __future__ import annotations

import sys
from pathlib import Path

#: The data folder's files (``--data``), and how to get them: checked before the imports below (~10 s of torch).
DATA_FILES = ("HAADF.mrc", "HAADF.rawtlt")
FETCH_HINT = ("pass --data a folder holding HAADF.mrc and HAADF.rawtlt (the etspy 1.3.0 wheel's etspy/tests/test_data/"
              "HAADF*: pip download etspy==1.3.0 --no-deps, then unzip the .whl), or leave --data out to download them "
              "into --cache")


def missing_data(argv) -> str | None:
    """The one-line error of a ``--data`` folder without :data:`DATA_FILES` (with :data:`FETCH_HINT`), else None
    (no ``--data``: they are fetched into ``--cache``; ``--reprint`` reads no data)."""
    import argparse

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--data", type=Path)
    p.add_argument("--reprint", action="store_true")
    given = p.parse_known_args(argv)[0]
    missing = [] if given.data is None or given.reprint else [f for f in DATA_FILES if not (given.data / f).is_file()]
    return f"{given.data} has no {' or '.join(missing)}: {FETCH_HINT}" if missing else None


if __name__ == "__main__" and missing_data(sys.argv[1:]):
    sys.exit(f"real_data_haadf.py: error: {missing_data(sys.argv[1:])}")

import argparse  # noqa: E402 (after the data check)
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import indreg   # first: it sets OMP_WAIT_POLICY=PASSIVE before torch loads OpenMP (indreg._openmp; 2 threads)
import numpy as np
import torch
from scipy import ndimage

from indreg import alignment
from indreg.domain import ImageDomain
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform, fbp, sirt, tv_reconstruction
from indreg.alignment.operator import AlignedOperator
from indreg.registration.run import count_halvings
from indreg.forward.tv import intensity_scale
from indreg.units import border_level, check_offset, prepare
from indreg.alignment.tilt_axis import align_tilt_axis, check_tilt_axis
from indreg.registration.extrapolation import blend, choose_extrapolation
from indreg.evaluation.score import relative_residual

sys.path.insert(0, str(Path(__file__).resolve().parent))   # its companion, haadf_files.py
from evaluation_steps import evaluation_png, extrapolation_table, flagged_voxels, split_check, write_scored  # noqa
from haadf_files import (ALIGNED_KEY, PIXEL_NM, SHIFTS_KEY, TILT_AXIS_ANGLE, WHEEL, alignment_figure,  # noqa
                         axis_offset, bilinear, bin_stack, compare_shifts, etspy_frame, fetch, figure, read_aligned,
                         read_etspy_shifts, read_raw, save, say, scale_bar_nm)

log = logging.getLogger("indreg")



# ------------------------------------------------------------------------------------------------ checks
def axis_checks(raw: np.ndarray, aligned) -> dict:
    """The tilt-axis check (``indreg.alignment.tilt_axis.check_tilt_axis``) of the stacks as stored (the check subtracts
    the level of the images' outer frame: an offset would add the same to every profile and hide their
    differences)."""
    stacks = {"raw": raw} if aligned is None else {"raw": raw, "aligned": aligned}
    out = {}
    for name, s in stacks.items():
        check = check_tilt_axis(s)
        say(f"  {name:22s} {check.describe()}")
        out[name] = check.metrics()
    return out


def background_report(stack: np.ndarray, name: str) -> dict:
    """The stack's levels: its border level (``background='auto'``), median and range; logs indreg's offset
    warning when it looks offset."""
    g = torch.from_numpy(stack)
    level, median = border_level(g), float(g.median())
    say(f"  {name}: dtype range {stack.min():.0f}..{stack.max():.0f}, median {median:.1f}, border level "
        f"(median of the outermost columns) {level:.1f}")
    check_offset(g, "background")
    return {"border_level": level, "median": median, "min": float(stack.min()), "max": float(stack.max())}


# ------------------------------------------------------------------------------------------------ geometry
def volume_domain(size: int, depth: int, cell: float) -> ImageDomain:
    """``(size, size, depth)`` cubic cells of side ``cell``, centred (x across the rod, y the tilt axis, z the
    beam at tilt 0)."""
    shape = (size, size, depth)
    return ImageDomain(shape, tuple(-cell * n / 2 for n in shape), tuple(cell * n / 2 for n in shape))


def operator(domain: ImageDomain, angles: np.ndarray) -> TiltSeriesTransform:
    """The tilt series of ``domain`` at ``angles`` (radians), columns as wide as the voxels."""
    half = domain.shape[0] * domain.cell_sides[0] / 2
    geometry = TiltSeriesGeometry(torch.as_tensor(angles), det_count=domain.shape[0], det_min=-half, det_max=half,
                                  angle_unit="rad")
    return TiltSeriesTransform(domain, geometry)


def handedness(data: np.ndarray, angles: np.ndarray, domain: ImageDomain, iters: int = 30) -> dict:
    """SIRT with the angles as given and negated (the tilt axis turned by +90 or by -90 degrees): the two fit the
    data equally and are mirror images of each other (z -> -z), since negating every angle of a single-axis series
    is the same as mirroring the specimen along the beam. The data cannot tell the sign; it only sets the
    volume's handedness, which matters against a template from elsewhere."""
    y = torch.from_numpy(data)
    x = {}
    out = {}
    for sign in (1, -1):
        T = operator(domain, sign * angles)
        x[sign], _ = sirt(T, y, num_iter=iters, nonneg=True)
        out[f"residual_{'as_given' if sign == 1 else 'negated'}"] = residual(T, x[sign], y)
    mirror = torch.flip(x[-1], dims=(-1,))
    out["mirror_difference"] = float((mirror - x[1]).norm() / x[1].norm())
    return out


def residual(T, x: torch.Tensor, y: torch.Tensor) -> float:
    """``||T x - y|| / ||y||`` in the data inner product: ``indreg.evaluation.score.relative_residual``, the score
    ``indreg-score`` prints (float64)."""
    return relative_residual(T, x, y)


# ------------------------------------------------------------------------------------------------ split
def split_tilts(angles: np.ndarray, fit_every: int = 4, max_angle: float = 90.0) -> dict:
    """Indices of the tilts (``angles`` in radians): ``template`` the even ones; of the odd ones within
    ``max_angle`` degrees, every ``fit_every``-th the ``fit`` and the ones halfway between them ``validation``
    (held out during the fits); every other odd tilt is ``test`` (used by nothing)."""
    odd = np.arange(1, len(angles), 2)
    inside = odd[np.abs(np.degrees(angles[odd])) <= max_angle + 1e-9]
    pos = np.arange(len(inside))
    fit = inside[pos % fit_every == 0]
    validation = inside[pos % fit_every == fit_every // 2]
    test = np.setdiff1d(odd, np.concatenate([fit, validation]))
    return {"template": np.arange(0, len(angles), 2), "fit": fit, "validation": validation, "test": test}


# ------------------------------------------------------------------------------------------------ template
def align_template_scan(T, y: torch.Tensor, angles: np.ndarray, rounds: int, iters: int, interpolation: str) -> tuple:
    """The template's tilts aligned by ``indreg.alignment.projection_matching`` (shifts and tilt-axis angle; the
    shifts keep the axis' offset, so its SIRT volume sits on the axis, centred). Returns ``(SIRT volume, (shifts
    (px, with the offset), angle (deg), offset (px, :func:`axis_offset`)))``."""
    A, x, records = alignment.projection_matching(T, y, "shifts+axis", rounds, iters, interpolation)
    shifts, offset = A.shifts.clone(), axis_offset(A.shifts.numpy(), angles)
    say(f"  projection matching: SIRT residual, largest shift update (px) per round {np.round(records, 3).tolist()}"
        f"; tilt-axis angle {math.degrees(float(A.angle)):.3f} deg, axis offset {offset:.3f} px")
    return x, (shifts.numpy(), math.degrees(float(A.angle)), offset)


def make_template(data: np.ndarray, angles: np.ndarray, shape: tuple, misalign: float, iters: int = 50,
                  smooth: float = 0.5, classes: int = 5, align_rounds: int = 0, interpolation: str = "cubic",
                  dtype: torch.dtype = torch.float64) -> tuple:
    """An "earlier scan": SIRT of ``data`` (background removed) on unit voxels (as IMOD / astra reconstruct, so
    its intensities are per voxel length, not per nm), smoothed by ``smooth`` voxels, segmented into ``classes``
    phases (multi-Otsu: vacuum, the rod's dim part, its bright bands) with each phase's mean, smoothed again;
    turned by ``misalign`` degrees about the beam (a specimen mounted differently). With ``align_rounds`` the
    tilts are aligned first (:func:`align_template_scan`); SIRT runs in ``dtype``. Returns ``(template, sirt volume,
    the alignment's (shifts (px), angle (deg), axis offset (px)) or None)``."""
    from skimage.filters import threshold_multiotsu

    unit = ImageDomain(shape, tuple(-n / 2 for n in shape), tuple(n / 2 for n in shape))
    T, y, found = operator(unit, angles), torch.from_numpy(data).to(dtype), None
    if align_rounds:
        x, found = align_template_scan(T, y, angles, align_rounds, iters, interpolation)
    else:
        x, _ = sirt(T, y, num_iter=iters, nonneg=True)
    v = ndimage.gaussian_filter(x.double().numpy(), smooth)
    thresholds = threshold_multiotsu(v, classes=classes)
    labels = np.digitize(v, thresholds)
    means = [0.0] + [float(v[labels == k].mean()) for k in range(1, classes)]
    template = ndimage.gaussian_filter(np.take(means, labels), smooth)
    if misalign:
        template = ndimage.rotate(template, misalign, axes=(0, 1), reshape=False, order=1)
    say(f"  SIRT of {len(angles)} even tilts on unit voxels ({iters} iterations), phases at {thresholds.round(1)}: "
        f"{[int((labels == k).sum()) for k in range(classes)]} voxels, means {np.round(means, 1)}; "
        f"turned by {misalign:g} deg")
    return template, x.double().numpy(), found


# ------------------------------------------------------------------------------------------------ baselines
def unwarped(T, y: torch.Tensor) -> tuple:
    """``(T, y)``, or for an ``AlignedOperator`` its plain operator and the data moved back, ``S_{s, alpha}^{-1} y =
    S_{s', -alpha} y`` with ``s' = -R(-alpha) s`` (square pixels): for FBP, which needs a plain ray transform."""
    if not isinstance(T, AlignedOperator):
        return T, y
    c, s = math.cos(float(T.angle)), math.sin(float(T.angle))
    back = -T.shifts @ torch.tensor([[c, -s], [s, c]], dtype=torch.float64)   # rows: -R(-alpha) s_k
    return T.operator, T.warp(y, back, -T.angle)


def baselines(T_fit, y_fit: torch.Tensor, T_val, y_val: torch.Tensor, sirt_iters=(10, 25, 50, 100, 200),
              tv_mus=(1.0, 10.0, 100.0, 1000.0), tv_iters: int = 200) -> dict:
    """FBP (Hamming, 0.4, the app's), SIRT (nonnegative, iterations chosen by the validation tilts) and TV
    (nonnegative, ``mu`` relative to the data's intensity unit chosen by the validation tilts) from the fit
    tilts. The default ``tv_mus`` bracket the validation residual's minimum on both stacks (100 x u; 0.0312 raw,
    0.0300 aligned, against 0.0336 / 0.0313 at 1 x u and 0.0370 / 0.0396 at 1000 x u: docs/real_data.md, section
    8). Returns ``{name: (volume, info)}``."""
    out = {"FBP": (fbp(*unwarped(T_fit, y_fit)), {})}
    return {**out, **tuned_sirt_tv(T_fit, y_fit, T_val, y_val, sirt_iters, tv_mus, tv_iters, bilinear(T_fit))}


def tuned_sirt_tv(T_fit, y_fit: torch.Tensor, T_val, y_val: torch.Tensor, sirt_iters, tv_mus, tv_iters: int,
                  T_sirt=None) -> dict:
    """``{"SIRT": (volume, info), "TV": (volume, info)}``: nonnegative SIRT stopped at the iteration count of
    ``sirt_iters`` (through ``T_sirt``, default ``T_fit``) and nonnegative TV at the weight of ``tv_mus`` (times the
    data's intensity unit) whose volumes predict the validation data best: each baseline's parameter chosen on the
    validation angles, as the registration's are."""
    best, x, done = None, None, 0
    for n in sirt_iters:
        x, _ = sirt(T_fit if T_sirt is None else T_sirt, y_fit, num_iter=n - done, x0=x, nonneg=True)
        done, r = n, residual(T_val, x, y_val)
        say(f"    SIRT {n:4d} iterations: validation residual {r:.4f}")
        if best is None or r < best[1]["validation_residual"]:
            best = (x.clone(), {"iterations": n, "validation_residual": r})
    out = {"SIRT": best}
    u, best, norms = intensity_scale(T_fit, y_fit), None, None
    for mu in tv_mus:   # the steps' norms from the first weight's run (the same operator)
        x, history = tv_reconstruction(T_fit, y_fit, mu=mu * u, num_iter=tv_iters, nonneg=True, norms=norms)
        norms = history["norms"]
        r = residual(T_val, x, y_val)
        say(f"    TV mu = {mu:g} x {u:.4g}: validation residual {r:.4f}")
        if best is None or r < best[1]["validation_residual"]:
            best = (x, {"mu_relative": mu, "mu": mu * u, "iterations": tv_iters, "validation_residual": r})
    out["TV"] = best
    return out


# ------------------------------------------------------------------------------------------------ alignment
def shifts_of(T, x: torch.Tensor, y: torch.Tensor, angle: float, gauge: str, interpolation: str) -> np.ndarray:
    """The shifts of the tilts ``y`` against the projection of ``x`` (cross-correlation, then
    ``indreg.alignment.estimate`` with the angle kept), in the registration's ``gauge``: for tilts no fit saw."""
    A = AlignedOperator(T, angle=angle, interpolation=interpolation)
    P = T(x)
    start = alignment.gauge(A, alignment.coarse_shifts(A, P, y), gauge)
    return alignment.estimate(A, P, y, start, A.angle, kind=gauge)[0].numpy()


def aligned_operators(result, T: dict, Y: dict, rows: np.ndarray, tilts: dict) -> dict:
    """The operators of the fit, validation and test tilts through the registration's alignment: its shifts for
    the tilts it saw, for the test tilts shifts fitted against the registered volume (:func:`shifts_of`)."""
    a = result.alignment
    shifts, axis = np.asarray(a["shifts_px"]), np.radians(a["axis_angle_deg"])
    say(f"  alignment: axis angle {a['axis_angle_deg']:.3f} deg, shifts RMS "
        f"{np.sqrt((shifts ** 2).mean(axis=0)).round(3).tolist()} px [across, along], {a['at_bound']} at their bound")
    fitted = {k: shifts[np.isin(rows, tilts[k])] for k in ("fit", "validation")}
    fitted["test"] = shifts_of(T["test"], result.deformed.double(), Y["test"], axis, a["gauge"], a["interpolation"])
    return {k: AlignedOperator(T[k], torch.as_tensor(v), axis, a["interpolation"]) for k, v in fitted.items()}


def score(volumes: dict, T: dict, Y: dict, chosen: dict) -> dict:
    """Every volume's relative residual on the test, validation and fit tilts (and the baselines' choices)."""
    scores = {}
    for name, v in volumes.items():
        x = torch.from_numpy(np.ascontiguousarray(v))
        s = scores[name] = {f"{k}_residual": residual(T[k], x, Y[k]) for k in ("test", "validation", "fit")}
        s.update(chosen.get(name, {}))
        say(f"  {name:10s} test {s['test_residual']:.4f}   validation {s['validation_residual']:.4f}   "
            f"fit {s['fit_residual']:.4f}")
    return scores


# ------------------------------------------------------------------------------------------------ pipeline
class Parts:
    """CPU seconds (``time.process_time``, all threads) and wall seconds (``time.perf_counter``) of the
    walk-through's parts: ``done(name)`` ends the part begun at the last call."""

    def __init__(self):
        self.last, self.seconds, self.wall = (time.process_time(), time.perf_counter()), {}, {}

    def done(self, name: str) -> None:
        now = (time.process_time(), time.perf_counter())
        self.seconds[name] = self.seconds.get(name, 0.0) + now[0] - self.last[0]
        self.wall[name] = self.wall.get(name, 0.0) + now[1] - self.last[1]
        self.last = now

    def line(self) -> str:
        """``name wall s (CPU s)`` per part."""
        return ", ".join(f"{k} {self.wall[k]:.0f} s ({v:.0f} CPU)" for k, v in self.seconds.items())


def run(folder: Path, out: Path, size: int = 64, depth: int = 64, iters: int = 60, sigma_cells: float = 3.0,
        num_steps: int = 10, misalign: float = 5.0, fit_every: int = 2, max_angle: float = 40.0,
        stack: str = "raw", align: str = "shifts", align_gauge: str = "none", align_interpolation: str = "cubic",
        align_rounds: int = 8,
        rescale: float = 1.0,
        gamma_rel: float | None = None, classes: int = 5, smooth: float = 0.5, baselines_too: bool = True,
        quick: bool = False, model: str = "residual", interpolation: str = "reinterpolate",
        dtype: str = "float32", extrapolation: bool = False) -> dict:
    """The whole walk-through (module docstring); returns the metrics written to ``out/metrics.json``.
    ``stack``: ``"raw"`` (``HAADF.mrc``: the template's tilts aligned by :func:`align_template_scan`, the data by the
    registration's ``align``) or ``"aligned"`` (etspy's). ``rescale``: every count multiplied by it (unit
    invariance). ``quick``: fewer SIRT / TV iterations and candidates (the tests). ``model``: ``register``'s
    (``"residual"``, the default: LDDMM plus an intensity residual regularised by TV, its weight chosen on the
    validation tilts; ``"lddmm"``); ``interpolation``: the deformation's
    (``"reinterpolate"``, the paper's, as this page was measured); ``dtype``: the registration's, the template
    scan's SIRT and projection matching's, the baselines' (the scores are in float64); ``extrapolation``: the edge
    validation (``indreg.registration.extrapolation``) and its table on the test tilts (:func:`extrapolate`)."""
    if stack not in ("raw", "aligned"):
        raise ValueError(f"stack must be 'raw' or 'aligned', got {stack!r}")
    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    t0, wall0, parts = time.process_time(), time.perf_counter(), Parts()
    out.mkdir(parents=True, exist_ok=True)
    metrics = {"data": str(folder), "stack": stack, "rescale": rescale}

    say("1. the raw stack")
    raw, angles = read_raw(folder)
    aligned = read_aligned(folder)
    say(f"  HAADF.mrc: {raw.shape} (tilts, rows, columns), angles {np.degrees(angles[0]):g}..{np.degrees(angles[-1]):g}"
        f" deg, {len(angles)} tilts; aligned stack: {None if aligned is None else aligned.shape}")
    metrics["raw_shape"], metrics["num_tilts"] = list(raw.shape), len(angles)
    if stack == "aligned" and aligned is None:
        raise FileNotFoundError(f"--stack aligned needs {folder / 'HAADF_Aligned.hspy'}")
    raw, aligned = raw * rescale, None if aligned is None else aligned * rescale

    say("2. the tilt axis (as stored; indreg wants it along the rows' index)")
    metrics["tilt_axis_as_stored"] = axis_checks(raw, aligned)
    chosen = aligned if stack == "aligned" else raw

    say("3. the background")
    metrics["background_raw"] = background_report(raw, "raw stack")
    if aligned is not None:
        metrics["background_aligned"] = background_report(aligned, "aligned stack")

    say(f"4. the {stack} stack binned to {size} x {size} pixels, turned by -{TILT_AXIS_ANGLE:g} degrees "
        f"(tilt_axis_angle)")
    binned = bin_stack(chosen, size)
    factor = chosen.shape[1] // size
    cell = PIXEL_NM * chosen.shape[1] / size
    turned = align_tilt_axis(binned, TILT_AXIS_ANGLE)
    check = check_tilt_axis(turned)
    say(f"  turned: {check.describe()}; voxel {cell:g} nm")
    metrics["tilt_axis_turned"] = check.metrics()
    level = border_level(torch.from_numpy(turned))
    domain = volume_domain(size, depth, cell)
    hand = handedness(turned - level, angles, domain, iters=10 if quick else 30)
    say(f"  the angles' sign: SIRT residual on all tilts {hand['residual_as_given']:.6f} as given, "
        f"{hand['residual_negated']:.6f} negated; the two volumes mirror images (z -> -z) to "
        f"{hand['mirror_difference']:.1e} (relative): the data cannot tell the sign, only the handedness changes")
    metrics["handedness"] = hand

    parts.done("reading, checks, binning")
    say("5. the template: an earlier scan (even tilts" + (", aligned by projection matching)" if stack == "raw"
                                                          else ")"))
    tilts = split_tilts(angles, fit_every, max_angle)
    metrics["tilts_deg"] = {k: np.degrees(angles[v]).round(2).tolist() for k, v in tilts.items()}
    for k, v in tilts.items():
        say(f"  {k:10s} {len(v):2d} tilts: {np.degrees(angles[v]).round(0).astype(int).tolist()}")
    template, sirt_even, even = make_template(
        turned[tilts["template"]] - level, angles[tilts["template"]], domain.shape, misalign,
        iters=20 if quick else 50, smooth=smooth, classes=classes, align_rounds=align_rounds if stack == "raw" else 0,
        interpolation=align_interpolation, dtype=getattr(torch, dtype))
    recorded = read_etspy_shifts(folder)
    if even is not None:
        metrics["template_alignment"] = {"shifts_px": even[0].tolist(), "axis_angle_deg": even[1]}
    if even is not None and recorded is not None:
        metrics["template_shifts_vs_etspy"] = compare_shifts(
            even[0], etspy_frame(recorded[tilts["template"]], factor), operator(domain, angles[tilts["template"]]),
            factor)
        say(f"  the even tilts' shifts against etspy's: {metrics['template_shifts_vs_etspy']}")
    if even is not None:   # the axis' offset, measured over the template's full range
        metrics["axis_offset_raw_px"] = even[2] * factor
        if recorded is not None:
            metrics["etspy_axis_offset_raw_px"] = factor * axis_offset(
                etspy_frame(recorded[tilts["template"]], factor), angles[tilts["template"]])
        say(f"  the tilt axis lies {even[2] * factor:.2f} raw px off the detector's middle (across)")

    parts.done("template (projection matching from the raw stack, SIRT)")
    say("6. the data and the units")
    rows = np.sort(np.concatenate([tilts["fit"], tilts["validation"]]))
    holdout = [int(i) for i in np.flatnonzero(np.isin(rows, tilts["validation"]))]
    d = indreg.load(template, binned[rows], "tilt_series", angles=np.degrees(angles[rows]).tolist(),
                    tilt_axis_angle=TILT_AXIS_ANGLE, half_width=cell * max(size, depth) / 2)
    metrics["load"] = d.report()
    _, _, units = prepare(d.template, d.data, d.operator, background="auto")   # what register checks first
    say(f"  template as made: ||T I|| / ||g|| = {units.projection_ratio:.4g}, c = {units.scale_fit:.4g} (the data "
        f"after the background {units.background:.4g}); 1 / voxel side = {1 / cell:.4g} per nm")

    align = align if stack == "raw" else "none"
    say(f"7. registration: {len(tilts['fit'])} tilts fitted, {len(holdout)} held out, align={align!r}"
        + (f", align_gauge={align_gauge!r}" if align != "none" else ""))
    sigma = sigma_cells * cell
    extra = {} if gamma_rel is None else {"gamma_rel": gamma_rel}
    options = dict(sigma=sigma, num_steps=num_steps, max_iter=iters, interpolation=interpolation, dtype=dtype,
                   template_scale="auto", background="auto", holdout=holdout, align=align, align_gauge=align_gauge,
                   align_interpolation=align_interpolation, log_every=10, **extra)
    result = indreg.register(d.template, d.data, d.operator, model=model, progress=True, **options)
    reg_seconds = result.seconds
    parts.done("registration (the alignment and the model's finish included)")
    halvings = count_halvings(result.history)
    say(f"  {result.status} after {result.iterations} iterations ({reg_seconds:.0f} s): template_scale "
        f"{result.units.template_scale:.4g}, background {result.units.background:.4g}, residual {result.residual:.4f}, "
        f"held-out {result.holdout.get('holdout_residual', float('nan')):.4f} (best "
        f"{result.holdout.get('holdout_best_residual', float('nan')):.4f} at iteration "
        f"{result.holdout.get('holdout_best_iteration')}), min Jacobian {result.min_jacobian:.3f}, {halvings} step "
        f"halvings")
    finish = getattr(result.problem, "finish_info", {})
    if finish:
        unit = finish["unit"]   # the model's mu per residual_tv
        tried = {f"{mu / unit:.0e}": round(v, 4) for mu, v in finish["holdout_by_weight"].items()}
        say(f"  the residual's finish ({finish['iterations']} Chambolle-Pock iterations, TV anchored at the deformed "
            f"template): residual_tv {finish['residual_tv'] / unit:.0e} chosen by the held-out tilts of {tried}; "
            f"kept: the {finish['chosen']}'s result (the loop's held-out {finish['holdout_loop']:.4f})")
        finish = {"residual_tv": finish["residual_tv"] / unit, "holdout_by_weight": tried, "chosen": finish["chosen"],
                  "holdout_loop": finish["holdout_loop"]}
    metrics["registration"] = {"status": result.status, "finish": finish, "iterations": result.iterations, "seconds": reg_seconds,
                               "model": model, "interpolation": interpolation,
                               "sigma_nm": sigma, "num_steps": num_steps, "template_scale": result.units.template_scale,
                               "background": result.units.background, "scale_fit": result.units.scale_fit,
                               "projection_ratio": result.units.projection_ratio, "data_scale": result.units.data_scale,
                               "gamma_rel": gamma_rel, "terms": result.terms,
                               "residual": result.residual, "min_jacobian": result.min_jacobian, "halvings": halvings,
                               "warnings": result.warnings, **result.holdout}
    y = torch.from_numpy(turned - result.units.background)
    T = {k: operator(domain, angles[v]) for k, v in tilts.items()}
    Y = {k: y[v] for k, v in tilts.items()}
    if result.alignment:
        metrics["alignment"] = result.alignment
        T = aligned_operators(result, T, Y, rows, tilts)
        if recorded is not None:
            ours, theirs = np.asarray(result.alignment["shifts_px"]), etspy_frame(recorded[rows], factor)
            metrics["shifts_vs_etspy"] = compare_shifts(ours, theirs, operator(domain, angles[rows]), factor)
            alignment_figure(ours, theirs, operator(domain, angles[rows]), factor, out / "alignment.png")
            say(f"  the fitted tilts' shifts against etspy's: {metrics['shifts_vs_etspy']}")

    parts.done("units, the test tilts' shifts")
    base = {}
    if baselines_too:
        say("8. baselines from the same fit tilts" + (" (through the registration's shifts)" if result.alignment
                                                      else ""))
        tb = time.process_time()
        base = baselines(T["fit"], Y["fit"].to(getattr(torch, dtype)), T["validation"],
                         Y["validation"].to(getattr(torch, dtype)),
                         sirt_iters=(10, 25) if quick else (10, 25, 50, 100, 200),
                         tv_mus=(0.1,) if quick else (1.0, 10.0, 100.0, 1000.0), tv_iters=20 if quick else 200)
        metrics["baselines_cpu_seconds"] = time.process_time() - tb
        parts.done("baselines (FBP, SIRT, TV, parameters chosen on the validation tilts)")

    say("9. scores on the test tilts (used by none of them; no ground truth exists)")
    volumes = {"template": (d.template * result.units.template_scale).numpy(),
               "registered": result.deformed.double().numpy(),
               **{k: v[0].double().numpy() for k, v in base.items()}}
    metrics["scores"] = score(volumes, T, Y, {k: v[1] for k, v in base.items()})

    evaluate(metrics, result, base, T, Y, domain, out)
    if extrapolation:
        say("11. which volume to trust on the missing range: the edge validation (docs/evaluation.md)")
        metrics["extrapolation"] = extrapolate(d, options, model, result, volumes["template"], T, Y)
        parts.done("extrapolation (the edge validation, the other model)")
    volumes["SIRT (even tilts)"] = sirt_even / cell   # per voxel length -> per nm, for the figure
    figure(volumes, out / "figure.png", cell, metrics["scores"])
    save(volumes, domain, out)
    odd = np.sort(np.concatenate([tilts[k] for k in ("fit", "validation", "test")]))
    metrics["score_command"] = scored_files(out, turned, angles, tilts, odd, T, result, cell)
    say(f"  the table again from the files (in {out}): {metrics['score_command']}")
    parts.done("scores, figure, files")
    metrics["cpu_seconds"], metrics["cpu_seconds_by_part"] = time.process_time() - t0, parts.seconds
    metrics["wall_seconds"], metrics["wall_seconds_by_part"] = time.perf_counter() - wall0, parts.wall
    metrics["threads"] = torch.get_num_threads()
    say(f"  seconds per part, wall (CPU, {metrics['threads']} thread(s)): {parts.line()}")
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, default=float))
    say(f"wrote {out}/metrics.json, figure.png and the volumes; {metrics['wall_seconds']:.0f} s wall, "
        f"{metrics['cpu_seconds']:.0f} s CPU in all")
    return metrics


def evaluate(metrics: dict, result, base: dict, T: dict, Y: dict, domain: ImageDomain, out: Path) -> None:
    """Section 10: the registered volume's split (and its check on the fitted tilts), its uncertainty (cost, and
    whether the voxels it flags hold the worst errors on the test tilts: those replaced by TV's, and those alone
    fitted to the test tilts, against random ones), the figure ``evaluation.png``."""
    say("10. what the data determine and what the template brings; the uncertainty (docs/evaluation.md)")
    ev = metrics["evaluation"] = {**result.evaluation, "split_check": split_check(result)}
    for how, c in ev["split_check"].items():
        say(f"  split by the {how}: prior-filled part {c['split_prior_fraction']:.4f} of the volume, its projection "
            f"on the fitted tilts {c['split_projection_difference']:.2e} of the volume's")
    if result.uncertainty is not None:
        say(f"  uncertainty: {ev['uncertainty_samples']} re-optimisations in {ev['uncertainty_seconds']:.1f} s "
            f"(the registration's loop {result.seconds:.1f} s), mean standard deviation "
            f"{ev['uncertainty_mean_sd']:.4g}")
        if "TV" in base:
            ev["flagged"] = flagged_voxels(result.deformed.double().numpy(), result.uncertainty.double().numpy(),
                                           base["TV"][0].double().numpy(), T["test"], Y["test"])
            f = ev["flagged"]
            say(f"  the {f['voxels']} voxels of largest standard deviation replaced by TV's: test residual "
                f"{f['as_is']:.4f} -> {f['flagged_replaced']:.4f}; as many random voxels: "
                f"{f['random_replaced_mean']:.4f} ({f['random_replaced_min']:.4f}..{f['random_replaced_max']:.4f})")
            say(f"  only those voxels fitted to the test tilts: {f['flagged_refitted']:.4f}; as many random voxels: "
                f"{f['random_refitted_mean']:.4f} ({f['random_refitted_min']:.4f}..{f['random_refitted_max']:.4f})")
    box = (domain.min_pt, domain.max_pt)
    angles = np.degrees(T["fit"].operator.geometry.angles.numpy() if hasattr(T["fit"], "operator")
                        else T["fit"].geometry.angles.numpy())
    evaluation_png(result, out / "evaluation.png", box, "nm", "HAADF: the registered volume, what the data "
                   "determine, what the template fills; its standard deviation",
                   {"axis": "y", "range_deg": (float(angles.min()), float(angles.max()))})


def extrapolate(d, options: dict, model: str, result, template: np.ndarray, T: dict, Y: dict) -> dict:
    """Section 11: the edge validation's choice (``indreg.registration.extrapolation.choose_extrapolation``, the
    run's options) and the test tilts' residual of the template alone, LDDMM, the residual model and the chosen
    volume (the chosen model's run blended towards the template by its ``alpha``)."""
    choice = choose_extrapolation(d.template, d.data, d.operator, **options)
    other = "lddmm" if model == "residual" else "residual"
    runs = {model: result, other: indreg.register(d.template, d.data, d.operator, model=other, uncertainty=False,
                                                  **options)}
    chosen = template if choice.choice == "template" else blend(runs[choice.choice], choice.alpha).double().numpy()
    volumes = {"template": template, "lddmm": runs["lddmm"].deformed.double().numpy(),
               "residual": runs["residual"].deformed.double().numpy(),
               f"chosen ({choice.choice}, alpha {choice.alpha:g})": chosen}
    table = extrapolation_table(volumes, T, Y, choice)
    for name, r in table["rows"].items():
        say(f"  {name:30s} test {r['test_residual']:.4f}   validation {r['validation_residual']:.4f}")
    return table


def scored_files(out: Path, turned: np.ndarray, angles: np.ndarray, tilts: dict, odd: np.ndarray, T: dict, result,
                 cell: float) -> str:
    """The files ``indreg-score`` reads to print this run's scores again (``evaluation_steps.write_scored``): the
    odd tilts as scored, their alignment (the registration's shifts, the test tilts' fitted ones) and the sets."""
    sets = {k: np.flatnonzero(np.isin(odd, tilts[k])) for k in ("test", "validation", "fit")}
    aligned = None
    if isinstance(T["fit"], AlignedOperator):
        shifts = torch.zeros(len(odd), 2, dtype=torch.float64)
        for k, idx in sets.items():
            shifts[torch.as_tensor(idx)] = T[k].shifts
        aligned = AlignedOperator(operator(T["fit"].operator.domain, angles[odd]), shifts, float(T["fit"].angle),
                                  T["fit"].interpolation)
    names = ["template.mrc", "registered.mrc"] + [f"{k.lower()}.mrc" for k in ("FBP", "SIRT", "TV")
                                                   if (out / f"{k.lower()}.mrc").exists()]
    return write_scored(out / "scored", turned[odd], np.degrees(angles[odd]), sets, aligned,
                        aligned.interpolation if aligned is not None else "linear", 10 * cell, names,
                        result.units.background)


def label(name: str, m: dict) -> str:
    """A volume's row label in :func:`table` (the parameters chosen on the validation tilts are in its last lines)."""
    return {"registered": f"registered (`model=\"{m['registration']['model']}\"`)", "SIRT": "SIRT",
            "TV": "TV"}.get(name, name)


def chosen(m: dict) -> str:
    """What the validation tilts chose in one run: the residual model's weight, SIRT's iterations, TV's weight."""
    parts = []
    if m["registration"].get("finish"):
        parts.append(f"residual_tv {m['registration']['finish']['residual_tv']:.0e}")
    s = m["scores"]
    if "SIRT" in s:
        parts.append(f"SIRT {s['SIRT']['iterations']} iterations")
    if "TV" in s:
        parts.append(f"TV mu = {s['TV']['mu_relative']:g} x u")
    return ", ".join(parts)


def table(runs: dict) -> str:
    """docs/real_data.md's comparison table from the walk-through's metrics by stack (``{"raw": ..., "aligned":
    ...}``): every volume's test and validation residual, then the registered volume's ratios to TV's and the raw
    stack's test residual to the aligned one's."""
    first = next(iter(runs.values()))
    cols = [f"{stack}: {kind} ({len(m['tilts_deg'][kind])})" for stack, m in runs.items()
            for kind in ("test", "validation")]
    lines = ["| volume | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for name in first["scores"]:
        cells = [f"{m['scores'][name][f'{kind}_residual']:.4f}" for m in runs.values() for kind in ("test",
                                                                                                    "validation")]
        lines.append(f"| {label(name, first)} | " + " | ".join(cells) + " |")
    lines.append("")
    for stack, m in runs.items():
        reg, tv = m["scores"]["registered"], m["scores"].get("TV")
        if tv:
            lines.append(f"{stack}: registered / TV {reg['test_residual'] / tv['test_residual']:.2f} on the test "
                         f"tilts, {reg['validation_residual'] / tv['validation_residual']:.2f} on the validation "
                         f"tilts; chosen on the validation tilts: {chosen(m)}")
    if {"raw", "aligned"} <= set(runs):
        ratio = runs["raw"]["scores"]["registered"]["test_residual"] / \
            runs["aligned"]["scores"]["registered"]["test_residual"]
        lines.append(f"registered, raw / aligned stack on the test tilts: {ratio:.2f}")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, help="folder with HAADF.mrc, HAADF.rawtlt (HAADF_Aligned.hspy); offline")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "indreg" / "etspy_haadf")
    p.add_argument("--out", type=Path, default=Path("real_data_haadf"))
    p.add_argument("--stack", choices=("raw", "aligned"), default="raw",
                   help="raw: HAADF.mrc, aligned in the fit; aligned: etspy's aligned stack")
    p.add_argument("--align", choices=("shifts", "shifts+axis"), default="shifts",
                   help="what the registration estimates (--stack raw)")
    p.add_argument("--align-gauge", choices=alignment.ALIGN_GAUGES, default="none",
                   help="what the shifts leave to the deformation (none: the template fixes the frame)")
    p.add_argument("--align-interpolation", choices=("linear", "cubic"), default="cubic",
                   help="how the shifts move a projection image (cubic: no blur at fractional shifts)")
    p.add_argument("--size", type=int, default=64, help="detector pixels after binning (divides 256)")
    p.add_argument("--depth", type=int, default=64, help="voxels along the beam")
    p.add_argument("--iters", type=int, default=60, help="the registration's iterations (60: docs/real_data.md, "
                   "section 9, as 100 to 0.0003 on every registered residual, at 2/3 of the time; the page's earlier "
                   "runs used 100)")
    p.add_argument("--sigma", type=float, default=3.0, help="kernel width in voxels")
    p.add_argument("--misalign", type=float, default=5.0, help="template turned by this many degrees")
    p.add_argument("--max-angle", type=float, default=40.0, help="fit and validation tilts within +-this (deg)")
    p.add_argument("--fit-every", type=int, default=2, help="every k-th odd tilt in the range is fitted")
    p.add_argument("--gamma-rel", type=float, help="regularisation weight relative to the data term (default: "
                   "indreg's)")
    p.add_argument("--rescale", type=float, default=1.0, help="multiply every count by this (unit invariance)")
    p.add_argument("--no-baselines", action="store_true", help="skip FBP / SIRT / TV")
    p.add_argument("--table", action="store_true", help="run the raw and the aligned stack (into --out/raw, "
                   "--out/aligned) and print docs/real_data.md's table")
    p.add_argument("--reprint", action="store_true", help="with --table: print it from --out/raw and --out/aligned's "
                   "metrics.json, without running")
    p.add_argument("--model", default="residual", help="register()'s model (residual, the default: LDDMM plus a "
                   "TV-regularised intensity residual, its weight chosen on the validation tilts; lddmm)")
    p.add_argument("--interpolation", choices=("reinterpolate", "compose"), default="reinterpolate")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="the registration's, the "
                   "template scan's and the baselines' (float32: the table's numbers as float64's, at half the time)")
    p.add_argument("--threads", type=int, help="torch's CPU threads (default: torch's, OMP_NUM_THREADS or the cores)")
    p.add_argument("--extrapolation", action="store_true", help="the edge validation and its table on the test "
                   "tilts (docs/evaluation.md; about 3 more registrations)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[indreg] %(message)s")
    if a.threads is not None:
        if a.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {a.threads}")
        torch.set_num_threads(a.threads)
    if a.table:   # both stacks, then docs/real_data.md's table
        runs = {stack: json.loads((a.out / stack / "metrics.json").read_text()) if a.reprint
                else walk(fetch_once(a), a, a.out / stack, stack) for stack in ("raw", "aligned")}
        say("\n" + table(runs))
        return
    walk(fetch_once(a), a, a.out, a.stack)


def fetch_once(a: argparse.Namespace) -> Path:
    """The data's folder: ``--data`` (an error naming how to get the files if they are not there), or the cache
    (downloaded there the first time)."""
    if a.data is not None and missing_data(["--data", str(a.data)]):
        raise FileNotFoundError(missing_data(["--data", str(a.data)]))
    return a.data if a.data is not None else fetch(a.cache)


def walk(folder: Path, a: argparse.Namespace, out: Path, stack: str) -> dict:
    """:func:`run` with the command line's options."""
    return run(folder, out, size=a.size, depth=a.depth, iters=a.iters, sigma_cells=a.sigma, misalign=a.misalign,
               max_angle=a.max_angle, fit_every=a.fit_every, stack=stack, align=a.align, align_gauge=a.align_gauge,
               align_interpolation=a.align_interpolation, rescale=a.rescale, gamma_rel=a.gamma_rel,
               baselines_too=not a.no_baselines, model=a.model, interpolation=a.interpolation, dtype=a.dtype,
               extrapolation=a.extrapolation)


if __name__ == "__main__":
    try:
        main()
    except (OSError, ValueError) as e:   # a missing file, a bad option or file: one line
        sys.exit(f"real_data_haadf.py: error: {e}")
