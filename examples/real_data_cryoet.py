"""A measured cryo-ET tilt series of a slab, from the raw intensities to held-out scores (docs/real_data_cryoet.md).

The data: 41 tilts over +-60 degrees (3 degree steps, dose-symmetric), 652 x 630 pixels of 10 Angstrom, raw
(bright-field counts, not aligned), of Mycoplasma pneumoniae cells in ice (EMPIAR-10499, tilt series 00254), as
Genentech's ``warpylib`` 1.1.2 ships it for its tests (``testdata/00254.stack.mrc``), with an IMOD alignment of it
(``testdata/xf_import/00254.xf`` and ``.tlt``, the tilt axis at -4.30 degrees) and Warp's own (``00254.xml``).
Package licence: MIT (``LICENSE.txt`` in the sdist). Without ``--data`` it is fetched once with ``pip download
warpylib==1.1.2 --no-deps --no-binary :all:`` (58 MB, nothing installed) and the files are unpacked into
``--cache``; ``--data DIR`` (a folder holding ``00254.stack.mrc``, ``00254.xf``, ``00254.tlt``) runs offline.

Steps: ``indreg-align`` on the raw intensities (``--intensities``: ``-ln(I / I0)``, I0 from the slab law; the
specimen found to be a slab by the detector's border; ``--axis-from-stack``: the angle by common lines); its
shifts against IMOD's in the gauge (across the axis ``a cos + b sin`` removed, along it the mean), its angle against
IMOD's; then WBP, SIRT and TV of the wide box (``indreg.forward.wide_box``) from 31 tilts, binned by ``--bin``,
through no alignment (the axis turned only), IMOD's and indreg's, each scored on the 10 held-out tilts: 6 inside
the fitted range and the 4 beyond it (+-57, +-60). Each alignment lies in the operator
(``indreg.alignment.slab.aligned_slab_operator``: the projections moved, bilinearly), so every alignment fits and
is scored against the same binned views, never resampled (WBP alone, which filters along the axis frame's rows,
takes the views resampled into it by cubic splines). The score is noise-aware: the mean squared residual of a
held-out view over its noise variance, the latter from the view itself (each pixel less its four neighbours' mean,
whose variance is 5/4 of white noise's): 1 is a prediction to the noise. ``--folds N``: the same comparison of IMOD's
and indreg's alignment for SIRT over N interleaved held-out sets of the inside tilts (every N-th of the 37 between
the two at each end), each fitted on the other 40 tilts: every inside tilt scored once (about 4 s a fold and
alignment at bin 4).

    python examples/real_data_cryoet.py [--data DIR] [--cache DIR] [--out DIR] [--bin 4] [--iters 30] [--folds 5]

Outputs in ``--out``: the app's folder (``align/``), ``metrics.json`` and the table on stdout.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import indreg  # noqa: F401  (first: it sets the OpenMP policy before torch loads)
import numpy as np
import torch

PACKAGE = "warpylib==1.1.2"
MEMBERS = {"testdata/00254.stack.mrc": "00254.stack.mrc", "testdata/xf_import/00254.xf": "00254.xf",
           "testdata/xf_import/00254.tlt": "00254.tlt", "testdata/00254.xml": "00254.xml",
           "LICENSE.txt": "LICENSE.txt"}
NEEDED = ("00254.stack.mrc", "00254.xf", "00254.tlt")
#: IMOD's tilt axis for this series (the .xf's rotation), the start given to indreg-align.
AXIS_DEG = -4.3


def held_out(count: int) -> tuple:
    """``(inside, beyond)`` indices of the held-out tilts: the two at each end of the range (41 tilts: +-57, +-60)
    and six spread between them (41 tilts: -45, -27, -9, 9, 27, 45)."""
    beyond = (0, 1, count - 2, count - 1)
    inside = tuple(int(round(v)) for v in np.linspace(5 * (count - 1) / 40, 35 * (count - 1) / 40, 6))
    return inside, beyond


def say(text: str) -> None:
    print(text, flush=True)


def fetch(cache: Path) -> Path:
    """The folder with the series: ``cache`` if it has it, else the warpylib sdist downloaded and unpacked there."""
    if all((cache / n).exists() for n in NEEDED):
        return cache
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        say(f"downloading {PACKAGE} (sdist, 58 MB, not installed) into {tmp}")
        subprocess.run([sys.executable, "-m", "pip", "download", PACKAGE, "--no-deps", "--no-binary", ":all:",
                        "-d", tmp], check=True)
        with tarfile.open(next(Path(tmp).glob("warpylib-*.tar.gz"))) as tar:
            for member in tar.getmembers():
                name = member.name.split("/", 1)[-1]
                if name in MEMBERS:
                    (cache / MEMBERS[name]).write_bytes(tar.extractfile(member).read())
    return cache


def check_folder(folder: Path) -> Path:
    missing = [n for n in NEEDED if not (folder / n).exists()]
    if missing:
        raise SystemExit(f"real_data_cryoet: {folder} lacks {', '.join(missing)}: run without --data to fetch "
                         f"them (pip download {PACKAGE} --no-deps --no-binary :all:), or unpack testdata/ of that "
                         "sdist there")
    return folder


def align(folder: Path, out: Path, axis: float, extra: list) -> dict:
    """``indreg-align`` on the raw intensities (module docstring); its record."""
    from indreg.alignment.app import main

    args = [str(folder / "00254.stack.mrc"), "--angles", str(folder / "00254.tlt"), "--tilt-axis-angle",
            str(axis), "--intensities", "--axis-from-stack", "--out", str(out)] + extra
    if main(args) != 0:
        raise SystemExit("real_data_cryoet: indreg-align failed (its error above)")
    return json.loads((out / "align.json").read_text())


def reference(folder: Path) -> tuple:
    """IMOD's alignment as axis-frame shifts ``v = M^-1 d`` (px) and its angle (degrees)."""
    from indreg.alignment.files import read_xf

    a = read_xf(folder / "00254.xf", folder / "00254.tlt")
    return np.einsum("kij,kj->ki", np.linalg.inv(a.matrices), a.shifts), a.axis_angle_deg


