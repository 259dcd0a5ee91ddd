"""The files of the HAADF walk-through (examples/real_data_haadf.py, docs/real_data.md): fetching and reading
etspy's HAADF series and its recorded alignment, binning, comparing shifts, and writing the figure and volumes.

Convention: stacks ``(tilt, row, column)`` as stored (the tilt axis along the columns' index); shifts in detector
pixels, etspy's ``[row, column]`` of the stored images, indreg's ``[across, along]`` of the turned ones
(docs/alignment.md); volumes ``(nx, ny, nz)`` on a domain in nm.
"""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import tempfile
import zipfile
from functools import partial
from pathlib import Path

import numpy as np
import torch

from indreg import alignment, io
from indreg.domain import ImageDomain
from indreg.alignment.operator import AlignedOperator

__all__ = ["WHEEL", "MEMBERS", "ALIGNED_KEY", "SHIFTS_KEY", "PIXEL_NM", "TILT_AXIS_ANGLE", "say", "fetch", "read_raw",
           "read_aligned", "read_etspy_shifts", "bin_stack", "scale_bar_nm", "figure", "save", "etspy_frame",
           "axis_offset", "bilinear", "compare_shifts", "alignment_figure"]

WHEEL = "etspy==1.3.0"
MEMBERS = "etspy/tests/test_data/HAADF"
ALIGNED_KEY = "/Experiments/__unnamed__/data"   # HyperSpy's signal array in the .hspy (HDF5) file
SHIFTS_KEY = "/Experiments/__unnamed__/metadata/Tomography/_sig_shifts/data"   # etspy's shifts (tilts, [row, col])
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


def read_etspy_shifts(folder: Path):
    """etspy's recorded shifts ``(tilts, 2)`` in raw pixels, ``[:, 0]`` along the stored rows' index (across the
    tilt axis), ``[:, 1]`` along the columns' (along it); etspy moved each raw image by them (``aligned(p + s) =
    raw(p)``). None without the file."""
    import h5py

    path = folder / "HAADF_Aligned.hspy"
    if not path.exists():
        return None
    with h5py.File(path, "r") as f:
        return np.asarray(f[SHIFTS_KEY], dtype=np.float64) if SHIFTS_KEY in f else None


def bin_stack(stack: np.ndarray, size: int) -> np.ndarray:
    """Every image averaged over square blocks down to ``size x size`` (the counts per pixel are kept)."""
    t, rows, cols = stack.shape
    f = rows // size
    if rows != cols or f * size != rows:
        raise ValueError(f"--size must divide the image size {rows} x {cols}, got {size}")
    return stack.reshape(t, size, f, size, f).mean(axis=(2, 4))


# ------------------------------------------------------------------------------------------------ outputs
def scale_bar_nm(width_nm: float) -> float:
    """A round length (1, 2 or 5 times a power of ten, in nm) of at most a third of ``width_nm``."""
    top = width_nm / 3
    power = 10.0 ** np.floor(np.log10(top))
    return max(m * power for m in (1, 2, 5) if m * power <= top)


