"""Sync's fractional delay (issue 44: aligned takes are computed from the raw take as they are read)."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.sync.aligned import delay_taps, mirror


def _delay(x: np.ndarray, frac: float) -> np.ndarray:
    k, h = delay_taps(frac)
    return np.array([np.dot(h, x[mirror(n + k, len(x))]) for n in range(len(x))])


@pytest.mark.parametrize("f_cycles", [0.02, 0.15, 0.3, 0.42])
@pytest.mark.parametrize("frac", [0.13, 0.5, 0.91])
def test_a_decaying_sinusoid_is_delayed_within_2e_4_up_to_0_42_of_the_frame_rate(f_cycles, frac):
    n = np.arange(400)

    def signal(t):
        return np.exp(-t / 250) * np.sin(2 * np.pi * f_cycles * t + 0.4)

    y = _delay(signal(n.astype(float)), frac)
    inner = slice(40, -40)   # the ends are mirrored: a decaying record is not symmetric there
    assert np.max(np.abs(y - signal(n + frac))[inner]) < 2e-4


def test_no_delay_is_the_identity_and_the_weights_sum_to_one():
    k, h = delay_taps(0.0)
    assert list(k) == [0] and list(h) == [1.0]
    for frac in (0.01, 0.5, 0.99):
        k, h = delay_taps(frac)
        assert len(k) == 32 and h.sum() == pytest.approx(1.0, abs=1e-12)
        assert k[np.argmax(h)] == round(frac)            # the largest weight on the nearest sample


def test_the_ends_are_mirrored_with_the_end_sample_repeated():
    assert list(mirror(np.arange(-3, 8), 5)) == [2, 1, 0, 0, 1, 2, 3, 4, 4, 3, 2]
