"""The resident memory of ``indreg.register`` on a tilt series with ``max_memory``, step by step.

The template and the data (float32) are made first and held; the process's high-water mark (``VmHWM``) is then
reset (``/proc/self/clear_refs``) and ``indreg.register(template, data, T, sigma=3, num_steps=10,
velocity_factor=8, max_iter=ITERS, max_memory=BUDGET)`` runs; a thread samples the resident set (``VmRSS``) every
20 ms and charges it to the step running (the set-up, the units' projection, the orientation probe, the loop, the
result's pieces). Prints the held memory, the registration's peak above it per step and in all, and the seconds
per iteration, as JSON.

    python scripts/bench_register_memory.py --shape 256 256 64 --max-memory 100e6       # 1/64 of the case below
    python scripts/bench_register_memory.py --shape 1024 1024 256 --max-memory 6GiB     # 61 tilts, ~20 GiB free
"""
from __future__ import annotations

import argparse
import ctypes
import json
import threading
import time
from contextlib import contextmanager

GIB = 2 ** 30


def _status(key: str) -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(key + ":")) * 1024


def _reset_peak() -> None:
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


class Sampler:
    """``VmRSS`` every ``period`` seconds; each step's peak (``peaks``) and its growth over the resident set at its
    start (``growth``, freed memory given back to the system first: ``malloc_trim``), charged to every step
    running (a step's growth includes its inner steps')."""

    def __init__(self, period: float = 0.02):
        self.period, self.stack, self.peaks, self.growth, self.done = period, [], {}, {}, False
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _note(self, rss: int) -> None:
        for name, start in list(self.stack):
            self.peaks[name] = max(self.peaks.get(name, 0), rss)
            self.growth[name] = max(self.growth.get(name, 0), rss - start)

    def _run(self):
        while not self.done:
            self._note(_status("VmRSS"))
            time.sleep(self.period)

    @contextmanager
    def step(self, name: str):
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        self.stack.append((name, _status("VmRSS")))
        try:
            yield
        finally:
            self._note(_status("VmRSS"))
            self.stack.pop()


def _wrap(sampler: Sampler, owner, attr: str, name: str) -> None:
    fn = getattr(owner, attr)

    def wrapped(*args, **kwargs):
        with sampler.step(name):
            return fn(*args, **kwargs)

    setattr(owner, attr, wrapped)


def _instrument(sampler: Sampler) -> None:
    import indreg.registration.api as api
    import indreg.registration.run as run
    from indreg.io import orientation
    from indreg.problems import lddmm, slabs

    _wrap(sampler, api, "setup", "set-up")
    _wrap(sampler, run, "measure", "set-up: units (background, projection ratio)")
    _wrap(sampler, run, "apply_units", "set-up: units applied (template_scale)")
    _wrap(sampler, orientation, "check", "set-up: orientation probe")
    _wrap(sampler, run, "as_tensor", "set-up: inputs as tensors")
    _wrap(sampler, run, "noise_residual", "set-up: noise estimate")
    _wrap(sampler, run, "data_term_scale", "set-up: data scale")
    from indreg.forward import tv
    from indreg.registration import models
    _wrap(sampler, tv, "tv_weight_unit", "set-up: TV weight unit")
    _wrap(sampler, slabs.SlabwiseRegistration, "__init__", "set-up: the problem")
    _wrap(sampler, models, "_slabwise", "set-up: the problem")
    _wrap(sampler, run.RegistrationLoop, "run", "the loop")
    _wrap(sampler, api, "build_result", "the result")
    for cls in (lddmm.IndirectRegistration, slabs.SlabwiseRegistration):
        for attr in ("reconstruction", "deformation_field", "image_trajectory", "min_jacobian", "relative_residual",
                     "evaluate_iterate", "outputs", "velocity"):
            if attr in vars(cls):
                _wrap(sampler, cls, attr, f"the result: {attr}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--shape", type=int, nargs=3, default=(256, 256, 64))
    p.add_argument("--tilts", type=int, default=61)
    p.add_argument("--iters", type=int, default=3)
    p.add_argument("--max-memory", default="100e6", help="bytes (6GiB, 6e9 ...)")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()

    import torch
    import torch.nn.functional as F

    import indreg
    from indreg import ImageDomain, phantoms
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
    from indreg.registration.run import count_halvings

    torch.set_num_threads(a.threads)
    budget = float(a.max_memory[:-3]) * GIB if a.max_memory.endswith("GiB") else float(a.max_memory)
    shape = tuple(a.shape)
    box = tuple(16.0 * n / shape[0] for n in shape)
    dom = ImageDomain(shape, tuple(-b for b in box), box)
    step = 120.0 / (a.tilts - 1)
    geom = TiltSeriesGeometry.uniform(-60, 60, step, det_count=shape[0], det_min=-box[0], det_max=box[0])
    T = TiltSeriesTransform(dom, geom)
    small = ImageDomain(tuple(max(8, n // 4) for n in shape), dom.min_pt, dom.max_pt)

    def volume(name):
        v = phantoms.get(name, small).to(torch.float32)
        return F.interpolate(v[None, None], size=shape, mode="trilinear", align_corners=False)[0, 0].contiguous()

    template = volume("shepp_logan_3d")
    data = T(volume("shepp_logan_3d_swirl"))
    sampler = Sampler()
    _instrument(sampler)
    _reset_peak()
    held = _status("VmRSS")
    sampler.thread.start()
    t0 = time.perf_counter()
    r = indreg.register(template, data, T, sigma=3.0, num_steps=10, velocity_factor=8, max_iter=a.iters,
                        max_memory=int(budget))
    seconds = time.perf_counter() - t0
    sampler.done = True
    peak = _status("VmHWM")
    per_iter = [h["seconds"] for h in r.history]
    print(json.dumps({
        "shape": shape, "tilts": a.tilts, "max_memory_GiB": budget / GIB, "held_GiB": held / GIB,
        "peak_GiB": peak / GIB, "peak_above_held_GiB": (peak - held) / GIB,
        "within_budget": peak - held <= budget, "seconds": seconds, "seconds_per_iteration": per_iter,
        "halvings": count_halvings(r.history), "problem": repr(r.problem)[:300],
        "steps_peak_GiB_above_held": {k: round((v - held) / GIB, 4) for k, v in sorted(sampler.peaks.items(),
                                                                                       key=lambda kv: -kv[1])},
        "steps_growth_GiB": {k: round(v / GIB, 4) for k, v in sorted(sampler.growth.items(), key=lambda kv: -kv[1])}},
        indent=1))


if __name__ == "__main__":
    main()