def figure(volumes: dict, path: Path, cell_nm: float, scores: dict | None = None) -> None:
    """Central slices of every volume, one column each: the x-z slice across the rod (orthogonal to the tilt
    axis) and the x-y slice along it, each volume on its own grey scale with its colour bar, axes and a scale bar
    in nm, and its held-out score in the title (``scores[name]["test_residual"]``: the relative residual on the
    test tilts, which no method used; no ground truth exists). Drawn by ``indreg.experiments.figures``. Beside it,
    ``<stem>.json``: the numbers as the titles print them and the figure's SHA-256 (docs/real_data.md's figure is
    checked against its table with them: tests/test_real_data_example.py)."""
    from matplotlib.figure import Figure

    from indreg.experiments import figures

    scores = scores or {}
    fig = Figure(figsize=(3.3 * len(volumes), 6.9), layout="constrained")
    ax = fig.subplots(2, len(volumes), squeeze=False)
    for j, (name, v) in enumerate(volumes.items()):
        nx, ny, nz = v.shape
        x, y, z = (n * cell_nm / 2 for n in (nx, ny, nz))
        low, high = float(v.min()), float(v.max())
        test = scores.get(name, {}).get("test_residual")
        title = name + (f"\ntest-tilt residual {test:.4f}" if test is not None else "\n(not scored)")
        figures.show_image(ax[0, j], v[:, ny // 2, :], f"{title}\nx-z, across the axis", low, high, (-x, x, -z, z),
                           axes=("x", "z"), unit="nm")
        figures.show_image(ax[1, j], v[:, :, nz // 2], "x-y, along the axis", low, high, (-x, x, -y, y),
                           axes=("x", "y"), unit="nm")
        ax[1, j].axvline(0.0, color="cyan", ls="--", lw=0.8)   # the tilt axis (y) in the x-y slice
    fig.suptitle("HAADF tilt series: central slices (own grey scale per volume; dashed: the tilt axis)")
    fig.savefig(path, dpi=100)
    shown = {name: f"{s['test_residual']:.4f}" for name, s in scores.items() if name in volumes and
             s.get("test_residual") is not None}
    path.with_suffix(".json").write_text(json.dumps(
        {"figure": path.name, "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "test_residual": shown},
        indent=1) + "\n")


def save(volumes: dict, domain: ImageDomain, out: Path) -> None:
    """Every volume as ``.npy`` and ``.mrc`` (the voxel size in Angstrom, as the MRC format has it)."""
    angstrom = ImageDomain(domain.shape, tuple(10 * float(m) for m in domain.min_pt),
                           tuple(10 * float(m) for m in domain.max_pt))
    for name, v in volumes.items():
        stem = name.lower().replace(" ", "_").replace("(", "").replace(")", "")
        np.save(out / f"{stem}.npy", v)
        io.write_volume(out / f"{stem}.mrc", v, angstrom)


# ------------------------------------------------------------------------------------------------ alignment
def etspy_frame(shifts: np.ndarray, factor: int) -> np.ndarray:
    """etspy's shifts (:func:`read_etspy_shifts`) as indreg's ``[across, along]`` in binned pixels: a feature at
    the ideal point ``q`` lies at ``q - s`` in the raw image, and the turn by ``tilt_axis_angle=90`` (``np.rot90``)
    takes the stored rows to indreg's columns (across) and the stored columns, reversed, to its rows (along)."""
    return np.stack([-shifts[:, 0], shifts[:, 1]], axis=1) / factor


def bilinear(T):
    """``T``, or for an ``AlignedOperator`` the same alignment with bilinear interpolation: SIRT needs a
    nonnegative matrix, and the cubic kernel has negative lobes."""
    if not isinstance(T, AlignedOperator):
        return T
    return AlignedOperator(T.operator, T.shifts, float(T.angle), "linear", T.edge)


def axis_offset(shifts: np.ndarray, angles: np.ndarray) -> float:
    """The tilt axis' offset (px, across) in ``shifts`` ``(K, 2)``: the constant of their least-squares fit by
    ``c + a cos(theta) + b sin(theta)`` (the rest is an object translation, docs/alignment.md)."""
    basis = np.stack([np.ones_like(angles), np.cos(angles), np.sin(angles)], axis=1)
    return float(np.linalg.lstsq(basis, shifts[:, 0], rcond=None)[0][0])


def compare_shifts(estimated: np.ndarray, reference: np.ndarray, T, factor: int) -> dict:
    """RMS differences ``[across, along]`` in raw pixels (``factor`` raw pixels per binned one) of two shift sets of
    the tilts of ``T`` in binned pixels, less a common offset, and in indreg's gauge (``indreg.alignment.gauge``);
    and the reference's RMS in the gauge."""
    d, ref = torch.as_tensor(estimated - reference), torch.as_tensor(reference)
    gauge = partial(alignment.gauge, AlignedOperator(T))
    rms = {"offset_removed": d - d.mean(dim=0), "gauge_removed": gauge(d), "reference_in_gauge": gauge(ref)}
    return {f"rms_px_{k}": (factor * v.pow(2).mean(dim=0).sqrt()).tolist() for k, v in rms.items()}


def alignment_figure(estimated: np.ndarray, reference: np.ndarray, T, factor: int, path: Path) -> None:
    """The estimated shifts and etspy's (both ``(K, 2)`` binned px) against the tilt angle, in raw pixels, across
    and along the axis; etspy's moved into the estimate's frame (the difference's offset and object translation,
    ``indreg.alignment.gauge``, added to them), so what is left between the curves is the RMS in the gauge."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = torch.as_tensor(estimated - reference)
    moved = reference + (d - alignment.gauge(AlignedOperator(T), d)).numpy()
    angles = np.degrees(T.geometry.angles.double().numpy())
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4), sharex=True)
    for i, name in enumerate(("across", "along")):
        ax[i].plot(angles, factor * estimated[:, i], "o-", ms=4, label="indreg (in the fit)")
        ax[i].plot(angles, factor * moved[:, i], "x--", ms=5, label="etspy (recorded), same frame")
        ax[i].set_title(f"shift {name} the tilt axis")
        ax[i].set_xlabel("tilt angle (deg)")
    ax[0].set_ylabel("raw pixels (3.36 nm)")
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
