"""A real tilt series, from the raw stack to the registered volume (docs/real_data.md).

The data: a HAADF-STEM tilt series of a rod-shaped specimen (77 tilts, -76..76 degrees in steps of 2, 256 x 256
pixels of 3.36 nm) that NIST ships as test data in the wheel of ``etspy`` 1.3.0 (NIST Public License: US federal
work, no copyright in the US; the licence text is in the wheel). Without ``--data`` it is fetched once with
``pip download etspy==1.3.0 --no-deps`` (66 MB) and its ``etspy/tests/test_data/HAADF*`` files are unpacked into
``--cache`` (nothing is installed); with ``--data DIR`` (a folder holding ``HAADF.mrc``, ``HAADF.rawtlt`` and
optionally ``HAADF_Aligned.hspy``) it runs offline.

Steps (each prints what it found): read the raw stack and its angles; check the tilt axis (which way it runs,
how consistent the stack is), raw vs aligned stack; the background (the raw int16 stack's offset); bin to
``--size`` detector pixels; a template "from an earlier scan" (a smoothed, segmented SIRT reconstruction from the
even tilts, reconstructed in voxel units as other programs do, so not in the data's units, and turned by
``--misalign`` degrees); the data: a sparse subset of the odd tilts within ``--max-angle`` (every ``--fit-every``-th),
the odd tilts between them held out for validation; registration with
``template_scale="auto"``, ``background="auto"`` and ``holdout``; FBP / SIRT / TV from the same sparse tilts; all
scored by the relative residual on the odd tilts that none of them used (there is no ground truth).

    python examples/real_data_haadf.py [--data DIR] [--out DIR] [--size 64] [--iters 100]

Outputs in ``--out``: ``metrics.json``, ``figure.png`` (central slices), the volumes as ``.npy`` and ``.mrc``
(voxel size in Angstrom).

Convention: the stack as stored is ``(tilt, row, column)`` with the tilt axis along the columns' index (the
image's X; the acquisition log says "Tilt Axis Angle: 90"); indreg's layout has it along the rows
(``tilt_axis_angle=90`` turns it, ``indreg.tilt_axis``). Volumes ``(nx, ny, nz)``: y the tilt axis (the rod's
length), z the beam at tilt 0; the domain is in nm.
"""
from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
import torch

import indreg
from indreg import io
from indreg.domain import ImageDomain
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform, fbp, sirt, tv_reconstruction
from indreg.forward.tv import intensity_scale
from indreg.units import border_level, check_offset, prepare
from indreg.tilt_axis import align_tilt_axis, check_tilt_axis

log = logging.getLogger("indreg")

WHEEL = "etspy==1.3.0"
MEMBERS = "etspy/tests/test_data/HAADF"
ALIGNED_KEY = "/Experiments/__unnamed__/data"   # HyperSpy's signal array in the .hspy (HDF5) file
PIXEL_NM = 3.36                                  # "Image pixel size [nm]: 3.36" of HAADF.txt
TILT_AXIS_ANGLE = 90.0                           # "Tilt Axis Angle: 90.00" of HAADF.txt


def say(text: str) -> None:
    print(text, flush=True)


# ------------------------------------------------------------------------------------------------ the data
def fetch(cache: Path) -> Path:
    """The folder with ``HAADF.*``: ``cache`` if it has them, else downloaded there (pip download, unzip)."""
    if (cache / "HAADF.mrc").exists():
        return cache
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        say(f"downloading {WHEEL} (66 MB, not installed) into {tmp}")
        subprocess.run([sys.executable, "-m", "pip", "download", WHEEL, "--no-deps", "-d", tmp], check=True)
        wheel = next(Path(tmp).glob("etspy-*.whl"))
        with zipfile.ZipFile(wheel) as z:
            for member in z.namelist():
                if member.startswith(MEMBERS) or member.endswith("LICENSE"):
                    (cache / Path(member).name).write_bytes(z.read(member))
    return cache


def read_raw(folder: Path) -> tuple:
    """The raw stack ``(tilts, rows, cols)`` as stored and its angles (radians): ``HAADF.mrc`` + ``HAADF.rawtlt``."""
    return io.read_tilt_series(folder / "HAADF.mrc", folder / "HAADF.rawtlt")


def read_aligned(folder: Path):
    """etspy's aligned stack (``HAADF_Aligned.hspy``, shifts removed), or None without that file."""
    path = folder / "HAADF_Aligned.hspy"
    return io.read_stack(f"{path}:{ALIGNED_KEY}", name="aligned stack") if path.exists() else None


def bin_stack(stack: np.ndarray, size: int) -> np.ndarray:
    """Every image averaged over square blocks down to ``size x size`` (the counts per pixel are kept)."""
    t, rows, cols = stack.shape
    f = rows // size
    if rows != cols or f * size != rows:
        raise ValueError(f"--size must divide the image size {rows} x {cols}, got {size}")
    return stack.reshape(t, size, f, size, f).mean(axis=(2, 4))


