"""The field's sub-pixel and noise protocol for motion magnification (issue 47), our implementation on our own
generated pairs, for each of our magnifiers and the textbook baseline.

The protocol is Oh et al. 2018's as the Axial-mm authors re-created it (FD4MM, EulerMormer and STB-VMM are scored
by it): a pair of frames whose second is the first moved by delta px, magnified by alpha = 10 / delta (so the
output motion is always 10 px), scored by SSIM against the first frame moved by alpha x delta, with an 8 px border
cropped; delta from 0.04 to 1.0 px; and a noise sweep at delta = 0.05 px, alpha = 200. Here the pairs are exact by
construction: a periodic, band-limited texture (speckle, smooth value noise, or hard edges, each low-passed below
Nyquist) moved by a Fourier phase ramp, so the first frame, the moved one and the truth are the same image at three
positions. Besides SSIM, each output's motion is measured (the exact move of the first frame that best matches the
output, least squares over the cropped middle) against alpha x delta: the magnification's accuracy, which SSIM
alone does not give.

Methods: phase, linear, learned (odsplat.processing, static against the first frame) and `textbook`, the
straightforward intensity Eulerian: second + (alpha - 1) x (second - first), no pyramid. Prints one JSON line on
stdout; progress on stderr.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.processing.magnify import MagnifySettings, make_magnifier  # noqa: E402
from odsplat.processing.metrics import ssim  # noqa: E402

log = logging.getLogger("bench.magnify_protocol")

METHODS = ("phase", "linear", "learned", "textbook")
DELTAS_PX = (0.04, 0.1, 0.2, 0.5, 1.0)
OUTPUT_MOTION_PX = 10.0
NOISE_DELTA_PX, NOISE_ALPHA = 0.05, 200.0
NOISE_SIGMAS = (0.0, 0.01, 0.02, 0.05, 0.1)
TEXTURES = ("speckle", "value_noise", "edges")
CROP_PX = 8
FPS = 500.0          # any: the pairs are magnified static, against their first frame


def texture(kind: str, size: int, seed: int = 0) -> np.ndarray:
    """(size, size) in [0.1, 0.9], periodic and band-limited below half Nyquist (so a Fourier shift moves it
    exactly and a magnified move of 10 px stays inside the band)."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(size)
    fr = np.hypot(*np.meshgrid(f, f, indexing="ij"))
    if kind == "speckle":            # fine grains: white noise up to a quarter of the sampling rate
        spec = np.fft.fft2(rng.random((size, size))) * (fr < 0.25)
    elif kind == "value_noise":      # smooth paint: power falling with frequency
        spec = np.fft.fft2(rng.random((size, size))) / np.maximum(fr, 1.0 / size) ** 1.5 * (fr < 0.25)
    elif kind == "edges":            # hard-edged blocks, then band-limited
        blocks = np.kron(rng.random((size // 16, size // 16)) > 0.5, np.ones((16, 16))).astype(float)
        spec = np.fft.fft2(blocks) * (fr < 0.25)
    else:
        raise ValueError(kind)
    spec[0, 0] = 0
    img = np.real(np.fft.ifft2(spec))
    img = (img - img.min()) / max(img.max() - img.min(), 1e-12)
    return (0.1 + 0.8 * img).astype(np.float64)


def shifted(img: np.ndarray, dx: float, dy: float = 0.0) -> np.ndarray:
    """The periodic image moved by (dx, dy) px, exactly (a Fourier phase ramp)."""
    n0, n1 = img.shape
    fy, fx = np.meshgrid(np.fft.fftfreq(n0), np.fft.fftfreq(n1), indexing="ij")
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (fx * dx + fy * dy))))


# Each method's own options (`--learned-weights` sets the learned network's weights file).
OPTIONS: dict[str, tuple] = {}


