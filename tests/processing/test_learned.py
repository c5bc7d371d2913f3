"""The learned magnifier (Oh et al. 2018): network, manipulator, synthetic data, trainer, shipped weights,
streaming."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from odsplat.processing.filters import make_filter
from odsplat.processing.learned.magnifier import DEFAULT_WEIGHTS, LearnedMagnifier
from odsplat.processing.learned.network import MagNet, from_net, load_magnet, to_net
from odsplat.processing.learned.synth import PATTERNS, SynthConfig, camera_noise, make_batch, make_sample, pattern
from odsplat.processing.learned.train import TrainConfig, log_path, losses, train
from odsplat.processing.metrics import estimate_translation, psnr, ssim
from odsplat.spine.errors import InputError

# One textured plane moving rigidly, no noise: the displacement is known exactly.
PLANE = SynthConfig(size=64, objects=(0, 0), p_background_moves=1.0, p_noise=0.0, p_gray=0.0,
                    alpha_range=(10.0, 10.0), min_magnified_px=2.0, max_magnified_px=4.0)


def test_the_papers_size():
    """Oh et al.'s network: about 0.9 M parameters (a 32-channel trunk, 9 decoder blocks); ours is 0.11 M."""
    count = lambda net: sum(p.numel() for p in net.parameters())  # noqa: E731
    assert 0.8e6 < count(MagNet.of_size("paper")) < 1.0e6 and count(MagNet.of_size("small")) < 0.12e6
    assert TrainConfig(size="paper").dec_blocks == 9
    with pytest.raises(InputError, match="size"):
        MagNet.of_size("huge")
    with pytest.raises(InputError, match="device"):
        train(TrainConfig(out=Path("unused.pt"), device="nonsense", progress=False))


def test_network_shapes_and_size():
    net = MagNet(16)
    x = torch.rand(2, 3, 64, 48) * 2 - 1
    texture, shape = net.encode(x)
    assert texture.shape == (2, 16, 16, 12)
    assert shape.shape == (2, 16, 32, 24)
    assert net.decode(texture, shape).shape == (2, 3, 64, 48)
    assert net(x, x, 5.0).shape == (2, 3, 64, 48)
    assert 50_000 < sum(p.numel() for p in net.parameters()) < 500_000
    assert DEFAULT_WEIGHTS.stat().st_size < 5 * 2 ** 20


def test_colour_helpers():
    mono = torch.rand(2, 1, 8, 8)
    x = to_net(mono)
    assert x.shape == (2, 3, 8, 8) and x.min() >= -1 and x.max() <= 1
    assert torch.allclose(from_net(x, 1), mono, atol=1e-6)
    rgb = torch.rand(1, 3, 4, 4)
    assert torch.allclose(from_net(to_net(rgb), 3), rgb, atol=1e-6)


def test_manipulator_equation():
    torch.manual_seed(0)
    man = MagNet(16).manipulator
    m_a, m_b = torch.randn(2, 16, 8, 8), torch.randn(2, 16, 8, 8)
    for alpha in (1.0, 7.0):
        assert torch.equal(man(m_a, m_a, alpha), m_a)  # no motion, no change
    assert torch.equal(man(m_a, m_b, 0.0), m_a)
    # The amplified term fed to h is alpha * g(M_b - M_a): linear in alpha, per batch item.
    seen = []
    hook = man.h_conv.register_forward_hook(lambda mod, inp, out: seen.append(inp[0].detach()))
    man(m_a, m_b, 1.0)
    man(m_a, m_b, torch.tensor([3.0, 0.5]))
    hook.remove()
    g = man.g_term(m_a, m_b)
    assert torch.allclose(seen[0], g)
    assert torch.allclose(seen[1][0], 3.0 * g[0]) and torch.allclose(seen[1][1], 0.5 * g[1])
    # And G_m is M_a plus h of that term.
    expected = m_a + man.h_res(man.h_conv(4.0 * g))
    assert torch.allclose(man(m_a, m_b, 4.0), expected)


def test_synthetic_ground_truth_is_the_motion_times_alpha():
    for i in range(3):
        s = make_sample(i, PLANE)
        dx, dy = s.background_displacement
        bx, by = estimate_translation(s.frame_a, s.frame_b)
        tx, ty = estimate_translation(s.frame_a, s.target)
        assert math.hypot(bx - dx, by - dy) < 0.03
        assert math.hypot(tx - s.alpha * dx, ty - s.alpha * dy) < 0.05 * math.hypot(s.alpha * dx, s.alpha * dy)
        assert s.alpha == pytest.approx(10.0)


