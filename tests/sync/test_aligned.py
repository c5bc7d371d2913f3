"""Sync's fractional delay (issue 44: aligned takes are computed from the raw take as they are read)."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.spine.manifest import Manifest
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake
from odsplat.sync.aligned import delay_taps, mirror, write_aligned


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


def test_dropped_frames_are_filled_linearly_from_their_neighbours_in_time(tmp_path):
    """A take that lost frames 3-4 and 7 (the camera's counter skipped them): the aligned take fills each from the
    stored frames either side of it, weighted by its distance in time; a stored frame is itself."""
    cap = Capture.create(tmp_path / "cap", Manifest(name="drops"))
    source = np.array([0, 1, 2, -1, -1, 3, 4, -1, 5, 6])
    values = np.array([10.0, 20.0, 40.0, 70.0, 100.0, 130.0, 160.0])      # stored frames 0..6, one grey level each
    stored = np.broadcast_to(values[:, None, None], (7, 4, 5)).astype(np.uint16)
    with cap.new_take("v00_000", view=0, frame_shape=(4, 5), bit_depth=12, fps=1000.0, channels=()) as take:
        take.append_frames(stored, times_s=np.arange(7) / 1000.0)
        take.finalize()
    times = (np.arange(len(source)) - 2) / 1000.0
    write_aligned(cap.derived_dir / "sync" / "v00_000.h5", take="v00_000", times_s=times, source_frame=source,
                  grid_shift_frames=0.0, bit_depth=12, rest_dn=None, attrs={}, capture_id=cap.id)
    with AlignedTake(cap, cap.paths.aligned("v00_000")) as at:
        got = at.read_frames()
        np.testing.assert_allclose(at.times_s, times)
    expected = [10, 20, 40, 40 + 30 / 3, 40 + 60 / 3, 70, 100, 115, 130, 160]
    assert got.shape == (10, 4, 5)
    np.testing.assert_allclose(got[:, 2, 3], expected, atol=1e-4)
    np.testing.assert_allclose(got, np.broadcast_to(got[:, :1, :1], got.shape))
