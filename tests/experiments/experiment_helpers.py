"""Helpers for the experiment-app tests: compose configs in-process and run the app on tiny problems."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

from indreg.experiments import register

# 32^2, N = 5, 10 iterations: seconds per run. Baselines and images are switched on where a test needs them.
TINY = ["phantom.size=32", "deformation.num_steps=5", "solver.max_iter=10", "baseline.tv_iterations=20",
        "logging.every=5", "logging.checkpoint_every=5", "logging.progress=false"]
FAST = TINY + ["baseline.enabled=false", "logging.figure=false", "logging.tensorboard=false"]


def compose(overrides=(), return_hydra_config=False):
    """The app's config for ``overrides`` (Hydra compose API on the same config dir as the entry point)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(version_base="1.3", config_dir=str(register.CONFIG_DIR), job_name="test"):
        return hydra_compose(register._CONFIG_NAME, overrides=list(overrides),
                             return_hydra_config=return_hydra_config)


def run_app(overrides, out_dir):
    """``register.run`` in-process (what the Hydra task does, minus Hydra's run dir handling)."""
    return register.run(compose(overrides), out_dir)


def entry_point():
    """The installed console script, else ``python -m indreg.experiments.register``."""
    exe = shutil.which("indreg-register", path=str(Path(sys.executable).parent) + os.pathsep + os.environ["PATH"])
    return [exe] if exe else [sys.executable, "-m", "indreg.experiments.register"]


def run_cli(args, cwd, timeout=240, env=None):
    return subprocess.run(entry_point() + list(args), cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, **(env or {})))


def write_tilt_series_files(d):
    """A 16 x 16 x 12 slab (1-unit voxels, ``data.half_width=8``) as ``template.mrc`` and its 7 tilts about y
    (-60..60 step 20, 16 columns on [-8, 8]) of a deformed phantom as ``tilts.mrc`` with ``tilts.tlt``."""
    from indreg import ImageDomain, phantoms
    from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
    from indreg.io import write_tilt_series, write_volume

    dom = ImageDomain((16, 16, 12), (-8.0, -8.0, -6.0), (8.0, 8.0, 6.0))
    g = TiltSeriesGeometry.uniform(-60, 60, 20, det_count=16, det_min=-8.0, det_max=8.0)
    template = phantoms.get("shepp_logan_3d", ImageDomain.paper(16, ndim=3))[:, :, 2:14]
    data = TiltSeriesTransform(dom, g)(phantoms.get("shepp_logan_3d_swirl", ImageDomain.paper(16, ndim=3))[:, :, 2:14])
    write_volume(d / "template.mrc", template.numpy(), dom)
    write_tilt_series(d / "tilts.mrc", data.numpy(), g.angles, pixel_size=1.0)
