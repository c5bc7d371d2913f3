"""Image metrics in torch (SSIM, PSNR, a global sub-pixel translation), shared by the learned magnifier's
trainer, its tests and the bench."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from odsplat.spine.similarity import ssim_map


def _as_nchw(x: torch.Tensor) -> torch.Tensor:
    if x.ndim == 2:
        return x[None, None]
    if x.ndim == 3:
        return x[None]
    if x.ndim == 4:
        return x
    raise ValueError(f"expected an image (H, W), (C, H, W) or (N, C, H, W), got shape {tuple(x.shape)}")


def psnr(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all elements (inf for identical images)."""
    mse = torch.mean((a.double() - b.double()) ** 2).item()
    return math.inf if mse == 0 else 10.0 * math.log10(data_range ** 2 / mse)


def ssim(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0, *, window: int = 11, sigma: float = 1.5) -> float:
    """Mean structural similarity (Wang et al. 2004): Gaussian window 11 x 11, sigma 1.5, K1 0.01, K2 0.03,
    per channel, over the 'valid' region (no padding), averaged over channels and images."""
    x, y = _as_nchw(a).double(), _as_nchw(b).double()
    if x.shape != y.shape:
        raise ValueError(f"images of different shapes: {tuple(x.shape)} and {tuple(y.shape)}")
    return ssim_map(x, y, data_range=data_range, window=window, sigma=sigma).mean().item()


def estimate_translation(a: torch.Tensor, b: torch.Tensor, *, border: int = 8, iters: int = 20) -> tuple[float, float]:
    """The global translation (dx, dy) in pixels with b(x) ~ a(x - d): an integer FFT cross-correlation
    peak, refined by Gauss-Newton (Lucas-Kanade) on the interior `border` px in from the edges.
    Images (H, W), (C, H, W) or (1, C, H, W); channels are averaged."""
    x = _as_nchw(a).double().mean(dim=1, keepdim=True)
    y = _as_nchw(b).double().mean(dim=1, keepdim=True)
    h, w = x.shape[-2:]
    # Coarse: the circular cross-correlation's peak of the Hann-windowed, mean-free images.
    win = (torch.hann_window(h, periodic=False, dtype=torch.float64)[:, None]
           * torch.hann_window(w, periodic=False, dtype=torch.float64)[None])
    fa = torch.fft.fft2((x[0, 0] - x.mean()) * win)
    fb = torch.fft.fft2((y[0, 0] - y.mean()) * win)
    cc = torch.fft.ifft2(fb * fa.conj()).real
    iy, ix = divmod(int(torch.argmax(cc)), w)
    d = torch.tensor([ix - w if ix > w // 2 else ix, iy - h if iy > h // 2 else iy], dtype=torch.float64)
    # Fine: warp a by d (bilinear) and solve the linearised least squares for the update.
    gy, gx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    inner = (slice(None), slice(None), slice(border, h - border), slice(border, w - border))
    for _ in range(iters):
        sx, sy = gx - d[0], gy - d[1]
        grid = torch.stack([2 * sx / (w - 1) - 1, 2 * sy / (h - 1) - 1], dim=-1)[None]
        aw = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=True)
        ax = torch.gradient(aw, dim=3)[0]
        ay = torch.gradient(aw, dim=2)[0]
        r = (y - aw)[inner].reshape(-1)
        jac = -torch.stack([ax[inner].reshape(-1), ay[inner].reshape(-1)], dim=1)
        step = torch.linalg.lstsq(jac, r[:, None]).solution[:, 0]
        d = d + step
        if step.abs().max() < 1e-5:
            break
    return float(d[0]), float(d[1])


__all__ = ["estimate_translation", "psnr", "ssim"]
