"""docs/file_formats.md's worked examples of the alignment formats, read from the page: the ``.xf`` line and the
``.aln`` row describe the same map (a tilt axis at 85.3 degrees, the raw image moved by (12.5, -3.2) px), the
``.xf`` numbers follow from IMOD's formula computed here with numpy alone, and the page's point and pixel are where
indreg's reading puts them."""
import re
from pathlib import Path

import numpy as np

from indreg.alignment.files import read_aln, read_xf, write_aln, write_xf

PAGE = Path(__file__).resolve().parents[2] / "docs" / "file_formats.md"


def _block_after(text: str, marker: str) -> str:
    """The first ```text block after ``marker``."""
    return re.search(r"```text\n(.*?)```", text[text.index(marker):], re.S).group(1)


def _rotation(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s], [s, c]])


def test_the_pages_xf_and_aln_examples(tmp_path):
    text = PAGE.read_text()
    (tmp_path / "ex.xf").write_text(_block_after(text, "**IMOD `.xf`**"))
    (tmp_path / "ex.aln").write_text(_block_after(text, "**AreTomo `.aln`.**"))
    xf, aln = read_xf(tmp_path / "ex.xf", [-60.0]), read_aln(tmp_path / "ex.aln")
    # IMOD's formula, independently: u' = A u + D with A = R(-85.3), D = -A (12.5, -3.2)
    A = _rotation(-85.3)
    D = -A @ np.array([12.5, -3.2])
    np.testing.assert_allclose(np.loadtxt(tmp_path / "ex.xf"), np.r_[A.ravel(), D], atol=1e-4)
    for a in (xf, aln):
        np.testing.assert_allclose(a.matrices[0], np.linalg.inv(A), atol=1e-6)
        np.testing.assert_allclose(a.shifts[0], [12.5, -3.2], atol=1e-4)
        assert abs(a.axis_angle_deg - 85.3) < 1e-4 and abs(a.tilt_angles_deg[0] + 60.0) < 1e-9
    assert aln.raw_size == (2048, 2048, 41)
    # the page's point: q = (0, 100) aligned is seen at p = A^-1 (q - D) raw, pixel index p + (n - 1) / 2
    p = xf.matrices[0] @ np.array([0.0, 100.0]) + xf.shifts[0]
    np.testing.assert_allclose(p, np.linalg.solve(A, np.array([0.0, 100.0]) - D), atol=1e-3)   # the file: 4 decimals
    quoted = [float(v) for v in re.search(r"p = A\^-1 \(q - D\) = \(([-\d.]+),\s+([-\d.]+)\)", text).groups()]
    np.testing.assert_allclose(p, quoted, atol=2e-3)
    column, row = (float(v) for v in re.search(r"pixel column\s+([\d.]+),\s+row ([\d.]+) of a 2048", text).groups())
    np.testing.assert_allclose(p + 1023.5, [column, row], atol=2e-3)
    # written back, the same lines (to the files' decimals)
    write_xf(tmp_path / "out.xf", xf)
    write_aln(tmp_path / "out.aln", aln)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "out.xf"), np.loadtxt(tmp_path / "ex.xf"), atol=1e-4)
    np.testing.assert_allclose(read_aln(tmp_path / "out.aln").shifts, aln.shifts, atol=1e-4)
