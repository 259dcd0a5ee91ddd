"""Check ``indreg.load(..., convention=...)`` against the other tools themselves (``indreg.io.conventions``).

For each tool: a phantom (scikit-image's Shepp-Logan picture plus an off-centre blob, no mirror symmetry) is
projected by the tool's own forward operator in its own convention, saved as the tool saves it, and loaded with
``convention=<tool>``. Printed: the relative difference between the loaded data and indreg's operator applied to
the loaded template (``rel``), the same with the detector reversed (``flipped``: what a wrong sign would give), and
with ``--register`` the SSIM of 60 iterations of ``indreg.register`` on the tool's data against the same problem
with data made by indreg's operator (the two should agree within 0.01).

    ASTRA   astra-toolbox, 2D "parallel" on its default volume (one unit a pixel), CPU projectors line/linear/strip
    ODL     odl.applications.tomo.RayTransform (impl="astra_cpu") on uniform_discr, parallel_beam_geometry
    TomoPy  tomopy.project (conda only); without it, the ray geometry of its source (libtomo calc_coords: rays
            along (cos theta, sin theta) of the slice's axes (1, 2), bins along (-sin theta, cos theta), centred)
            on Gaussian blobs, whose line integrals are exact
    IMOD    MRC files as IMOD writes them (mrcfile): a section of ``tilt``'s reconstruction (Y, Z, X) read as a 2D
            ``convention=imod`` problem against the tilt series' row (IMOD's sense and pixel sums), against the
            3D ``convention=imod`` loader's data

Tools that are not installed are skipped. Usage (a venv with the tools beside indreg's)::

    pip install astra-toolbox odl
    python scripts/verify_conventions.py [--register]
"""
from __future__ import annotations

import argparse
import importlib
import logging
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

import indreg
from indreg.metrics import ssim

THETA = np.linspace(0.0, 180.0, 20, endpoint=False) + 7.0        # degrees, not starting at 0


def picture(n: int) -> np.ndarray:
    """scikit-image's Shepp-Logan phantom as displayed, plus an off-centre blob."""
    from skimage.data import shepp_logan_phantom
    from skimage.transform import resize

    r, c = np.mgrid[:n, :n]
    blob = np.exp(-((r - 0.3 * n) ** 2 + (c - 0.65 * n) ** 2) / (2 * (n / 12) ** 2))
    return resize(shepp_logan_phantom(), (n, n), anti_aliasing=True) + blob


def warped(pic: np.ndarray) -> np.ndarray:
    """The picture under a smooth known deformation (the registration's target)."""
    from skimage.transform import warp

    r, c = np.mgrid[:pic.shape[0], :pic.shape[1]].astype(float)
    return warp(pic, np.array([r + 2.5 * np.sin(c / 9), c + 1.5]), order=1)


def relative(a, b) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def compare(folder: Path, template: np.ndarray, data: np.ndarray, name: str, **load) -> tuple:
    """``(rel, flipped)`` of the tool's data saved as .npy and loaded with ``convention=name``."""
    np.save(folder / "t.npy", template)
    np.save(folder / "s.npy", data)
    np.save(folder / "f.npy", np.flip(data, -1 if indreg.io.conventions.CONVENTIONS[name].sinogram == "angle_bin" else 0))
    d, f = (indreg.load(folder / "t.npy", folder / s, convention=name, **load) for s in ("s.npy", "f.npy"))
    return relative(d.operator(d.template), d.data), relative(f.operator(f.template), f.data)


def registration(template, target, data, name: str, **load) -> tuple:
    """SSIM of ``indreg.register`` on the tool's data and on indreg's own data of the same problem."""
    d = indreg.load(template, data, convention=name, target=target, **load)
    runs = [indreg.register(d.template, g, d.operator, sigma=2.0, max_iter=60).deformed for g in
            (d.data, d.operator(d.target))]
    return tuple(ssim(x, d.target) for x in runs)


# --- the tools --------------------------------------------------------------------------------------------------

def astra_sinogram(astra, image: np.ndarray, theta_deg, det_count: int, kind: str) -> np.ndarray:
    """ASTRA's sinogram ``(angles, bins)`` of its volume array ``image`` (default geometry, one unit a pixel)."""
    n = image.shape[0]
    vol, proj = astra.create_vol_geom(n, n), astra.create_proj_geom("parallel", 1.0, det_count, np.deg2rad(theta_deg))
    pid = astra.create_projector(kind, proj, vol)
    sid, g = astra.create_sino(image.astype(np.float32), pid)
    astra.data2d.delete(sid)
    astra.projector.delete(pid)
    return g


