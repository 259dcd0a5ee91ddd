"""Start-up: the app's modules import nothing that a run needs only after its first log line (matplotlib,
TensorBoard, scipy.stats, sympy) or not at all (scipy.fft, scikit-image's plug-ins), and the entry points answer
``--help`` without torch."""
import json
import subprocess
import sys

import pytest

LATE = ("matplotlib", "torch.utils.tensorboard", "scipy.stats", "sympy", "scipy.fft", "skimage")


def _loaded(code: str, names) -> dict:
    """Which of ``names`` are in ``sys.modules`` after ``code`` runs in a fresh interpreter."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps({{n: n in sys.modules for n in {list(names)!r}}}))"
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.splitlines()[-1])


@pytest.mark.slow
def test_the_run_modules_and_a_problem_import_nothing_late():
    code = ("import torch\nfrom indreg import metrics\nfrom indreg.registration import run\nfrom indreg.experiments import runner, outputs, figures\n"
            "from indreg import ImageDomain, ParallelBeamGeometry, RayTransform, LDDMMDeformation\n"
            "d = ImageDomain.paper(16); T = RayTransform(d, ParallelBeamGeometry.paper(4, 20))\n"
            "y = T(torch.rand(16, 16, dtype=torch.float64)); T.inner_data(y, y)\n"
            "LDDMMDeformation(d, 2)(torch.zeros(3, 2, 16, 16, dtype=torch.float64),"
            " torch.rand(16, 16, dtype=torch.float64))\n"
            "from indreg import phantoms\nphantoms.j(d), phantoms.v(d)")
    assert _loaded(code, LATE) == dict.fromkeys(LATE, False)


#: What ``--help`` and the light modules need none of (each 0.1-2 s of CPU), nor the registration's config schema.
HEAVY = ("torch", "matplotlib", "tensorboard", "scipy", "skimage", "indreg.experiments.config")


@pytest.mark.parametrize("module", ["indreg.experiments.register", "indreg.learn.entry", "indreg.alignment.app"])
def test_help_imports_nothing_heavy(module):
    code = (f"import sys\nsys.argv = ['prog', '--help']\nfrom {module} import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass")
    assert _loaded(code, HEAVY) == dict.fromkeys(HEAVY, False)


def test_the_light_modules_import_nothing_heavy():
    code = "import indreg, indreg.experiments.cli, indreg.learn"
    assert _loaded(code, HEAVY) == dict.fromkeys(HEAVY, False)


def test_the_light_entry_point_names_the_trainings_config():
    from indreg.learn import entry, train
    from indreg.learn.conf import CONFIG_DIR

    assert (entry._CONFIG, entry._CONFIG_NAME) == (CONFIG_DIR, train.CONFIG_NAME)


@pytest.mark.parametrize("name", ["j.png", "v.png"])
def test_the_papers_pictures_are_read_as_scikit_image_reads_them(name):
    from importlib import resources

    import numpy as np
    from skimage.io import imread

    from indreg import phantoms

    with resources.as_file(resources.files("indreg").joinpath("data", name)) as path:
        raw = imread(path, as_gray=True)
    expected = np.rot90(raw.astype(np.float64) / np.iinfo(raw.dtype).max, -1)
    assert np.array_equal(phantoms._raster(name), expected)


def test_the_kernels_fft_length_is_scipys():
    import scipy.fft

    from indreg.deform.kernel import fast_length

    assert [fast_length(n) for n in range(1, 5000)] == [scipy.fft.next_fast_len(n) for n in range(1, 5000)]


#: ``indreg-register`` (``sys.argv[1:]`` its arguments) that prints, as one json line, the first log record of level
#: INFO from indreg and whether torch was loaded then, and exits; or, if it exits first, whether torch was loaded.
FIRST_LINE = """
import json, logging, os, sys
make = logging.getLogRecordFactory()
def first(name, level, *args, **kwargs):
    record = make(name, level, *args, **kwargs)
    if level >= logging.INFO and name.startswith("indreg"):
        print(json.dumps({"line": record.getMessage(), "torch": "torch" in sys.modules}), flush=True)
        os._exit(0)
    return record
logging.setLogRecordFactory(first)
sys.argv = ["indreg-register", *sys.argv[1:]]
from indreg.experiments.register import main
try:
    main()
except SystemExit as e:
    print(json.dumps({"exit": e.code, "torch": "torch" in sys.modules}), flush=True)
    raise
"""


def _first_line(tmp_path, *overrides) -> tuple:
    """(the json line of :data:`FIRST_LINE`, stderr) of ``indreg-register overrides`` run in ``tmp_path``."""
    proc = subprocess.run([sys.executable, "-c", FIRST_LINE, f"hydra.run.dir={tmp_path / 'run'}", *overrides],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def test_the_first_line_says_what_will_run_before_torch_is_imported(tmp_path):
    seen, err = _first_line(tmp_path)
    assert seen["torch"] is False, seen
    assert seen["line"] == (f"suite1_jv: model lddmm, solver algorithm1 (200 iterations), data phantom j -> v (64^2 "
                            f"cells, parallel geometry), float32 on device auto; run dir {(tmp_path / 'run').resolve()}"), err


def test_a_bad_option_is_refused_without_torch(tmp_path):
    seen, err = _first_line(tmp_path, "kernel.sigma=-1")
    assert seen == {"exit": 1, "torch": False}
    assert err.strip() == ("indreg-register: error: invalid config value kernel.sigma=-1: expected None, 'auto' or "
                           "a finite number > 0")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_every_presets_checks_and_first_line_need_no_torch(tmp_path):
    """Every ``experiment=`` preset passes the preflight and gets its first line without torch (the solvers that
    read their classes' options in their checks, ``solver=fast`` and torch.optim's, are not among the presets)."""
    code = f"""
import sys
from pathlib import Path
from indreg.conf import CONFIG_DIR
from indreg.experiments import cli, register
names = sorted(p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml"))
for name in names:
    argv = [f"experiment={{name}}", "hydra.run.dir={tmp_path / 'run'}"]
    register.preflight(argv)
    line = register.plan_line(cli.job_config(cli.compose(CONFIG_DIR, "config", argv)), Path("{tmp_path}"))
    assert ": model " in line and "; run dir {tmp_path.resolve()}" in line, line
print(len(names), "torch" in sys.modules)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    count, torch_loaded = proc.stdout.split()
    assert int(count) >= 10 and torch_loaded == "False", proc.stdout
