"""Poles from the camera alone, straight from the synced takes' raw frames: no magnification, no reconstruction.

For motion well below a pixel, a pixel's intensity change is linear in the displacement (dI = -grad I . u), so
every textured pixel of every view is a response channel of the same free decay. Each view's most textured
pixels, scaled by their own noise, are pooled over the takes on the impact-locked timeline; the pooled channels'
principal components (from their time-by-time Gram matrix, so memory does not grow with the pixel count) carry
the motion, and the matrix pencil on the components that stand above the noise, kept where stable over ranks,
gives the poles.

The pencil works at the frame rate. LSCE there resolves low modes poorly (23.5 Hz at 2000 fps is 85 samples a
period, its roots sit next to z = 1, and 23.5 and 31 Hz merge into one pole of 6 % damping), and needed the
band split into octaves, each fitted on components decimated to suit it; the pencil's truncated Hankel matrix
finds them at the full rate, within 0.1 % on the bench's 200 ms takes, and on a 70 ms window finds 31 and
142 Hz as well as 262 Hz, where the multi-rate LSCE found 262 Hz alone.

This uses every frame of the takes, so its frequency resolution follows the take's length, not the
reconstruction's window (which is a few tens of milliseconds on a CPU). It cannot say which pole moves what:
the shapes come from the reconstruction (`ods.py`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, load_sync

from .ods import default_ranks, stable_poles

MIN_SNR = 10.0   # a principal component is used when its power is this many times the noise floor's
CHUNK_FRAMES = 64  # frames read at a time

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImagePoles:
    """Poles of the pooled image intensities of the synced takes."""

    freq_hz: np.ndarray           # (R,) stable over orders, in the band
    damping: np.ndarray           # (R,)
    n_views: int
    n_pixels: int                 # channels pooled over the views
    times_s: np.ndarray           # (T',) the samples used, on the impact-locked timeline
    snr: np.ndarray               # (n_components,) each principal component's power over the noise floor's
    components: np.ndarray        # (T', C) the strong components' time histories, as fitted

    @property
    def window_s(self) -> tuple[float, float]:
        return float(self.times_s[0]), float(self.times_s[-1])


def textured_pixels(frame: np.ndarray, fraction: float) -> np.ndarray:
    """Boolean mask of the `fraction` of pixels with the strongest intensity gradient in a (H, W) frame."""
    gy, gx = np.gradient(np.asarray(frame, np.float32))
    g = np.hypot(gx, gy)
    return g >= np.quantile(g, 1.0 - fraction)


def pixel_channels(frames: np.ndarray, times_s: np.ndarray, *, t_min_s: float, fraction: float) -> np.ndarray:
    """(T', P) the textured pixels' intensities at times_s >= t_min_s, each less its mean and divided by its own
    noise (the rms of first differences over the whole take, over sqrt 2: nearly all noise at a high frame
    rate)."""
    frames = _gray(np.asarray(frames, np.float32))
    return normalised(frames[:, textured_pixels(frames[0], fraction)], times_s, t_min_s)


def normalised(x: np.ndarray, times_s: np.ndarray, t_min_s: float) -> np.ndarray:
    """pixel_channels' channels from the pixels' intensities x (T, P)."""
    noise = np.std(np.diff(x, axis=0), axis=0) / np.sqrt(2.0)
    use = np.asarray(times_s) >= t_min_s
    y = x[use] - x[use].mean(axis=0)
    return y / np.maximum(noise, 1e-6 * max(float(noise.max()), 1e-30))


def _gray(frames: np.ndarray) -> np.ndarray:
    return frames.mean(axis=-1) if frames.ndim == 4 else frames


def textured_series(f, fraction: float, chunk_frames: int = CHUNK_FRAMES) -> np.ndarray:
    """(T, P) float32: the intensities over the whole take of the textured pixels of its first frame
    (pixel_channels' pixels), read CHUNK_FRAMES frames at a time, the pixels chosen before sync's time filter:
    memory and work in the pixels kept, not in the frames (a seed-size take, 640 frames of 1024^2, is 2.7 GB as
    float32)."""
    mask = textured_pixels(_gray(np.asarray(f.read_frames(0, 1), np.float32))[0], fraction)

    def kept(frame: np.ndarray) -> np.ndarray:
        return (frame.mean(axis=-1) if frame.ndim == 3 else frame)[mask]

    return np.concatenate([np.asarray(f.read_frames(a, a + chunk_frames, kept), np.float32)
                           for a in range(0, f.n_frames, chunk_frames)])


def image_poles(capture: Capture, *, fmax_hz: float, ranks: tuple[int, ...] | None = None,
                t_min_s: float = 1.5e-3, pixel_fraction: float = 0.05,
                n_components: int = 16, progress: bool = True) -> ImagePoles | None:
    """Poles from every synced take's aligned frames (`derived/sync/*.h5`); None when there are none. ranks None:
    the pencil's default for the frames after t_min_s (`default_ranks`)."""
    from tqdm import tqdm


    if not capture.paths.sync_json.exists():   # one that is there must read: load_sync refuses a bad one
        log.info("no image poles: %s not found", capture.paths.sync_json)
        return None
    sync = load_sync(capture)
    takes = [tk for tk in sync.ok if tk.aligned_file and capture.paths.listed(tk.aligned_file).is_file()]
    if not takes:
        log.info("no image poles: no synced take has aligned frames")
        return None
    gram, times, n_pix = None, None, 0
    for tk in tqdm(takes, desc="analysis: image poles", unit="take", disable=not progress):
        path = capture.paths.listed(tk.aligned_file)
        with AlignedTake(capture, path, sync.generation) as f:
            x, t = textured_series(f, pixel_fraction), f.times_s
        if times is None:
            times = t
        elif len(t) != len(times) or np.max(np.abs(t - times)) > 1e-9:
            raise InputError(f"{path}: times_s", "expected the capture's common sync grid, as the first take's")
        y = normalised(x, t, t_min_s).astype(np.float64)
        gram = y @ y.T if gram is None else gram + y @ y.T
        n_pix += y.shape[1]
    tt = times[times >= t_min_s]
    ranks = ranks or default_ranks(len(tt))
    if not ranks or len(tt) < 2 * max(ranks) + 2:  # the pencil's Hankel matrix needs rank + 1 rows
        log.warning("no image poles: %d frames after %.1f ms", len(tt), 1e3 * t_min_s)
        return None
    w, v = np.linalg.eigh(gram)
    w, v = np.maximum(w[::-1], 0.0), v[:, ::-1]
    k = min(n_components, len(w))
    floor = float(np.median(w[k:])) if len(w) > k else float(w[-1])
    snr = w[:k] / max(floor, 1e-300)
    strong = max(int(np.sum(snr >= MIN_SNR)), 1)
    y = v[:, :strong] * np.sqrt(w[:strong])                        # the strong components' time histories
    f_hz, zeta = stable_poles(tt, y, ranks, fmax_hz)
    log.info("image poles (%d views, %d px): %s Hz", len(takes), n_pix, ", ".join(f"{f:.2f}" for f in f_hz))
    return ImagePoles(f_hz, zeta, len(takes), n_pix, tt, snr, y)


__all__ = ["ImagePoles", "image_poles", "normalised", "pixel_channels", "textured_pixels", "textured_series"]
