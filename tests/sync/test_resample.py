"""Fractional delay by phase shift, and filling dropped frames."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.sync.resample import fill_dropped, fractional_shift


def _decay(t):
    return np.exp(-t / 60.0) * np.sin(2 * np.pi * t / 17.0) + 0.3 * np.cos(2 * np.pi * t / 41.0)


@pytest.mark.parametrize("shift", [0.3, -0.45, 0.9, -1.0])
def test_fractional_shift_of_a_smooth_record(shift):
    n = np.arange(120.0)
    y = fractional_shift(_decay(n), shift)
    err = y - _decay(n + shift)
    # Inside the record the shift is exact to a few thousandths; beyond its ends the mirror is only a guess,
    # which is why sync's common grid never reaches past any take's first or last frame.
    assert np.abs(err[4:-4]).max() < 0.002
    assert np.abs(err[12:-12]).max() < 0.0005


def test_fractional_shift_along_an_axis_of_frames():
    n = np.arange(64.0)
    frames = _decay(n)[:, None, None] * np.array([[1.0, 2.0], [3.0, -1.0]])
    y = fractional_shift(frames, 0.25, axis=0)
    assert y.shape == frames.shape
    np.testing.assert_allclose(y[8:-8], _decay(n + 0.25)[8:-8, None, None] * frames[1] / _decay(n)[1], atol=0.01)
    np.testing.assert_array_equal(fractional_shift(frames, 0.0), frames)


def test_fill_dropped_gives_the_regular_counter_run():
    """Where each stored frame sits in the run its counters cover (the aligned take fills the gaps:
    tests/sync/test_aligned.py)."""
    counters = np.array([-2, -1, 0, 3, 4])
    full, pos = fill_dropped(counters)
    np.testing.assert_array_equal(full, np.arange(-2, 5))
    np.testing.assert_array_equal(full[pos], counters)
