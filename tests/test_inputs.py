"""Tests of ``indreg.load``: it builds the operator that produced the data (parallel, fan beam, tilt series), from
paths or arrays alike, and every bad input is one line naming the argument."""
import numpy as np
import pytest
import torch

import indreg
from indreg import ImageDomain, phantoms
from indreg.forward import FanBeamGeometry, TiltSeriesGeometry, TiltSeriesTransform
from indreg.io import DataFileError, write_tilt_series, write_volume

DEG = np.arange(-60.0, 61.0, 10.0)    # 13 tilts


def parallel_problem():
    """Template J, target V (16^2 on [-16, 16]^2) and the target's data at DEG, 24 bins on [-24, 24]."""
    domain = ImageDomain.paper(16)
    T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(det_count=24, det_min=-24.0, det_max=24.0,
                                                                angles=torch.from_numpy(np.deg2rad(DEG))))
    template, target = phantoms.get("j", domain), phantoms.get("v", domain)
    return template, target, T(target)


def tilt_series_problem(d):
    """A 16 x 16 x 12 slab (1-unit voxels), 7 tilts about y, written as MRC volume + MRC stack with its .tlt."""
    dom = ImageDomain((16, 16, 12), (-8.0, -8.0, -6.0), (8.0, 8.0, 6.0))
    g = TiltSeriesGeometry.uniform(-60, 60, 20, det_count=16, det_min=-8.0, det_max=8.0)
    template = phantoms.get("shepp_logan_3d", ImageDomain.paper(16, ndim=3))[:, :, 2:14]
    target = phantoms.get("shepp_logan_3d_swirl", ImageDomain.paper(16, ndim=3))[:, :, 2:14]
    data = TiltSeriesTransform(dom, g)(target)
    write_volume(d / "template.mrc", template.numpy(), dom)
    write_tilt_series(d / "tilts.mrc", data.numpy(), g.angles, pixel_size=1.0)
    return template, target, data, g


