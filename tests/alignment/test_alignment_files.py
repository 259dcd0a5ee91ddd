"""Alignment files in and out (IMOD .xf, AreTomo .aln) applied in the operator: the per-tilt matrices' adjoint, the
operator through an .xf made by an independent implementation of IMOD's formula, round trips, a registration started
from an imported .xf, and one-line errors."""
import json
import math

import numpy as np
import pytest
import torch
from scipy.ndimage import affine_transform

import indreg
from indreg import ImageDomain
from indreg.alignment.files import (from_operator, read_alignment, read_aln, read_xf, to_operator, write_alignment,
                                    write_xf)
from indreg.forward import TiltSeriesGeometry, TiltSeriesTransform
from indreg.forward.operator import adjointness
from indreg.alignment.operator import AlignedOperator

F64 = torch.float64
N = 24


def _blobs(domain, seed=0):
    """A few Gaussian blobs within radius 6 of the centre (a rotation keeps them inside the detector)."""
    gen = np.random.default_rng(seed)
    x, y, z = (torch.linspace(-N / 2 + 0.5, N / 2 - 0.5, N, dtype=F64),) * 3
    X, Y, Z = torch.meshgrid(x, y, z, indexing="ij")
    f = torch.zeros(domain.shape, dtype=F64)
    for _ in range(5):
        c = gen.uniform(-4, 4, 3)
        f += gen.uniform(0.5, 1.0) * torch.exp(-((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) / 4.0)
    return f


@pytest.fixture(scope="module")
def series():
    domain = ImageDomain((N, N, N), (-N / 2,) * 3, (N / 2,) * 3)   # one unit a voxel
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 10, det_count=N, det_min=-N / 2,
                                                               det_max=N / 2))
    return T, _blobs(domain)


def _true_alignment(K, seed=1, axis=85.0):
    """IMOD-style raw-to-aligned transforms: a rotation by -(axis + small per-tilt part), shifts up to 2 px."""
    gen = np.random.default_rng(seed)
    theta = np.radians(-(axis + gen.uniform(-3, 3, K)))
    A = np.stack([np.stack([np.cos(theta), -np.sin(theta)], -1), np.stack([np.sin(theta), np.cos(theta)], -1)], -2)
    return A, gen.uniform(-2, 2, (K, 2))


def _imod_raw_stack(aligned: np.ndarray, A: np.ndarray, D: np.ndarray, centre: float) -> np.ndarray:
    """The raw stack whose IMOD alignment ``u' = A (u - c) + c + D`` gives ``aligned`` (x = column, y = row,
    ``c`` the pixel index of the centre): raw(u) = aligned(A (u - c) + c + D), with scipy's bilinear
    affine_transform (its own code, indexed (row, column))."""
    out = []
    for k, image in enumerate(aligned):
        m = np.array([[A[k, 1, 1], A[k, 1, 0]], [A[k, 0, 1], A[k, 0, 0]]])   # (row, column) order
        c = np.array([centre, centre])
        offset = np.array([D[k, 1], D[k, 0]]) + c - m @ c
        out.append(affine_transform(image, m, offset, order=1, mode="nearest"))
    return np.stack(out)


def _displacement(a: torch.Tensor, b: torch.Tensor) -> float:
    """RMS difference over the RMS gradient of ``b``: about the displacement (px) between the two images."""
    grads = torch.gradient(b, dim=(-2, -1))
    return float((a - b).pow(2).mean().sqrt() / (grads[0] ** 2 + grads[1] ** 2).mean().sqrt())


def test_adjoint_with_per_tilt_matrices(series):
    T, _ = series
    K = T.geometry.num_tilts
    A, d = _true_alignment(K)
    for interpolation in ("linear", "cubic"):
        op = AlignedOperator(T, torch.from_numpy(d), 0.03, interpolation, matrices=torch.from_numpy(A))
        y = torch.randn(T.range_shape, dtype=F64)
        assert not torch.allclose(op.warp(y, op.shifts, op.angle), y)
        assert adjointness(op) < 1e-13


