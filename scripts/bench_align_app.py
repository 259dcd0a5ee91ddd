"""indreg-align on a synthetic raw tilt series: N x N images, K tilts from -60 to 60 degrees, Gaussian blobs projected
analytically, shifted by random drift (up to 8 px, scipy.ndimage.shift), as an MRC + .tlt; then indreg-align in a
child process under ``/usr/bin/time -v`` (its peak RSS and CPU seconds are its own) with the given options. Prints
the summary line, the JSON's numbers and the shifts' error against the drift (RMS in the gauge of docs/alignment.md,
and with only a common offset removed).

    OMP_NUM_THREADS=1 python scripts/bench_align_app.py --size 1024 --tilts 61 -- --max-memory 8GiB \
        --rounds 3 --fine-rounds 1 --iters 15 --thickness 320      # docs/file_formats.md's run
"""
import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.ndimage import shift as nd_shift


def synthetic(n: int, tilts: int, seed: int = 0) -> tuple:
    """Projections of 40 Gaussian blobs in a slab (x, y in +-n/3, z in +-n/8), tilt axis along Y, and the drift."""
    gen = np.random.default_rng(seed)
    theta = np.radians(np.linspace(-60, 60, tilts))
    c = (np.arange(n) - (n - 1) / 2)
    blobs = gen.uniform(-1, 1, (40, 3)) * [n / 3, n / 3, n / 8]
    sigma = gen.uniform(0.01, 0.03, 40) * n
    stack = np.zeros((tilts, n, n), dtype=np.float32)
    drift = gen.uniform(-8, 8, (tilts, 2))
    for k, t in enumerate(theta):
        image = np.zeros((n, n))
        for (x, y, z), s in zip(blobs, sigma):
            u = x * np.cos(t) + z * np.sin(t)
            image += np.outer(np.exp(-(c - y) ** 2 / (2 * s * s)), np.exp(-(c - u) ** 2 / (2 * s * s))) * s
        stack[k] = nd_shift(image, drift[k, ::-1], order=1, mode="nearest")
    return stack, np.degrees(theta), drift


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--tilts", type=int, default=61)
    p.add_argument("--dir", default=None)
    p.add_argument("rest", nargs="*", help="indreg-align's options (after --)")
    a = p.parse_args()
    import mrcfile

    d = Path(a.dir or tempfile.mkdtemp())
    d.mkdir(parents=True, exist_ok=True)
    stack, degrees, drift = synthetic(a.size, a.tilts)
    with mrcfile.new(d / "raw.mrc", overwrite=True) as mrc:
        mrc.set_data(stack)
        mrc.voxel_size = 2.0
    np.savetxt(d / "raw.tlt", degrees, fmt="%.3f")
    del stack
    timer = ["/usr/bin/time", "-v"] if Path("/usr/bin/time").exists() else []
    r = subprocess.run(timer + [sys.executable, "-m", "indreg.alignment.app", str(d / "raw.mrc"), "--out",
                                str(d / "out")] + a.rest, capture_output=True, text=True)
    print(r.stderr[-6000:], r.stdout)
    s = json.loads((d / "out/align.json").read_text())
    xf = np.loadtxt(d / "out/alignment.xf")
    theta = np.radians(degrees)
    basis = np.stack([np.cos(theta), np.sin(theta)], 1)

    def gauge(v):
        return np.stack([v[:, 0] - basis @ np.linalg.lstsq(basis, v[:, 0], rcond=None)[0], v[:, 1] - v[:, 1].mean()], 1)

    def rms(e):
        return np.sqrt((e ** 2).mean(0)).round(3).tolist()
    error = -xf[:, 4:] - drift   # IMOD's D moves the raw image back: D = -drift
    print(json.dumps({k: s[k] for k in ("residual_before", "residual_after", "binning", "recon_binning",
                                        "volume_shape", "seconds", "cpu_seconds", "peak_rss_bytes",
                                        "max_memory_bytes")}))
    print("levels:", json.dumps([(h["bin"], [round(v[0], 4) for v in h["rounds"]]) for h in s["levels"]]))
    print("shift RMS error across / along (px): in the gauge", rms(gauge(-xf[:, 4:]) - gauge(drift)),
          "a common offset removed", rms(error - error.mean(0)))


if __name__ == "__main__":
    main()
