"""Tests of indreg.phantoms: registry, shapes, known pixel values, integrals, raster resampling."""
import math

import numpy as np
import pytest
import torch
from skimage.io import imread

from indreg import phantoms
from indreg.domain import ImageDomain
from indreg.phantoms import ellipse_phantom

NAMES = ["j", "v", "six_objects_target", "six_objects_template", "shepp_logan", "shepp_logan_template",
         "shepp_logan_template_missing", "shepp_logan_template_extra", "shepp_logan_template_contrast"]
NAMES_3D = ["shepp_logan_3d", "shepp_logan_3d_swirl"]
DATA = __import__("pathlib").Path(phantoms.__file__).parent / "data"


def value_at(img, dom, x, y):
    """Pixel value at the cell containing the physical point (x, y)."""
    hx, hy = dom.cell_sides
    return float(img[int((x - dom.min_pt[0]) // hx), int((y - dom.min_pt[1]) // hy)])


def test_registry_names_shapes_dtype():
    assert phantoms.names() == NAMES + NAMES_3D
    dom = ImageDomain((24, 20))
    for name in NAMES:
        f = phantoms.get(name, dom)
        assert f.shape == (24, 20) and f.dtype == torch.float64, name
        assert float(f.min()) >= -1e-12 and float(f.max()) <= 1.0 + 1e-12 and float(f.max()) > 0.2, name


def test_registry_errors():
    with pytest.raises(ValueError, match="unknown phantom 'shepp'.*shepp_logan_template_extra"):
        phantoms.get("shepp", ImageDomain.paper(8))
    with pytest.raises(TypeError, match="ImageDomain"):
        phantoms.get("j", (64, 64))
    with pytest.raises(ValueError, match="6 entries"):
        ellipse_phantom(ImageDomain.paper(8), [(1.0, 0.5, 0.5)])
    with pytest.raises(ValueError, match="semi-axes"):
        ellipse_phantom(ImageDomain.paper(8), [(1.0, 0.0, 0.5, 0, 0, 0)])


def test_shepp_logan_known_values_and_orientation():
    dom = ImageDomain.paper(256)  # normalised coordinate u <-> physical 16 u
    f = phantoms.shepp_logan(dom)
    assert value_at(f, dom, 0.0, 0.0) == pytest.approx(0.2)            # brain: 1.0 - 0.8
    assert value_at(f, dom, 0.0, -16 * 0.606) == pytest.approx(0.3)     # small ellipse at the bottom (y < 0)
    assert value_at(f, dom, 0.0, 16 * 0.606) == pytest.approx(0.2)      # ... and not at the top
    assert value_at(f, dom, 16 * 0.22, 0.0) == pytest.approx(0.0)       # right ventricle: 0.2 - 0.2
    assert value_at(f, dom, 0.0, 16 * 0.35) == pytest.approx(0.3)       # upper ellipse at y = +0.35
    assert value_at(f, dom, 0.0, -16 * 0.9) == pytest.approx(1.0)       # skull rim, thick at the bottom
    assert value_at(f, dom, 15.0, 15.0) == 0.0
    # right ventricle (rotation -18 deg) leans outward: at x = 0.30 its top half is there, its bottom half not
    assert value_at(f, dom, 16 * 0.30, 16 * 0.2) == pytest.approx(0.0)
    assert value_at(f, dom, 16 * 0.30, -16 * 0.2) == pytest.approx(0.2)


def test_shepp_logan_templates():
    dom = ImageDomain.paper(128)
    t, miss, extra = (phantoms.get(n, dom) for n in ["shepp_logan_template", "shepp_logan_template_missing",
                                                      "shepp_logan_template_extra"])
    assert value_at(t, dom, 0.0, 16 * 0.55) == pytest.approx(0.2)          # brain of the compressed head
    assert value_at(t, dom, 16 * -0.25, 16 * 0.2) == pytest.approx(0.0)    # left ventricle ...
    assert value_at(miss, dom, 16 * -0.25, 16 * 0.2) == pytest.approx(0.2)  # ... removed in "missing"
    assert value_at(extra, dom, 16 * -0.25, 16 * -0.15) == pytest.approx(0.5)  # extra bright disc
    assert value_at(t, dom, 16 * -0.25, 16 * -0.15) == pytest.approx(0.2)
    # the variants differ from the template only at their object: area of the disc / ventricle
    cv = dom.cell_volume
    assert float((extra - t).sum()) * cv == pytest.approx(0.3 * math.pi * (16 * 0.08) ** 2, rel=0.02)
    assert float((miss - t).sum()) * cv == pytest.approx(0.2 * math.pi * (16 * 0.13) ** 2, rel=0.02)


def test_ellipse_integral_and_supersampling():
    dom = ImageDomain((100, 80), (-16.0, -10.0), (16.0, 10.0))  # non-square box: frame scales per axis
    a, b = 0.5, 0.3
    f = ellipse_phantom(dom, [(0.7, a, b, 0.1, -0.2, 30.0)])
    exact = 0.7 * math.pi * (a * 16) * (b * 10)
    assert float(f.sum()) * dom.cell_volume == pytest.approx(exact, rel=5e-3)
    fs = ellipse_phantom(dom, [(0.7, a, b, 0.1, -0.2, 30.0)], supersample=1)
    assert set(np.unique(fs.numpy()).tolist()) == {0.0, 0.7}  # no anti-aliasing with one sample
    assert 0 < int(((f > 0) & (f < 0.7)).sum())                # partial pixels on the edge with 4 x 4


def test_rotation_convention():
    dom = ImageDomain.paper(64)
    f = ellipse_phantom(dom, [(1.0, 0.05, 0.5, 0.0, 0.0, -45.0)])  # long axis along (1, 1) for -45 deg
    assert value_at(f, dom, 16 * 0.25, 16 * 0.25) == 1.0 and value_at(f, dom, -16 * 0.25, 16 * 0.25) == 0.0


@pytest.mark.parametrize("name", ["j", "v"])
def test_letters_equal_png(name):
    img = imread(DATA / f"{name}.png").astype(np.float64) / 255.0
    f = phantoms.get(name, ImageDomain.paper(64)).numpy()
    np.testing.assert_array_equal(f, np.rot90(img, -1))
    assert np.array_equal(np.rot90(f), img)  # shown with rot90 it is the PNG as drawn


@pytest.mark.parametrize("name,n", [("v", 128), ("six_objects_target", 438)])
def test_resampling_preserves_integral(name, n):
    native = ImageDomain.paper(64 if name == "v" else 256)
    f0, f1 = phantoms.get(name, native), phantoms.get(name, ImageDomain.paper(n))
    i0, i1 = float(f0.sum()) * native.cell_volume, float(f1.sum()) * ImageDomain.paper(n).cell_volume
    assert i1 == pytest.approx(i0, rel=0.02)


def test_raster_on_other_box_is_function_on_frame():
    # a domain covering the left half of the frame at the native pixel size reproduces the left half exactly
    v64 = phantoms.v(ImageDomain.paper(64))
    half = phantoms.v(ImageDomain((32, 64), (-16.0, -16.0), (0.0, 16.0)))
    torch.testing.assert_close(half, v64[:32], rtol=0, atol=1e-12)
    outside = phantoms.v(ImageDomain((8, 8), (20.0, 20.0), (30.0, 30.0)))  # zero beyond [-16, 16]^2
    assert float(outside.abs().max()) == 0.0
    t = phantoms.six_objects_template(ImageDomain.paper(256))
    np.testing.assert_array_equal(t.numpy(), np.load(DATA / "six_objects_template_256.npy").astype(np.float64))


def test_3d_phantoms_registry_and_values():
    dom = ImageDomain((20, 24, 16))
    for name in NAMES_3D:
        assert phantoms.ndim(name) == 3
        f = phantoms.get(name, dom)
        assert f.shape == (20, 24, 16) and f.dtype == torch.float64, name
        assert float(f.min()) >= -1e-12 and float(f.max()) <= 1.0 + 1e-12, name
    assert phantoms.ndim("j") == 2
    with pytest.raises(ValueError, match="phantom 'shepp_logan_3d' is 3D but the domain has shape"):
        phantoms.get("shepp_logan_3d", ImageDomain.paper(8))
    with pytest.raises(ValueError, match="phantom 'j' is 2D"):
        phantoms.get("j", dom)
    with pytest.raises(ValueError, match="10 entries"):
        phantoms.ellipsoid_phantom(dom, [(1.0, 0.5, 0.5, 0.5)])
    with pytest.raises(ValueError, match="semi-axes > 0"):
        phantoms.ellipsoid_phantom(dom, [(1.0, 0.5, 0.0, 0.5, 0, 0, 0, 0, 0, 0)])


def test_shepp_logan_3d_known_values():
    """Kak-Slaney head: skull 1.0 at (0, 0.9, 0), brain 0.2 at the centre, ventricles 0.0, a small ellipsoid at
    z = 0.25 (value 0.3) that is absent at z = -0.25; the ball's volume is 4/3 pi a b c."""
    dom = ImageDomain.paper(64, 3)
    f = phantoms.get("shepp_logan_3d", dom)

    def at(x, y, z):   # normalised point -> cell value
        i, j, k = (min(63, int((16 * c + 16) // 0.5)) for c in (x, y, z))
        return float(f[i, j, k])

    assert at(0.0, 0.9, 0.0) == pytest.approx(1.0)
    assert at(0.0, 0.0, 0.0) == pytest.approx(0.2)
    assert at(0.22, 0.0, 0.0) == pytest.approx(0.0, abs=1e-12)
    assert at(0.0, -0.1, 0.25) == pytest.approx(0.3)
    assert at(0.0, -0.1, -0.25) == pytest.approx(0.2)
    ball = phantoms.ellipsoid_phantom(dom, [(1.0, 0.5, 0.25, 0.375, 0.1, 0.0, -0.1, 30.0, 40.0, 0.0)])
    volume = 4 / 3 * math.pi * (8 * 4 * 6)
    assert float(ball.sum()) * dom.cell_volume == pytest.approx(volume, rel=0.01)


def test_ellipsoid_rotation_is_orthonormal_and_2d_compatible():
    rot = phantoms.ellipsoid_rotation(25.0, 40.0, -70.0)
    torch.testing.assert_close(rot @ rot.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-14)
    assert float(torch.linalg.det(rot)) == pytest.approx(1.0)
    t = math.radians(25.0)
    torch.testing.assert_close(phantoms.ellipsoid_rotation(25.0, 0.0, 0.0)[:2, :2],
                               torch.tensor([[math.cos(t), math.sin(t)], [-math.sin(t), math.cos(t)]],
                                            dtype=torch.float64))


def test_swirl_bend_is_volume_preserving_diffeomorphism():
    """phi^-1(phi(u)) = u; det D phi = 1 (central differences); the target is the template at phi^-1."""
    u = torch.rand(3, 500, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 2 - 1
    torch.testing.assert_close(phantoms.swirl_bend(phantoms.swirl_bend(u), inverse=True), u, rtol=0, atol=1e-13)
    torch.testing.assert_close(phantoms.swirl_bend(phantoms.swirl_bend(u, inverse=True)), u, rtol=0, atol=1e-13)
    eps = 1e-6
    jac = torch.stack([(phantoms.swirl_bend(u + eps * e[:, None]) - phantoms.swirl_bend(u - eps * e[:, None]))
                       / (2 * eps) for e in torch.eye(3, dtype=torch.float64)], dim=-1)   # (3, 500, 3)
    det = torch.linalg.det(jac.permute(1, 0, 2))
    torch.testing.assert_close(det, torch.ones_like(det), rtol=0, atol=1e-8)
    moved = phantoms.swirl_bend(torch.zeros(3, 1, dtype=torch.float64))      # the bend moves the centre along x
    assert float(moved[0, 0]) == pytest.approx(phantoms.BEND)
    dom = ImageDomain.paper(24, 3)
    template, target = phantoms.get("shepp_logan_3d", dom), phantoms.get("shepp_logan_3d_swirl", dom)
    assert float((template - target).abs().sum() / template.abs().sum()) > 0.3          # a large deformation
    assert float(target.sum()) == pytest.approx(float(template.sum()), rel=0.01)      # det = 1: mass kept


def test_missing_ventricle_mask_is_the_targets_ventricle_the_template_lacks():
    dom = ImageDomain.paper(128)
    mask = phantoms.missing_ventricle_mask(dom)
    target, template = phantoms.get("shepp_logan", dom), phantoms.get("shepp_logan_template_missing", dom)
    assert 800 < int(mask.sum()) < 900    # the ellipse's area, 0.11 x 0.31 x pi of [-1, 1]^2 in 128^2 pixels
    assert float((target[mask] < 0.1).double().mean()) > 0.9 and float(template[mask].min()) > 0.19