def test_xf_from_the_independent_formula_gives_the_true_operator(series, tmp_path):
    """A stack made from known shifts and rotations by IMOD's formula (scipy, not indreg), its .xf read back:
    the operator's projections equal the stack to a displacement under 0.1 px; IMOD's centre taken a half pixel
    off (index n / 2) or the matrix the other way round misses by more."""
    T, f = series
    K = T.geometry.num_tilts
    A, D = _true_alignment(K)
    ideal = T(f).numpy()
    raw = torch.from_numpy(_imod_raw_stack(ideal, A, D, (N - 1) / 2))
    np.savetxt(tmp_path / "s.xf", np.concatenate([A.reshape(K, 4), D], 1), fmt="%.7f")
    np.savetxt(tmp_path / "s.tlt", np.degrees(T.geometry.angles.numpy()), fmt="%.4f")
    op = to_operator(T, read_xf(tmp_path / "s.xf"))
    assert _displacement(op(f), raw) < 0.1, _displacement(op(f), raw)
    off_centre = torch.from_numpy(_imod_raw_stack(ideal, A, D, N / 2))
    assert _displacement(op(f), off_centre) > 0.3
    inverted = to_operator(T, read_xf(tmp_path / "s.xf"))
    inverted.matrices = inverted.matrices.transpose(1, 2)   # the rotation the other way
    assert _displacement(inverted(f), raw) > 1.0


def test_round_trip_xf_and_aln(series, tmp_path):
    """Write an operator's alignment (shifts, tilt-axis angle, per-tilt rotations), read it back: the same
    projections (to 1e-3 px: the files keep 4 decimals)."""
    T, f = series
    K = T.geometry.num_tilts
    A, d = _true_alignment(K, seed=3, axis=5.0)
    op = AlignedOperator(T, torch.from_numpy(d), math.radians(2.0), matrices=torch.from_numpy(A))
    record = write_alignment(tmp_path, from_operator(op, raw_size=(N, N, K)), pixel_size=2.5)
    assert record["files"] == {"xf": "alignment.xf", "tlt": "alignment.tlt", "aln": "alignment.aln"}
    saved = json.loads((tmp_path / "alignment.json").read_text())
    assert saved["units"]["shifts"] == "pixel" and "xf" in saved["conventions"]
    for name in ("alignment.xf", "alignment.aln"):
        back = to_operator(T, read_alignment(tmp_path / name))
        assert _displacement(back(f), op(f)) < 1e-3, name
        again = from_operator(back)
        np.testing.assert_allclose(again.tilt_angles_deg, np.degrees(T.geometry.angles.numpy()), atol=1e-2)