def test_parallel_from_files_is_the_operator_of_the_data(tmp_path):
    template, target, data = parallel_problem()
    np.save(tmp_path / "t.npy", template.numpy()), np.save(tmp_path / "s.npy", data.numpy())
    np.save(tmp_path / "g.npy", target.numpy())
    (tmp_path / "a.tlt").write_text("".join(f"{a:g}\n" for a in DEG))
    d = indreg.load(tmp_path / "t.npy", str(tmp_path / "s.npy"), angles=tmp_path / "a.tlt", det_min=-24,
                    det_max=24, target=tmp_path / "g.npy")
    assert d.domain == ImageDomain.paper(16) and d.label == "t.npy" and d.template.dtype == torch.float64
    torch.testing.assert_close(d.operator(target.double()), data.double(), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(d.target, target.double(), rtol=0, atol=0)
    assert d.geometry is d.operator.geometry and d.geometry.det_count == 24


def test_arrays_give_what_files_give(tmp_path):
    """Numpy arrays, torch tensors and an inline angle list in radians: the same template, data, operator."""
    template, target, data = parallel_problem()
    np.save(tmp_path / "t.npy", template.numpy()), np.save(tmp_path / "s.npy", data.numpy())
    (tmp_path / "a.tlt").write_text("".join(f"{a:g}\n" for a in DEG))
    files = indreg.load(tmp_path / "t.npy", tmp_path / "s.npy", angles=tmp_path / "a.tlt", det_min=-24, det_max=24)
    arrays = indreg.load(template.numpy(), data.float(), angles=np.deg2rad(DEG).tolist(), angle_unit="rad",
                         det_min=-24, det_max=24)
    assert arrays.label == "array" and arrays.target is None and arrays.data.dtype == torch.float64
    torch.testing.assert_close(arrays.template, files.template, rtol=0, atol=0)
    torch.testing.assert_close(arrays.data, data.float().double(), rtol=0, atol=0)
    x = torch.rand(16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(arrays.operator(x), files.operator(x), rtol=1e-14, atol=1e-14)


def test_fan_beam():
    domain = ImageDomain.paper(16)
    template, target = phantoms.get("j", domain), phantoms.get("v", domain)
    angles = np.deg2rad(np.arange(0.0, 360.0, 30.0))
    T = indreg.RayTransform(domain, FanBeamGeometry(det_count=32, src_radius=40.0, det_radius=40.0,
                                                    angles=torch.from_numpy(angles)))
    d = indreg.load(template, T(target), "fan_flat", angles=angles, angle_unit="rad", src_radius=40,
                    det_radius=40)
    assert isinstance(d.geometry, FanBeamGeometry) and d.geometry.magnification == 2.0
    torch.testing.assert_close(d.operator(target), T(target), rtol=1e-12, atol=1e-12)


def test_tilt_series_from_files_and_arrays(tmp_path):
    """An MRC volume and an MRC stack with its sibling .tlt: the slab's box domain, voxel-wide detector columns,
    the operator of the data; the same from arrays."""
    template, target, data, g = tilt_series_problem(tmp_path)
    d = indreg.load(tmp_path / "template.mrc", tmp_path / "tilts.mrc", "tilt_series", half_width=8)
    assert d.domain.shape == (16, 16, 12) and d.domain.cell_sides == (1.0, 1.0, 1.0)
    assert d.geometry.det_min == -8.0 and d.operator.range_shape == (7, 16, 16)
    torch.testing.assert_close(d.template, template.double(), rtol=1e-6, atol=1e-6)   # float32 in MRC
    torch.testing.assert_close(d.operator(target), data, rtol=1e-12, atol=1e-12)
    arrays = indreg.load(d.template, d.data.numpy(), "tilt_series", angles=g.angles, angle_unit="rad",
                         half_width=8, tilt_axis="y")
    torch.testing.assert_close(arrays.operator(d.template), d.operator(d.template), rtol=1e-14, atol=1e-14)


def one_line(exc_type, match, *args, **kwargs):
    with pytest.raises(exc_type, match=match) as info:
        indreg.load(*args, **kwargs)
    assert "\n" not in str(info.value)


def test_bad_input_is_one_line_naming_the_argument(tmp_path):
    template, target, data = parallel_problem()
    t, s, a = template.numpy(), data.numpy(), np.deg2rad(DEG)
    kw = {"angles": a, "angle_unit": "rad"}
    one_line(DataFileError, r"^template: shape 16 x 12 is not square", t[:, :12], s, **kw)
    one_line(DataFileError, r"^data: 12 rows \(one per angle\) but angles gives 13 angles", t, s[:-1], **kw)
    one_line(DataFileError, r"^data: 24 detector bins but det_count=92", t, s, det_count=92, **kw)
    one_line(DataFileError, r"^angles is required", t, s)
    one_line(DataFileError, r"^target: shape \(8, 8\) differs from the template's \(16, 16\)", t, s,
             target=t[:8, :8], **kw)
    one_line(DataFileError, r"^template file .*nope\.npy: no such file", tmp_path / "nope.npy", s, **kw)
    one_line(DataFileError, r"^geometry: src_radius", t, s, "fan_flat", **kw)
    one_line(ValueError, r"^template must be a non-empty 2D array, got shape \(2, 16, 16\)", np.stack([t, t]), s,
             **kw)
    one_line(ValueError, r"^data has 1 non-finite values", t, np.where(s == s.max(), np.nan, s), **kw)
    one_line(TypeError, r"^template has complex values", t + 0j, s, **kw)
    one_line(ValueError, r"^geometry must be one of parallel, fan_flat, tilt_series, got 'cone'", t, s, "cone",
             **kw)
    one_line(ValueError, r"^angle_unit must be 'deg' or 'rad', got 'degree'", t, s, angles=a, angle_unit="degree")
    one_line(ValueError, r"^half_width must be a finite number > 0", t, s, half_width=-1, **kw)
    one_line(ValueError, r"^angles must be finite", t, s, angles=[0.0, float("nan")])


def test_tilt_series_bad_input(tmp_path):
    template, target, data, g = tilt_series_problem(tmp_path)
    (tmp_path / "tilts.tlt").unlink()
    one_line(DataFileError, r"^angles is required: .* or a file tilts\.tlt \(or \.rawtlt\) next to",
             tmp_path / "template.mrc", tmp_path / "tilts.mrc", "tilt_series")
    one_line(DataFileError, r"^data: shape \(7, 12, 16\) but the template \(16, 16, 12\) with tilt axis y needs "
             r"\(7, 16, 16\)", template, data[:, :12], "tilt_series", angles=g.angles, angle_unit="rad")
    one_line(ValueError, r"^tilt_axis must be 'x', 'y' or 'z', got 'xy'", template, data, "tilt_series",
             angles=g.angles, angle_unit="rad", tilt_axis="xy")
