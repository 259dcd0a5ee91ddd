"""indreg-score (indreg.evaluation.score, score_app, score_run): any volume scored on held-out tilts through an
alignment, each format read, bad volumes refused in one line, the same numbers as the library's."""
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

import indreg
from indreg import io
from indreg.evaluation import score_app
from indreg.evaluation.score import NOISE_ROW, fitted_scale, relative_residual, score_table, score_volumes
from indreg.alignment.operator import AlignedOperator
from indreg.alignment.files import write_alignment

ANGLES = np.linspace(-60.0, 60.0, 13)
VOXEL = 2.0   # Angstrom


def _setup():
    d = indreg.ImageDomain((16, 12, 10), (-16.0, -12.0, -10.0), (16.0, 12.0, 10.0))
    T = indreg.TiltSeriesTransform(d, indreg.TiltSeriesGeometry(torch.tensor(ANGLES), det_count=16, det_min=-16.0,
                                                                det_max=16.0, angle_unit="deg"))
    gen = torch.Generator().manual_seed(0)
    x = indreg.phantoms.ellipsoid_phantom(d, [(1.0, 0.5, 0.4, 0.45, 0.1, 0.0, -0.1, 0, 0, 0)]).double()
    A = AlignedOperator(T, 0.7 * torch.randn(13, 2, generator=gen, dtype=torch.float64), 0.02, "cubic")
    y = A(x) + 0.002 * torch.randn(A.range_shape, generator=gen, dtype=torch.float64)
    return d, A, x, y, x + 0.05 * torch.randn(d.shape, generator=gen, dtype=torch.float64)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A stack (MRC, offset by 5 counts) with its .tlt, the alignment as .xf / .aln / .json, the volume as MRC,
    .npy and (with ome-zarr) OME-Zarr, and a noisier volume; the library's scores of both."""
    folder = tmp_path_factory.mktemp("score")
    d, A, x, y, x2 = _setup()
    io.write_tilt_series(folder / "stack.mrc", (y + 5.0).numpy(), np.radians(ANGLES), pixel_size=VOXEL)
    write_alignment(folder, A, pixel_size=VOXEL, extra={"interpolation": "cubic"})
    io.write_volume(folder / "vol.mrc", x.numpy(), d)
    np.save(folder / "vol.npy", x.numpy())
    np.save(folder / "noisy.npy", x2.numpy())
    sets = {"odd": list(range(1, 13, 2)), "edge": [0, 1, 11, 12]}
    expected = {name: {k: relative_residual(indreg.restrict(A, rows), v, y[rows]) for k, rows in sets.items()}
                for name, v in (("vol", x), ("noisy", x2))}
    return folder, expected


def _run(folder, *args, capsys):
    capsys.readouterr()
    code = score_app.main([str(folder / "stack.mrc"), *args, "--background", "5", "--tilts", "odd=odd",
                           "--tilts", "edge=>=50"])
    out = capsys.readouterr()
    return code, out.out, out.err


def _cells(table: str) -> dict:
    return {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in table.splitlines()[2:]}


@pytest.mark.parametrize("alignment", ["alignment.json", "alignment.xf", "alignment.aln"])
def test_each_alignment_format_gives_the_librarys_numbers(files, alignment, capsys):
    folder, expected = files
    volumes = [str(folder / v) for v in ("vol.mrc", "vol.npy", "noisy.npy")]
    code, out, err = _run(folder, *volumes, "--alignment", str(folder / alignment), "--interpolation", "cubic",
                          capsys=capsys)
    assert code == 0, err
    cells = _cells(out)
    for name, stem in (("vol.mrc", "vol"), ("vol.npy", "vol"), ("noisy.npy", "noisy")):
        assert cells[name][:2] == [f"{expected[stem]['odd']:.4f}", f"{expected[stem]['edge']:.4f}"], name
    assert float(cells["noisy.npy"][0]) > 5 * float(cells["vol.npy"][0]) and NOISE_ROW in cells


