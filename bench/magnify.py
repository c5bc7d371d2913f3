"""Benchmark of motion magnification on hil_sim renders with known motion: quality against the natively
amplified ground truth, calibrated gain, noise, temporal filtering, multi-view consistency, speed and memory.

- Quality: each method's output against `SimCamera.truth(t, alpha)` (the rig rendered with its motion
  multiplied by alpha): SSIM and PSNR, and the measured gain: the dense optical flow (Farneback) of the
  output against its first frame, regressed on the flow of the true amplified render, times alpha.
- Noise: Gaussian noise of sigma 0.01 to 0.05 (images in [0, 1]) on the input, as in Oh et al.
- Temporal: static (against the first frame) and a Butterworth band around the first two modes.
- Multi-view: the gain spread across views of the same motion.
- Speed: frames/s at 256^2 and 512^2 per method (a Butterworth band), against the straightforward
  implementation: the whole video in memory, an ideal FFT band-pass along time per pixel, added back.
- Memory: peak RSS (VmHWM) of a streamed run (chunks of 16 from a generator) at 64 and 512 frames of 256^2,
  against the straightforward whole-video implementation, each in a fresh process.

Prints one JSON line on stdout; progress goes to stderr.
"""
from __future__ import annotations

import argparse
import json
import logging
import resource
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.hil_sim.render import PinholeCamera  # noqa: E402
from odsplat.hil_sim.rig import SimRig  # noqa: E402
from odsplat.hil_sim.scene import STRUCTURE, STRUCTURE_TAG  # noqa: E402
from odsplat.processing.magnify import MagnifySettings, make_magnifier  # noqa: E402
from odsplat.processing.metrics import psnr, ssim  # noqa: E402

log = logging.getLogger("bench.magnify")

METHODS = ("phase", "linear", "learned")
ALPHAS = (10.0, 50.0, 100.0)
NOISE = (0.01, 0.02, 0.05)
FPS = 500.0
BAND_HZ = (18.0, 40.0)  # the rig's first two modes, 23.5 and 31 Hz


def render_clip(size: int, n_frames: int, eye_m, alphas, *, peak_n: float = 60.0):
    """Noise-free input frames, the natively amplified truth for each alpha, and the structure's mask."""
    rig = SimRig()
    rig.hammer.peak_n = peak_n
    rig.hit(time_s=0.004)
    cam = rig.mount_camera(PinholeCamera.look_at(eye_m, (0.25, 0.0, 0.4), fov_deg=38.0, width_px=size, height_px=size))
    times = np.arange(n_frames) / FPS
    inputs = np.stack([cam.radiance(t) for t in times]).astype(np.float32)
    truths = {a: np.stack([cam.truth(t, alpha=a).image for t in times]).astype(np.float32) for a in alphas}
    r = cam.truth(0.0)
    mask = np.isin(r.object_id, (STRUCTURE, STRUCTURE_TAG))
    return inputs, truths, mask


# Each method's own options (`--learned-weights` sets the learned network's weights file).
OPTIONS: dict[str, tuple] = {}


def magnify(method: str, alpha: float, frames: np.ndarray, band: bool, chunk: int = 16) -> np.ndarray:
    s = MagnifySettings(method=method, alpha=alpha, band_hz=BAND_HZ if band else None,
                        options=OPTIONS.get(method, ()))
    mag = make_magnifier(s, FPS)
    x = torch.from_numpy(frames)[:, None]
    out = [mag.push(x[i:i + chunk]) for i in range(0, len(x), chunk)] + [mag.flush()]
    return torch.cat(out)[:, 0].numpy()


def _flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    to8 = lambda x: np.clip(x * 255, 0, 255).astype(np.uint8)  # noqa: E731
    return cv2.calcOpticalFlowFarneback(to8(a), to8(b), None, 0.5, 3, 9, 5, 5, 1.1, 0)


def measured_gain(out: np.ndarray, truth: np.ndarray, alpha: float, mask: np.ndarray, frames: list[int]) -> float:
    """alpha x (flow of the output . flow of the truth) / |flow of the truth|^2, over the structure's pixels."""
    num = den = 0.0
    for k in frames:
        fo, ft = _flow(out[0], out[k])[mask], _flow(truth[0], truth[k])[mask]
        num += float((fo * ft).sum())
        den += float((ft * ft).sum())
    return alpha * num / den if den > 0 else float("nan")


