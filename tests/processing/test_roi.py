"""Where a take moves (processing/roi.py): a textured patch moving by a tenth of a pixel in a noisy frame is found,
with the margin around it; a still take has no region (the whole frame is used)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import shift

from odsplat.processing.roi import BIN_PX, MIN_MARGIN_PX, motion_box

H, W, N_BEFORE, N_AFTER = 240, 320, 12, 60


def _take(rng, amplitude_px: float, noise_dn: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A still textured scene with a 40 x 32 px patch at rows 100-140, columns 200-232 moving sideways."""
    scene = rng.uniform(100, 3000, (H, W))
    times = (np.arange(N_BEFORE + N_AFTER) - N_BEFORE) / 1000.0
    frames = []
    for t in times:
        f = scene.copy()
        if t > 0:
            moved = shift(scene, (0, amplitude_px * np.sin(2 * np.pi * 40 * t)), order=3, mode="nearest")
            f[100:140, 200:232] = moved[100:140, 200:232]
        frames.append(f + rng.normal(0, noise_dn, (H, W)))
    return np.asarray(frames, np.float32), times


def test_a_sub_pixel_motion_is_found_with_its_margin():
    frames, times = _take(np.random.default_rng(0), 0.1)
    box = motion_box([frames[:30], frames[30:]], times, frames.shape[1:])       # read in two chunks
    assert box is not None
    assert box.y0 <= 100 - MIN_MARGIN_PX + BIN_PX and box.y1 >= 140 + MIN_MARGIN_PX - BIN_PX
    assert box.x0 <= 200 - MIN_MARGIN_PX + BIN_PX and box.x1 >= 232 + MIN_MARGIN_PX - BIN_PX
    assert box.share(frames.shape[1:]) < 0.2                                      # not the whole frame
    np.testing.assert_array_equal(frames[(slice(None), *box.slices)].shape[1:], (box.y1 - box.y0, box.x1 - box.x0))


@pytest.mark.parametrize("seed", range(3))
def test_a_still_take_has_no_region(seed):
    frames, times = _take(np.random.default_rng(seed), 0.0)
    assert motion_box([frames], times, frames.shape[1:]) is None


def test_too_few_frames_before_the_impact_to_tell():
    frames, times = _take(np.random.default_rng(0), 0.1)
    assert motion_box([frames[N_BEFORE - 2:]], times[N_BEFORE - 2:], frames.shape[1:]) is None
