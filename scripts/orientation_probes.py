"""The orientation probes of docs/reliability.md: data read the wrong way (2D: the own-data example's files in ASTRA's
layout read with the default convention, its angles in the opposite sense, its detector reversed; 3D: a tilt series
of suite ET-3D turned by 180 degrees, given tilt_axis_angle=180 when it is not turned, its angles in the opposite
sense, its columns reversed), each with its right reading. Prints, per case, what ``indreg.load`` and the probe
before the run (``indreg.io.orientation``) say, and with ``--register`` the SSIM of the registration against the
ground truth (the run with ``orientation="warn"``, so that a refused reading still runs).

    python scripts/orientation_probes.py [--register] [--size3d 32] [--iter3d 40]
"""
from __future__ import annotations

import argparse
import logging
import math

import numpy as np
import torch

import indreg
from indreg import phantoms
from indreg.io import conventions, orientation
from indreg.io import read_angles, read_image
from indreg.alignment.tilt_axis import align_tilt_axis


def data_path(name: str) -> str:
    """A file shipped in indreg/data."""
    from pathlib import Path

    return str(Path(indreg.__file__).parent / "data" / name)


class Messages(logging.Handler):
    """The warnings of the "indreg" logger, kept."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


def own_data():
    """The own-data example: template (grey levels 0..255), target, sinogram (indreg's layout) and angles (deg)."""
    template = read_image(data_path("own_data_template.png"), integer_scale="raw")
    target = np.load(data_path("own_data_target.npy"))
    sino = np.load(data_path("own_data_sinogram.npy"))
    degrees = np.rad2deg(read_angles(data_path("own_data_angles.tlt")))
    return template, target, sino, degrees


def cases_2d():
    """``[(case, wrong load kwargs, right load kwargs)]`` of the 2D probes (the example's 64^2 on [-16, 16]^2)."""
    template, target, sino, deg = own_data()
    base = dict(half_width=16.0, det_min=-24.0, det_max=24.0)
    right = dict(template=template, data=sino, angles=deg, target=target, **base)
    # ASTRA's files of the same problem: pictures as displayed, pixel units, one pixel a bin (92 bins of 0.5)
    h = 0.5
    domain = conventions.domain_for("astra", 64, 16.0)
    lo, hi = conventions.detector_for("astra", 92, h)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=torch.from_numpy(np.deg2rad(deg)),
                                                                det_count=92, det_min=lo, det_max=hi))
    rng = np.random.default_rng(0)
    clean = T(torch.from_numpy(target)).numpy()
    noisy = clean + rng.normal(size=clean.shape) * np.linalg.norm(clean) / np.sqrt(clean.size) * 10 ** (-15 / 20)
    astra = dict(template=conventions.image_from_indreg(template, "astra"),
                 data=conventions.sinogram_from_indreg(noisy, "astra", h), angles=deg,
                 target=conventions.image_from_indreg(target, "astra"), half_width=16.0)
    return [("ASTRA's layout read with the default convention", astra, dict(astra, convention="astra")),
            ("angles in the opposite sense", dict(right, angles=-deg), right),
            ("detector reversed", dict(right, data=sino[:, ::-1].copy()), right)]


def cases_3d(n: int):
    """The 3D probes: suite ET-3D at ``n^3`` (Shepp-Logan -> swirled, -60..60 step 2, 10 dB noise)."""
    domain = indreg.ImageDomain.paper(n, ndim=3)
    template = phantoms.get("shepp_logan_3d", domain).numpy()
    target = phantoms.get("shepp_logan_3d_swirl", domain).numpy()
    deg = np.arange(-60.0, 60.1, 2.0)
    T = indreg.TiltSeriesTransform(domain, indreg.TiltSeriesGeometry(torch.from_numpy(np.deg2rad(deg)), n, -16.0,
                                                                     16.0, angle_unit="rad"))
    clean = T(torch.from_numpy(target)).numpy()
    rng = np.random.default_rng(1)
    g = clean + rng.normal(size=clean.shape) * np.linalg.norm(clean) / np.sqrt(clean.size) * 10 ** (-10 / 20)
    right = dict(template=template, data=g, geometry="tilt_series", angles=deg, target=target, half_width=16.0,
                 det_min=-16.0, det_max=16.0)
    turned = np.ascontiguousarray(g[:, ::-1, ::-1])
    tilted = align_tilt_axis(g, -12.0)                 # the axis 12 degrees off the rows
    return [("stack turned by 180 degrees", dict(right, data=turned), dict(right, data=turned, tilt_axis_angle=180)),
            ("tilt_axis_angle=180 on an unturned stack", dict(right, tilt_axis_angle=180), right),
            ("tilt axis 12 degrees off", dict(right, data=tilted), dict(right, data=tilted, tilt_axis_angle=12)),
            ("angles in the opposite sense", dict(right, angles=-deg), right),
            ("detector columns reversed", dict(right, data=np.ascontiguousarray(g[..., ::-1])), right)]


