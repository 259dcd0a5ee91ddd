"""A small U-Net mapping (template, FBP of the data) to an initial momentum (rem:AltLDDMM, learned momenta)."""
from __future__ import annotations

import torch
from torch import nn

from .._checks import check_int, check_positive


def _block(c_in: int, c_out: int) -> nn.Sequential:
    """Two 3x3 convolutions with GroupNorm and SiLU."""
    groups = max(1, min(8, c_out // 4))
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=1), nn.GroupNorm(groups, c_out), nn.SiLU(),
        nn.Conv2d(c_out, c_out, 3, padding=1), nn.GroupNorm(groups, c_out), nn.SiLU())


class MomentumUNet(nn.Module):
    """U-Net ``Lambda_Theta: (template, fbp) -> m0`` with ``levels`` resolutions and ``width * 2^l`` channels.

    The output is ``momentum_scale * net(x)``: choose ``momentum_scale`` so that an O(1) network output is a
    momentum of the intended size (for the Gaussian kernel ``K m ~ 2 pi sigma^2 m`` on smooth ``m``, so
    ``momentum_scale = displacement / (2 pi sigma^2)`` makes the output a velocity in physical units).
    The last convolution starts at zero, so an untrained net predicts ``m0 = 0`` (the identity deformation).

    Parameters
    ----------
    in_channels : int
        Input channels (2: template and FBP).
    width : int
        Channels at the finest level.
    levels : int
        Resolutions (>= 1).
    momentum_scale : float
        The output's factor (> 0).

    Raises
    ------
    ValueError, TypeError
        A count or scale out of range.

    Notes
    -----
    input ``(B, in_channels, nx, ny)`` with ``nx``, ``ny`` divisible by ``2^(levels-1)``; output
    ``(B, 2, nx, ny)`` (component 0 = x, 1 = y, as ``GeodesicShooting`` expects).
    """

    def __init__(self, in_channels: int = 2, width: int = 16, levels: int = 3, momentum_scale: float = 1.0):
        super().__init__()
        self.in_channels = check_int(in_channels, "in_channels", 1)
        self.levels = check_int(levels, "levels", 1)
        width = check_int(width, "width", 1)
        self.momentum_scale = check_positive(momentum_scale, "momentum_scale")
        chans = [width * 2 ** level for level in range(self.levels)]
        self.down = nn.ModuleList(_block(c_in, c_out) for c_in, c_out in zip([self.in_channels] + chans, chans))
        self.up = nn.ModuleList(nn.ConvTranspose2d(c, c // 2, 2, stride=2) for c in chans[:0:-1])
        self.merge = nn.ModuleList(_block(c, c // 2) for c in chans[:0:-1])
        self.head = nn.Conv2d(chans[0], 2, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        factor = 2 ** (self.levels - 1)
        if x.dim() != 4 or x.shape[1] != self.in_channels or x.shape[-1] % factor or x.shape[-2] % factor:
            raise ValueError(f"input must have shape (B, {self.in_channels}, nx, ny) with nx, ny divisible by "
                             f"{factor}, got {tuple(x.shape)}")
        skips = []
        for level, block in enumerate(self.down):
            x = block(x if level == 0 else nn.functional.max_pool2d(x, 2))
            skips.append(x)
        for up, merge, skip in zip(self.up, self.merge, reversed(skips[:-1])):
            x = merge(torch.cat([up(x), skip], dim=1))
        return self.momentum_scale * self.head(x)