def gauge_rms(v: np.ndarray, ref: np.ndarray, deg: np.ndarray) -> tuple:
    """RMS (across, along) px of ``v - ref`` in the gauge (module docstring)."""
    from indreg.alignment.slab import gauge_fix

    e = gauge_fix(v - ref, np.radians(deg))
    return float(np.sqrt((e[:, 0] ** 2).mean())), float(np.sqrt((e[:, 1] ** 2).mean()))


def noise_variance(view: np.ndarray) -> float:
    """White noise's variance from a view: each pixel less its four neighbours' mean has 5/4 of it."""
    core = view[1:-1, 1:-1] - 0.25 * (view[:-2, 1:-1] + view[2:, 1:-1] + view[1:-1, :-2] + view[1:-1, 2:])
    return float(core.var() / 1.25)


@dataclass
class Series:
    """The raw line integrals binned by ``b`` (``lines (K, ny, nx)``, never resampled for a score), indreg's angles
    ``theta`` (radians) and the wide box of a slab ``thickness`` px deep about ``centre`` (binned px), widened for
    all the tilts."""
    lines: np.ndarray
    theta: np.ndarray
    thickness: float
    centre: float
    b: int

    def operator(self, alpha_deg: float, v: np.ndarray, rows: np.ndarray, aligned: bool = True):
        """The tilts ``rows`` on the wide box with the alignment ``(alpha_deg, v full-size px)`` in the operator
        (``indreg.alignment.slab.aligned_slab_operator``, bilinear); ``aligned=False``: the axis frame's plain
        operator."""
        from indreg.alignment.slab import aligned_slab_operator, slab_operators

        K, ny, nx = self.lines.shape
        if not aligned:
            return slab_operators(self.theta[rows], nx, ny, self.thickness, self.centre, self.theta)[0]
        return aligned_slab_operator(self.theta[rows], nx, ny, self.thickness, alpha_deg,
                                     np.asarray(v)[rows] / self.b, self.centre, self.theta)

    def views(self, rows: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(self.lines[rows], dtype=np.float32))


def binned_series(lines: np.ndarray, deg: np.ndarray, box: tuple, b: int) -> Series:
    """The line integrals ``(K, ny, nx)`` binned by ``b``, the IMOD-signed angles ``deg`` as indreg's, the box
    ``(thickness, centre)`` in full-size px."""
    from indreg.alignment.slab import binned

    return Series(binned(lines, b), -np.radians(deg), box[0] / b, box[1] / b, b)


