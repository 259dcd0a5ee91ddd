"""Seeded additive white Gaussian noise at a requested signal-to-noise ratio (paper's eq. ``snr``).

Notes
-----
- One data set is the last ``event_dims`` axes of a tensor (default 2: a sinogram
  ``(..., num_angles, det_count)``); leading dims are a batch, each item gets its own noise and SNR.
- Two SNR conventions, both in dB, with means and (unweighted; a constant weight cancels) norms over
  one data set:
    ``"paper"``: ``10 log10(||g - mean g||^2 / ||n - mean n||^2)``, the printed formula ``snr``;
    ``"code"``:  ``10 log10(||g - mean g|| / ||n - mean n||)``, what the authors' code computes, i.e.
    half the paper's dB. The paper's reported values (:data:`PAPER_SNR_DB`) are in this convention.
- Noise is drawn in float64 on the CPU from a seeded ``torch.Generator`` and then cast and moved to the
  data's dtype/device, so a seed gives the same noise on every device.
"""
from __future__ import annotations

import torch

from ._checks import check_int, check_nonnegative, check_number, check_tensor

#: SNR of the paper's test suites, in the authors' code convention (``convention="code"``).
PAPER_SNR_DB = {"suite1": 4.87, "suite2": 4.75, "suite3": 7.06, "suite4_missing": 7.06, "suite4_extra": 6.46}

_CONVENTIONS = ("code", "paper")
#: Largest |SNR| in dB accepted: a norm ratio of at most 1e30 either way, far from float64 over/underflow.
_SNR_DB_MAX = 300.0


def _check_convention(convention: str) -> float:
    """dB per decade of the norm ratio: 10 for "code" (norms), 20 for "paper" (squared norms)."""
    if convention not in _CONVENTIONS:
        raise ValueError(f"convention must be one of {_CONVENTIONS}, got {convention!r}")
    return 10.0 if convention == "code" else 20.0


def _centred_norm(x: torch.Tensor, event_dims: int) -> torch.Tensor:
    dims = tuple(range(-event_dims, 0))
    return (x - x.mean(dim=dims, keepdim=True)).square().sum(dim=dims).sqrt()


def snr_db(ideal: torch.Tensor, noise: torch.Tensor, convention: str = "code", event_dims: int = 2) -> torch.Tensor:
    """SNR in dB of ``ideal + noise``: ``factor * log10(||ideal - mean|| / ||noise - mean||)`` with ``factor`` 10
    (``"code"``) or 20 (``"paper"``, the printed formula ``snr``).

    Parameters
    ----------
    ideal : torch.Tensor
        The noise-free data ``(..., *event)``.
    noise : torch.Tensor
        The noise, ``ideal``'s last ``event_dims`` axes (its batch broadcasts).
    convention : {"code", "paper"}
        The SNR convention (module Notes).
    event_dims : int
        The axes of one data set (>= 1).

    Returns
    -------
    torch.Tensor
        The SNR in dB per data set, the batch dims kept.

    Raises
    ------
    ValueError
        An unknown convention, shapes that do not fit, non-finite values.
    TypeError
        Inputs that are not real floating tensors.
    """
    factor = _check_convention(convention)
    k = check_int(event_dims, "event_dims", 1)
    check_tensor(ideal, "ideal", min_dim=k)
    check_tensor(noise, "noise", tuple(ideal.shape[ideal.dim() - k:]))
    return factor * torch.log10(_centred_norm(ideal, k) / _centred_norm(noise, k))


def _generator(seed) -> torch.Generator:
    if isinstance(seed, torch.Generator):
        if seed.device.type != "cpu":
            raise ValueError(f"seed generator must live on the CPU (noise is drawn there), got {seed.device}")
        return seed
    return torch.Generator().manual_seed(check_int(seed, "seed", 0))


def add_white_noise(data: torch.Tensor, snr_db: float | None = None, std: float | None = None,
                    convention: str = "code", seed=0, event_dims: int = 2) -> tuple:
    """Add seeded white Gaussian noise ``noise = c z`` (``z`` a standard normal draw) at an SNR or a standard
    deviation.

    Parameters
    ----------
    data : torch.Tensor
        ``(..., *event)``, ``event`` its last ``event_dims`` axes (one data set each).
    snr_db : float, optional
        The SNR in dB (``|snr_db| <= 300``): ``z`` is scaled per data set by
        ``c = ||g - mean g|| / (||z - mean z|| 10^(snr_db / factor))``, so that :func:`snr_db`
        ``(data, noise, convention)`` equals the request exactly (``factor`` as there).
    std : float, optional
        ``noise = std * z`` (suite 1 of the authors' code: ``std = 1.0``). Give exactly one of ``snr_db`` and
        ``std``.
    convention : {"code", "paper"}
        The SNR convention (module Notes).
    seed : int or torch.Generator
        An int >= 0 or a CPU ``torch.Generator`` (advanced by the draw).
    event_dims : int
        The axes of one data set (>= 1).

    Returns
    -------
    noisy : torch.Tensor
        ``data + noise``.
    noise : torch.Tensor
        The noise, in the data's dtype and device.

    Raises
    ------
    ValueError
        Both or neither of ``snr_db`` and ``std``, an unknown convention, an SNR out of range, constant data (no
        signal power), a generator not on the CPU, a negative ``std``.
    TypeError
        Data that are not a real floating tensor.
    """
    k = check_int(event_dims, "event_dims", 1)
    check_tensor(data, "data", min_dim=k)
    factor, generator = _check_convention(convention), _generator(seed)
    if (snr_db is None) == (std is None):
        raise ValueError(f"give exactly one of snr_db and std, got snr_db={snr_db!r}, std={std!r}")
    if std is not None:
        return _added(data, check_nonnegative(std, "std") * _draw(data, generator))
    target = check_number(snr_db, "snr_db", "a finite number (dB)")
    if not abs(target) <= _SNR_DB_MAX:
        raise ValueError(f"snr_db must be a finite number (dB) in [-{_SNR_DB_MAX:g}, {_SNR_DB_MAX:g}], got {snr_db!r}")
    signal = _centred_norm(data.detach().to(torch.float64).cpu(), k)
    if not bool((signal > 0).all()):
        raise ValueError("data is constant over a data set (zero signal power): the SNR is undefined")
    z = _draw(data, generator)
    scale = signal / (_centred_norm(z, k) * 10.0 ** (target / factor))
    return _added(data, scale.reshape(scale.shape + (1,) * k) * z)


def _draw(data: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """A standard normal draw shaped like ``data``, float64 on the CPU."""
    return torch.randn(data.shape, generator=generator, dtype=torch.float64)


def _added(data: torch.Tensor, noise: torch.Tensor) -> tuple:
    """``(data + noise, noise)`` with the noise cast and moved to the data's dtype and device."""
    noise = noise.to(dtype=data.dtype, device=data.device)
    return data + noise, noise