def check_astra(folder: Path, register: bool) -> list:
    astra = importlib.import_module("astra")
    rows = []
    for n, det_count in ((64, 64), (65, 91)):
        for kind in ("line", "linear", "strip"):
            g = astra_sinogram(astra, picture(n), THETA, det_count, kind)
            rel, flip = compare(folder, picture(n), g, "astra", angles=THETA, half_width=16.0)
            rows.append((f"astra {astra.__version__}", f"{n}^2, {det_count} bins, '{kind}'", rel, flip))
    if register:
        target = warped(picture(64))
        g = astra_sinogram(astra, target, THETA, 64, "linear")
        rows.append(("astra", "register 'linear' data", *registration(picture(64), target, g, "astra", angles=THETA)))
    return rows


def odl_sinogram(odl, image: np.ndarray, half_width: float):
    """ODL's data of its element ``image`` (axis 0 = x) on ``[-half_width, half_width]^2``: (data, geometry)."""
    from odl.applications import tomo

    n = image.shape[0]
    space = odl.uniform_discr([-half_width] * 2, [half_width] * 2, (n, n), dtype="float32")
    geometry = tomo.parallel_beam_geometry(space, num_angles=20)
    g = tomo.RayTransform(space, geometry, impl="astra_cpu")(space.element(image.astype(np.float32))).asarray()
    return np.asarray(g.cpu() if hasattr(g, "cpu") else g), geometry


def check_odl(folder: Path, register: bool) -> list:
    odl = importlib.import_module("odl")
    rows = []
    for n, half_width in ((64, 16.0), (65, 10.0)):
        f = np.rot90(picture(n), k=-1).copy()                   # ODL's arrays are (x, y): indreg's layout
        g, geometry = odl_sinogram(odl, f, half_width)
        angles = np.asarray(geometry.angles)
        for given in (True, False):      # parallel_beam_geometry's detector given, or left to indreg
            det = dict(det_min=geometry.det_partition.min_pt[0], det_max=geometry.det_partition.max_pt[0]) if given \
                else {}
            rel, flip = compare(folder, f, g, "odl", angles=angles, angle_unit="rad", half_width=half_width, **det)
            rows.append((f"odl {odl.__version__}", f"{n}^2, {g.shape[1]} bins, detector "
                                                   f"{'given' if given else 'fitted by indreg'}", rel, flip))
    if register:
        f, target = (np.rot90(a, k=-1).copy() for a in (picture(64), warped(picture(64))))
        g, geometry = odl_sinogram(odl, target, 16.0)
        rows.append(("odl", "register", *registration(f, target, g, "odl", angles=np.asarray(geometry.angles),
                                                      angle_unit="rad")))
    return rows


BLOBS = ((-9.0, 5.0, 3.0, 1.0), (6.0, 10.0, 2.0, 0.7), (4.0, -7.0, 4.0, 0.5))     # (x_t, y_t, std, amplitude)


def tomopy_model(n: int, theta_rad: np.ndarray) -> tuple:
    """Gaussian blobs in TomoPy's slice coordinates (pixels; ``x_t`` along array axis 1, ``y_t`` along axis 2 of
    ``obj``, centred) sampled as ``obj[0]`` and their exact projections in the geometry of libtomo's
    ``calc_coords`` (source ``R(theta) (xi, yi)``, detector ``R(theta) (-xi, yi)``: rays along
    ``(cos theta, sin theta)``, bin ``d`` at ``yi = d - (n - 1) / 2`` along ``(-sin theta, cos theta)``)."""
    c = np.arange(n) - (n - 1) / 2
    xt, yt = np.meshgrid(c, c, indexing="ij")
    image = sum(a * np.exp(-((xt - x) ** 2 + (yt - y) ** 2) / (2 * s ** 2)) for x, y, s, a in BLOBS)
    centre = lambda x, y: (-x * np.sin(theta_rad) + y * np.cos(theta_rad))[:, None]     # blob's position on the bins
    data = sum(a * np.sqrt(2 * np.pi) * s * np.exp(-(c[None, :] - centre(x, y)) ** 2 / (2 * s ** 2))
               for x, y, s, a in BLOBS)
    return image, data


