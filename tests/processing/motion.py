"""Shared by the phase and linear magnification tests: a band-limited texture translated by a known sub-pixel
sinusoid, and how far the output moved against how far the gain convention says it should."""
from __future__ import annotations

import math

import numpy as np
import torch

from odsplat.processing.base import rgb_to_yiq
from odsplat.processing.filters import make_filter
from odsplat.processing.phase import measure_shift_px, shift_image_px

FPS_HZ, F0_HZ, AMP_PX = 30.0, 3.0, 0.05
BAND_HZ = (2.0, 4.5)
DIRECTION = (math.cos(0.5), math.sin(0.5))  # between the pyramid's orientations on purpose


def texture(n: int = 128, lam_min_px: float = 20.0, lam_max_px: float = 40.0, seed: int = 0) -> torch.Tensor:
    """Periodic random texture with wavelengths between lam_min_px and lam_max_px, mean 0.5, sd 0.08."""
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(n, n, generator=g, dtype=torch.float64)
    f = torch.fft.fftfreq(n, dtype=torch.float64)
    r = torch.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    band = ((r >= 1 / lam_max_px) & (r <= 1 / lam_min_px)).double()
    t = torch.fft.ifft2(torch.fft.fft2(noise) * band).real
    return 0.5 + 0.08 * t / t.std()


def displacement_px(n_frames: int) -> np.ndarray:
    return AMP_PX * np.sin(2 * np.pi * F0_HZ * np.arange(n_frames) / FPS_HZ)


def translating_video(tex: torch.Tensor, d_px: np.ndarray) -> torch.Tensor:
    """(T, 1, H, W) float32: tex moved by d_px[t] along DIRECTION (exact FFT shift)."""
    return torch.stack([shift_image_px(tex, float(d) * DIRECTION[0], float(d) * DIRECTION[1]) for d in d_px]
                       ).float()[:, None]


def run(magnifier, video: torch.Tensor, chunk: int | None = None) -> torch.Tensor:
    chunk = chunk or video.shape[0]
    outs = [magnifier.push(video[i:i + chunk]) for i in range(0, video.shape[0], chunk)]
    return torch.cat(outs + [magnifier.flush()])


def measured_motion_px(out: torch.Tensor, ref: torch.Tensor, border_px: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Global shift of every output frame against the unmoved input, along and across DIRECTION."""
    luma = rgb_to_yiq(out)[:, 0] if out.shape[1] == 3 else out[:, 0]
    shifts = np.array([measure_shift_px(ref, f, border_px=border_px) for f in luma])
    along = shifts @ np.array(DIRECTION)
    across = shifts @ np.array([-DIRECTION[1], DIRECTION[0]])
    return along, across


def expected_motion_px(alpha: float, d_px: np.ndarray, kind: str | None = None, *,
                       attenuate_other: bool = False) -> np.ndarray:
    """The motion the convention promises: alpha * d in static mode; with a band-pass, the band part
    bp(d) scaled by alpha and the rest kept (or dropped). bp is the same streaming filter run on d, fed the
    last value after the end as the magnifier does, and realigned by its delay."""
    if kind is None:
        return alpha * d_px
    filt = make_filter(kind, FPS_HZ, *BAND_HZ)
    delay = filt.delay_frames
    padded = torch.tensor(np.concatenate([d_px, np.repeat(d_px[-1:], delay)]))[:, None]
    bp = filt(padded)[delay:, 0].numpy()
    return alpha * bp if attenuate_other else d_px + (alpha - 1) * bp


def gain(measured: np.ndarray, expected: np.ndarray) -> float:
    """Least-squares factor measured / expected over the whole clip."""
    return float(measured @ expected / (expected @ expected))
