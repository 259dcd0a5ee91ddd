"""``indreg-align --convention``: IMOD's sign in, IMOD's sign out. A tilt series projected by IMOD's formula
(``flib/tilt/tilt.f90``: the point ``(x, z)`` of a section lands on the detector at ``x cos b - z sin b``, ``b`` the
``.tlt`` angle; docs/file_formats.md, "IMOD's projection convention"), written with numpy only, with its ``.tlt``:
read as ``imod`` the reconstruction is the phantom, read as ``indreg`` its mirror in z; the written ``.tlt`` holds
the angles in the convention's sign."""
import json

import mrcfile
import numpy as np
import pytest

from indreg.alignment.app import main

N = 32
BLOBS = ((0.25, -0.2, 0.1, 1.0), (-0.2, 0.22, -0.15, 0.8), (0.05, 0.1, 0.2, 0.6))   # (x, z, y) / N, amplitude


def _imod_series(tilts_deg, width=2.0):
    """``(volume (x, y, z), stack (tilt, Y, X))``: Gaussian blobs, and their projections by IMOD's formula."""
    c = np.arange(N) - (N - 1) / 2
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    rows, cols = np.meshgrid(c, c, indexing="ij")
    b = np.radians(tilts_deg)[:, None, None]
    f, g = np.zeros((N, N, N)), np.zeros((len(tilts_deg), N, N))
    for bx, bz, by, a in BLOBS:
        x0, y0, z0 = bx * N, by * N, bz * N
        f += a * np.exp(-((x - x0) ** 2 + (y - y0) ** 2 + (z - z0) ** 2) / (2 * width ** 2))
        p0 = x0 * np.cos(b) - z0 * np.sin(b)
        g += a * np.sqrt(2 * np.pi) * width * np.exp(-((cols - p0) ** 2 + (rows - y0) ** 2) / (2 * width ** 2))
    return f, g


def _corr(a, b):
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


@pytest.mark.parametrize("convention", ["imod", "indreg"])
def test_convention_acts_on_angles_in_and_out(tmp_path, convention):
    tilts = np.arange(-60.0, 61.0, 6.0)
    f, g = _imod_series(tilts)
    with mrcfile.new(tmp_path / "s.mrc") as mrc:
        mrc.set_data(g.astype(np.float32))
    np.savetxt(tmp_path / "s.tlt", tilts, fmt="%.2f")
    out = tmp_path / convention
    assert main([str(tmp_path / "s.mrc"), "--convention", convention, "--specimen", "compact", "--bin", "1",
                 "--rounds", "1", "--iters", "30", "--thickness", str(N), "--threads", "1", "--out", str(out)]) == 0
    np.testing.assert_allclose(np.loadtxt(out / "alignment.tlt"), tilts, atol=1e-3)   # the file's sign, out
    np.testing.assert_allclose(np.loadtxt(out / "aligned.tlt"), tilts, atol=1e-3)
    with mrcfile.open(out / "reconstruction.mrc") as mrc:
        volume = np.asarray(mrc.data, dtype=np.float64).transpose(2, 1, 0)              # stored (z, y, x)
    same, mirror = _corr(volume, f), _corr(volume, f[:, :, ::-1])
    if convention == "imod":
        assert same > mirror + 0.2, (same, mirror)
    else:
        assert mirror > same + 0.2, (same, mirror)
    record = json.loads((out / "align.json").read_text())
    assert record["convention"] == convention
    tlt = next(o for o in record["outputs"] if o["path"] == "alignment.tlt")
    assert ("IMOD's sign" in tlt["contents"]) == (convention == "imod")