def test_ome_zarr_csv_and_markdown(files, capsys, tmp_path):
    from indreg.io.volume_files import ome_zarr_available, write_ome_zarr

    folder, expected = files
    vols = [str(folder / "vol.npy")]
    if ome_zarr_available():
        write_ome_zarr(tmp_path / "vol.zarr", np.load(folder / "vol.npy"), (VOXEL,) * 3)
        vols.append(str(tmp_path / "vol.zarr"))
    code, out, _ = _run(folder, *vols, "--alignment", str(folder / "alignment.json"), "--csv",
                        str(tmp_path / "t.csv"), "--markdown", str(tmp_path / "t.md"), capsys=capsys)
    assert code == 0 and (tmp_path / "t.md").read_text() == out
    csv = (tmp_path / "t.csv").read_text().splitlines()
    assert csv[0] == "volume,odd,edge,scale" and csv[1].startswith(f"vol.npy,{expected['vol']['odd']:.4f},")
    if ome_zarr_available():
        assert _cells(out)["vol.zarr"][:2] == _cells(out)["vol.npy"][:2]


def test_wrong_shape_units_and_tilts_are_one_line_errors(files, capsys, tmp_path):
    folder, _ = files
    np.save(tmp_path / "flat.npy", np.zeros((16, 8, 10)))
    np.save(tmp_path / "scaled.npy", 10 * np.load(folder / "vol.npy"))
    a = ["--alignment", str(folder / "alignment.json")]
    for args, words in (([str(tmp_path / "flat.npy"), *a], "8 slices along y"),
                        ([str(tmp_path / "scaled.npy"), *a], "times the data's"),
                        ([str(folder / "vol.npy"), *a, "--voxel-size", "4"], "voxel side 4 A along y"),
                        ([str(folder / "vol.npy"), *a, "--tilts", "x=40-41"], "outside the stack's sections"),
                        ([str(tmp_path / "missing.npy")], "no such file")):
        code, out, err = _run(folder, *args, capsys=capsys)
        assert code == 2 and out == "" and len(err.strip().splitlines()) == 1 and words in err, err
    code, out, _ = _run(folder, str(tmp_path / "scaled.npy"), *a, "--scale", "fit", capsys=capsys)
    assert code == 0 and _cells(out)["scaled.npy"][-1] == "0.1"   # the fitted scale puts it back


def test_tilt_sets():
    deg = np.array([-60.0, -40.0, -20.0, 0.0, 20.0, 40.0, 60.0])
    assert score_app.tilt_set("odd&>=40", deg) == [1, 5]
    assert score_app.tilt_set("0-2,6", deg) == [0, 1, 2, 6]
    assert score_app.tilt_set("<30", deg) == [2, 3, 4]
    with pytest.raises(ValueError, match="selects no tilt"):
        score_app.tilt_set(">=70", deg)
    with pytest.raises(ValueError, match="--tilts"):
        score_app.parse_sets(["nameless"], deg)


def test_the_score_and_the_fitted_scale():
    d, A, x, y, _ = _setup()
    assert relative_residual(A, x, A(x)) == pytest.approx(0.0, abs=1e-12)
    assert relative_residual(A, torch.zeros(d.shape, dtype=torch.float64), y) == pytest.approx(1.0)
    assert fitted_scale([A], 3 * x, [A(x)]) == pytest.approx(1 / 3)
    s = score_volumes({"a": x}, {"all": A}, {"all": A(x)}, {"a": 2.0})
    assert s["a"]["all_residual"] == pytest.approx(1.0) and math.isfinite(s[NOISE_ROW]["all_residual"])
    table = score_table(s, ["all"], counts={"all": 13})
    assert table.splitlines()[0] == "| volume | all (13) | scale |" and "| a | 1.0000 | 2 |" in table


def test_help_imports_no_torch():
    code = ("import sys\nsys.argv = ['indreg-score', '--help']\nfrom indreg.evaluation.score_app import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\nprint('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == "False"
