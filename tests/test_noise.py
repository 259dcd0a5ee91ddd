"""Tests of indreg.noise: seeding, exact SNR in both conventions, batch dims, errors."""
import math

import pytest
import torch

from indreg.noise import PAPER_SNR_DB, add_white_noise, snr_db


def sinogram(*batch, dtype=torch.float64):
    a = torch.linspace(0, 3, 10, dtype=dtype)[:, None]
    s = torch.linspace(-1, 1, 92, dtype=dtype)
    return (torch.cos(a + 2 * s) * (1 - s ** 2)).expand(*batch, 10, 92).clone()


def test_seed_reproducible():
    g = sinogram()
    n1 = add_white_noise(g, std=1.0, seed=0)[1]
    n2 = add_white_noise(g, std=1.0, seed=0)[1]
    n3 = add_white_noise(g, std=1.0, seed=1)[1]
    assert torch.equal(n1, n2) and not torch.allclose(n1, n3)
    gen = torch.Generator().manual_seed(0)
    assert torch.equal(add_white_noise(g, std=1.0, seed=gen)[1], n1)  # a generator works like its seed
    assert not torch.equal(add_white_noise(g, std=1.0, seed=gen)[1], n1)  # ... and advances


def test_std_noise():
    g = sinogram()
    noisy, noise = add_white_noise(torch.zeros(200, 300, dtype=torch.float64), std=2.0, seed=3)
    assert torch.equal(noisy, noise)
    assert float(noise.std()) == pytest.approx(2.0, rel=0.01) and abs(float(noise.mean())) < 0.02
    noisy, noise = add_white_noise(g, std=0.0)
    assert torch.equal(noisy, g) and float(noise.abs().max()) == 0.0


@pytest.mark.parametrize("convention", ["code", "paper"])
@pytest.mark.parametrize("target", [4.87, -3.0, 20.0])
def test_requested_snr_realised(convention, target):
    g = sinogram()
    noisy, noise = add_white_noise(g, snr_db=target, convention=convention, seed=7)
    torch.testing.assert_close(noisy, g + noise, rtol=0, atol=0)
    assert float(snr_db(g, noise, convention)) == pytest.approx(target, abs=1e-10)
    # direct formula (the paper's printed eq. snr uses squared norms)
    c = lambda x: x - x.mean()  # noqa: E731
    ratio = float(c(g).norm() / c(noise).norm())
    assert (10 if convention == "code" else 20) * math.log10(ratio) == pytest.approx(target, abs=1e-10)


def test_code_db_is_half_paper_db():
    g = sinogram()
    _, noise = add_white_noise(g, std=0.3, seed=2)
    assert float(snr_db(g, noise, "code")) == pytest.approx(float(snr_db(g, noise, "paper")) / 2, rel=1e-14)
    # the same request in the paper's convention is a weaker noise (half the dB in code convention)
    _, np_ = add_white_noise(g, snr_db=4.87, convention="paper", seed=2)
    assert float(snr_db(g, np_, "code")) == pytest.approx(4.87 / 2, abs=1e-10)


def test_batch_each_item_gets_own_noise_and_snr():
    g = sinogram(2, 3)
    g[1] *= 5.0
    noisy, noise = add_white_noise(g, snr_db=PAPER_SNR_DB["suite1"], seed=0)
    assert noisy.shape == noise.shape == (2, 3, 10, 92)
    snr = snr_db(g, noise)
    assert snr.shape == (2, 3)
    torch.testing.assert_close(snr, torch.full((2, 3), 4.87, dtype=torch.float64), rtol=0, atol=1e-10)
    assert not torch.allclose(noise[0, 0], noise[0, 1])
    # event_dims=3 treats (3, 10, 92) as one data set
    _, n3 = add_white_noise(g, snr_db=6.0, seed=0, event_dims=3)
    assert snr_db(g, n3, event_dims=3).shape == (2,)


def test_dtype_and_presets():
    g = sinogram(dtype=torch.float32)
    noisy, noise = add_white_noise(g, snr_db=7.06, seed=0)
    assert noisy.dtype == noise.dtype == torch.float32
    assert float(snr_db(g, noise)) == pytest.approx(7.06, abs=1e-5)
    assert PAPER_SNR_DB == {"suite1": 4.87, "suite2": 4.75, "suite3": 7.06, "suite4_missing": 7.06,
                            "suite4_extra": 6.46}


def test_errors():
    g = sinogram()
    with pytest.raises(ValueError, match="exactly one of snr_db and std"):
        add_white_noise(g)
    with pytest.raises(ValueError, match="exactly one of snr_db and std"):
        add_white_noise(g, snr_db=3.0, std=1.0)
    with pytest.raises(ValueError, match="std must be a finite number >= 0"):
        add_white_noise(g, std=-1.0)
    with pytest.raises(ValueError, match="std must be a finite number >= 0"):
        add_white_noise(g, std=float("nan"))
    with pytest.raises(ValueError, match="snr_db must be a finite"):
        add_white_noise(g, snr_db=float("inf"))
    with pytest.raises(ValueError, match=r"snr_db must be a finite number \(dB\) in \[-300, 300\], got 100000"):
        add_white_noise(g, snr_db=1e5)  # 10^(snr/10) overflows
    with pytest.raises(TypeError, match="std must be a finite number >= 0, got 'a'"):
        add_white_noise(g, std="a")
    with pytest.raises(TypeError, match=r"snr_db must be a finite number \(dB\), got 'a'"):
        add_white_noise(g, snr_db="a")
    with pytest.raises(TypeError, match=r"std must be a finite number >= 0, got \[1.0\]"):
        add_white_noise(g, std=[1.0])
    for bad in ("1", True, 1 + 0j):  # float() took "1" and True
        with pytest.raises(TypeError, match="^std must be a finite number >= 0, got "):
            add_white_noise(g, std=bad)
        with pytest.raises(TypeError, match=r"^snr_db must be a finite number \(dB\), got "):
            add_white_noise(g, snr_db=bad)
    with pytest.raises(TypeError, match="data must be float32 or float64, got torch.float16"):
        add_white_noise(g.half(), std=1.0)
    with pytest.raises(ValueError, match="convention"):
        add_white_noise(g, snr_db=3.0, convention="db")
    with pytest.raises(ValueError, match="constant"):
        add_white_noise(torch.ones(10, 92, dtype=torch.float64), snr_db=3.0)
    with pytest.raises(TypeError, match="floating"):
        add_white_noise(torch.ones(10, 92, dtype=torch.int64), std=1.0)
    with pytest.raises(ValueError, match="seed"):
        add_white_noise(g, std=1.0, seed=-1)
    with pytest.raises(ValueError, match="noise must have shape"):
        snr_db(g, torch.zeros(10, 91, dtype=torch.float64))
