"""Benchmark the ray transform against scikit-image on the paper's three geometries and a fan beam.

Prints one Markdown table: one-time construction, memory, indreg forward / adjoint (median of repeats),
skimage ``radon`` / ``iradon(filter_name=None)`` (pure backprojection) on the same image, and the
speed-up ``(radon + iradon) / (forward + adjoint)`` in float64 (the dtype skimage computes in).
The fan-beam row (256^2, 360 views over 2 pi, 512 bins, source and detector at 40 from the origin) has no
scikit-image counterpart: its yardstick is skimage's parallel ``radon``/``iradon`` with the same number of
views (over [0, 180) degrees) on the same image, in the same run; the row before it is indreg's parallel
projector at the same size (360 uniform angles on [0, pi), 512 bins, detector fitted to the domain).
ASTRA columns (``astra``'s CPU ``line_fanflat`` / ``linear`` projectors, same geometry) are added only when
``astra`` imports.

Memory: "matrix MB" is the exact size of the CSR pair (A and A^T, values + indices) for one dtype;
"RSS delta MB" is the growth of the process's peak resident set size (``ru_maxrss``) while building the
operator and running it once, i.e. including construction temporaries (0 if an earlier, larger peak
was not exceeded, so geometries are run from small to large).

A second table times the 3D single-axis tilt series (``TiltSeriesTransform``; 61 tilts, -60..60 degrees in
2-degree steps, tilt axis y, detector as wide as the volume) on 64^3 and 128^3 in float32: forward and adjoint
seconds (median), one batched sparse product over all slices.

Usage: python scripts/bench_operators.py [--repeats 20] [--threads 2] [--only-3d]
"""
import argparse
import resource
import time

import numpy as np
import torch
from skimage.transform import iradon, radon

from indreg import ImageDomain, ParallelBeamGeometry, RayTransform
from indreg.forward import FanBeamGeometry, TiltSeriesGeometry, TiltSeriesTransform

GEOMETRIES = [(64, 10, 92), (256, 10, 362), (438, 6, 620)]   # grid n, angles, bins; detector [-24, 24]
FAN = (256, 360, 512, 40.0, 40.0)                              # grid n, views over 2 pi, bins, src/det radius
TILT_GRIDS = (64, 128)                                         # n^3 volumes on [-16, 16]^3, 61 tilts +-60 deg

try:
    import astra
except ImportError:   # optional: not a dependency
    astra = None


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