def probe(kwargs: dict, options: dict, register: bool) -> dict:
    """Load, probe and (``register``) run one reading: the warnings, the probe's table and the SSIM."""
    handler = Messages()
    log = logging.getLogger("indreg")
    log.addHandler(handler)
    log.setLevel(logging.WARNING)
    try:
        kw = dict(kwargs)
        d = indreg.load(kw.pop("template"), kw.pop("data"), kw.pop("geometry", "parallel"), **kw)
        template, data = d.template, d.data
        table = orientation.scores(template, data, d.operator)
        level, _ = orientation.verdict(table)
        out = {"load": [m for m in handler.lines], "verdict": level or "none",
               "table": {k: round(v, 3) for k, (v, _) in table.items()}}
        if register:
            r = indreg.register(template, data, d.operator, target=d.target, orientation="warn", **options)
            out.update(ssim=r.ssim, residual=r.residual, poor_fit=bool(r.poor_fit), status=r.status)
    finally:
        log.removeHandler(handler)
    out["warnings"] = handler.lines
    return out


def presets(size2d: int, size3d: int) -> None:
    """The probe's table and verdict on every preset's data (at ``size2d`` / ``size3d`` cells a side)."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from indreg.experiments import register, sources

    names = sorted(p.stem for p in (Path(register.CONFIG_DIR) / "experiment").glob("*.yaml"))
    for name in names:
        with initialize_config_dir(version_base="1.3", config_dir=str(register.CONFIG_DIR), job_name="probe"):
            cfg = compose(register._CONFIG_NAME, overrides=[f"experiment={name}"])
        if cfg.data.source == "phantom":
            with initialize_config_dir(version_base="1.3", config_dir=str(register.CONFIG_DIR), job_name="probe"):
                three = cfg.phantom.get("ndim", 2) == 3
                extra = [f"phantom.size={size3d if three else size2d}"]
                extra += ["phantom.thickness=null", "phantom.rows=null"] if three else []
                try:
                    cfg = compose(register._CONFIG_NAME, overrides=[f"experiment={name}", *extra])
                except Exception:   # noqa: BLE001  (a preset without these keys: as it is)
                    cfg = compose(register._CONFIG_NAME, overrides=[f"experiment={name}", extra[0]])
        data = sources.load(cfg)
        if not data.template_known:
            print(f"preset {name}: template unknown, no probe")
            continue
        op = data.operator
        table = orientation.scores(data.template_64, data.data_64, op)
        level, _ = orientation.verdict(table)
        print(f"preset {name} {tuple(data.template_64.shape)}: verdict {level or 'none'} | "
              f"{ {k: round(v, 3) for k, (v, _) in table.items()} }", flush=True)


def _compose(overrides):
    from hydra import compose, initialize_config_dir

    from indreg.experiments import register

    with initialize_config_dir(version_base="1.3", config_dir=str(register.CONFIG_DIR), job_name="probe"):
        return compose(register._CONFIG_NAME, overrides=list(overrides))


def _probe_cfg(overrides) -> tuple:
    """``(verdict, load's warnings, table)`` of the app's data for ``overrides`` (``sources.load``, then the probe on
    the prepared inputs, as ``indreg.registration.run.setup`` runs it)."""
    from indreg.experiments import sources
    from indreg.units import prepare   # = measure + apply_units, as indreg.registration.run.setup

    handler = Messages()
    log = logging.getLogger("indreg")
    log.addHandler(handler)
    log.setLevel(logging.WARNING)
    try:
        data = sources.load(_compose(overrides))
        template, g, _ = prepare(data.template_64, data.data_64, data.operator, "auto", "auto", lambda n: n)
        table = orientation.scores(template, g, data.operator)
    finally:
        log.removeHandler(handler)
    return orientation.verdict(table)[0] or "none", handler.lines, table


#: The presets of indreg's own simulated data the false-warning rate runs on (2D; the 3D suite at small sizes).
OWN_2D = ("suite1_jv", "suite2_six_objects", "suite3_shepp_logan", "suite3_contrast_metamorphosis",
          "suite4_extra_object", "suite4_missing_object", "shepp_logan_limited_angle_metamorphosis")


def false_rate(seeds: int, sizes2d=(16, 24, 32, 48, 64), sizes3d=(16, 24)) -> None:
    """The probe on indreg's own simulated data read right: every 2D phantom preset at ``sizes2d`` (the detector
    1.5 bins a pixel, as the paper's 92 at 64^2, and the preset's own count), the ET-3D suite at ``sizes3d``,
    ``seeds`` noise seeds each; prints every case that warns and the rate."""
    cases, warned, margins = 0, [], {}
    for seed in range(seeds):
        runs = [[f"experiment={name}", f"phantom.size={n}", f"geometry.det_count={d}", f"seed={seed}"]
                for name in OWN_2D for n in sizes2d for d in sorted({round(1.5 * n), round(92 * n / 64) + 1})]
        runs += [["experiment=suite_et_3d", f"phantom.size={n}", f"geometry.det_count={n}", "geometry.tilt_step=4",
                  f"seed={seed}"] for n in sizes3d]
        for overrides in runs:
            level, _, table = _probe_cfg(overrides)
            cases += 1
            size = next(o for o in overrides if o.startswith("phantom.size")).split("=")[1]
            margin = max(v for v, _ in table.values()) - table["as given"][0]
            margins.setdefault(size, []).append((round(margin, 3), " ".join(overrides)))
            if level != "none":
                best = max(table, key=lambda k: table[k][0])
                warned.append(overrides)
                print(f"  {level}: {' '.join(overrides)}: as given {table['as given'][0]:.3f}, {best} "
                      f"{table[best][0]:.3f}", flush=True)
        print(f"seed {seed}: {len(warned)} of {cases} cases warned so far", flush=True)
    for size, values in sorted(margins.items(), key=lambda kv: int(kv[0])):
        print(f"size {size}: {len(values)} cases, largest margins of another reading over the data as given: "
              f"{sorted(values, reverse=True)[:3]}")
    print(f"false-warning rate: {len(warned)} of {cases} ({100 * len(warned) / max(cases, 1):.1f} %)")


#: Wrong readings of the shipped own-data example (the files are in indreg's layout) and the fix each needs.
WRONG_READINGS = (["data.convention=astra"], ["data.convention=skimage"], ["data.convention=tomopy"],
                  ["data.convention=imod"])


def catch_rate() -> None:
    """The own-data example (``experiment=own_data_example``) read wrongly: whether ``indreg.load``'s check or the
    probe names it; and the right reading's verdict."""
    caught = 0
    readings = [r for r in WRONG_READINGS if _known(r)]
    for overrides in [[]] + readings:
        try:
            level, lines, table = _probe_cfg(["experiment=own_data_example", *overrides])
        except Exception as e:   # noqa: BLE001  (a reading the loader refuses outright is caught)
            level, lines, table = "refused by the loader", [str(e)], {"as given": (float("nan"), None)}
        named = level != "none" or any("convention" in w or "orientation" in w for w in lines)
        caught += bool(overrides) and named
        best = max(table, key=lambda k: table[k][0])
        print(f"{' '.join(overrides) or 'right reading'}: probe {level}, as given {table['as given'][0]:.3f}, "
              f"best {best} {table[best][0]:.3f}; load warned {len(lines)}: {[w[:100] for w in lines]}", flush=True)
    print(f"catch rate: {caught} of {len(readings)} wrong readings")


