"""Benchmark the ray transform against scikit-image on the paper's three geometries.

Prints one Markdown table: one-time construction, memory, indreg forward / adjoint (median of repeats),
skimage ``radon`` / ``iradon(filter_name=None)`` (pure backprojection) on the same image, and the
speed-up ``(radon + iradon) / (forward + adjoint)`` in float64 (the dtype skimage computes in).

Memory: "matrix MB" is the exact size of the CSR pair (A and A^T, values + indices) for one dtype;
"RSS delta MB" is the growth of the process's peak resident set size (``ru_maxrss``) while building the
operator and running it once, i.e. including construction temporaries (0 if an earlier, larger peak
was not exceeded, so geometries are run from small to large).

Usage: python scripts/bench_operators.py [--repeats 20] [--threads 2]
"""
import argparse
import resource
import time

import numpy as np
import torch
from skimage.transform import iradon, radon

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform

GEOMETRIES = [(64, 10, 92), (256, 10, 362), (438, 6, 620)]   # grid n, angles, bins; detector [-24, 24]


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024   # Linux: kilobytes


def bench(n: int, num_angles: int, bins: int, repeats: int) -> dict:
    domain, geometry = ImageDomain.paper(n), ParallelBeamGeometry.paper(num_angles, bins)
    rss0 = peak_rss_mb()
    t = time.perf_counter()
    T = RayTransform(domain, geometry)
    build_ms = 1e3 * (time.perf_counter() - t)
    image = torch.rand(n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    data = T(image)
    row = dict(grid=f"{n}^2", geom=f"{num_angles} x {bins}", nnz=T.system.nnz, build=build_ms,
               matrix_mb=T.system.nbytes(torch.float64) / 2**20, rss_mb=peak_rss_mb() - rss0)
    with torch.no_grad():
        for dtype, tag in ((torch.float64, "64"), (torch.float32, "32")):
            x, y = image.to(dtype), data.to(dtype)
            row["fwd" + tag] = median_ms(lambda: T(x), repeats)
            row["adj" + tag] = median_ms(lambda: T.adjoint(y), repeats)
    theta = np.rad2deg(geometry.angles.numpy())
    upright = np.rot90(image.numpy()).copy()             # skimage rows = y (descending), cols = x
    sino = radon(upright, theta, circle=False)
    row["radon"] = median_ms(lambda: radon(upright, theta, circle=False), max(3, repeats // 4))
    row["iradon"] = median_ms(lambda: iradon(sino, theta, output_size=n, filter_name=None, circle=False),
                              max(3, repeats // 4))
    row["speedup"] = (row["radon"] + row["iradon"]) / (row["fwd64"] + row["adj64"])
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = [bench(n, a, b, args.repeats) for n, a, b in GEOMETRIES]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; times are medians in ms\n")
    print("| grid | angles x bins | nnz(A) | build ms | matrix MB (f64) | RSS delta MB | fwd f64 | adj f64 "
          "| fwd f32 | adj f32 | skimage radon | skimage iradon | speed-up (f64) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['grid']} | {r['geom']} | {r['nnz']:,} | {r['build']:.0f} | {r['matrix_mb']:.1f} "
              f"| {r['rss_mb']:.0f} | {r['fwd64']:.2f} | {r['adj64']:.2f} | {r['fwd32']:.2f} | {r['adj32']:.2f} "
              f"| {r['radon']:.1f} | {r['iradon']:.1f} | {r['speedup']:.1f}x |")


if __name__ == "__main__":
    main()