def check_tomopy(folder: Path, register: bool) -> list:
    try:
        tomopy = importlib.import_module("tomopy")
    except ImportError:
        tomopy = None
    rows, theta = [], np.deg2rad(THETA)
    for n in (64, 65):
        image, g = tomopy_model(n, theta)
        rel, flip = compare(folder, image, g, "tomopy", angles=THETA, half_width=16.0)
        rows.append(("tomopy (calc_coords)", f"{n}^2 Gaussian blobs, exact line integrals", rel, flip))
        if tomopy is not None:
            obj = picture(n)[None].astype(np.float32)
            g = tomopy.project(obj, theta, pad=False)[:, 0, :]             # (angles, rows, bins): row 0
            rel, flip = compare(folder, obj[0], g, "tomopy", angles=THETA, half_width=16.0)
            rows.append((f"tomopy {tomopy.__version__}", f"{n}^2, tomopy.project(pad=False)", rel, flip))
    return rows


def check_imod(folder: Path, register: bool) -> list:
    """IMOD's files: the tilt series (tilt, Y, X) of a volume as IMOD's ``tilt`` projects it (column
    ``x cos b - z sin b``, pixel sums: indreg's operator at the angles ``-b``, divided by the pixel side, with the
    ``.tlt`` holding ``b``) and one section of ``tilt``'s unrotated reconstruction (Y, Z, X), i.e. a 2D image (Z, X)
    with Z up; the 2D load of that section and the series' row against the 3D ``convention=imod`` load of the whole
    series (docs/file_formats.md, "IMOD's projection convention")."""
    mrcfile = importlib.import_module("mrcfile")
    n, j = 32, 13
    domain = indreg.ImageDomain((n, n, n), (-8.0,) * 3, (8.0,) * 3)       # volume (x, y, z), tilt axis y
    h = domain.cell_sides[0]
    rng = np.random.default_rng(0)
    f = indreg.phantoms.get("shepp_logan", indreg.ImageDomain.paper(n)).numpy()[:, None, :] * rng.uniform(0.5, 1.5, n)[
        None, :, None] + np.where(np.arange(n)[None, None, :] < 9, 0.4, 0.0)     # (x, y, z), no mirror symmetry
    tilts = THETA - 60.0
    geometry = indreg.TiltSeriesGeometry(torch.from_numpy(-np.deg2rad(tilts)), n, -8.0, 8.0, angle_unit="rad")
    g = indreg.TiltSeriesTransform(domain, geometry)(torch.from_numpy(f)).numpy() / h     # (tilt, Y, X), IMOD's
    indreg.io.writers.write_tilt_series(folder / "ts.mrc", g, tilts)
    with mrcfile.new(folder / "rec.mrc", overwrite=True) as mrc:
        mrc.set_data(np.ascontiguousarray(f.transpose(1, 2, 0)[j:j + 1]).astype(np.float32))   # (Y, Z, X): section j
    with mrcfile.new(folder / "row.mrc", overwrite=True) as mrc:
        mrc.set_data(np.ascontiguousarray(g[:, j:j + 1, :]).astype(np.float32))                # (tilt, 1, X)
    three = indreg.load(f, folder / "ts.mrc", "tilt_series", half_width=8.0, convention="imod")
    two, own = (indreg.load(folder / "rec.mrc", folder / "row.mrc", angles=tilts, half_width=8.0,
                            convention=name) for name in ("imod", "indreg"))
    assert np.array_equal(two.template.numpy(), f[:, j, :].astype(np.float32)), "the section is not the slice"
    return [("imod (mrcfile)", f"{n}^2 section (Z, X) of (Y, Z, X), row {j} of (tilt, Y, X)",
             relative(two.operator(two.template), three.data[:, j]), relative(own.operator(own.template), own.data))]


CHECKS = {"astra": check_astra, "odl": check_odl, "tomopy": check_tomopy, "imod": check_imod}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--register", action="store_true", help="also register each tool's data (a few seconds each)")
    p.add_argument("--tools", nargs="+", default=list(CHECKS), choices=list(CHECKS))
    args = p.parse_args()
    warnings.simplefilter("ignore")
    logging.getLogger("indreg").setLevel(logging.ERROR)     # the flipped controls' orientation warnings
    print("tool, case, then: rel and flipped (relative differences), or register: SSIM on the tool's data and on "
          "indreg's")
    with tempfile.TemporaryDirectory() as tmp:
        for tool in args.tools:
            try:
                rows = CHECKS[tool](Path(tmp), args.register)
            except ImportError as e:
                print(f"{tool}: skipped ({e})")
                continue
            for row in rows:
                print(f"{row[0]:22s} {row[1]:62s} " + " ".join(f"{v:.4g}" for v in row[2:]))


if __name__ == "__main__":
    main()