def bench(n: int, num_angles: int, bins: int, repeats: int, geometry=None) -> dict:
    domain = ImageDomain.paper(n)
    fan = isinstance(geometry, FanBeamGeometry)
    label = "fan " if fan else ("" if geometry is None else "uniform ")
    geometry = ParallelBeamGeometry.paper(num_angles, bins) if geometry is None else geometry
    rss0 = peak_rss_mb()
    t = time.perf_counter()
    T = RayTransform(domain, geometry)
    build_ms = 1e3 * (time.perf_counter() - t)
    image = torch.rand(n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    data = T(image)
    row = dict(grid=f"{n}^2", geom=label + f"{num_angles} x {bins}", nnz=T.system.nnz,
               build=build_ms,
               matrix_mb=T.system.nbytes(torch.float64) / 2**20, rss_mb=peak_rss_mb() - rss0)
    with torch.no_grad():
        for dtype, tag in ((torch.float64, "64"), (torch.float32, "32")):
            x, y = image.to(dtype), data.to(dtype)
            row["fwd" + tag] = median_ms(lambda: T(x), repeats)
            row["adj" + tag] = median_ms(lambda: T.adjoint(y), repeats)
    theta = np.arange(num_angles) * (180.0 / num_angles) if fan else np.rad2deg(geometry.angles.numpy())
    theta = theta if fan else np.mod(theta, 180.0)
    upright = np.rot90(image.numpy()).copy()             # skimage rows = y (descending), cols = x
    sino = radon(upright, theta, circle=False)
    row["radon"] = median_ms(lambda: radon(upright, theta, circle=False), max(3, repeats // 4))
    row["iradon"] = median_ms(lambda: iradon(sino, theta, output_size=n, filter_name=None, circle=False),
                              max(3, repeats // 4))
    row["speedup"] = (row["radon"] + row["iradon"]) / (row["fwd64"] + row["adj64"])
    if astra is not None:
        row.update(bench_astra(T, upright, max(3, repeats // 4)))
    return row


def bench_astra(T, upright: np.ndarray, repeats: int) -> dict:
    """ASTRA CPU forward / backprojection (float32) on the same geometry (docs/geometry.md's mapping)."""
    (nx, ny), g = T.domain.shape, T.geometry
    vol = astra.create_vol_geom(ny, nx, T.domain.min_pt[0], T.domain.max_pt[0], T.domain.min_pt[1],
                                T.domain.max_pt[1])
    if isinstance(g, FanBeamGeometry):
        proj = astra.create_proj_geom("fanflat", g.det_cell, g.det_count, g.angles.numpy(), g.src_radius,
                                      g.det_radius)
        pid = astra.create_projector("line_fanflat", proj, vol)
    else:
        proj = astra.create_proj_geom("parallel", g.det_cell, g.det_count, g.angles.numpy())
        pid = astra.create_projector("linear", proj, vol)
    image = upright.astype(np.float32)
    sino_id, sino = astra.create_sino(image, pid)
    out = dict(astra_fwd=median_ms(lambda: astra.create_sino(image, pid, returnData=False), repeats),
               astra_adj=median_ms(lambda: astra.create_backprojection(sino, pid), repeats))
    astra.data2d.delete(sino_id)
    astra.projector.delete(pid)
    return out


def bench_tilt_series(n: int, repeats: int) -> dict:
    """Forward / adjoint seconds (float32) of the tilt series on n^3 (module docstring)."""
    domain = ImageDomain.paper(n, 3)
    t = time.perf_counter()
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 2, det_count=n, det_min=-16.0,
                                                               det_max=16.0))
    build = time.perf_counter() - t
    x = torch.rand(domain.shape, generator=torch.Generator().manual_seed(0)).float()
    y = T(x)
    with torch.no_grad():
        fwd, adj = (median_ms(fn, repeats) / 1e3 for fn in (lambda: T(x), lambda: T.adjoint(y)))
    return dict(grid=f"{n}^3", data=" x ".join(map(str, T.range_shape)), nnz=T.system.nnz, build=build,
                fwd=fwd, adj=adj)


def print_tilt_series(repeats: int) -> None:
    print("\n| volume | data (tilts x rows x cols) | nnz per slice | build s | fwd f32 s | adj f32 s |")
    print("|---" * 6 + "|")
    for n in TILT_GRIDS:
        r = bench_tilt_series(n, max(3, repeats // 4))
        print(f"| {r['grid']} | {r['data']} | {r['nnz']:,} | {r['build']:.2f} | {r['fwd']:.3f} | {r['adj']:.3f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--only-3d", action="store_true", help="only the tilt-series table")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.only_3d:
        print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
        print_tilt_series(args.repeats)
        return
    rows = [bench(n, a, b, args.repeats) for n, a, b in GEOMETRIES]
    n, views, bins, src, det = FAN
    rows.append(bench(n, views, bins, args.repeats, ParallelBeamGeometry(views, bins)))   # same size, parallel
    rows.append(bench(n, views, bins, args.repeats, FanBeamGeometry(views, bins, src_radius=src, det_radius=det)))
    astra_cols = astra is not None
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; times are medians in ms; "
          f"astra {'version ' + str(astra.__version__) if astra_cols else 'not installed (no ASTRA columns)'}\n")
    print("| grid | angles x bins | nnz(A) | build ms | matrix MB (f64) | RSS delta MB | fwd f64 | adj f64 "
          "| fwd f32 | adj f32 | skimage radon | skimage iradon | speed-up (f64) |"
          + (" ASTRA fwd f32 | ASTRA adj f32 |" if astra_cols else ""))
    print("|---" * (13 + 2 * astra_cols) + "|")
    for r in rows:
        print(f"| {r['grid']} | {r['geom']} | {r['nnz']:,} | {r['build']:.0f} | {r['matrix_mb']:.1f} "
              f"| {r['rss_mb']:.0f} | {r['fwd64']:.2f} | {r['adj64']:.2f} | {r['fwd32']:.2f} | {r['adj32']:.2f} "
              f"| {r['radon']:.1f} | {r['iradon']:.1f} | {r['speedup']:.1f}x |"
              + (f" {r['astra_fwd']:.1f} | {r['astra_adj']:.1f} |" if astra_cols else ""))
    print("\nThe fan row's skimage columns are the parallel radon / iradon with the same number of views.")
    print_tilt_series(args.repeats)


if __name__ == "__main__":
    main()
