"""A measured X-ray fan-beam sinogram, from the file to the registered image (docs/real_data_walnut.md).

The data: one slice of the walnut of Hämäläinen et al. (2015), "Tomographic X-ray data of a walnut" (University
of Helsinki, FIPS; CC BY 4.0, doi:10.5281/zenodo.1254206): 120 fan-beam projections over a full turn in steps of
3 degrees, 328 detector bins of 0.35 mm, source 110 mm from the rotation axis and 300 mm from the detector,
already flat/dark corrected and log-transformed (attenuation line integrals). ``gratopy`` 0.1.0 ships it as
``tests/walnut_sinogram.png`` (16-bit, detector x angle) in its source distribution on PyPI. Without ``--data`` it
is fetched once with ``pip download gratopy==0.1.0 --no-deps --no-binary gratopy`` (1.3 MB, nothing installed)
into ``--cache``; with ``--data DIR`` (a folder holding ``walnut_sinogram.png``) it runs offline.

Steps (each prints what it found): read the sinogram (value / 65535: line integrals in an arbitrary unit); the
background; the detector's orientation and the centre of rotation (a detector shift), both chosen by the
consistency of the full turn (SIRT's residual on all 120 angles); bin the detector; a template "from an earlier
scan" (a smoothed, segmented SIRT image of the even angles, per cell length as other programs reconstruct, turned
by ``--misalign`` degrees); the data: of the odd angles within ``--max-angle`` of 0, every ``--fit-every``-th
fitted, those between held out for validation, and the odd angles whose directions (modulo 180 degrees) lie
outside that range the test set (the missing wedge); registration with ``register()``'s defaults (``--model``;
``template_scale="auto"``, ``background="auto"``, ``holdout``); SIRT and TV from the same angles, their parameters
chosen on the validation angles (fan-beam FBP needs a full turn); everything scored by the relative residual on
the test angles (there is no ground truth).

    python examples/real_data_walnut.py [--data DIR] [--out DIR] [--model lddmm|residual] [--size 64]

Outputs in ``--out``: ``metrics.json``, ``figure.png``, the images as ``.npy``. Convention: the sinogram
``(angle, detector)``, angles ``3 k`` degrees; images ``(nx, ny)`` on a square domain in mm centred on the
rotation axis; indreg's ``FanBeamGeometry`` (docs/geometry.md).
"""
from __future__ import annotations

import sys
from pathlib import Path

#: The data folder's file (``--data``), and how to get it: checked before the imports below (~10 s of torch).
DATA_FILE = "walnut_sinogram.png"
FETCH_HINT = ("pass --data a folder holding walnut_sinogram.png (gratopy 0.1.0's tests/walnut_sinogram.png: pip "
              "download gratopy==0.1.0 --no-deps --no-binary gratopy, then untar the .tar.gz), or leave --data out "
              "to download it into --cache")


def missing_data(argv) -> str | None:
    """The one-line error of a ``--data`` folder without :data:`DATA_FILE` (with :data:`FETCH_HINT`), else None
    (no ``--data``: it is fetched into ``--cache``)."""
    import argparse

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--data", type=Path)
    data = p.parse_known_args(argv)[0].data
    return None if data is None or (data / DATA_FILE).is_file() else f"{data} has no {DATA_FILE}: {FETCH_HINT}"


if __name__ == "__main__" and missing_data(sys.argv[1:]):
    sys.exit(f"real_data_walnut.py: error: {missing_data(sys.argv[1:])}")

import argparse  # noqa: E402 (after the data check)
import json  # noqa: E402
import logging  # noqa: E402
import subprocess  # noqa: E402
import tarfile  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np
import torch
from scipy import ndimage

import indreg
from indreg.domain import ImageDomain
from indreg.forward import FanBeamGeometry, RayTransform, sirt
from indreg.registration.run import count_halvings
from indreg.units import prepare

