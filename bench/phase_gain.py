"""The phase method's gain, by its options (issue 47: "alpha = 10 gives 8.2"): where the shortfall comes from.

Two measures, each beside the default settings (the baseline) in the same run:
- whole-frame: bench/magnify_protocol.py's exact pairs (a periodic band-limited texture moved by a Fourier ramp),
  delta 0.02 and 0.1 px at alpha 10 (output 0.2 and 1 px: inside the phase method's linear range), the output's
  motion read by least squares, over delta: the gain on a texture that fills the frame;
- the rig clip: bench/magnify.py's `render_clip` (192 px, 96 frames, static), the Farneback gain over the structure
  at alpha 10 and 50, and SSIM/PSNR against the natively amplified truth: a thin structure over a static background.

Variants: half- and quarter-octave pyramids (`scales_per_octave`), 8 orientations, no phase smoothing
(`sigma_px` 0), the top octave magnified (`top_band`), and the Lagrangian synthesis (`warp`). Prints one JSON
line on stdout; progress on stderr.
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
sys.path.insert(0, str(REPO / "bench"))

import magnify as clip_bench  # noqa: E402
import magnify_protocol as protocol  # noqa: E402

from odsplat.processing.metrics import psnr, ssim  # noqa: E402
from odsplat.processing.phase import PhaseMagnifier  # noqa: E402

log = logging.getLogger("bench.phase_gain")

VARIANTS = {"default": {}, "half_octave": {"scales_per_octave": 2}, "quarter_octave": {"scales_per_octave": 4},
            "orientations_8": {"n_orientations": 8}, "no_smoothing": {"sigma_px": 0.0}, "top_band": {"top_band": True},
            "warp": {"warp": True}}
DELTAS_PX = (0.02, 0.1)
ALPHA = 10.0


def _magnify(options: dict, alpha: float, frames: np.ndarray) -> np.ndarray:
    m = PhaseMagnifier(alpha, None, **options)
    x = torch.from_numpy(frames.astype(np.float32))[:, None]
    out = [m.push(x[i:i + 16]) for i in range(0, len(x), 16)] + [m.flush()]
    return torch.cat(out)[:, 0].numpy().astype(np.float64)


def whole_frame_gain(options: dict, kind: str, size: int, delta: float, alpha: float = ALPHA) -> float:
    """The output's motion over the input's, on an exact pair of a texture filling the frame."""
    img = protocol.texture(kind, size, seed=0)
    out = _magnify(options, alpha, np.stack([img, protocol.shifted(img, delta)]))[1]
    return protocol.measured_motion_px(img, out) / delta


def clip_scores(options: dict, clip, alpha: float) -> dict:
    inputs, truths, mask = clip
    out, truth = _magnify(options, alpha, inputs), truths[alpha]
    frames = list(range(1, len(inputs), max(1, (len(inputs) - 1) // 12)))
    o, t = (torch.from_numpy(np.clip(a[1:], 0, 1).astype(np.float32))[:, None] for a in (out, truth))
    return {"gain": round(clip_bench.measured_gain(out, truth, alpha, mask, frames), 3), "ssim": round(ssim(o, t), 4),
            "psnr_db": round(psnr(o, t), 2)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128, help="the whole-frame textures' side")
    ap.add_argument("--clip-size", type=int, default=192, help="the rig clip's side (0: no clip)")
    ap.add_argument("--clip-frames", type=int, default=96)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    started = time.perf_counter()
    clip = clip_bench.render_clip(a.clip_size, a.clip_frames, (1.4, -0.6, 0.9), (ALPHA, 50.0)) if a.clip_size else None
    out: dict = {"bench": "phase_gain", "alpha": ALPHA, "deltas_px": list(DELTAS_PX), "size_px": a.size,
                 "clip_size_px": a.clip_size, "textures": list(protocol.TEXTURES)}
    for name in a.variants.split(","):
        options = VARIANTS[name]
        r: dict = {"options": options, "whole_frame_gain": {
            k: [round(whole_frame_gain(options, k, a.size, d), 3) for d in DELTAS_PX] for k in protocol.TEXTURES}}
        gains = [g for v in r["whole_frame_gain"].values() for g in v]
        r["whole_frame_worst_rel_err"] = round(max(abs(g / ALPHA - 1) for g in gains), 4)
        if clip is not None:
            r["clip"] = {f"alpha_{al:g}": clip_scores(options, clip, al) for al in (ALPHA, 50.0)}
        print(f"{name}: {r}", file=sys.stderr)
        out[name] = r
    out["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
