"""Linear Eulerian magnification against ground truth, with the same gain convention as the phase method."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from odsplat.processing.base import rgb_to_yiq
from odsplat.processing.eulerian import LinearMagnifier, collapse, laplacian_pyramid, level_gains, max_levels
from odsplat.processing.filters import make_filter
from odsplat.spine.errors import InputError

from .motion import (
    BAND_HZ,
    FPS_HZ,
    displacement_px,
    expected_motion_px,
    gain,
    measured_motion_px,
    run,
    texture,
    translating_video,
)

BORDER_PX = 8  # the Laplacian pyramid mirrors at the borders; the test texture is periodic


@pytest.mark.parametrize("h,w", [(64, 64), (67, 90), (31, 17)])
def test_laplacian_pyramid_collapses_exactly(h, w):
    x = torch.rand(2, h, w)
    levels = max_levels(h, w)
    pyr = laplacian_pyramid(x, levels)
    assert len(pyr) == levels + 1 and min(pyr[-1].shape[-2:]) >= 4
    assert float((collapse(pyr) - x).abs().max()) < 1e-5


def test_level_gains_follow_the_wavelength_cutoff():
    # Levels hold ~2**(k+2)..2**(k+3) px; centres 5.7, 11.3, 22.6, 45, 91 px against a 16 px cut-off.
    assert np.allclose(level_gains(10.0, 4, 16.0), [10 * 2 ** 2.5 / 16 - 1, 10 * 2 ** 3.5 / 16 - 1, 9, 9, 9])
    assert level_gains(1.5, 2, 1000.0) == [0.0, 0.0, 0.0]  # never below the input motion
    assert level_gains(0.5, 2, 16.0) == [-0.5, -0.5, -0.5]  # attenuation is applied everywhere


@pytest.mark.parametrize("kind,n_frames", [(None, 30), ("butter", 45), ("fir", 60)])
def test_gain_is_alpha_within_15_percent(tex, kind, n_frames):
    d = displacement_px(n_frames)
    video = translating_video(tex, d)
    temporal = make_filter(kind, FPS_HZ, *BAND_HZ) if kind else None
    out = run(LinearMagnifier(10.0, temporal), video)
    assert out.shape == video.shape
    along, across = measured_motion_px(out, video[0, 0], BORDER_PX)
    expected = expected_motion_px(10.0, d, kind)
    g = gain(along, expected)
    assert abs(g - 1) < 0.15, g  # measured 0.89: the 16 px cut-off trims the texture's finer part
    resid = np.sqrt(np.mean((along - g * expected) ** 2)) / np.sqrt(np.mean(expected ** 2))
    assert resid < 0.05, resid
    assert np.sqrt(np.mean(across ** 2)) < 0.02 * np.abs(expected).max()


@pytest.mark.parametrize("alpha", [2.0, 10.0])
def test_cutoff_at_the_motion_bound_gives_full_gain(tex, alpha):
    # Wu et al.'s bound alpha * d < lambda / 8 allows every wavelength above 8 * alpha * 0.05 <= 4 px here.
    # At alpha = 2, a gain of 1 +- 5 % also tells alpha from alpha + 1 (which would read 1.5).
    d = displacement_px(30)
    video = translating_video(tex, d)
    out = run(LinearMagnifier(alpha, cutoff_wavelength_px=4.0), video)
    along, _ = measured_motion_px(out, video[0, 0], BORDER_PX)
    g = gain(along, alpha * d)
    assert abs(g - 1) < 0.05, g


def test_cutoff_keeps_fine_texture_from_blowing_up():
    fine = translating_video(texture(64, 3.0, 6.0, seed=5), displacement_px(10))
    change = {}
    for cutoff in (16.0, 1e-3):
        out = run(LinearMagnifier(50.0, cutoff_wavelength_px=cutoff), fine)
        change[cutoff] = float((out - fine).abs().max())
    # Unattenuated, 50x the intensity change of a 3-6 px texture moving 0.05 px saturates; cut off, the
    # finest levels get at most 50 * 5.7 / 16 = 18x.
    assert change[16.0] < 0.45 * change[1e-3], change


def test_rgb_moves_like_mono_and_carries_chroma(tex):
    d = displacement_px(20)
    mono = translating_video(tex, d)
    rgb = (mono * torch.tensor([0.9, 0.7, 0.5])[None, :, None, None] + 0.1).clamp(0, 1)
    luma = rgb_to_yiq(rgb)[:, :1]
    out_rgb = run(LinearMagnifier(10.0), rgb)
    out_y = run(LinearMagnifier(10.0), luma)
    assert out_rgb.shape == rgb.shape
    along_rgb, _ = measured_motion_px(out_rgb, luma[0, 0], BORDER_PX)
    along_y, _ = measured_motion_px(out_y, luma[0, 0], BORDER_PX)
    assert np.abs(along_rgb - along_y).max() < 1e-3
    assert float((rgb_to_yiq(out_rgb)[:, 1:] - rgb_to_yiq(rgb)[:, 1:]).abs().max()) < 1e-4


def test_8_bit_quantised_input(tex):
    d = displacement_px(30)
    video = torch.round(translating_video(tex, d) * 255) / 255
    along, _ = measured_motion_px(run(LinearMagnifier(10.0), video), tex.float(), BORDER_PX)
    assert abs(gain(along, 10 * d) - 1) < 0.15


@pytest.mark.parametrize("kind", [None, "fir", "butter"])
def test_streaming_chunks_give_identical_frames_in_bounded_state(kind):
    video = translating_video(texture(64, 10, 20, seed=3), displacement_px(24))
    outs = {}
    for chunk in (1, 7, 24):
        m = LinearMagnifier(20.0, make_filter(kind, FPS_HZ, 5.0, 10.0) if kind else None)
        got = []
        for i in range(0, 24, chunk):
            got.append(m.push(video[i:i + chunk]))
            pushed = min(i + chunk, 24)
            assert sum(len(g) for g in got) == max(0, pushed - m.delay_frames)
            assert m.held_frames == min(pushed, m.delay_frames)
        got.append(m.flush())
        outs[chunk] = torch.cat(got)
        assert outs[chunk].shape == video.shape
    assert float((outs[1] - outs[24]).abs().max()) < 1e-5
    assert float((outs[7] - outs[24]).abs().max()) < 1e-5
    assert float((outs[24] - video).abs().max()) > 1e-3


def test_input_errors():
    for alpha in (0.0, -1.0):
        with pytest.raises(InputError, match=r"alpha: expected a finite number > 0"):
            LinearMagnifier(alpha)
    m = LinearMagnifier(5.0)
    m.push(torch.rand(2, 3, 32, 32))
    with pytest.raises(InputError, match="mixed shape"):
        m.push(torch.rand(2, 1, 32, 32))
    m = LinearMagnifier(5.0, make_filter("fir", FPS_HZ, *BAND_HZ))
    m.push(torch.rand(10, 1, 32, 32))
    with pytest.raises(InputError, match=r"fir temporal filter: needs at least 45 frames, got 10"):
        m.flush()
    with pytest.raises(InputError, match="cutoff"):
        LinearMagnifier(5.0, cutoff_wavelength_px=0.0)