sys.path.insert(0, str(Path(__file__).resolve().parent))   # the HAADF walk-through, whose scoring this reuses
from real_data_haadf import residual, say, score, tuned_sirt_tv  # noqa: E402
from evaluation_steps import evaluation_png, extrapolation_table, flagged_voxels, split_check  # noqa: E402

__all__ = ["SDIST", "MEMBER", "SRC_MM", "DET_MM", "DETECTOR_MM", "STEP_DEG", "SIRT_ITERS", "TV_MUS", "TV_ITERS",
           "fetch", "read_sinogram", "bin_detector", "square_domain", "operator", "background_report", "orientation",
           "centre_of_rotation", "split_angles", "make_template", "baselines", "figure", "run", "main"]

SDIST = "gratopy==0.1.0"
MEMBER = "tests/walnut_sinogram.png"          # in gratopy-0.1.0/ of the sdist
SRC_MM = 110.0                                # source to rotation axis (Hämäläinen et al. 2015)
DET_MM = 300.0 - SRC_MM                       # rotation axis to detector (source to detector: 300 mm)
DETECTOR_MM = 114.8                           # 328 bins of 0.35 mm
STEP_DEG = 3.0                                # 120 angles over a full turn
SIRT_ITERS = (10, 25, 50, 100, 200, 500, 1000, 2000, 5000)   # candidates, chosen on the validation angles
TV_MUS = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 100.0)   # x the data's intensity unit (both bracket the choice)
TV_ITERS = 2000                                # TV's validation residual within 1e-4 of 5000 iterations'


# ------------------------------------------------------------------------------------------------ the data
def fetch(cache: Path) -> Path:
    """The folder with ``walnut_sinogram.png``: ``cache`` if it has it, else downloaded there (pip download of
    gratopy's source distribution, unpacked; gratopy's README, which states the data's licence, beside it)."""
    if (cache / "walnut_sinogram.png").exists():
        return cache
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        say(f"downloading the source distribution of {SDIST} (1.3 MB, not installed) into {tmp}")
        subprocess.run([sys.executable, "-m", "pip", "download", SDIST, "--no-deps", "--no-binary", "gratopy",
                        "-d", tmp], check=True)
        sdist = next(Path(tmp).glob("gratopy-*.tar.gz"))
        with tarfile.open(sdist) as t:
            for member in t.getmembers():
                name = member.name.split("/", 1)[-1]
                if name in (MEMBER, "README.md", "LICENSE"):
                    target = cache / ("gratopy_" + name if name != MEMBER else Path(name).name)
                    target.write_bytes(t.extractfile(member).read())
    return cache


def read_sinogram(folder: Path) -> tuple:
    """``(sinogram (angles, bins) float64, angles in radians)``: the 16-bit PNG (stored detector x angle) as
    value / 65535, the angles ``3 k`` degrees."""
    from PIL import Image

    path = folder / "walnut_sinogram.png"
    if not path.exists():
        raise FileNotFoundError(f"{folder} has no {DATA_FILE}: {FETCH_HINT}")
    stored = np.asarray(Image.open(path))
    if stored.dtype != np.uint16 or stored.ndim != 2:
        raise ValueError(f"{path}: expected a 16-bit greyscale sinogram, got {stored.dtype} {stored.shape}")
    sino = stored.T.astype(np.float64) / 65535.0
    return sino, np.radians(STEP_DEG * np.arange(sino.shape[0]))


