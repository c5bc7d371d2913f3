"""Structural similarity (Wang et al. 2004) in torch, differentiable: one implementation for the metric and the loss."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def ssim_map(x: torch.Tensor, y: torch.Tensor, *, data_range: float = 1.0, window: int = 11, sigma: float = 1.5,
             pad: bool = False) -> torch.Tensor:
    """Per-pixel SSIM of two (N, C, H, W) batches: Gaussian window (11, sigma 1.5), K1 0.01, K2 0.03, per channel.

    pad=False keeps the 'valid' region (the evaluation metric); pad=True zero-pads by half a window so the map
    covers every pixel (the 3DGS training loss).
    """
    if x.shape != y.shape or x.ndim != 4:
        raise ValueError(f"expected two (N, C, H, W) batches of one shape, got {tuple(x.shape)} and {tuple(y.shape)}")
    c = x.shape[1]
    window = min(window, x.shape[2], x.shape[3])
    r = torch.arange(window, dtype=x.dtype, device=x.device) - (window - 1) / 2
    g = torch.exp(-r ** 2 / (2 * sigma ** 2))
    g = g / g.sum()
    padding = window // 2 if pad else 0
    # The Gaussian window is separable: one row pass and one column pass over the five maps at once (22 taps a
    # pixel instead of 121, in two convolution calls instead of five).
    z = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    n = z.shape[1]
    z = F.conv2d(z, g.view(1, 1, 1, window).expand(n, 1, 1, window), padding=(0, padding), groups=n)
    z = F.conv2d(z, g.view(1, 1, window, 1).expand(n, 1, window, 1), padding=(padding, 0), groups=n)
    mx, my, bxx, byy, bxy = z.split(c, dim=1)
    sxx, syy, sxy = bxx - mx * mx, byy - my * my, bxy - mx * my
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


__all__ = ["ssim_map"]