def test_synthetic_samples_deterministic_and_varied():
    a, b = make_sample((4, 2)), make_sample((4, 2))
    assert torch.equal(a.frame_b, b.frame_b) and torch.equal(a.target, b.target) and a.alpha == b.alpha
    c = make_sample((4, 3))
    assert not torch.equal(a.frame_a, c.frame_a)
    batch = make_batch(1, 0, 3, SynthConfig(size=32))
    assert batch["frame_a"].shape == (3, 3, 32, 32) and batch["alpha"].shape == (3,)
    for k in ("frame_a", "frame_b", "target", "frame_b_c", "target_c"):
        assert 0 <= float(batch[k].min()) and float(batch[k].max()) <= 1
    # Noise goes on the inputs only: the clean target of a static scene is frame a without noise.
    noisy = make_sample(0, SynthConfig(objects=(0, 0), p_background_moves=0.0, p_noise=1.0, noise="gauss",
                                       gauss_sigma=(0.04, 0.04)))
    assert psnr(noisy.frame_a, noisy.target) < 35
    camera = make_sample(0, SynthConfig(objects=(0, 0), p_background_moves=0.0, p_noise=1.0))
    assert psnr(camera.frame_a, camera.target) < 60 and torch.equal(camera.target, noisy.target)


def test_camera_noise_is_shot_read_and_quantisation():
    """A flat grey at half scale through a 10 000 e- well with 10 e- read noise: the sd of sqrt(5000 + 100)
    electrons; at 8 bits every value is a multiple of 1/255 (1.8 LSB sd), at 12 bits the same sd comes through."""
    rng = np.random.default_rng(0)
    flat = np.full((200, 200), 0.5)
    twelve = camera_noise(rng, flat, 10_000.0, 10.0, 12)
    assert float(twelve.std()) == pytest.approx(math.sqrt(5100) / 10_000, rel=0.05)
    assert float(twelve.mean()) == pytest.approx(0.5, abs=1e-3)
    eight = camera_noise(rng, flat, 10_000.0, 10.0, 8)
    assert np.allclose(eight * 255, np.round(eight * 255)) and len(np.unique(eight)) <= 20   # +-5 sd of 1.8 LSB
    assert float(camera_noise(rng, np.ones((50, 50)), 1000.0, 5.0, 10).max()) == 1.0   # clipped at full scale


def test_synthetic_textures_include_a_tests_surfaces():
    """Tags are black-bordered grids of bits on white (two levels, both present); paint is a faint gradient
    (low contrast at any pixel's neighbourhood); edges are steps (few levels); every kind spans [0, 1]."""
    rng = np.random.default_rng(3)
    for kind in PATTERNS:
        p = pattern(rng, 96, kind)
        assert p.shape == (96, 96) and float(p.min()) == 0.0 and float(p.max()) == pytest.approx(1.0)
    tags = pattern(rng, 96, "tags")
    assert set(np.unique(np.round(tags, 6))) == {0.0, 1.0} and 0.2 < float(tags.mean()) < 0.8
    paint = pattern(rng, 96, "paint")
    assert float(np.abs(np.diff(paint, axis=1)).max()) < 0.2
    assert len(np.unique(np.round(pattern(rng, 96, "edges"), 6))) <= 16


def test_metrics():
    x = torch.rand(1, 3, 32, 32)
    assert ssim(x, x) == pytest.approx(1.0)
    assert psnr(x, x) == math.inf
    noisy = (x + 0.1 * torch.randn_like(x)).clamp(0, 1)
    assert 0 < ssim(x, noisy) < 0.97
    # Flat images: only the luminance term is left, (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1).
    c1 = 0.01 ** 2
    expected = (2 * 0.3 * 0.6 + c1) / (0.3 ** 2 + 0.6 ** 2 + c1)
    assert ssim(torch.full((3, 20, 20), 0.3), torch.full((3, 20, 20), 0.6)) == pytest.approx(expected, rel=1e-9)
    assert psnr(x, torch.full_like(x, 0.5)) == pytest.approx(-10 * math.log10(float(((x - 0.5) ** 2).mean())), rel=1e-6)