# ------------------------------------------------------------------------------------------------ checks
def axis_checks(raw: np.ndarray, aligned) -> dict:
    """The tilt-axis check (``indreg.tilt_axis.check_tilt_axis``) of the stacks as stored (the check subtracts
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
    """``||T x - y|| / ||y||`` in the data inner product."""
    with torch.no_grad():
        r = T(x) - y
        return float(T.inner_data(r, r).sum().sqrt() / T.inner_data(y, y).sum().sqrt())


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
def make_template(data: np.ndarray, angles: np.ndarray, shape: tuple, misalign: float, iters: int = 50,
                  smooth: float = 0.5, classes: int = 5) -> tuple:
    """An "earlier scan": SIRT of ``data`` (background removed) on unit voxels (as IMOD / astra reconstruct, so
    its intensities are per voxel length, not per nm), smoothed by ``smooth`` voxels, segmented into ``classes``
    phases (multi-Otsu: vacuum, the rod's dim part, its bright bands) with each phase's mean, smoothed again;
    turned by ``misalign`` degrees about the beam (a specimen mounted differently). Returns
    ``(template, sirt volume)``."""
    from scipy import ndimage
    from skimage.filters import threshold_multiotsu

    unit = ImageDomain(shape, tuple(-n / 2 for n in shape), tuple(n / 2 for n in shape))
    x, _ = sirt(operator(unit, angles), torch.from_numpy(data), num_iter=iters, nonneg=True)
    v = ndimage.gaussian_filter(x.numpy(), smooth)
    thresholds = threshold_multiotsu(v, classes=classes)
    labels = np.digitize(v, thresholds)
    means = [0.0] + [float(v[labels == k].mean()) for k in range(1, classes)]
    template = ndimage.gaussian_filter(np.take(means, labels), smooth)
    if misalign:
        template = ndimage.rotate(template, misalign, axes=(0, 1), reshape=False, order=1)
    say(f"  SIRT of {len(angles)} even tilts on unit voxels ({iters} iterations), phases at {thresholds.round(1)}: "
        f"{[int((labels == k).sum()) for k in range(classes)]} voxels, means {np.round(means, 1)}; "
        f"turned by {misalign:g} deg")
    return template, x.numpy()


# ------------------------------------------------------------------------------------------------ baselines
def baselines(T_fit, y_fit: torch.Tensor, T_val, y_val: torch.Tensor, sirt_iters=(10, 25, 50, 100, 200),
              tv_mus=(0.03, 0.1, 0.3, 1.0), tv_iters: int = 200) -> dict:
    """FBP (Hamming, 0.4, the app's), SIRT (nonnegative, iterations chosen by the validation tilts) and TV
    (nonnegative, ``mu`` relative to the data's intensity unit chosen by the validation tilts) from the fit
    tilts. Returns ``{name: (volume, info)}``."""
    out = {"FBP": (fbp(T_fit, y_fit), {})}
    best, x, done = None, None, 0
    for n in sirt_iters:
        x, _ = sirt(T_fit, y_fit, num_iter=n - done, x0=x, nonneg=True)
        done, r = n, residual(T_val, x, y_val)
        say(f"    SIRT {n:4d} iterations: validation residual {r:.4f}")
        if best is None or r < best[1]["validation_residual"]:
            best = (x.clone(), {"iterations": n, "validation_residual": r})
    out["SIRT"] = best
    u, best = intensity_scale(T_fit, y_fit), None
    for mu in tv_mus:
        x, _ = tv_reconstruction(T_fit, y_fit, mu=mu * u, num_iter=tv_iters, nonneg=True)
        r = residual(T_val, x, y_val)
        say(f"    TV mu = {mu:g} x {u:.4g}: validation residual {r:.4f}")
        if best is None or r < best[1]["validation_residual"]:
            best = (x, {"mu_relative": mu, "mu": mu * u, "iterations": tv_iters, "validation_residual": r})
    out["TV"] = best
    return out


# ------------------------------------------------------------------------------------------------ outputs
def scale_bar_nm(width_nm: float) -> float:
    """A round length (1, 2 or 5 times a power of ten, in nm) of at most a third of ``width_nm``."""
    top = width_nm / 3
    power = 10.0 ** np.floor(np.log10(top))
    return max(m * power for m in (1, 2, 5) if m * power <= top)


def figure(volumes: dict, path: Path, cell_nm: float) -> None:
    """Central slices of every volume: the x-z slice across the rod (orthogonal to the tilt axis) and the x-y
    slice along it, each on its own grey scale, with a scale bar in nm (voxels of ``cell_nm``)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    fig, ax = plt.subplots(2, len(volumes), figsize=(3.0 * len(volumes), 6.6), squeeze=False)
    for j, (name, v) in enumerate(volumes.items()):
        nx, ny, nz = v.shape
        ax[0, j].imshow(v[:, ny // 2, :].T, cmap="gray", origin="lower")
        ax[1, j].imshow(v[:, :, nz // 2].T, cmap="gray", origin="lower")
        ax[0, j].set_title(name, fontsize=13)
        bar = scale_bar_nm(nx * cell_nm)
        for a in ax[:, j]:
            a.set_xticks([]), a.set_yticks([])
            a.add_artist(AnchoredSizeBar(a.transData, bar / cell_nm, f"{bar:g} nm", "lower right", pad=0.4,
                                         color="yellow", frameon=False, size_vertical=max(nz, ny) / 80,
                                         fontproperties={"size": 12}))
    ax[0, 0].set_ylabel("x-z (across)", fontsize=13)
    ax[1, 0].set_ylabel("x-y (along axis)", fontsize=13)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def save(volumes: dict, domain: ImageDomain, out: Path) -> None:
    """Every volume as ``.npy`` and ``.mrc`` (the voxel size in Angstrom, as the MRC format has it)."""
    angstrom = ImageDomain(domain.shape, tuple(10 * float(m) for m in domain.min_pt),
                           tuple(10 * float(m) for m in domain.max_pt))
    for name, v in volumes.items():
        stem = name.lower().replace(" ", "_").replace("(", "").replace(")", "")
        np.save(out / f"{stem}.npy", v)
        io.write_volume(out / f"{stem}.mrc", v, angstrom)


# ------------------------------------------------------------------------------------------------ pipeline
def run(folder: Path, out: Path, size: int = 64, depth: int = 64, iters: int = 100, sigma_cells: float = 3.0,
        num_steps: int = 10, misalign: float = 5.0, fit_every: int = 2, max_angle: float = 40.0,
        step_size: float = 0.02, max_halvings: int = 40, classes: int = 5, smooth: float = 0.5,
        quick: bool = False) -> dict:
    """The whole walk-through (module docstring); returns the metrics written to ``out/metrics.json``.
    ``quick``: fewer SIRT / TV iterations and candidates (the tests)."""
    t0 = time.process_time()
    out.mkdir(parents=True, exist_ok=True)
    metrics = {"data": str(folder)}

    say("1. the raw stack")
    raw, angles = read_raw(folder)
    aligned = read_aligned(folder)
    say(f"  HAADF.mrc: {raw.shape} (tilts, rows, columns), angles {np.degrees(angles[0]):g}..{np.degrees(angles[-1]):g}"
        f" deg, {len(angles)} tilts; aligned stack: {None if aligned is None else aligned.shape}")
    metrics["raw_shape"], metrics["num_tilts"] = list(raw.shape), len(angles)

    say("2. the tilt axis (as stored; indreg wants it along the rows' index)")
    metrics["tilt_axis_as_stored"] = axis_checks(raw, aligned)
    stack = aligned if aligned is not None else raw

    say("3. the background")
    metrics["background_raw"] = background_report(raw, "raw stack")
    if aligned is not None:
        metrics["background_aligned"] = background_report(aligned, "aligned stack")

    say(f"4. binned to {size} x {size} pixels, turned by -{TILT_AXIS_ANGLE:g} degrees (tilt_axis_angle)")
    binned = bin_stack(stack, size)
    cell = PIXEL_NM * stack.shape[1] / size
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

    say("5. the template: an earlier scan (even tilts)")
    tilts = split_tilts(angles, fit_every, max_angle)
    metrics["tilts_deg"] = {k: np.degrees(angles[v]).round(2).tolist() for k, v in tilts.items()}
    for k, v in tilts.items():
        say(f"  {k:10s} {len(v):2d} tilts: {np.degrees(angles[v]).round(0).astype(int).tolist()}")
    template, sirt_even = make_template(turned[tilts["template"]] - level, angles[tilts["template"]],
                                        domain.shape, misalign, iters=20 if quick else 50, smooth=smooth,
                                        classes=classes)

    say("6. the data and the units")
    rows = np.sort(np.concatenate([tilts["fit"], tilts["validation"]]))
    holdout = [int(i) for i in np.flatnonzero(np.isin(rows, tilts["validation"]))]
    d = indreg.load(template, binned[rows], "tilt_series", angles=np.degrees(angles[rows]).tolist(),
                    tilt_axis_angle=TILT_AXIS_ANGLE, half_width=cell * max(size, depth) / 2)
    metrics["load"] = d.report()
    _, _, units = prepare(d.template, d.data, d.operator, background="auto")   # what register checks first
    say(f"  template as made: ||T I|| / ||g|| = {units.projection_ratio:.4g}, c = {units.scale_fit:.4g} (the data "
        f"after the background {units.background:.4g}); 1 / voxel side = {1 / cell:.4g} per nm")

    say(f"7. registration: {len(tilts['fit'])} tilts fitted, {len(holdout)} held out")
    sigma = sigma_cells * cell
    result = indreg.register(d.template, d.data, d.operator, sigma=sigma, num_steps=num_steps, max_iter=iters,
                             template_scale="auto", background="auto", holdout=holdout, log_every=10,
                             step_size=step_size, max_halvings=max_halvings, progress=True)
    reg_seconds = result.seconds
    say(f"  {result.status} after {result.iterations} iterations ({reg_seconds:.0f} s): template_scale "
        f"{result.units.template_scale:.4g}, background {result.units.background:.4g}, residual {result.residual:.4f}, "
        f"held-out {result.holdout.get('holdout_residual', float('nan')):.4f} (best "
        f"{result.holdout.get('holdout_best_residual', float('nan')):.4f} at iteration "
        f"{result.holdout.get('holdout_best_iteration')}), min Jacobian {result.min_jacobian:.3f}")
    metrics["registration"] = {"status": result.status, "iterations": result.iterations, "seconds": reg_seconds,
                               "sigma_nm": sigma, "num_steps": num_steps, "template_scale": result.units.template_scale,
                               "background": result.units.background, "scale_fit": result.units.scale_fit,
                               "projection_ratio": result.units.projection_ratio, "residual": result.residual,
                               "min_jacobian": result.min_jacobian, "warnings": result.warnings, **result.holdout}

    say("8. baselines from the same fit tilts")
    y = torch.from_numpy(turned - result.units.background)
    T = {k: operator(domain, angles[v]) for k, v in tilts.items()}
    Y = {k: y[v] for k, v in tilts.items()}
    tb = time.process_time()
    base = baselines(T["fit"], Y["fit"], T["validation"], Y["validation"],
                     sirt_iters=(10, 25) if quick else (10, 25, 50, 100, 200),
                     tv_mus=(0.1,) if quick else (0.3, 1.0, 3.0, 10.0), tv_iters=20 if quick else 200)
    metrics["baselines_cpu_seconds"] = time.process_time() - tb

    say("9. scores on the test tilts (used by none of them; no ground truth exists)")
    volumes = {"template": (d.template * result.units.template_scale).numpy(),
               "registered": result.deformed.double().numpy(),
               **{k: v[0].numpy() for k, v in base.items()}}
    scores = {}
    for name, v in volumes.items():
        x = torch.from_numpy(np.ascontiguousarray(v))
        scores[name] = {"test_residual": residual(T["test"], x, Y["test"]),
                        "validation_residual": residual(T["validation"], x, Y["validation"]),
                        "fit_residual": residual(T["fit"], x, Y["fit"]),
                        **({} if name not in base else base[name][1])}
        s = scores[name]
        say(f"  {name:10s} test {s['test_residual']:.4f}   validation {s['validation_residual']:.4f}   "
            f"fit {s['fit_residual']:.4f}")
    metrics["scores"] = scores

    volumes["SIRT (even tilts)"] = sirt_even / cell   # per voxel length -> per nm, for the figure
    figure(volumes, out / "figure.png", cell)
    save(volumes, domain, out)
    metrics["cpu_seconds"] = time.process_time() - t0
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, default=float))
    say(f"wrote {out}/metrics.json, figure.png and the volumes; {metrics['cpu_seconds']:.0f} s CPU in all")
    return metrics


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, help="folder with HAADF.mrc, HAADF.rawtlt (HAADF_Aligned.hspy); offline")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "indreg" / "etspy_haadf")
    p.add_argument("--out", type=Path, default=Path("real_data_haadf"))
    p.add_argument("--size", type=int, default=64, help="detector pixels after binning (divides 256)")
    p.add_argument("--depth", type=int, default=64, help="voxels along the beam")
    p.add_argument("--iters", type=int, default=100)
    p.add_argument("--sigma", type=float, default=3.0, help="kernel width in voxels")
    p.add_argument("--misalign", type=float, default=5.0, help="template turned by this many degrees")
    p.add_argument("--max-angle", type=float, default=40.0, help="fit and validation tilts within +-this (deg)")
    p.add_argument("--fit-every", type=int, default=2, help="every k-th odd tilt in the range is fitted")
    p.add_argument("--max-halvings", type=int, default=40, help="step halvings per iteration (register's)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[indreg] %(message)s")
    torch.set_num_threads(1)
    folder = a.data if a.data is not None else fetch(a.cache)
    run(folder, a.out, size=a.size, depth=a.depth, iters=a.iters, sigma_cells=a.sigma, misalign=a.misalign,
        max_angle=a.max_angle, fit_every=a.fit_every, max_halvings=a.max_halvings)


if __name__ == "__main__":
    main()
