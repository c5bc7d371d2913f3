"""Where a take moves: the region magnify works in (`magnify.roi = "auto"`).

One pass over the take's frames: each pixel's mean square change from rest after the impact, and its noise (half
the mean square frame-to-frame difference before it), both summed over blocks of BIN_PX x BIN_PX pixels (squares,
so fine texture does not average out; 64 pixels make the noise's estimate good to about 5 %). The region is the box
of the blocks whose rms change passes MIN_RATIO times their noise, widened by a margin (the magnifier's filters
reach past what moves, and the box's edges are image edges to them). Outside it nothing moves above the noise, and
the magnified take keeps the input frames there.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from .base import luma

BIN_PX = 8           # the detection's pixel: 8 x 8 frame pixels
MIN_RATIO = 1.5      # a binned pixel's rms change after the impact over its noise (noise alone: 1 +- 1/sqrt(2T))
MARGIN_SHARE = 1 / 16  # the margin: this share of the frame's larger side, at least MIN_MARGIN_PX
MIN_MARGIN_PX = 32


@dataclass(frozen=True)
class Box:
    """Rows y0..y1-1 and columns x0..x1-1 of a frame."""

    y0: int
    y1: int
    x0: int
    x1: int

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    def share(self, frame_shape: tuple[int, ...]) -> float:
        return (self.y1 - self.y0) * (self.x1 - self.x0) / float(frame_shape[0] * frame_shape[1])

    def as_list(self) -> list[int]:
        return [self.y0, self.y1, self.x0, self.x1]


def _block_sum(image: np.ndarray, h: int, w: int) -> np.ndarray:
    """Sums over BIN_PX x BIN_PX blocks (the last partial ones dropped)."""
    return image[:h * BIN_PX, :w * BIN_PX].reshape(h, BIN_PX, w, BIN_PX).sum(axis=(1, 3))


def motion_box(chunks: Iterable[np.ndarray], times_s: np.ndarray, frame_shape: tuple[int, ...]) -> Box | None:
    """The box of the frames where the take moves above its noise, with its margin; None where nothing does (or
    the take has too few frames before or after the impact to tell), and the whole frame is to be used."""
    h, w = int(frame_shape[0]), int(frame_shape[1])
    bh, bw = h // BIN_PX, w // BIN_PX
    times_s = np.asarray(times_s, float)
    n_before = int(np.sum(times_s < 0))
    if n_before < 3 or len(times_s) - n_before < 2 or bh < 1 or bw < 1:
        return None
    total, diff2, change2, prev, rest, k = np.zeros((h, w)), np.zeros((h, w)), np.zeros((h, w)), None, None, 0
    for block in chunks:
        for frame in np.asarray(luma(block), np.float64):
            if k < n_before:
                total += frame
                if prev is not None:
                    diff2 += (frame - prev) ** 2
                prev = frame
            else:
                rest = total / n_before if rest is None else rest
                change2 += (frame - rest) ** 2
            k += 1
    noise2 = _block_sum(diff2, bh, bw) / (2 * (n_before - 1))
    moved2 = _block_sum(change2, bh, bw) / max(k - n_before, 1)
    ratio = np.sqrt(moved2 / np.maximum(noise2, 1e-12 + 1e-6 * float(np.median(noise2))))
    rows, cols = np.nonzero(ratio > MIN_RATIO)
    if not len(rows):
        return None
    margin = max(MIN_MARGIN_PX, int(round(MARGIN_SHARE * max(h, w))))
    return Box(max(0, int(rows.min()) * BIN_PX - margin), min(h, (int(rows.max()) + 1) * BIN_PX + margin),
               max(0, int(cols.min()) * BIN_PX - margin), min(w, (int(cols.max()) + 1) * BIN_PX + margin))


__all__ = ["Box", "motion_box"]