def reconstructions(series: Series, alpha: float, v: np.ndarray, fit: np.ndarray, iters: int,
                    methods: tuple = ("WBP", "SIRT", "TV")) -> dict:
    """``methods`` of WBP, SIRT and TV of the wide box from the tilts ``fit``: SIRT and TV through the operator
    with the alignment in it, WBP (which filters along the axis frame's rows) from the views resampled into the
    axis frame by cubic splines."""
    from indreg.alignment.xcorr import axis_frame
    from indreg.forward import fbp, sirt, tv_reconstruction
    from indreg.forward.tv import tv_weight_unit

    T, y = series.operator(alpha, v, fit), series.views(fit)
    x_sirt = sirt(T, y, num_iter=iters, nonneg=True)[0]
    out = {"SIRT": x_sirt}
    if "WBP" in methods:
        frames = axis_frame(series.lines[fit], alpha, v[fit] / series.b, order=3)
        out["WBP"] = fbp(series.operator(alpha, v, fit, aligned=False),
                         torch.from_numpy(np.ascontiguousarray(frames, dtype=np.float32)))
    if "TV" in methods:
        out["TV"] = tv_reconstruction(T, y, 0.1 * tv_weight_unit(T, y), num_iter=iters, x0=x_sirt, nonneg=True)[0]
    return {m: out[m] for m in methods}


def scores(series: Series, volumes: dict, alpha: float, v: np.ndarray, held: np.ndarray) -> dict:
    """Per volume, the noise-aware score (module docstring) of the raw held-out views against the volume's
    projections through the alignment: ``{name: (len(held),) array}``."""
    T, views = series.operator(alpha, v, held), series.lines[held]
    sigma2 = np.array([noise_variance(view) for view in views])
    return {name: ((T(x).numpy() - views) ** 2).mean(axis=(1, 2)) / sigma2 for name, x in volumes.items()}


def cross_validation(series: Series, alignments: dict, iters: int, folds: int) -> dict:
    """SIRT's score (module docstring) of every inside tilt, held out in one of ``folds`` interleaved sets and
    predicted from the other tilts, per alignment ``(alpha_deg, v full-size px)``: ``{label: (K,) array}`` (NaN at
    the 4 tilts beyond the range)."""
    count = len(series.theta)
    out = {}
    for label, (alpha, v) in alignments.items():
        chi = np.full(count, np.nan)
        for j in range(folds):
            held = np.arange(2 + j, count - 2, folds)
            x = reconstructions(series, alpha, v, np.setdiff1d(np.arange(count), held), iters, ("SIRT",))["SIRT"]
            chi[held] = scores(series, {"SIRT": x}, alpha, v, held)["SIRT"]
        out[label] = chi
    return out


def held_out_table(series: Series, alignments: dict, iters: int) -> dict:
    """For each alignment ``(alpha_deg, v full-size px)``: WBP / SIRT / TV from the 31 fit tilts, scored on the
    10 held out (inside / beyond)."""
    inside_k, beyond_k = held_out(len(series.theta))
    held = np.array(sorted(inside_k + beyond_k))
    fit = np.setdiff1d(np.arange(len(series.theta)), held)
    inside = np.isin(held, inside_k)
    table = {}
    for label, (alpha, v) in alignments.items():
        chi = scores(series, reconstructions(series, alpha, v, fit, iters), alpha, v, held)
        table[label] = {m: {"inside": float(c[inside].mean()), "beyond": float(c[~inside].mean())}
                        for m, c in chi.items()}
    return table


def beads_table(lines: np.ndarray, deg: np.ndarray, alignments: dict) -> dict:
    """The gold beads' fit (``indreg.alignment.fiducials``) with each alignment's shifts held: RMS (across, along)
    px, the beads' positions solved alone."""
    from indreg.alignment.fiducials import bead_residual, fiducial_alignment

    theta = -np.radians(deg)
    axis, v = alignments["indreg-align"]
    fit = fiducial_alignment(lines, theta, axis, v)
    if not fit.determined:
        return {"not determined": fit.reason}
    return {label: bead_residual(fit, theta, a, s) for label, (a, s) in alignments.items()}


