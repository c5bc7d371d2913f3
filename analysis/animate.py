"""Animated operational deflection shapes for the report: the structure deformed by one mode's (or ODS line's)
shape through a cycle, over the undeformed structure, as a looping GIF that plays inline in the page.

Drawn directly into the frames' pixels with numpy, one vectorised pass per frame (points projected orthographically
from one oblique view), and encoded by Pillow, not through matplotlib: a dozen frames of ten thousand points take
about 50 ms, so every analysis can afford one per mode.
"""
from __future__ import annotations

import io
import math

import numpy as np
from PIL import Image, ImageDraw

N_FRAMES = 12          # one cycle
SIZE_PX = (480, 400)
DEFORM = 0.08          # the largest displacement drawn: this fraction of the structure's size
FRAME_MS = 80


def _view(points: np.ndarray, azimuth_deg: float = 35.0, elevation_deg: float = 25.0) -> np.ndarray:
    """(3, 2) projection onto the image plane of a camera looking from (azimuth, elevation), z up."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    right = np.array([-math.sin(a), math.cos(a), 0.0])
    up = np.array([-math.cos(a) * math.sin(e), -math.sin(a) * math.sin(e), math.cos(e)])
    return np.stack([right, up], axis=1)


def ods_gif(points_m: np.ndarray, shape: np.ndarray, *, title: str = "", n_frames: int = N_FRAMES,
            size_px: tuple[int, int] = SIZE_PX) -> bytes:
    """A looping GIF of `shape` ((N, 3) complex, any unit) animated on `points_m` ((N, 3), metres) through one
    cycle: Re(shape e^(i phi)) scaled so the largest displacement is DEFORM of the structure's size, the points
    coloured by |shape|, the rest positions in grey beneath."""
    p = np.asarray(points_m, float)
    s = np.asarray(shape, complex)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(s).all(axis=1)
    p, s = p[ok], s[ok]
    w, h = size_px
    if not len(p):
        raise ValueError("no finite point to animate")
    # the structure's size and the view's bounds from the 1st-99th percentiles: a stray point does not shrink it
    size = float(np.linalg.norm(np.percentile(p, 99, axis=0) - np.percentile(p, 1, axis=0))) or 1.0
    amp = np.linalg.norm(np.abs(s), axis=1)
    peak = float(amp.max()) if amp.size and amp.max() > 0 else 1.0
    scale = DEFORM * size / peak
    P = _view(p)
    xy0 = p @ P
    lo = np.percentile(xy0, 1, axis=0) - 0.15 * size
    hi = np.percentile(xy0, 99, axis=0) + 0.15 * size
    k = min((w - 20) / max(hi[0] - lo[0], 1e-12), (h - 50) / max(hi[1] - lo[1], 1e-12))

    def to_px(xy: np.ndarray) -> np.ndarray:
        return np.stack([10 + (xy[:, 0] - lo[0]) * k, h - 10 - (xy[:, 1] - lo[1]) * k], axis=1)

    colour = _plasma(amp / peak)
    depth = np.argsort(p @ np.cross(P[:, 0], P[:, 1]))     # far points first
    rest = to_px(xy0)
    grey = np.full((h, w, 3), 255, np.uint8)
    _stamp(grey, rest[depth], np.full((len(depth), 3), 200, np.uint8), radius_px=0)
    frames = []
    for j in range(n_frames):
        phase = np.exp(2j * np.pi * j / n_frames)
        q = to_px((p + scale * np.real(s * phase)) @ P)
        rgb = grey.copy()
        _stamp(rgb, q[depth], colour[depth], radius_px=1)
        im = Image.fromarray(rgb)
        d = ImageDraw.Draw(im)
        if title:
            d.text((10, 8), title, fill=(0, 0, 0))
        d.text((10, 24), f"displacement x {scale:.3g} (largest = {100 * DEFORM:.0f} % of {size:.2f} m)",
               fill=(90, 90, 90))
        frames.append(im.convert("P", palette=Image.Palette.ADAPTIVE, colors=64))
    buf = io.BytesIO()
    frames[0].save(buf, format="GIF", save_all=True, append_images=frames[1:], duration=FRAME_MS, loop=0,
                   optimize=False, disposal=2)
    return buf.getvalue()


def _stamp(rgb: np.ndarray, xy_px: np.ndarray, colour: np.ndarray, radius_px: int) -> None:
    """Paint squares of (2 radius_px + 1) px at xy_px in the given order, a later point over an earlier one (the
    painter's order: far to near), in one vectorised pass: for every pixel the last point that covers it wins."""
    h, w = rgb.shape[:2]
    centre = np.rint(xy_px).astype(int)
    offsets = np.arange(-radius_px, radius_px + 1)
    dx, dy = (a.ravel() for a in np.meshgrid(offsets, offsets))
    x = (centre[:, 0, None] + dx[None]).ravel()
    y = (centre[:, 1, None] + dy[None]).ravel()
    who = np.repeat(np.arange(len(centre)), len(dx))
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    flat, who = (y * w + x)[inside], who[inside]
    last = len(flat) - 1 - np.unique(flat[::-1], return_index=True)[1]     # each pixel's last writer
    rgb.reshape(-1, 3)[flat[last]] = colour[who[last]]


def _plasma(x: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours from dark blue (0) through magenta to yellow (1)."""
    stops = np.array([[13, 8, 135], [126, 3, 168], [204, 71, 120], [248, 149, 64], [240, 249, 33]], float)
    t = np.clip(np.asarray(x, float), 0, 1) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[:, None]
    return np.round(stops[i] * (1 - f) + stops[i + 1] * f).astype(np.uint8)


__all__ = ["ods_gif"]