def test_training_steps_reduce_the_loss():
    torch.manual_seed(0)
    net = MagNet(8, enc_blocks=1, dec_blocks=1)
    batch = make_batch(7, 0, 4, SynthConfig(size=32))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    first = None
    for _ in range(40):
        loss, parts = losses(net, batch, 0.1)
        first = first if first is not None else parts["rec"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert losses(net, batch, 0.1)[1]["rec"] < 0.6 * first


def test_train_writes_weights_and_resumes(tmp_path):
    out = tmp_path / "m.pt"
    cfg = TrainConfig(out=out, steps=2, batch_size=2, crop=32, channels=8, enc_blocks=1, dec_blocks=1,
                      val_samples=2, val_every=100, progress=False)
    rep = train(cfg)
    assert rep.steps == 2 and out.is_file() and (tmp_path / "m.pt.ckpt").is_file()
    assert 0 < rep.val_ssim <= 1 and math.isfinite(rep.val_psnr)
    assert not list(tmp_path.glob("*.tmp"))
    rep2 = train(TrainConfig(**{**cfg.__dict__, "steps": 3, "resume": True}))
    assert rep2.steps == 3
    net = load_magnet(out)
    assert net.config == {"channels": 8, "enc_blocks": 1, "dec_blocks": 1}
    # The log beside the weights: the settings, the network and each validation, the resumed run's included.
    doc = json.loads(log_path(out).read_text())
    assert log_path(out).name == "m.log.json" and doc["steps"] == 3 and doc["network"] == net.config
    assert [v["step"] for v in doc["validation"]] == [2, 3] and doc["settings"]["crop"] == 32
    # A worker process makes the same batches as the trainer in line: the same weights, bit for bit.
    inline, ahead = (train(TrainConfig(**{**cfg.__dict__, "out": tmp_path / f"{n}.pt", "workers": w}))
                     for n, w in (("inline", 0), ("ahead", 1)))
    a, b = load_magnet(inline.out).state_dict(), load_magnet(ahead.out).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(InputError):
        train(TrainConfig(out=tmp_path / "none.pt", resume=True, progress=False))
    with pytest.raises(InputError):
        train(TrainConfig(out=tmp_path / "bad.pt", crop=30, progress=False))


def _measured_gain(alpha: float, n: int = 4, mono: bool = False) -> float:
    """Median over n textured planes of (output displacement) / (input displacement), static mode."""
    gains = []
    cfg = SynthConfig(**{**PLANE.__dict__, "alpha_range": (alpha, alpha), "size": 96})
    for i in range(n):
        s = make_sample((99, i), cfg)
        frames = torch.stack([s.frame_a, s.frame_b])
        if mono:
            frames = frames.mean(dim=1, keepdim=True)
        out = LearnedMagnifier(alpha).push(frames)
        dx, dy = estimate_translation(out[0], out[1])
        ix, iy = s.background_displacement
        gains.append((dx * ix + dy * iy) / (ix * ix + iy * iy))
    return sorted(gains)[n // 2]


def test_shipped_weights_magnify_a_subpixel_shift():
    net = load_magnet(DEFAULT_WEIGHTS)
    assert isinstance(net, MagNet)
    # Measured when shipped: 9.3 (RGB), 9.0 (mono) at alpha 10; 44.8 at alpha 50.
    assert 6.0 < _measured_gain(10.0) < 14.0
    assert 6.0 < _measured_gain(10.0, mono=True) < 14.0
    assert 30.0 < _measured_gain(50.0) < 70.0


def _shifted_plane(shifts: list[tuple[float, float]], size: int = 96) -> torch.Tensor:
    """One noise-free texture (a speckle-like sample) moved by each (dx, dy) with a Fourier phase ramp."""
    base = make_sample((99, 3), SynthConfig(size=size + 32, objects=(0, 0), p_noise=0.0, p_gray=0.0)).frame_a
    n = base.shape[-1]
    fy, fx = torch.fft.fftfreq(n)[:, None], torch.fft.fftfreq(n)[None, :]
    spec = torch.fft.fft2(base)
    out = [torch.fft.ifft2(spec * torch.exp(-2j * math.pi * (fx * dx + fy * dy))).real for dx, dy in shifts]
    return torch.stack(out).clamp(0, 1)[:, :, 16:16 + size, 16:16 + size]


def test_shipped_weights_dynamic_mode_tracks_static_on_a_ramp():
    frames = _shifted_plane([(0.04 * k, 0.03 * k) for k in range(5)])
    ends = {}
    for mode in ("static", "dynamic"):
        out = LearnedMagnifier(10.0, mode=mode).push(frames)
        ends[mode] = estimate_translation(out[0], out[-1])[0] / (0.04 * 4)
    assert ends["static"] > 5.0
    assert ends["dynamic"] == pytest.approx(ends["static"], rel=0.1)


def test_shipped_weights_temporal_mode_magnifies_the_band_only():
    fps, n = 30.0, 48
    dx = [0.1 * math.sin(2 * math.pi * 5.0 * k / fps) + 0.005 * k for k in range(n)]  # 5 Hz + a slow drift
    frames = _shifted_plane([(d, 0.0) for d in dx])
    mag = LearnedMagnifier(10.0, make_filter("fir", fps, 3.0, 8.0))
    out = torch.cat([mag.push(frames[:20]), mag.push(frames[20:]), mag.flush()])
    assert out.shape == frames.shape
    meas = torch.tensor([estimate_translation(frames[0], o)[0] for o in out], dtype=torch.float64)
    t = torch.arange(n, dtype=torch.float64) / fps
    basis = torch.stack([torch.sin(2 * math.pi * 5 * t), torch.cos(2 * math.pi * 5 * t), torch.ones(n), t], 1)
    keep = slice(12, 36)  # away from the filter's ends
    coef = torch.linalg.lstsq(basis[keep], meas[keep, None]).solution[:, 0]
    assert 4.0 < float(torch.hypot(coef[0], coef[1])) / 0.1 < 14.0  # the 5 Hz band, alpha 10
    assert float(coef[3]) == pytest.approx(0.005 * fps, rel=0.3)  # the drift is left as it is


def _frames(t: int = 11, c: int = 3, hw: tuple[int, int] = (30, 26)) -> torch.Tensor:
    """A texture shaking sub-pixel (a Fourier shift per frame); sizes not multiples of 4 on purpose."""
    s = make_sample(5, SynthConfig(size=32, objects=(0, 0), p_noise=0.0))
    base = s.frame_a
    fy = torch.fft.fftfreq(32)[:, None]
    fx = torch.fft.fftfreq(32)[None, :]
    out = []
    for k in range(t):
        d = 0.3 * math.sin(2 * math.pi * k / 5)
        ramp = torch.exp(-2j * math.pi * (fx * d + fy * 0.5 * d))
        out.append(torch.fft.ifft2(torch.fft.fft2(base) * ramp).real.clamp(0, 1))
    x = torch.stack(out)[:, :, : hw[0], : hw[1]]
    return x.mean(dim=1, keepdim=True) if c == 1 else x


@pytest.mark.parametrize("mode,temporal,c", [("static", None, 3), ("dynamic", None, 1), ("static", "fir", 3),
                                             ("static", "butter", 1)])
def test_streaming_in_chunks_matches_one_chunk(mode, temporal, c):
    frames = _frames(c=c)

    def make():
        filt = None if temporal is None else make_filter(temporal, 30.0, 3.0, 9.0, taps=5)
        return LearnedMagnifier(20.0, filt, mode=mode)

    one = make()
    whole = torch.cat([one.push(frames), one.flush()])
    assert whole.shape == frames.shape and whole.dtype == torch.float32
    assert 0 <= float(whole.min()) and float(whole.max()) <= 1
    chunked = make()
    parts = [chunked.push(frames[a:b]) for a, b in ((0, 1), (1, 4), (4, 5), (5, 11))] + [chunked.flush()]
    assert torch.allclose(torch.cat(parts), whole, atol=1e-5)


def test_errors():
    with pytest.raises(InputError):
        LearnedMagnifier(0.0)
    with pytest.raises(InputError):
        LearnedMagnifier(-2.0)
    with pytest.raises(InputError):
        LearnedMagnifier(10.0, mode="sideways")
    with pytest.raises(InputError):
        LearnedMagnifier(10.0, weights="/nonexistent/magnet.pt")
    m = LearnedMagnifier(10.0)
    m.push(torch.rand(2, 3, 16, 16))
    with pytest.raises(InputError):
        m.push(torch.rand(2, 3, 16, 20))
    with pytest.raises(InputError):
        m.push(torch.rand(2, 2, 16, 16))
    short = LearnedMagnifier(10.0, make_filter("fir", 30.0, 3.0, 9.0, taps=9))
    short.push(torch.rand(4, 1, 16, 16))
    with pytest.raises(InputError):
        short.flush()


def test_cli_train_mm_runs_a_few_steps(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "w.pt"
    run = subprocess.run([sys.executable, "-m", "odsplat", "train-mm", "-o", str(out), "--steps", "3",
                          "--batch-size", "2", "--crop", "32", "--channels", "8"], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "3 steps in" in run.stdout and out.stat().st_size > 10_000
    bad = subprocess.run([sys.executable, "-m", "odsplat", "train-mm", "-o", str(out), "--crop", "30"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "crop" in bad.stderr