def quality(method, alpha, inputs, truths, mask, *, band, noise=0.0, seed=0):
    x = inputs
    if noise:
        x = np.clip(x + np.random.default_rng(seed).normal(0, noise, x.shape).astype(np.float32), 0, 1)
    out = magnify(method, alpha, x, band)
    truth = truths[alpha]
    skip = len(x) // 4 if band else 1  # a band-pass needs its warm-up
    frames = list(range(skip, len(x), max(1, (len(x) - skip) // 12)))
    sel = slice(skip, None)
    o, t = torch.from_numpy(np.clip(out[sel], 0, 1))[:, None], torch.from_numpy(np.clip(truth[sel], 0, 1))[:, None]
    return {"ssim": round(ssim(o, t), 4), "psnr_db": round(psnr(o, t), 2),
            # With a band, the truth still holds every mode amplified; the first two (inside the band) carry nearly
            # all of the displacement, so the gain measures the band's, less the Butterworth's phase lag.
            "gain": round(measured_gain(out, truth, alpha, mask, frames), 3)}


def straightforward(frames: np.ndarray, alpha: float, band_hz=BAND_HZ) -> np.ndarray:
    """The textbook implementation: the whole video in memory, an ideal band-pass by FFT along time for every
    pixel, the band multiplied by alpha - 1 and added back (intensity Eulerian, no pyramid)."""
    spec = np.fft.rfft(frames, axis=0)
    f = np.fft.rfftfreq(len(frames), 1.0 / FPS)
    spec[(f < band_hz[0]) | (f > band_hz[1])] = 0.0
    return frames + (alpha - 1.0) * np.fft.irfft(spec, n=len(frames), axis=0).astype(np.float32)


def _texture_video(size: int, n_frames: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 2.0)
    return np.stack([np.roll(base, k % 3, axis=1) for k in range(n_frames)])


def speed(method: str, size: int, n_frames: int) -> dict:
    frames = _texture_video(size, n_frames)
    t = time.perf_counter()
    magnify(method, 20.0, frames, True)
    ours = n_frames / (time.perf_counter() - t)
    t = time.perf_counter()
    straightforward(frames, 20.0)
    base = n_frames / (time.perf_counter() - t)
    return {"fps": round(ours, 2), "straightforward_fps": round(base, 2)}


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM; unlike ru_maxrss it does not carry a parent's over exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def rss_child(method: str, n_frames: int, streamed: bool) -> None:
    """In a fresh process: magnify n_frames of 256^2 (ours, streamed in chunks of 16 from a generator; or the
    straightforward whole-video implementation) and print the peak RSS in MB."""
    base = _texture_video(256, 3)
    gen = (base[k % 3][None] for k in range(n_frames))
    if streamed:
        mag = make_magnifier(MagnifySettings(method=method, alpha=20.0, band_hz=BAND_HZ), FPS)
        for k in range(0, n_frames, 16):
            block = np.stack([next(gen) for _ in range(min(16, n_frames - k))])
            mag.push(torch.from_numpy(block))
        mag.flush()
    else:
        straightforward(np.concatenate(list(gen)), 20.0)
    print(peak_rss_mb())


def rss(method: str, n_frames: int, streamed: bool) -> float:
    run = subprocess.run([sys.executable, __file__, "--rss-child", method, str(n_frames), str(int(streamed))],
                         capture_output=True, text=True, check=True)
    return round(float(run.stdout.strip().splitlines()[-1]), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--learned-weights", type=Path, default=None, help="the learned weights (default: shipped)")
    ap.add_argument("--rss-child", nargs=3, metavar=("METHOD", "N", "STREAMED"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.learned_weights is not None:
        OPTIONS["learned"] = (("weights", str(args.learned_weights)),)
    if args.rss_child:
        m, n, streamed = args.rss_child
        rss_child(m, int(n), bool(int(streamed)))
        return
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    methods = [m for m in args.methods.split(",") if m]
    eyes = [(1.4, -0.6, 0.9), (0.9, -1.3, 0.7), (1.5, 0.5, 1.2)]
    t = time.perf_counter()
    inputs, truths, mask = render_clip(args.size, args.frames, eyes[0], ALPHAS)
    views = [render_clip(args.size, args.frames, e, (10.0,)) for e in eyes[1:]]
    print(f"rendered in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    out: dict = {"bench": "magnify", "size_px": args.size, "frames": args.frames, "fps": FPS, "band_hz": BAND_HZ}
    for m in methods:
        r: dict = {}
        for band in (False, True):
            key = "band" if band else "static"
            r[key] = {f"alpha_{a:g}": quality(m, a, inputs, truths, mask, band=band) for a in ALPHAS}
            print(f"{m} {key}: {r[key]}", file=sys.stderr)
        r["noise_alpha_10"] = {f"sigma_{s:g}": quality(m, 10.0, inputs, truths, mask, band=False, noise=s)
                               for s in NOISE}
        gains = [quality(m, 10.0, inputs, truths, mask, band=False)["gain"]]
        gains += [quality(m, 10.0, v[0], v[1], v[2], band=False)["gain"] for v in views]
        r["multiview_gain_alpha_10"] = {"gains": gains, "spread_rel": round(float(np.std(gains) / np.mean(gains)), 4)}
        r["speed"] = {f"{s}px": speed(m, s, 64 if s == 256 else 32) for s in (256, 512)}
        r["peak_rss_mb"] = {"streamed_64": rss(m, 64, True), "streamed_512": rss(m, 512, True)}
        print(f"{m}: {r}", file=sys.stderr)
        out[m] = r
    out["straightforward_peak_rss_mb"] = {"whole_64": rss("linear", 64, False), "whole_512": rss("linear", 512, False)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