def format_table(m: dict) -> str:
    rows = [f"indreg-align vs IMOD: shifts {m['rms_across']:.2f} / {m['rms_along']:.2f} px RMS across / along "
            f"(gauge; no shifts: {m['none_across']:.2f} / {m['none_along']:.2f}), tilt axis {m['axis_deg']:.2f} "
            f"deg (IMOD {m['imod_axis_deg']:.2f}), {m['seconds']:.0f} s, peak {m['peak_gib']:.2f} GiB",
            "the gold beads' fit with the shifts held (px RMS across / along): " + ", ".join(
                f"{label} {r}" if isinstance(r, str) else f"{label} {r[0]:.2f} / {r[1]:.2f}"
                for label, r in m["beads"].items()),
            "", "held-out score (mean squared residual / noise variance; 1 = to the noise), bin "
            f"{m['bin']}", f"{'alignment':<14}{'method':<7}{'inside':>12}{'beyond':>12}"]
    for label, methods in m["held_out"].items():
        for method, s in methods.items():
            rows.append(f"{label:<14}{method:<7}{s['inside']:>12.3f}{s['beyond']:>12.3f}")
    if "folds" in m:
        f = m["folds"]
        rows += ["", f"SIRT over {f['folds']} interleaved held-out sets (each inside tilt held out once): IMOD "
                 f"{f['IMOD']:.3f}, indreg-align {f['indreg-align']:.3f}, ratio {f['ratio']:.3f}; indreg-align "
                 f"better at {f['better']} of {f['tilts']} tilts"]
    return "\n".join(rows)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, help="a folder with the series (default: fetched into --cache)")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "indreg" / "cryoet")
    p.add_argument("--out", type=Path, default=Path("cryoet_out"))
    p.add_argument("--bin", type=int, default=4, help="binning of the held-out reconstructions (default 4)")
    p.add_argument("--iters", type=int, default=30, help="SIRT / TV iterations (default 30)")
    p.add_argument("--tilt-axis-angle", type=float, default=AXIS_DEG, help="the start (default IMOD's -4.3)")
    p.add_argument("--align-args", default="", help="more indreg-align options, one string")
    p.add_argument("--folds", type=int, default=0, help="SIRT's cross-validation over this many held-out sets "
                   "(default 0: off)")
    a = p.parse_args(argv)
    folder = check_folder(a.data) if a.data is not None else fetch(a.cache)
    from indreg.io import read_tilt_series

    stack, radians = read_tilt_series(folder / "00254.stack.mrc", folder / "00254.tlt")
    deg = np.degrees(radians)
    t0 = time.perf_counter()
    record = align(folder, a.out / "align", a.tilt_axis_angle, a.align_args.split())
    ref, ref_axis = reference(folder)
    v = np.asarray(record["slab"]["shifts_axis_frame_px"]) if record.get("slab") else None
    if v is None:
        raise SystemExit("real_data_cryoet: indreg-align did not take the slab path (see its log)")
    from indreg.alignment.slab_app import line_integrals

    lines = line_integrals(stack, -radians)[0]
    lines = lines - float(record["background"])
    axis = record["axis_angle_deg"]
    m = {"bin": a.bin, "axis_deg": axis, "imod_axis_deg": ref_axis, "seconds": record["seconds"],
         "peak_gib": record["peak_rss_bytes"] / 2**30}
    m["rms_across"], m["rms_along"] = gauge_rms(v, ref, deg)
    m["none_across"], m["none_along"] = gauge_rms(np.zeros_like(ref), ref, deg)
    m["beads"] = beads_table(lines, deg, {"indreg-align": (axis, v), "IMOD": (ref_axis, ref),
                                          "no shifts": (axis, np.zeros_like(ref))})
    series = binned_series(lines, deg, (record["slab"]["thickness_px"], record["slab"]["centre_px"]), a.bin)
    m["held_out"] = held_out_table(series, {"axis only": (a.tilt_axis_angle, np.zeros_like(ref)),
                                            "IMOD": (ref_axis, ref), "indreg-align": (axis, v)}, a.iters)
    if a.folds:
        chi = cross_validation(series, {"IMOD": (ref_axis, ref), "indreg-align": (axis, v)}, a.iters, a.folds)
        inside = np.isfinite(chi["IMOD"])
        m["folds"] = {"folds": a.folds, "tilts": int(inside.sum()), "IMOD": float(chi["IMOD"][inside].mean()),
                      "indreg-align": float(chi["indreg-align"][inside].mean()),
                      "better": int((chi["indreg-align"] < chi["IMOD"])[inside].sum()),
                      "per_tilt": {k: [None if not np.isfinite(c) else float(c) for c in x] for k, x in chi.items()}}
        m["folds"]["ratio"] = m["folds"]["indreg-align"] / m["folds"]["IMOD"]
    m["walk_seconds"] = time.perf_counter() - t0
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "metrics.json").write_text(json.dumps(m, indent=1) + "\n")
    say(format_table(m))


if __name__ == "__main__":
    main()
