"""Procedural training data for the learned magnifier: textured layers moving sub-pixel, and their motion
rendered exactly alpha times larger (Oh et al. 2018's recipe, with procedural textures instead of COCO/VOC).

Every layer (a background and 0-N foreground objects) is a band-limited texture with a soft mask. A layer
is moved by a Fourier phase ramp, which translates a band-limited image exactly by any real displacement, so
frame b (the layer shifted by d), the ground truth (shifted by alpha * d) and frame a (not shifted) differ by
motion only. Layers are composited back to front (premultiplied colour). The textures are those of a test:
speckle paint, tags (AprilTag-like bit grids), sharp edges of parts, smooth paint with its shading, and
general noise, stripes, checkers and blobs. Sensor noise goes on the inputs only: by default a camera's
(`noise="camera"`: shot noise of a full well of electrons, read noise, quantisation to 8, 10 or 12 bits).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from odsplat.spine.errors import InputError


@dataclass(frozen=True)
class SynthConfig:
    """How samples are drawn. Displacements are set in the magnified frame: |alpha * d| in
    [min_magnified_px, max_magnified_px] (the paper caps the magnified motion, not the input one)."""

    size: int = 64
    alpha_range: tuple[float, float] = (2.0, 50.0)  # log-uniform
    min_magnified_px: float = 0.5
    max_magnified_px: float = 6.0
    objects: tuple[int, int] = (1, 4)  # inclusive range of foreground objects
    p_background_moves: float = 0.5
    p_object_static: float = 0.1
    p_gray: float = 0.3
    p_noise: float = 0.8
    noise: str = "camera"  # camera: shot + read + quantisation (below); gauss: gauss_sigma and poisson_gain
    full_well_e: tuple[float, float] = (200.0, 20000.0)  # electrons at full scale, log-uniform
    read_noise_e: tuple[float, float] = (2.0, 15.0)  # electrons rms, log-uniform
    bit_depths: tuple[int, ...] = (8, 10, 12)
    gauss_sigma: tuple[float, float] = (0.002, 0.05)  # noise="gauss": in [0, 1] units
    poisson_gain: tuple[float, float] = (0.0, 0.003)  # noise="gauss": variance = gain * intensity
    blur_sigma: float = 0.7  # band limit of every layer, pixels
    color_perturb: bool = True

    def __post_init__(self) -> None:
        if self.noise not in ("camera", "gauss"):
            raise InputError("SynthConfig.noise", f"camera or gauss, got {self.noise!r}")


@dataclass
class SynthSample:
    """(3, H, W) float32 tensors in [0, 1]. `frame_b_c` / `target_c` are frame b and the target with one
    random colour transform applied (for the texture/shape regularisation); displacements are (dx, dy) px."""

    frame_a: torch.Tensor
    frame_b: torch.Tensor
    target: torch.Tensor
    alpha: float
    frame_b_c: torch.Tensor
    target_c: torch.Tensor
    background_displacement: tuple[float, float] = (0.0, 0.0)
    object_displacements: list[tuple[float, float]] = field(default_factory=list)


# --- textures ---------------------------------------------------------------------------------------------

def _grid(s: int) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:s, 0:s].astype(np.float64)
    return x, y


def _smooth_noise(rng: np.random.Generator, s: int, scale: float) -> np.ndarray:
    """White noise low-passed by a Gaussian of `scale` px, normalised to [0, 1]."""
    n = rng.standard_normal((s, s))
    f = np.fft.fftfreq(s)
    k2 = f[:, None] ** 2 + f[None, :] ** 2
    out = np.real(np.fft.ifft2(np.fft.fft2(n) * np.exp(-2 * (math.pi * scale) ** 2 * k2)))
    lo, hi = out.min(), out.max()
    return (out - lo) / (hi - lo + 1e-12)


PATTERNS = ("noise", "stripes", "checkers", "blobs", "speckle", "tags", "paint", "edges")


def pattern(rng: np.random.Generator, s: int, kind: str | None = None) -> np.ndarray:
    """One scalar pattern in [0, 1] on an s x s canvas: of `kind` (one of PATTERNS), or of one drawn at random."""
    x, y = _grid(s)
    if kind is None:
        kind = PATTERNS[rng.integers(0, len(PATTERNS))]
    elif kind not in PATTERNS:
        raise InputError("pattern", f"one of {', '.join(PATTERNS)}, got {kind!r}")
    theta = rng.uniform(0, math.pi)
    u = x * math.cos(theta) + y * math.sin(theta)
    v = -x * math.sin(theta) + y * math.cos(theta)
    if kind == "noise":  # multi-octave noise
        octaves = rng.integers(1, 4)
        p = sum(_smooth_noise(rng, s, rng.uniform(0.7, 8.0)) / (o + 1) for o in range(octaves))
    elif kind == "stripes":  # stripes, smooth or hard
        period = rng.uniform(3.0, 20.0)
        p = 0.5 + 0.5 * np.sin(2 * math.pi * u / period + rng.uniform(0, 2 * math.pi))
        if rng.random() < 0.5:
            p = (p > 0.5).astype(np.float64)
    elif kind == "checkers":  # checkers
        period = rng.uniform(4.0, 20.0)
        p = ((np.floor(u / period) + np.floor(v / period)) % 2).astype(np.float64)
    elif kind == "blobs":  # blobs: discs and Gaussians
        p = np.zeros((s, s))
        for _ in range(rng.integers(5, 40)):
            cx, cy, r = rng.uniform(0, s), rng.uniform(0, s), rng.uniform(1.5, s / 6)
            d2 = (x - cx) ** 2 + (y - cy) ** 2
            blob = (d2 < r * r).astype(np.float64) if rng.random() < 0.5 else np.exp(-d2 / (2 * r * r))
            p = np.maximum(p, blob * rng.uniform(0.3, 1.0))
    elif kind == "speckle":  # sparse dots / speckle, like a painted speckle pattern on a test structure
        p = (_smooth_noise(rng, s, rng.uniform(0.8, 2.5)) > rng.uniform(0.5, 0.7)).astype(np.float64)
    elif kind == "tags":  # tags: AprilTag-like grids of bits in a black border, on white, tiled
        cell = rng.uniform(1.5, 5.0)
        bits = rng.integers(0, 2, (64, 64))
        i, j = (np.floor((w - w.min()) / cell).astype(int) for w in (u, v))
        pos_i, pos_j = i % 10, j % 10   # a tag is 10 cells: a white margin, a black border, 6 x 6 bits
        inner = (pos_i >= 2) & (pos_i <= 7) & (pos_j >= 2) & (pos_j <= 7)
        border = (pos_i >= 1) & (pos_i <= 8) & (pos_j >= 1) & (pos_j <= 8) & ~inner
        p = np.where(inner, bits[i % 64, j % 64], np.where(border, 0.0, 1.0)).astype(np.float64)
    elif kind == "paint":  # smooth paint: a gentle gradient with faint grain (little texture to follow)
        p = 0.5 + 0.5 * u / max(float(np.ptp(u)), 1.0) + rng.uniform(0.02, 0.1) * _smooth_noise(rng, s, 1.0)
    else:  # edges: a few parts' sharp outlines (half planes and steps)
        p = np.zeros((s, s))
        for _ in range(rng.integers(1, 5)):
            a = rng.uniform(0, 2 * math.pi)
            side = (x - rng.uniform(0, s)) * math.cos(a) + (y - rng.uniform(0, s)) * math.sin(a) > 0
            p += rng.uniform(0.3, 1.0) * side
    p = p - p.min()
    return p / (p.max() + 1e-12)


def _texture(rng: np.random.Generator, s: int) -> np.ndarray:
    """(3, s, s) in [0, 1]: one or two patterns mapped between random colours, with a smooth shading."""
    p = pattern(rng, s)
    if rng.random() < 0.4:
        q = pattern(rng, s)
        p = p * q if rng.random() < 0.5 else 0.5 * (p + q)
    c0, c1 = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
    if np.abs(c1 - c0).max() < 0.2:  # no invisible textures
        c1 = np.clip(c0 + np.sign(rng.standard_normal(3)) * 0.4, 0, 1)
    tex = c0[:, None, None] + (c1 - c0)[:, None, None] * p[None]
    shading = 1.0 + rng.uniform(0, 0.4) * (_smooth_noise(rng, s, s / 4) - 0.5)
    return np.clip(tex * shading[None], 0, 1)


def _mask(rng: np.random.Generator, s: int, size: int) -> np.ndarray:
    """A random object silhouette (ellipse, star polygon or noise blob) inside the central crop."""
    x, y = _grid(s)
    c = s / 2 + rng.uniform(-0.35, 0.35, 2) * size
    r = rng.uniform(0.12, 0.35) * size
    kind = rng.integers(0, 3)
    if kind == 0:
        th = rng.uniform(0, math.pi)
        ax, ay = r, r * rng.uniform(0.4, 1.0)
        u = (x - c[0]) * math.cos(th) + (y - c[1]) * math.sin(th)
        v = -(x - c[0]) * math.sin(th) + (y - c[1]) * math.cos(th)
        m = (u / ax) ** 2 + (v / ay) ** 2 < 1
    elif kind == 1:
        n = rng.integers(3, 9)
        radii = r * rng.uniform(0.5, 1.2, n)
        angles = np.sort(rng.uniform(0, 2 * math.pi, n))
        ang = np.arctan2(y - c[1], x - c[0]) % (2 * math.pi)
        # Radius at each pixel's angle, interpolated around the polygon's vertices (a star-shaped region).
        rr = np.interp(ang, np.r_[angles - 2 * math.pi, angles, angles + 2 * math.pi], np.r_[radii, radii, radii])
        m = np.hypot(x - c[0], y - c[1]) < rr
    else:
        blob = _smooth_noise(rng, s, r / 2)
        env = np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2) / (2 * r * r))
        m = blob * env > 0.35 * (blob * env).max()
    return m.astype(np.float64)


# --- exact sub-pixel motion ------------------------------------------------------------------------------

class _Shifter:
    """Band-limits a layer once (Gaussian of blur_sigma) and translates it exactly by any (dx, dy)."""

    def __init__(self, s: int, blur_sigma: float):
        self.s = s
        self.fy = np.fft.fftfreq(s)[:, None]
        self.fx = np.fft.rfftfreq(s)[None, :]
        self.lp = np.exp(-2 * (math.pi * blur_sigma) ** 2 * (self.fx ** 2 + self.fy ** 2))

    def spectrum(self, img: np.ndarray) -> np.ndarray:
        return np.fft.rfft2(img) * self.lp

    def shift(self, spec: np.ndarray, dx: float, dy: float) -> np.ndarray:
        ramp = np.exp(-2j * math.pi * (self.fx * dx + self.fy * dy))
        return np.fft.irfft2(spec * ramp, s=(self.s, self.s))


def _render(layers, shifter: _Shifter, k: float) -> np.ndarray:
    """Composite layers (premult spectrum, mask spectrum or None, displacement) each moved by k * d."""
    out = None
    for prem, mask, (dx, dy) in layers:
        p = shifter.shift(prem, k * dx, k * dy)
        if mask is None:
            out = p
        else:
            m = np.clip(shifter.shift(mask, k * dx, k * dy), 0, 1)
            out = p + (1 - m)[None] * out
    return np.clip(out, 0, 1)


def _displacement(rng: np.random.Generator, cfg: SynthConfig, alpha: float) -> tuple[float, float]:
    mag = rng.uniform(cfg.min_magnified_px, cfg.max_magnified_px) / alpha
    th = rng.uniform(0, 2 * math.pi)
    return (mag * math.cos(th), mag * math.sin(th))


def _noise(rng: np.random.Generator, img: np.ndarray, sigma: float, gain: float) -> np.ndarray:
    var = sigma ** 2 + gain * img
    return np.clip(img + np.sqrt(var) * rng.standard_normal(img.shape), 0, 1)


def _log_uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(math.exp(rng.uniform(math.log(lo_hi[0]), math.log(lo_hi[1]))))


def camera_noise(rng: np.random.Generator, img: np.ndarray, full_well_e: float, read_noise_e: float,
                 bits: int) -> np.ndarray:
    """`img` (intensity in [0, 1] of full scale) as a camera records it: Poisson shot noise of its electrons,
    Gaussian read noise, clipped at full scale and quantised to `bits` bits; back in [0, 1]."""
    electrons = rng.poisson(np.clip(img, 0, 1) * full_well_e) + read_noise_e * rng.standard_normal(img.shape)
    levels = 2 ** bits - 1
    return np.clip(np.round(electrons / full_well_e * levels), 0, levels) / levels


def make_sample(seed: int | tuple[int, ...] | list[int], cfg: SynthConfig = SynthConfig()) -> SynthSample:
    """One sample, a deterministic function of `seed` (an int or a sequence of ints) and `cfg`."""
    rng = np.random.default_rng(list(seed) if isinstance(seed, (tuple, list)) else seed)
    size = cfg.size
    margin = int(math.ceil(cfg.max_magnified_px + 4 * cfg.blur_sigma + 4))
    s = size + 2 * margin
    shifter = _Shifter(s, cfg.blur_sigma)
    alpha = float(math.exp(rng.uniform(math.log(cfg.alpha_range[0]), math.log(cfg.alpha_range[1]))))

    bg = _texture(rng, s)
    d_bg = _displacement(rng, cfg, alpha) if rng.random() < cfg.p_background_moves else (0.0, 0.0)
    layers = [(np.stack([shifter.spectrum(c) for c in bg]), None, d_bg)]
    d_objs = []
    for _ in range(rng.integers(cfg.objects[0], cfg.objects[1] + 1)):
        tex, m = _texture(rng, s), _mask(rng, s, size)
        d = (0.0, 0.0) if rng.random() < cfg.p_object_static else _displacement(rng, cfg, alpha)
        d_objs.append(d)
        layers.append((np.stack([shifter.spectrum(c * m) for c in tex]), shifter.spectrum(m), d))

    sl = slice(margin, margin + size)
    frames = [_render(layers, shifter, k)[:, sl, sl] for k in (0.0, 1.0, alpha)]
    if rng.random() < cfg.p_gray:
        frames = [np.repeat((0.299 * f[0] + 0.587 * f[1] + 0.114 * f[2])[None], 3, 0) for f in frames]
    a, b, y = frames

    # Colour perturbation for the regularisers: a random per-channel gain and offset (equal for grey).
    gray = bool(np.allclose(b[0], b[1]) and np.allclose(b[1], b[2]))
    n_c = 1 if gray else 3
    gain = np.resize(rng.uniform(0.5, 1.3, n_c), 3)[:, None, None]
    offset = np.resize(rng.uniform(-0.2, 0.2, n_c), 3)[:, None, None]
    bc, yc = (np.clip(f * gain + offset, 0, 1) for f in (b, y))
    if not cfg.color_perturb:
        bc, yc = b, y

    if rng.random() < cfg.p_noise:
        if cfg.noise == "camera":
            well, read = _log_uniform(rng, cfg.full_well_e), _log_uniform(rng, cfg.read_noise_e)
            bits = int(rng.choice(cfg.bit_depths))
            a, b, bc = (camera_noise(rng, f, well, read, bits) for f in (a, b, bc))
        else:
            sigma = rng.uniform(*cfg.gauss_sigma)
            pg = rng.uniform(*cfg.poisson_gain) if rng.random() < 0.5 else 0.0
            a, b, bc = (_noise(rng, f, sigma, pg) for f in (a, b, bc))

    t = lambda f: torch.from_numpy(np.ascontiguousarray(f, dtype=np.float32))  # noqa: E731
    return SynthSample(t(a), t(b), t(y), alpha, t(bc), t(yc), d_bg, d_objs)


def make_batch(seed: int, index: int, n: int, cfg: SynthConfig = SynthConfig()) -> dict[str, torch.Tensor]:
    """Samples (seed, index + i) for i < n, stacked: frame_a, frame_b, target, frame_b_c, target_c
    (N, 3, H, W) in [0, 1] and alpha (N,)."""
    samples = [make_sample((seed, index + i), cfg) for i in range(n)]
    keys = ("frame_a", "frame_b", "target", "frame_b_c", "target_c")
    out = {k: torch.stack([getattr(s, k) for s in samples]) for k in keys}
    out["alpha"] = torch.tensor([s.alpha for s in samples], dtype=torch.float32)
    return out


__all__ = ["PATTERNS", "SynthConfig", "SynthSample", "camera_noise", "pattern", "make_batch", "make_sample"]
