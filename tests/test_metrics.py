"""Tests of indreg.metrics: known values of SSIM / PSNR / relative error in both conventions."""
import math

import numpy as np
import pytest
import torch

from indreg.metrics import psnr, psnr_paper, relative_error, ssim, ssim_paper


def images():
    gt = np.zeros((32, 32))
    gt[8:24, 10:20] = 0.5  # range 0.5
    x = gt + 0.05 * np.random.default_rng(0).standard_normal(gt.shape)
    return x, gt


def test_identical():
    _, gt = images()
    assert ssim(gt, gt) == pytest.approx(1.0) and ssim_paper(gt, gt) == pytest.approx(1.0)
    assert psnr(gt, gt) == math.inf and psnr_paper(gt, gt) == math.inf
    assert relative_error(gt, gt) == 0.0


def test_known_mse_psnr():
    _, gt = images()
    x = gt + 0.01  # MSE = 1e-4, nonnegative
    assert psnr(x, gt) == pytest.approx(10 * math.log10(0.5 ** 2 / 1e-4))       # range of gt = 0.5
    assert psnr_paper(x, gt) == pytest.approx(10 * math.log10(1.0 / 1e-4))      # 2017: range 1 if nonnegative
    xn = gt - 0.01  # negative values -> 2017 range 2
    assert psnr_paper(xn, gt) == pytest.approx(10 * math.log10(4.0 / 1e-4))
    assert psnr_paper(xn, gt) - psnr_paper(x, gt) == pytest.approx(20 * math.log10(2))


def test_ssim_conventions():
    x, gt = images()
    from skimage.metrics import structural_similarity
    assert ssim(x, gt) == pytest.approx(structural_similarity(x, gt, data_range=0.5))
    assert ssim_paper(x, gt) == pytest.approx(structural_similarity(x, gt, data_range=2.0))
    assert 0 < ssim(x, gt) < ssim_paper(x, gt) < 1  # a larger data range hides the same error


def test_relative_error_and_inputs():
    x, gt = images()
    assert relative_error(2 * gt, gt) == pytest.approx(1.0)
    assert relative_error(x, gt) == pytest.approx(np.linalg.norm(x - gt) / np.linalg.norm(gt))
    xt, gtt = torch.from_numpy(x).float(), torch.from_numpy(gt)  # torch, mixed dtypes, numpy all fine
    assert ssim(xt, gtt) == pytest.approx(ssim(x, gt), rel=1e-5)
    assert psnr(xt, gt) == pytest.approx(psnr(x, gt), rel=1e-5)


def test_errors():
    x, gt = images()
    with pytest.raises(ValueError, match="same shape"):
        ssim(x[:30], gt)
    with pytest.raises(ValueError, match="2D"):
        psnr(x[None, None], gt[None, None])
    with pytest.raises(TypeError, match="torch.Tensor or numpy"):
        relative_error([[1.0]], gt)
    with pytest.raises(ValueError, match="constant"):
        psnr(x, np.ones_like(gt))
    with pytest.raises(ValueError, match="zero"):
        relative_error(x, np.zeros_like(gt))
    with pytest.raises(ValueError, match="non-finite"):
        ssim(np.full_like(x, np.nan), gt)


def test_3d_volumes():
    gt = np.zeros((16, 16, 16))
    gt[4:12, 5:11, 6:10] = 1.0
    noise = 0.05 * np.random.default_rng(1).standard_normal(gt.shape)
    from skimage.metrics import structural_similarity
    assert ssim(gt + noise, gt) == pytest.approx(structural_similarity(gt + noise, gt, data_range=1.0))
    one_slice = gt.copy()
    one_slice[:, :, 8] += noise[:, :, 8]
    assert ssim(gt + noise, gt) < ssim(one_slice, gt) < 1.0  # a 7^3 window sees every slice's error
    assert psnr(gt + 0.01, gt) == pytest.approx(40.0)


@pytest.mark.parametrize("metric", [ssim, psnr, ssim_paper, psnr_paper, relative_error])
def test_complex_boolean_and_small_inputs_are_refused(metric):
    # issue #19: psnr(I + 5j, I) cast the complex image to its real part, i.e. I, and returned inf
    x, gt = images()
    xt = torch.from_numpy(x)
    for bad, dtype in ((x + 5j, "complex128"), (xt + 5j, "torch.complex128"), (x > 0.5, "bool"),
                       (xt > 0.5, "torch.bool"), (x.astype(str), "<U32")):
        with pytest.raises(TypeError, match=f"^x must have real numeric values, got dtype {dtype}"):
            metric(bad, gt)
        with pytest.raises(TypeError, match=f"^gt must have real numeric values, got dtype {dtype}"):
            metric(gt, bad)
    with pytest.raises(ValueError, match=r"^x must be a non-empty 2D image .* got shape \(0, 32\)"):
        metric(x[:0], gt[:0])
    with pytest.raises(ValueError, match="^gt contains non-finite values"):
        metric(x, np.where(gt > 0.25, np.inf, gt))
    with pytest.raises(ValueError, match=r"^x and gt must have the same shape, got \(32, 32\) and \(32, 31\)"):
        metric(x, gt[:, :-1])
    assert metric(xt.to(torch.bfloat16), gt) == pytest.approx(metric(xt.to(torch.bfloat16).double(), gt))


def test_ssim_needs_its_window():
    x, gt = images()
    for metric in (ssim, ssim_paper):
        with pytest.raises(ValueError, match=r"^x and gt must be at least 7 cells along every axis for SSIM .* "
                                             r"got shape \(6, 32\)"):
            metric(x[8:14], gt[8:14])
    assert psnr(x[8:14], gt[8:14]) > 0  # PSNR has no window


@pytest.mark.parametrize("chunk", [1, 3, 16])
@pytest.mark.parametrize("shape", [(23, 9, 11), (7, 8, 9), (40, 7, 12)])
def test_volumes_in_chunks_equal_whole_volumes(monkeypatch, chunk, shape):
    """A volume's SSIM, PSNR and relative error read in float64 chunks of slices (any chunk size, a float32
    tensor as it is) equal scikit-image's / numpy's on the whole float64 arrays to rounding."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from indreg import metrics
    monkeypatch.setattr(metrics, "CHUNK", chunk)
    rng = np.random.default_rng(0)
    gt = torch.from_numpy(rng.random(shape)).float()
    x = gt + 0.1 * torch.from_numpy(rng.standard_normal(shape)).float()
    a, b = x.double().numpy(), gt.double().numpy()
    r = float(b.max() - b.min())
    assert ssim(x, gt) == pytest.approx(structural_similarity(a, b, data_range=r), rel=1e-13)
    assert ssim_paper(x, gt) == pytest.approx(structural_similarity(a, b, data_range=2.0), rel=1e-13)
    assert psnr(x, gt) == pytest.approx(peak_signal_noise_ratio(b, a, data_range=r), rel=1e-13)
    assert psnr_paper(x, gt) == pytest.approx(peak_signal_noise_ratio(b, a, data_range=2.0), rel=1e-13)
    assert relative_error(x, gt) == pytest.approx(np.linalg.norm(a - b) / np.linalg.norm(b), rel=1e-13)
    assert psnr(gt, gt) == math.inf and ssim(gt.numpy(), gt.numpy()) == pytest.approx(1.0, rel=1e-13)