def magnify_pair(method: str, alpha: float, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The second frame magnified alpha times against the first."""
    if method == "textbook":
        return second + (alpha - 1.0) * (second - first)
    mag = make_magnifier(MagnifySettings(method=method, alpha=alpha, options=OPTIONS.get(method, ())), FPS)
    x = torch.from_numpy(np.stack([first, second]).astype(np.float32))[:, None]
    out = torch.cat([mag.push(x), mag.flush()])[:, 0].numpy()
    return out[1].astype(np.float64)


MOTION_SEARCH_PX = (-2.0, 2.0 * OUTPUT_MOTION_PX)   # where the output's motion is sought, in steps of a quarter px


def measured_motion_px(first: np.ndarray, out: np.ndarray) -> float:
    """The output's motion along x: the move of the clean first frame that best matches the output over the
    cropped middle (least squares; the pair's image is moved exactly, so no interpolation biases the answer, which
    OpenCV's phase correlation did by 25 % at 0.3 px)."""
    from scipy.optimize import minimize_scalar

    c = slice(CROP_PX, -CROP_PX)
    target = np.clip(out, 0, 1)[c, c]
    cost = lambda d: float(np.mean((shifted(first, d)[c, c] - target) ** 2))  # noqa: E731
    grid = np.arange(MOTION_SEARCH_PX[0], MOTION_SEARCH_PX[1] + 1e-9, 0.25)
    best = float(grid[int(np.argmin([cost(d) for d in grid]))])
    return float(minimize_scalar(cost, bounds=(best - 0.25, best + 0.25), method="bounded",
                                 options={"xatol": 1e-4}).x)


def score(method: str, delta: float, alpha: float, img: np.ndarray, sigma: float = 0.0, seed: int = 0) -> dict:
    first, second = img, shifted(img, delta)
    truth = shifted(img, alpha * delta)
    if sigma:
        rng = np.random.default_rng(seed)
        first = first + rng.normal(0, sigma, first.shape)
        second = second + rng.normal(0, sigma, second.shape)
    out = magnify_pair(method, alpha, first, second)
    c = slice(CROP_PX, -CROP_PX)
    t = lambda a: torch.from_numpy(np.clip(a[c, c], 0, 1).astype(np.float32))[None, None]  # noqa: E731
    return {"ssim": ssim(t(out), t(truth)), "motion_px": measured_motion_px(img, out)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--learned-weights", type=Path, default=None, help="the learned weights (default: shipped)")
    ap.add_argument("--textures", default=",".join(TEXTURES))
    a = ap.parse_args(argv)
    OPTIONS.clear()
    if a.learned_weights is not None:
        OPTIONS["learned"] = (("weights", str(a.learned_weights)),)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    torch.manual_seed(0)
    images = {k: texture(k, a.size, seed=i) for i, k in enumerate(a.textures.split(","))}
    out: dict = {"bench": "magnify_protocol", "size_px": a.size, "textures": list(images), "crop_px": CROP_PX,
                 "output_motion_px": OUTPUT_MOTION_PX, "noise_delta_px": NOISE_DELTA_PX, "noise_alpha": NOISE_ALPHA}
    started = time.perf_counter()
    for m in a.methods.split(","):
        r: dict = {"subpixel": {}, "noise": {}}
        for delta in DELTAS_PX:
            alpha = OUTPUT_MOTION_PX / delta
            s = [score(m, delta, alpha, img) for img in images.values()]
            motion = float(np.mean([x["motion_px"] for x in s]))
            r["subpixel"][f"delta_{delta:g}"] = {
                "alpha": alpha, "ssim": round(float(np.mean([x["ssim"] for x in s])), 4),
                "motion_px": round(motion, 3), "motion_rel_err": round(motion / (alpha * delta) - 1, 4)}
        for sigma in NOISE_SIGMAS:
            s = [score(m, NOISE_DELTA_PX, NOISE_ALPHA, img, sigma, seed=k) for k, img in enumerate(images.values())]
            r["noise"][f"sigma_{sigma:g}"] = {"ssim": round(float(np.mean([x["ssim"] for x in s])), 4),
                                              "motion_px": round(float(np.mean([x["motion_px"] for x in s])), 3)}
        errs = [abs(v["motion_rel_err"]) for v in r["subpixel"].values()]
        r["worst_motion_rel_err"] = round(max(errs), 4)
        print(f"{m}: {r}", file=sys.stderr)
        out[m] = r
    out["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
