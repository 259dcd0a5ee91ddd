"""Golden numbers: every experiment preset, a few solver / model variants of suite 1 and ``indreg.register`` on
suite 1 give the numbers stored in tests/data/presets_golden.json (recorded by scripts/make_presets_golden.py).

Each case re-runs a few iterations and compares every stored number (floats: rtol 1e-4, atol 1e-7; ints, bools and
strings exactly); a stored key missing from the new run fails, a new key is allowed. The 64^2 cases (suite 1 and its
variants, the own-data example, the Python API) take about a second each; the 256^2, 438^2 and 3D presets are
``slow``. After an intended change of the numbers: ``python scripts/make_presets_golden.py`` and say why in the
commit.
"""
import json
import math

import pytest

from golden_helpers import GOLDEN, api_numbers, app_numbers, mismatches

GOLD = json.loads(GOLDEN.read_text())
# 64^2 presets (and their variants "<preset>-<variant>")
QUICK = ("suite1_jv", "own_data_example", "suite_dynamic_2d", "suite_dynamic_2d_unknown")


def _case(kind: str, name: str):
    quick = kind == "api" or name.split("-")[0] in QUICK
    return pytest.param(kind, name, id=f"{kind}-{name}", marks=() if quick else (pytest.mark.slow,))


@pytest.mark.parametrize("kind,name", [_case(kind, name) for kind in ("app", "api") for name in GOLD[kind]])
def test_same_numbers_as_stored(kind, name, tmp_path):
    case = GOLD[kind][name]
    if kind == "app":
        stored, new = case["metrics"], app_numbers(case["overrides"], tmp_path)
    else:
        stored, new = case["result"], api_numbers(case["options"])
    bad = mismatches(stored, new)
    exact = [line for line in bad if not isinstance(stored.get(line.split(":")[0]), float)]
    assert not bad, (f"{kind} case {name} differs from {GOLDEN.name}"
                     f"{' in exact keys (status, counts, names): a change of behaviour' if exact else ''}"
                     f"{'; numbers beyond rtol 1e-4' if len(exact) < len(bad) else ''}:\n"
                     + "\n".join(exact + [line for line in bad if line not in exact])
                     + f"\nIf the change is intended: python scripts/make_presets_golden.py --only {kind}:{name} "
                       "(and say why in the commit)")


def test_every_preset_has_golden_numbers():
    from indreg.experiments.register import CONFIG_DIR

    presets = {p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml")}
    assert presets and presets <= set(GOLD["app"]), f"no golden numbers for {sorted(presets - set(GOLD['app']))}"


def test_mismatches_catch_every_kind_of_change():
    stored = {"ssim": 0.5, "tiny": 0.0, "iterations": 3, "converged": False, "status": "completed",
              "grad_norm": math.nan}
    assert mismatches(stored, dict(stored, ssim=0.5 * (1 + 5e-5), tiny=5e-8, extra=1.0)) == []
    changed = {"ssim": 0.5 * (1 + 2e-4), "tiny": 2e-7, "iterations": 3.0, "converged": 0, "status": "failed",
               "grad_norm": 1.0}
    for key, value in changed.items():
        assert [line.split(":")[0] for line in mismatches(stored, dict(stored, **{key: value}))] == [key]
    assert mismatches(stored, {k: v for k, v in stored.items() if k != "status"}) == [
        "status: missing (stored 'completed')"]