def test_off_centre_detector_round_trip(tmp_path):
    """A detector whose middle is off the axis (det_min != -det_max): the pixel centre is the image's middle."""
    domain = ImageDomain((16, 12, 16), (-8, -6, -8), (8, 6, 8))
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-40, 40, 20, det_count=16, det_min=-6., det_max=10.))
    f = torch.rand(domain.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    A, d = _true_alignment(T.geometry.num_tilts, axis=10)
    op = AlignedOperator(T, torch.from_numpy(d), 0.0, matrices=torch.from_numpy(A))
    write_xf(tmp_path / "a.xf", from_operator(op))
    back = to_operator(T, read_xf(tmp_path / "a.xf"))
    assert torch.allclose(back(f), op(f), atol=1e-4 * float(op(f).abs().max()))


def test_aln_header_dark_frames_and_one_based_sections(tmp_path):
    path = tmp_path / "s.aln"
    path.write_text("# AreTomo Alignment / Priims bprmMn\n# RawSize = 64 64 5\n# NumPatches = 0\n"
                    "# DarkFrame =     5    5    60.00\n"
                    "# SEC     ROT         GMAG       TX          TY      SMEAN     SFIT    SCALE     BASE     TILT\n"
                    + "".join(f"{k + 1:5d}  -85.0  1.0  {k:.1f}  {-k:.1f}  1 1 1 0  {-60 + 30 * k:.2f}\n"
                              for k in range(4)))
    a = read_aln(path)
    assert a.frames.tolist() == [0, 1, 2, 3] and a.raw_size == (64, 64, 5)
    np.testing.assert_allclose(a.shifts[2], [2.0, -2.0])
    assert abs(a.axis_angle_deg + 85.0) < 1e-9
    np.testing.assert_allclose(a.tilt_angles_deg, [-60, -30, 0, 30])


def test_load_with_alignment_and_a_registration_started_from_it(tmp_path):
    """indreg.load(..., alignment=FILE) applies the .xf in the operator; a registration started from it equals one
    started from the same shifts given directly."""
    n = 16
    domain = ImageDomain((n, n, n), (-n / 2,) * 3, (n / 2,) * 3)
    T = TiltSeriesTransform(domain, TiltSeriesGeometry.uniform(-60, 60, 10, det_count=n, det_min=-n / 2,
                                                               det_max=n / 2))
    target = indreg.phantoms.get("shepp_logan_3d", domain).double()
    template = torch.roll(target, 1, 0)
    shifts = torch.from_numpy(np.random.default_rng(2).uniform(-1.5, 1.5, (T.geometry.num_tilts, 2)))
    direct = AlignedOperator(T, shifts)
    data = direct(target)
    indreg.io.write_tilt_series(tmp_path / "s.mrc", data, T.geometry.angles)
    K = T.geometry.num_tilts   # IMOD: u' = u + D with D = -shift (the aligned image moves the raw one back)
    np.savetxt(tmp_path / "s.xf", np.concatenate([np.tile([1., 0., 0., 1.], (K, 1)), -shifts.numpy()], 1))
    np.save(tmp_path / "t.npy", template.numpy())
    d = indreg.load(tmp_path / "t.npy", tmp_path / "s.mrc", "tilt_series", alignment=tmp_path / "s.xf",
                    half_width=n / 2)
    assert torch.allclose(d.operator.shifts, shifts, atol=1e-4)
    options = dict(num_steps=2, max_iter=2, sigma=2.0, step_size=0.05, align="shifts", align_gauge="none")
    imported = indreg.register(d.template, d.data, d.operator, **options)
    given = indreg.register(template, data, direct, **options)
    assert np.allclose(imported.alignment["shifts_px"], given.alignment["shifts_px"], atol=1e-3)
    assert abs(imported.residual - given.residual) < 1e-4 * given.residual
    assert torch.allclose(imported.deformed, given.deformed, atol=1e-6)


def test_errors(tmp_path):
    bad = tmp_path / "b.xf"
    bad.write_text("1 0 0 1 0\n")
    with pytest.raises(ValueError, match="line 1 has 5 numbers"):
        read_xf(bad)
    bad.write_text("1 0 0 1 0 0\n")
    with pytest.raises(ValueError, match="no tilt angles"):
        read_xf(bad)
    (tmp_path / "b.tlt").write_text("0\n10\n")
    with pytest.raises(ValueError, match="1 transforms but 2 tilt angles"):
        read_xf(bad)
    (tmp_path / "b.tlt").write_text("0\n")
    (tmp_path / "b.xtilt").write_text("1.5\n")
    with pytest.raises(ValueError, match="tilt about X is not modelled"):
        read_xf(bad)
    with pytest.raises(ValueError, match="unknown alignment format '.txt'"):
        read_alignment(tmp_path / "b.txt")
    (tmp_path / "c.aln").write_text("# RawSize = 8 8 2\n0 1 1 0 0\n")
    with pytest.raises(ValueError, match="line 2 has 5 numbers"):
        read_aln(tmp_path / "c.aln")
