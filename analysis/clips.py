"""Amplified clips, the way engineers use them: one mode's band magnified, beside the recorded frames, over the
displacement spectrum with the band marked, written as a browser-playable H.264 mp4 (`odsplat.spine.mp4`).

The magnification is the phase-based method (`odsplat.processing`) with its warp synthesis (the frames resampled
by the magnified motion: no bound on alpha x motion, docs/processing.md), a Butterworth band of +-10 % around the
mode, over the box around the points that move (plus a margin). Its factor makes the mode's rms motion at its
largest point about TARGET_PX pixels."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from odsplat.processing import MagnifySettings, make_magnifier
from odsplat.spine.mp4 import Mp4Info, Mp4Writer, display_range, to_8bit

log = logging.getLogger(__name__)

TARGET_PX = 3.0          # the magnified mode's rms motion at its largest point
MAX_ALPHA = 2000.0
BAND = 0.10              # the band: f (1 -+ BAND)
MARGIN_PX = 24
MIN_HEIGHT_PX = 240      # panels smaller than this are enlarged (nearest neighbour: pixels stay pixels)
PLAYBACK_FPS = 30.0


@dataclass(frozen=True)
class ClipSpec:
    """What one clip shows: the mode's frequency, the magnification, the box (y0, y1, x0, x1) and its title."""

    freq_hz: float
    alpha: float
    box: tuple[int, int, int, int]
    title: str


def band_hz(freq_hz: float, fps: float) -> tuple[float, float]:
    """A mode's band, f (1 -+ BAND), its top kept under 0.49 x the frame rate (Nyquist, with the filter's margin):
    what a clip magnifies and what a mode's amplitude is read over."""
    return freq_hz * (1 - BAND), min(freq_hz * (1 + BAND), 0.49 * fps)


def clip_box(points_px: np.ndarray, shape: tuple[int, int], margin_px: int = MARGIN_PX) -> tuple[int, int, int, int]:
    """The box around the points, plus a margin, within the frame; even sides (H.264)."""
    h, w = shape
    x0, y0 = np.floor(points_px.min(axis=0)).astype(int) - margin_px
    x1, y1 = np.ceil(points_px.max(axis=0)).astype(int) + margin_px + 1
    y0, y1, x0, x1 = max(0, y0), min(h, y1), max(0, x0), min(w, x1)
    y1 -= (y1 - y0) % 2
    x1 -= (x1 - x0) % 2
    return int(y0), int(y1), int(x0), int(x1)


def clip_alpha(amplitude_px: float) -> float:
    """The factor that makes a mode of this rms motion about TARGET_PX pixels, 1 to MAX_ALPHA."""
    if not np.isfinite(amplitude_px) or amplitude_px <= 0:
        return MAX_ALPHA
    return float(np.clip(TARGET_PX / amplitude_px, 1.0, MAX_ALPHA))


def spectrum_strip(freq_hz: np.ndarray, level: np.ndarray, f0_hz: float, width_px: int, height_px: int = 150,
                   ylabel: str = "displacement PSD (px²/Hz)") -> np.ndarray:
    """The spectrum (log) as an RGB image (height_px, width_px, 3), the band around f0_hz shaded."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    dpi = 100
    fig = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.1, 0.3, 0.88, 0.62))
    y = np.maximum(np.asarray(level, float), 1e-30)
    ax.semilogy(freq_hz, y, color="0.2", lw=0.8)
    ax.axvspan(f0_hz * (1 - BAND), f0_hz * (1 + BAND), color="C1", alpha=0.35, lw=0)
    ax.axvline(f0_hz, color="C1", lw=1.0)
    ax.set_xlim(float(freq_hz[0]), float(freq_hz[-1]))
    ax.set_xlabel("frequency (Hz)", fontsize=8)
    ax.set_ylabel(ylabel, fontsize=7)
    ax.tick_params(labelsize=7)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    return np.ascontiguousarray(cv2.resize(rgb, (width_px, height_px), interpolation=cv2.INTER_AREA))


def _panel(frame8: np.ndarray, scale: int) -> np.ndarray:
    p = np.repeat(np.repeat(frame8, scale, axis=0), scale, axis=1) if scale > 1 else frame8
    return np.stack([p] * 3, axis=-1) if p.ndim == 2 else p


def _title(width: int, text: str) -> np.ndarray:
    bar = np.full((28, width, 3), 255, np.uint8)
    cv2.putText(bar, text, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return bar


def write_clip(path: Path, frames, fps: float, spec: ClipSpec, spectrum: tuple[np.ndarray, np.ndarray],
               comment: str = "") -> Mp4Info:
    """One clip: `frames` (an iterable of mono float frames (H, W), at most the clip's length) magnified in the
    box at spec.alpha over f (1 -+ BAND), the recorded box on the left, the magnified on the right, the title above
    and the spectrum below, at PLAYBACK_FPS."""
    y0, y1, x0, x1 = spec.box
    mag = make_magnifier(MagnifySettings(method="phase", alpha=spec.alpha, band_hz=band_hz(spec.freq_hz, fps),
                                         roi="none", video=False, options=(("warp", True),)), fps)
    h = y1 - y0
    scale = max(1, int(np.ceil(MIN_HEIGHT_PX / max(h, 1))))
    strip = None
    held: list[np.ndarray] = []
    dn_range = None
    writer = Mp4Writer(path, PLAYBACK_FPS, comment)

    def emit(y: torch.Tensor) -> None:
        nonlocal strip
        for out in y[:, 0].numpy():
            rec = held.pop(0)
            left = _panel(to_8bit(rec[None], dn_range)[0], scale)
            right = _panel(to_8bit((out * full)[None], dn_range)[0], scale)
            top = np.concatenate([left, np.full((left.shape[0], 4, 3), 255, np.uint8), right], axis=1)
            if strip is None:
                strip = spectrum_strip(*spectrum, spec.freq_hz, top.shape[1])
            writer.write(np.concatenate([_title(top.shape[1], spec.title), top, strip], axis=0))

    full = None
    try:
        block: list[np.ndarray] = []
        for frame in frames:
            box = np.asarray(frame, np.float32)[y0:y1, x0:x1]
            if full is None:
                full = max(float(box.max()), 1.0) * 1.25
                dn_range = display_range(box[None])
            held.append(box)
            block.append(box)
            if len(block) == 16:
                emit(mag.push(torch.from_numpy(np.stack(block) / full)[:, None]))
                block = []
        if block:
            emit(mag.push(torch.from_numpy(np.stack(block) / full)[:, None]))
        emit(mag.flush())
    except BaseException:
        writer.abort()
        raise
    return writer.close()


__all__ = ["BAND", "ClipSpec", "band_hz", "clip_alpha", "clip_box", "spectrum_strip", "write_clip"]