def bin_detector(sino: np.ndarray, factor: int) -> np.ndarray:
    """Every ``factor`` neighbouring bins averaged (the line integrals per bin are kept)."""
    n = sino.shape[-1]
    if factor < 1 or n % factor:
        raise ValueError(f"--bin must divide the {n} detector bins, got {factor}")
    return sino.reshape(*sino.shape[:-1], n // factor, factor).mean(axis=-1)


def square_domain(size: int, side_mm: float) -> ImageDomain:
    """``size x size`` square cells on ``[-side/2, side/2]^2`` mm, centred on the rotation axis."""
    return ImageDomain((size, size), (-side_mm / 2,) * 2, (side_mm / 2,) * 2)


def operator(domain: ImageDomain, angles: np.ndarray, det_count: int, shift_mm: float = 0.0) -> RayTransform:
    """The fan-beam ray transform at ``angles`` (radians), the detector moved by ``shift_mm`` along itself (the
    rotation axis' projection lies ``-shift_mm`` from the detector's middle)."""
    half = DETECTOR_MM / 2
    geometry = FanBeamGeometry(det_count=det_count, src_radius=SRC_MM, det_radius=DET_MM, det_min=-half + shift_mm,
                               det_max=half + shift_mm, angles=torch.as_tensor(angles), angle_unit="rad")
    return RayTransform(domain, geometry)


# ------------------------------------------------------------------------------------------------ checks
def background_report(sino: np.ndarray) -> dict:
    """The level outside the walnut: the median of the outermost 8 bins on each side, against the maximum."""
    edge = np.concatenate([sino[:, :8], sino[:, -8:]], axis=1)
    out = {"min": float(sino.min()), "max": float(sino.max()), "border_level": float(np.median(edge))}
    say(f"  values {out['min']:.4f}..{out['max']:.4f}, border level (median of the outermost 8 bins) "
        f"{out['border_level']:.4f} ({100 * out['border_level'] / out['max']:.1f} % of the maximum)")
    return out


def _full_turn_residual(y: torch.Tensor, angles: np.ndarray, domain: ImageDomain, shift_mm: float,
                        iters: int) -> float:
    T = operator(domain, angles, y.shape[-1], shift_mm)
    x, _ = sirt(T, y, num_iter=iters, nonneg=True)
    return residual(T, x, y)


def orientation(sino: np.ndarray, angles: np.ndarray, domain: ImageDomain, iters: int = 30) -> dict:
    """SIRT's residual on the full turn with the detector as stored and reversed: over 360 degrees every line is
    measured twice, and only the right orientation makes the two agree (reversing it and negating the angles
    together only mirrors the image)."""
    y = torch.from_numpy(sino)
    out = {"as_stored": _full_turn_residual(y, angles, domain, 0.0, iters),
           "reversed": _full_turn_residual(torch.flip(y, (-1,)), angles, domain, 0.0, iters)}
    out["reverse"] = out["reversed"] < out["as_stored"]
    return out


def centre_of_rotation(sino: np.ndarray, angles: np.ndarray, domain: ImageDomain, shifts_mm=None,
                       iters: int = 30) -> dict:
    """The detector shift (mm at the detector) that makes the full turn most consistent: SIRT's residual on all
    angles over a grid of shifts, refined by the parabola through the smallest and its neighbours."""
    grid = np.arange(-1.4, 1.41, 0.2) if shifts_mm is None else np.asarray(shifts_mm, dtype=float)
    y = torch.from_numpy(sino)
    res = np.array([_full_turn_residual(y, angles, domain, s, iters) for s in grid])
    k = int(np.clip(np.argmin(res), 1, len(grid) - 2))
    a, b, _ = np.polyfit(grid[k - 1:k + 2], res[k - 1:k + 2], 2)
    best = float(np.clip(-b / (2 * a), grid[k - 1], grid[k + 1])) if a > 0 else float(grid[np.argmin(res)])
    say("  SIRT residual on all angles by detector shift (mm): " + ", ".join(
        f"{s:+.1f}: {r:.4f}" for s, r in zip(grid, res)))
    return {"grid_mm": grid.tolist(), "residuals": res.tolist(), "shift_mm": best,
            "residual": _full_turn_residual(y, angles, domain, best, iters)}


# ------------------------------------------------------------------------------------------------ split
def split_angles(angles: np.ndarray, max_angle: float = 45.0, fit_every: int = 2) -> dict:
    """Indices of the angles (radians, a full turn in equal steps): ``template`` the even ones; of the odd ones
    within ``max_angle`` degrees of 0, every ``fit_every``-th the ``fit`` and those between ``validation``; the
    odd ones whose direction modulo 180 degrees lies outside that range ``test`` (the missing wedge). The odd
    ones opposite the range (their source across the axis: nearly the same lines as the fitted ones) are used by
    none."""
    deg = np.degrees(angles)
    index = np.arange(len(angles))
    odd = index % 2 == 1
    wrapped = (deg + 180.0) % 360.0 - 180.0                     # in [-180, 180)
    direction = (deg + 90.0) % 180.0 - 90.0                      # modulo 180, in [-90, 90)
    inside = np.flatnonzero(odd & (np.abs(wrapped) <= max_angle + 1e-9))
    inside = inside[np.argsort(wrapped[inside])]
    return {"template": index[~odd], "fit": np.sort(inside[::fit_every]),
            "validation": np.sort(np.setdiff1d(inside, inside[::fit_every])),
            "test": np.flatnonzero(odd & (np.abs(direction) > max_angle + 1e-9))}


def make_template(sino: np.ndarray, angles: np.ndarray, domain: ImageDomain, det_shift: float, misalign: float,
                  iters: int = 50, smooth: float = 0.5, classes: int = 4) -> tuple:
    """An "earlier scan": SIRT of ``sino`` (background removed) per cell length (as programs that reconstruct on
    unit pixels give it, so not in the data's unit), smoothed by ``smooth`` cells, segmented into ``classes``
    phases (multi-Otsu: air, and the walnut's shell and kernel) with each phase's mean, smoothed again, turned by
    ``misalign`` degrees (a walnut mounted differently). Returns ``(template, SIRT image per mm)``."""
    from skimage.filters import threshold_multiotsu

    T = operator(domain, angles, sino.shape[-1], det_shift)
    x, _ = sirt(T, torch.from_numpy(sino), num_iter=iters, nonneg=True)
    v = ndimage.gaussian_filter(x.numpy() * domain.cell_sides[0], smooth)
    thresholds = threshold_multiotsu(v, classes=classes)
    labels = np.digitize(v, thresholds)
    means = [0.0] + [float(v[labels == k].mean()) for k in range(1, classes)]
    template = ndimage.gaussian_filter(np.take(means, labels), smooth)
    if misalign:
        template = ndimage.rotate(template, misalign, reshape=False, order=1)
    say(f"  SIRT of {len(angles)} even angles per cell length ({iters} iterations), phases at "
        f"{thresholds.round(4)}: {[int((labels == k).sum()) for k in range(classes)]} cells, means "
        f"{np.round(means, 4)}; turned by {misalign:g} deg")
    return template, x.numpy()


# ------------------------------------------------------------------------------------------------ baselines
def baselines(T_fit, y_fit: torch.Tensor, T_val, y_val: torch.Tensor, sirt_iters=SIRT_ITERS, tv_mus=TV_MUS,
              tv_iters: int = TV_ITERS) -> dict:
    """SIRT (nonnegative, iterations chosen by the validation angles) and TV (nonnegative, ``mu`` relative to the
    data's intensity unit, chosen by the validation angles) from the fit angles, as the HAADF walk-through's
    baselines (fan-beam FBP needs a full turn: none here). Returns ``{name: (image, info)}``."""
    return tuned_sirt_tv(T_fit, y_fit, T_val, y_val, sirt_iters, tv_mus, tv_iters)


def figure(images: dict, path: Path, side_mm: float, scores: dict) -> None:
    """Every image on its own grey scale with its colour bar and axes in mm, the test-angle residual in its title
    (``indreg.experiments.figures``)."""
    from matplotlib.figure import Figure

    from indreg.experiments import figures

    fig = Figure(figsize=(3.3 * len(images), 3.8), layout="constrained")
    ax = fig.subplots(1, len(images), squeeze=False)[0]
    h = side_mm / 2
    for j, (name, v) in enumerate(images.items()):
        test = scores.get(name, {}).get("test_residual")
        title = name + (f"\ntest-angle residual {test:.4f}" if test is not None else "\n(not scored)")
        figures.show_image(ax[j], v, title, float(v.min()), float(v.max()), (-h, h, -h, h), axes=("x", "y"),
                           unit="mm")
    fig.suptitle("walnut, fan beam: the images (own grey scale each)")
    fig.savefig(path, dpi=100)


# ------------------------------------------------------------------------------------------------ pipeline
def run(folder: Path, out: Path, size: int = 64, side_mm: float = 40.0, bin_factor: int = 4, misalign: float = 5.0,
        max_angle: float = 45.0, fit_every: int = 2, model: str = "lddmm", sigma: float | None = None,
        iters: int | None = None, num_steps: int | None = None, classes: int = 4, baselines_too: bool = True,
        quick: bool = False, extrapolation: bool = False) -> dict:
    """The whole walk-through (module docstring); returns the metrics written to ``out/metrics.json``.
    ``sigma`` (mm), ``iters`` and ``num_steps``: ``None`` leaves ``register()``'s defaults. ``quick``: fewer SIRT /
    TV iterations and candidates (the tests). ``extrapolation``: the edge validation and its table on the test
    angles (docs/evaluation.md)."""
    t0 = time.process_time()
    out.mkdir(parents=True, exist_ok=True)
    metrics = {"data": str(folder), "model": model}

    say("1. the sinogram")
    sino, angles = read_sinogram(folder)
    say(f"  walnut_sinogram.png: {sino.shape} (angles, bins), angles 0..{np.degrees(angles[-1]):g} deg in steps "
        f"of {STEP_DEG:g}; detector {DETECTOR_MM} mm, source {SRC_MM:g} mm from the axis, detector {DET_MM:g} mm")
    metrics["shape"] = list(sino.shape)

    say("2. the background")
    metrics["background"] = background_report(sino)

    say(f"3. the detector binned by {bin_factor} ({sino.shape[1] // bin_factor} bins of "
        f"{DETECTOR_MM / sino.shape[1] * bin_factor:g} mm), a {size}^2 image of a {side_mm:g} mm square")
    binned = bin_detector(sino, bin_factor) - metrics["background"]["border_level"]
    domain = square_domain(size, side_mm)
    checks = 10 if quick else 30
    orient = orientation(binned, angles, domain, iters=checks)
    say(f"  orientation: SIRT residual on all angles {orient['as_stored']:.4f} as stored, {orient['reversed']:.4f} "
        f"reversed: {'reversed' if orient['reverse'] else 'as stored'}")
    if orient["reverse"]:
        sino, binned = sino[:, ::-1].copy(), binned[:, ::-1].copy()
    centre = centre_of_rotation(binned, angles, domain, iters=checks)
    shift = centre["shift_mm"]
    say(f"  centre of rotation: detector shift {shift:+.3f} mm ({shift / (DETECTOR_MM / sino.shape[1]):+.2f} "
        f"unbinned bins), SIRT residual {centre['residual']:.4f}")
    metrics["orientation"], metrics["centre"] = orient, centre

    say("4. the template: an earlier scan (the even angles)")
    tilts = split_angles(angles, max_angle, fit_every)
    metrics["angles_deg"] = {k: np.degrees(angles[v]).round(1).tolist() for k, v in tilts.items()}
    for k, v in tilts.items():
        say(f"  {k:10s} {len(v):2d} angles: {np.degrees(angles[v]).round(0).astype(int).tolist()}")
    template, sirt_even = make_template(binned[tilts["template"]], angles[tilts["template"]], domain, shift,
                                        misalign, iters=20 if quick else 50, classes=classes)

    say("5. the data and the units")
    rows = np.sort(np.concatenate([tilts["fit"], tilts["validation"]]))
    holdout = [int(i) for i in np.flatnonzero(np.isin(rows, tilts["validation"]))]
    data = binned[rows] + metrics["background"]["border_level"]      # as measured: register removes the level
    T_data = operator(domain, angles[rows], binned.shape[1], shift)
    _, _, units = prepare(torch.from_numpy(template), torch.from_numpy(data), T_data, background="auto")
    say(f"  template as made: ||T I|| / ||g|| = {units.projection_ratio:.4g}, c = {units.scale_fit:.4g} (the data "
        f"after the background {units.background:.4g}); 1 / cell side = {1 / domain.cell_sides[0]:.4g} per mm")

    say(f"6. registration (model={model!r}): {len(tilts['fit'])} angles fitted, {len(holdout)} held out")
    options = {k: v for k, v in (("sigma", sigma), ("max_iter", iters), ("num_steps", num_steps)) if v is not None}
    common = dict(template_scale="auto", background="auto", holdout=holdout, log_every=20, **options)
    result = indreg.register(torch.from_numpy(template), torch.from_numpy(data), T_data, model=model, progress=True,
                             **common)
    halvings = count_halvings(result.history)
    say(f"  {result.status} after {result.iterations} iterations ({result.seconds:.1f} s): template_scale "
        f"{result.units.template_scale:.4g}, background {result.units.background:.4g}, residual "
        f"{result.residual:.4f}, held-out {result.holdout.get('holdout_residual', float('nan')):.4f}, min Jacobian "
        f"{result.min_jacobian:.3f}, {halvings} step halvings")
    metrics["registration"] = {"status": result.status, "iterations": result.iterations, "seconds": result.seconds,
                               "model": model, "options": options, "template_scale": result.units.template_scale,
                               "background": result.units.background, "scale_fit": result.units.scale_fit,
                               "residual": result.residual, "min_jacobian": result.min_jacobian,
                               "halvings": halvings, "warnings": result.warnings, **result.holdout}
    y = torch.from_numpy(binned + metrics["background"]["border_level"] - result.units.background)
    T = {k: operator(domain, angles[v], binned.shape[1], shift) for k, v in tilts.items()}
    Y = {k: y[v] for k, v in tilts.items()}

    base = {}
    if baselines_too:
        say("7. baselines from the same fit angles")
        tb = time.process_time()
        base = baselines(T["fit"], Y["fit"], T["validation"], Y["validation"],
                         sirt_iters=(10, 25) if quick else SIRT_ITERS, tv_mus=(0.1,) if quick else TV_MUS,
                         tv_iters=20 if quick else TV_ITERS)
        metrics["baselines_cpu_seconds"] = time.process_time() - tb

    say("8. scores on the test angles (the missing wedge, used by none of them; no ground truth exists)")
    images = {"template": template * result.units.template_scale, "registered": result.deformed.double().numpy(),
              **{k: v[0].numpy() for k, v in base.items()}}
    metrics["scores"] = score(images, T, Y, {k: v[1] for k, v in base.items()})
    say("9. what the data determine and what the template brings; the uncertainty (docs/evaluation.md)")
    ev = metrics["evaluation"] = {**result.evaluation, "split_check": split_check(result)}
    c = ev["split_check"]["range"]
    say(f"  split: prior-filled part {c['split_prior_fraction']:.4f} of the image, its projection on the fitted "
        f"angles {c['split_projection_difference']:.2e} of the image's")
    if result.uncertainty is not None and "TV" in base:
        ev["flagged"] = flagged_voxels(images["registered"], result.uncertainty.double().numpy(),
                                       base["TV"][0].numpy(), T["test"], Y["test"])
        f = ev["flagged"]
        say(f"  uncertainty in {ev['uncertainty_seconds']:.1f} s; the {f['voxels']} cells of largest standard "
            f"deviation replaced by TV's: test residual {f['as_is']:.4f} -> {f['flagged_replaced']:.4f}, as many "
            f"random cells {f['random_replaced_mean']:.4f}; only those cells fitted to the test angles: "
            f"{f['flagged_refitted']:.4f}, random cells {f['random_refitted_mean']:.4f}")
    h = side_mm / 2
    evaluation_png(result, out / "evaluation.png", ((-h, -h), (h, h)), "mm", "walnut: the registered image, what the "
                   "data determine, what the template fills; its standard deviation")
    if extrapolation:
        say("10. which image to trust on the missing range: the edge validation (docs/evaluation.md)")
        metrics["extrapolation"] = extrapolate(torch.from_numpy(template), torch.from_numpy(data), T_data, common,
                                               model, result, images["template"], T, Y)
    images["SIRT (even angles)"] = sirt_even
    figure(images, out / "figure.png", side_mm, metrics["scores"])
    for name, v in images.items():
        np.save(out / f"{name.lower().replace(' ', '_').replace('(', '').replace(')', '')}.npy", v)
    metrics["cpu_seconds"] = time.process_time() - t0
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, default=float))
    say(f"wrote {out}/metrics.json, figure.png and the images; {metrics['cpu_seconds']:.0f} s CPU in all")
    return metrics