def _known(overrides) -> bool:
    try:
        _compose(["experiment=own_data_example", *overrides])
    except Exception:   # noqa: BLE001  (a key this version has not)
        return False
    return True


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--register", action="store_true", help="run the registrations too (minutes)")
    p.add_argument("--size3d", type=int, default=32)
    p.add_argument("--iter3d", type=int, default=40)
    p.add_argument("--iter2d", type=int, default=200)
    p.add_argument("--presets", action="store_true", help="the probe on every preset's data instead")
    p.add_argument("--false-rate", type=int, metavar="SEEDS", help="the false-warning rate on indreg's own data")
    p.add_argument("--catch-rate", action="store_true", help="wrong readings of the own-data example")
    a = p.parse_args()
    torch.set_num_threads(1)
    if a.presets:
        return presets(64, 32)
    if a.false_rate:
        return false_rate(a.false_rate)
    if a.catch_rate:
        return catch_rate()
    opts2 = dict(sigma=3.0, gamma=1e-6, step_size=0.02, max_iter=a.iter2d)
    opts3 = dict(sigma=3.0, gamma=1e-6, step_size=0.1, max_iter=a.iter3d, num_steps=10, interpolation="compose",
                 dtype="float32")
    for dim, cases, opts in (("2D", cases_2d(), opts2), ("3D", cases_3d(a.size3d), opts3)):
        for name, wrong, right in cases:
            for which, kw in (("wrong", wrong), ("right", right)):
                r = probe(kw, opts, a.register)
                ssim = "" if "ssim" not in r else f" ssim {r['ssim']:.3f} residual {r['residual']:.3f} " \
                                                  f"poor_fit {r['poor_fit']}"
                print(f"{dim} | {name} | {which} | verdict {r['verdict']} |{ssim} | {r['table']}")
                for w in r["warnings"]:
                    print(f"    warning: {w}")
                print(flush=True)


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)
    main()
