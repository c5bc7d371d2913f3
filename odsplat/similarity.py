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
    k = (g[:, None] * g[None, :]).expand(c, 1, window, window).contiguous()
    padding = window // 2 if pad else 0
    blur = lambda z: F.conv2d(z, k, padding=padding, groups=c)  # noqa: E731
    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


__all__ = ["ssim_map"]
