"""Poles from the camera's raw frames: the matrix pencil against LSCE on a known decay, the pixel channels, and
the whole path on a simulated capture (hil_sim's modes as ground truth)."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.analysis.imagepoles import image_poles, normalised, pixel_channels, textured_pixels, textured_series
from odsplat.analysis.ods import stable_poles
from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture
from odsplat.hil_sim.structure import ModalStructure
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, SyncSettings, load_sync, sync_capture

F0 = np.array([23.5, 31.0, 86.0, 262.0])
Z0 = np.array([0.01, 0.008, 0.015, 0.02])


def _decay(noise: float, n: int = 390, fs: float = 2000.0, seed: int = 0):
    """Two channels of a free decay of F0/Z0 sampled at fs from 1.5 ms, with white noise (relative to the peak)."""
    t = 1.5e-3 + np.arange(n) / fs
    lam = -Z0 * 2 * np.pi * F0 + 1j * 2 * np.pi * F0 * np.sqrt(1 - Z0 ** 2)
    rng = np.random.default_rng(seed)
    amp = (rng.normal(size=(4, 2)) + 1j * rng.normal(size=(4, 2))) * np.array([1.5, 1.1, 0.5, 1.0])[:, None]
    x = 2 * np.real(np.exp(np.outer(t, lam)) @ amp)
    return t, x + rng.normal(0, noise * np.abs(x).max(), x.shape)


@pytest.mark.parametrize("noise", [0.01, 0.03])
def test_the_pencil_resolves_at_the_frame_rate_the_low_modes_that_lsce_merges(noise):
    t, y = _decay(noise)
    f, z = stable_poles(t, y, (16, 20, 24), 800.0)
    assert len(f) == 4, f
    assert np.all(np.abs(f - F0) / F0 < 0.002), f
    assert np.all(np.abs(z - Z0) / Z0 < 0.4), z          # 31 Hz: 6 periods in 200 ms
    # the baseline: LSCE at the frame rate finds 262 Hz alone (23.5 Hz is 85 samples a period there)
    f1, _ = stable_poles(t, y, (16, 20, 24), 800.0, method="lsce")
    assert not any(np.min(np.abs(f1 - f0)) < 0.005 * f0 for f0 in F0[:2]) if len(f1) else True


def test_pixel_channels_are_the_textured_pixels_scaled_by_their_noise():
    rng = np.random.default_rng(2)
    frame = np.zeros((40, 50), np.float32)
    frame[:, 25:] = 1.0                                                  # one vertical edge
    frames = frame[None] + rng.normal(0, 0.01, (60, 40, 50)).astype(np.float32)
    frames[:, :, 24:26] += 0.05 * np.sin(np.arange(60) / 5.0)[:, None, None]   # the edge's pixels flicker
    mask = textured_pixels(frames[0], 0.04)                              # the edge's 80 of 2000 pixels
    assert mask[:, 24:26].mean() > 0.9 and mask.mean() < 0.05
    times = (np.arange(60) - 5) / 2000.0
    y = pixel_channels(frames, times, t_min_s=0.0, fraction=0.04)
    assert y.shape == (55, int(mask.sum()))
    assert np.allclose(y.mean(axis=0), 0, atol=1e-4)
    # the flicker is 0.05 / 0.01 = 5 noise units at its peak
    assert 2.5 < np.median(np.std(y, axis=0)) < 5.0


@pytest.fixture(scope="module")
def long_takes(tmp_path_factory) -> Capture:
    """Three views of 400 frames (200 ms at 2000 fps), synced: long enough for 23.5 and 31 Hz."""
    out = tmp_path_factory.mktemp("imagepoles") / "cap"
    report = simulate_capture(out, n_views=3, n_frames=400, pretrigger_frames=6, record_s=0.5,
                              settings=SimBenchSettings(seed=3))
    assert report.complete
    cap = Capture.open(out)
    sync_capture(cap, SyncSettings(), progress=False)
    return cap


def test_image_poles_of_a_simulated_capture(long_takes):
    res = image_poles(long_takes, fmax_hz=900.0, progress=False)
    assert res is not None and res.n_views == 3 and res.n_pixels > 10_000
    assert res.window_s[0] == pytest.approx(1.5e-3, abs=5e-4) and res.window_s[1] > 0.19
    f_true = ModalStructure().freqs_hz
    # every pole found is one of the rig's, within 0.5 %; the hit moves the four strong modes
    for f in res.freq_hz:
        assert np.min(np.abs(f_true - f) / f_true) < 0.005, res.freq_hz
    found = [f0 for f0 in f_true if len(res.freq_hz) and np.min(np.abs(res.freq_hz - f0)) < 0.005 * f0]
    assert {23.5, 31.0, 86.0, 262.0} <= set(found), res.freq_hz


def test_a_take_read_in_chunks_gives_the_channels_of_the_take_read_whole(long_takes):
    """Issue 44: image poles read each aligned take CHUNK_FRAMES frames at a time and keep only the textured
    pixels (a seed-size take is 2.7 GB as float32): the same channels as the whole take read at once."""
    take = load_sync(long_takes).ok[0]
    with AlignedTake(long_takes, long_takes.paths.listed(take.aligned_file)) as f:
        times = f.times_s
        whole = pixel_channels(f.read_frames(), times, t_min_s=0.0, fraction=0.05)
        x = textured_series(f, 0.05, chunk_frames=64)                # 400 frames in 7 reads
    assert x.shape == (len(times), whole.shape[1])
    np.testing.assert_allclose(normalised(x, times, 0.0), whole, rtol=0, atol=1e-5)


def test_no_image_poles_without_synced_frames(tmp_path):
    out = tmp_path / "cap"
    simulate_capture(out, n_views=1, n_frames=40, pretrigger_frames=6, record_s=0.3)
    assert image_poles(Capture.open(out), fmax_hz=900.0, progress=False) is None      # not synced
