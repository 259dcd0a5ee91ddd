"""Golden numbers of the presets (tests/data/presets_golden.json): run one stored case, compare with its numbers.

Shared by ``scripts/make_presets_golden.py`` (which records the numbers) and ``test_presets_golden.py`` (which
re-runs every case and compares). An ``app`` case is a list of ``indreg-register`` overrides run in-process
(``register.run``); its numbers are the scalar entries of the returned metrics dict except timings, config and
device (``SKIPPED``). An ``api`` case is a dict of ``indreg.register`` options on suite 1 (README, "Example"); its
numbers are ``API_FIELDS`` of the result.
"""
import math
from pathlib import Path

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "presets_golden.json"
SKIPPED = ("seconds", "seconds_per_iteration", "config", "hparams", "device")
API_FIELDS = ("objective", "ssim", "psnr", "residual", "min_jacobian", "iterations", "status", "warnings")
RTOL, ATOL = 1e-4, 1e-7


def _scalars(items) -> dict:
    """The bool / int / float / str entries of ``items`` ((key, value) pairs); numpy scalars as Python ones."""
    out = {}
    for k, v in items:
        v = v.item() if hasattr(v, "item") and getattr(v, "ndim", None) == 0 else v
        if isinstance(v, (bool, int, float, str)):
            out[k] = v
    return out


def app_numbers(overrides, out_dir) -> dict:
    """``register.run`` of the app config for ``overrides`` in ``out_dir``: its metrics' scalars (no timings)."""
    from hydra.core.global_hydra import GlobalHydra

    from experiment_helpers import run_app

    try:
        metrics = run_app(overrides, out_dir)
    finally:
        GlobalHydra.instance().clear()
    return _scalars((k, v) for k, v in metrics.items() if k not in SKIPPED)


def suite1_problem():
    """Suite 1 as in the README's example: J -> V, 64^2, 10 angles x 92 bins, white noise at 4.87 dB (seed 0).

    Returns ``(template, data, T, target)``."""
    import indreg
    from indreg import noise, phantoms

    domain = indreg.ImageDomain.paper(64)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry.paper(10, 92))
    template, target = phantoms.get("j", domain), phantoms.get("v", domain)
    data, _ = noise.add_white_noise(T(target), snr_db=4.87, seed=0)
    return template, data, T, target


def api_numbers(options: dict) -> dict:
    """``indreg.register`` on suite 1 with ``options`` (and ``target=``): ``API_FIELDS`` of the result."""
    import indreg

    template, data, T, target = suite1_problem()
    result = indreg.register(template, data, T, target=target, **options)
    return _scalars((k, getattr(result, k)) for k in API_FIELDS)


def _same(stored, new) -> bool:
    if isinstance(stored, (bool, int, str)):  # exactly, type included (True is not 1, 3 is not 3.0)
        return type(new) is type(stored) and new == stored
    if isinstance(new, bool) or not isinstance(new, (int, float)):
        return False
    if math.isnan(stored) or math.isnan(new):
        return math.isnan(stored) and math.isnan(new)
    return new == stored or abs(new - stored) <= ATOL + RTOL * abs(stored)  # numpy.isclose's convention


def mismatches(stored: dict, new: dict) -> list:
    """One line per stored key that is missing from ``new`` or differs (floats: more than
    ``ATOL + RTOL |stored|``); new keys are allowed."""
    lines = []
    for k, v in sorted(stored.items()):
        if k not in new:
            lines.append(f"{k}: missing (stored {v!r})")
        elif not _same(v, new[k]):
            lines.append(f"{k}: {new[k]!r} != stored {v!r}")
    return lines