def extrapolate(template, data, T_data, options: dict, model: str, result, scaled_template, T: dict, Y: dict) -> dict:
    """The edge validation's choice and the test angles' residual of the template alone, LDDMM, the residual model
    and the chosen image (as the HAADF walk-through's ``extrapolate``)."""
    from indreg.registration.extrapolation import blend, choose_extrapolation

    choice = choose_extrapolation(template, data, T_data, **options)
    other = "lddmm" if model == "residual" else "residual"
    runs = {model: result, other: indreg.register(template, data, T_data, model=other, uncertainty=False, **options)}
    chosen = scaled_template if choice.choice == "template" else blend(runs[choice.choice], choice.alpha).numpy()
    table = extrapolation_table({"template": scaled_template, "lddmm": runs["lddmm"].deformed.double().numpy(),
                                 "residual": runs["residual"].deformed.double().numpy(),
                                 f"chosen ({choice.choice}, alpha {choice.alpha:g})": chosen}, T, Y, choice)
    for name, r in table["rows"].items():
        say(f"  {name:30s} test {r['test_residual']:.4f}   validation {r['validation_residual']:.4f}")
    return table


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, help="folder with walnut_sinogram.png; offline")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "indreg" / "walnut")
    p.add_argument("--out", type=Path, default=Path("real_data_walnut"))
    p.add_argument("--model", default="lddmm", help="register()'s model (residual: LDDMM plus a TV-regularised "
                   "intensity residual)")
    p.add_argument("--size", type=int, default=64, help="image cells per side")
    p.add_argument("--side", type=float, default=40.0, help="the image's side (mm)")
    p.add_argument("--bin", type=int, default=4, help="detector bins averaged (divides 328)")
    p.add_argument("--misalign", type=float, default=5.0, help="template turned by this many degrees")
    p.add_argument("--max-angle", type=float, default=45.0, help="fit and validation angles within +-this (deg)")
    p.add_argument("--fit-every", type=int, default=2, help="every k-th odd angle in the range is fitted")
    p.add_argument("--sigma", type=float, help="kernel width in mm (default: register()'s)")
    p.add_argument("--iters", type=int, help="iterations (default: register()'s)")
    p.add_argument("--no-baselines", action="store_true", help="skip SIRT / TV")
    p.add_argument("--extrapolation", action="store_true", help="the edge validation and its table on the test "
                   "angles (docs/evaluation.md; about 3 more registrations)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[indreg] %(message)s")
    torch.set_num_threads(1)
    folder = a.data if a.data is not None else fetch(a.cache)
    run(folder, a.out, size=a.size, side_mm=a.side, bin_factor=a.bin, misalign=a.misalign, max_angle=a.max_angle,
        fit_every=a.fit_every, model=a.model, sigma=a.sigma, iters=a.iters, baselines_too=not a.no_baselines,
        extrapolation=a.extrapolation)


if __name__ == "__main__":
    try:
        main()
    except (OSError, ValueError) as e:   # a missing file, a bad option or file: one line
        sys.exit(f"real_data_walnut.py: error: {e}")
