"""Benchmark of the CPU Gaussian rasterizer: forward + backward ms of the numba path at 128^2 and 256^2 with 10k and
50k Gaussians, against the torch tile path and the brute-force reference at 128^2 with 10k Gaussians, all measured
in the same run.

The scene is fixed and random: Gaussians 2 to 4 scene units in front of the camera, 91 % of the centres on
screen, projected standard deviations 0.15 to 1.5 px (times up to ~1.5 of anisotropy) before the 0.3 px^2
dilation, so footprint radii of 2 to 6 px (5th to 95th percentile, median 4), random orientations, 3 colour
channels; alpha averages 0.89 at 128^2 with 10k. Float32, the training dtype. The loss is sum(image * fixed
weights) + sum(depth) so every output is used. Figures are the median of `repeats` runs after one warm-up (the
reference: one run after the warm-up), with torch.set_num_threads(--threads), tile_px = 8 (the default);
numba_ms_128px_10k_tile16 is the numba path with tile_px = 16, numba_ms_128px_10k_1thread the numba path on one
thread. The target is numba_ms_128px_10k <= 15 ms on 2 threads: target_met is null when --threads is not 2.
numba_first_call_ms is the first forward + backward in this process (1k Gaussians at 64^2): numba's compile
(~15 s), or loading its on-disk cache when the kernels were compiled before (reconstruction/__pycache__).

Prints one JSON line on stdout; progress goes to stderr. Peak RSS is this process's (VmHWM): peak_rss_mb_numba
after the numba runs, peak_rss_mb after the torch path and the reference too; both include what glibc's
allocator keeps. On two cores shared with other jobs, two threads can stall for a long time (OpenMP waits on a
descheduled thread): compare with --threads 1.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.reconstruction.raster import rasterize  # noqa: E402

log = logging.getLogger("bench.raster")

CONFIGS = ((10_000, 128), (50_000, 128), (10_000, 256), (50_000, 256))
TARGET_MS = 15.0  # numba path, 128^2, 10k Gaussians, forward + backward
TARGET_THREADS = 2


def bench_scene(n_gaussians: int, size_px: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """The fixed random scene (float32) seen by an identity camera with a ~53 degree field of view."""
    g = torch.Generator().manual_seed(seed)
    f_px = float(size_px)
    z = 2.0 + 2.0 * torch.rand(n_gaussians, generator=g)
    xy = (torch.rand(n_gaussians, 2, generator=g) - 0.5) * 1.05 * (size_px / f_px) * z[:, None]
    sigma_px = 0.15 + 1.35 * torch.rand(n_gaussians, generator=g)
    aniso = torch.exp(0.25 * torch.randn(n_gaussians, 3, generator=g))
    c = (size_px - 1) / 2
    return {
        "means": torch.cat([xy, z[:, None]], 1),
        "quats": torch.randn(n_gaussians, 4, generator=g),
        "scales": (sigma_px * z / f_px)[:, None] * aniso,
        "opacities": 0.1 + 0.8 * torch.rand(n_gaussians, generator=g),
        "colors": torch.rand(n_gaussians, 3, generator=g),
        "viewmat": torch.eye(4),
        "K": torch.tensor([[f_px, 0.0, c], [0.0, f_px, c], [0.0, 0.0, 1.0]]),
    }


def time_forward_backward(n_gaussians: int, size_px: int, backend: str = "numba", repeats: int = 3,
                          threads: int = 2, tile_px: int = 8) -> float:
    """Median ms of one forward + backward of `rasterize` on `bench_scene`, after one warm-up run."""
    return _forward_backward_ms(n_gaussians, size_px, backend, repeats, threads, tile_px)[1]


def _forward_backward_ms(n_gaussians: int, size_px: int, backend: str, repeats: int, threads: int,
                         tile_px: int) -> tuple[float, float]:
    """(ms of the warm-up run, median ms of the `repeats` runs after it)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        scene = bench_scene(n_gaussians, size_px)
        weights = torch.rand(size_px, size_px, 3, generator=torch.Generator().manual_seed(1))
        params = {k: v.requires_grad_(k not in ("viewmat", "K")) for k, v in scene.items()}
        times = []
        for _ in range(repeats + 1):
            t = time.perf_counter()
            out = rasterize(**params, width_px=size_px, height_px=size_px, backend=backend, tile_px=tile_px)
            ((out.image * weights).sum() + out.depth.sum()).backward()
            times.append(1e3 * (time.perf_counter() - t))
            for p in params.values():
                p.grad = None
        return times[0], statistics.median(times[1:]) if repeats else math.nan
    finally:
        torch.set_num_threads(before)


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM; unlike ru_maxrss it does not carry a parent's over exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=TARGET_THREADS)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    out: dict = {"bench": "raster", "threads": args.threads, "repeats": args.repeats}
    first, _ = _forward_backward_ms(1_000, 64, "numba", 0, args.threads, 8)
    out["numba_first_call_ms"] = round(first, 1)
    for n, size in CONFIGS:
        ms = time_forward_backward(n, size, "numba", args.repeats, args.threads)
        out[f"numba_ms_{size}px_{n // 1000}k"] = round(ms, 2)
        print(f"numba {size}^2 {n}: {ms:.2f} ms", file=sys.stderr)
    ms = time_forward_backward(10_000, 128, "numba", args.repeats, args.threads, tile_px=16)
    out["numba_ms_128px_10k_tile16"] = round(ms, 2)
    ms = time_forward_backward(10_000, 128, "numba", args.repeats, 1)
    out["numba_ms_128px_10k_1thread"] = round(ms, 2)
    print(f"numba 128^2 10000, tile 16: {out['numba_ms_128px_10k_tile16']} ms, 1 thread: {ms:.2f} ms", file=sys.stderr)
    out["peak_rss_mb_numba"] = round(peak_rss_mb(), 1)
    ms = time_forward_backward(10_000, 128, "torch", args.repeats, args.threads)
    out["torch_ms_128px_10k"] = round(ms, 1)
    print(f"torch 128^2 10000: {ms:.1f} ms", file=sys.stderr)
    # the brute force is slow (seconds): one timed run after the warm-up
    ms = time_forward_backward(10_000, 128, "reference", 1, args.threads)
    out["reference_ms_128px_10k"] = round(ms, 1)
    print(f"reference 128^2 10000: {ms:.1f} ms", file=sys.stderr)
    numba_ms = out["numba_ms_128px_10k"]
    out["speedup_reference_over_numba_128px_10k"] = round(out["reference_ms_128px_10k"] / numba_ms, 1)
    out["speedup_torch_over_numba_128px_10k"] = round(out["torch_ms_128px_10k"] / numba_ms, 2)
    out["target_ms_128px_10k"] = TARGET_MS
    out["target_threads"] = TARGET_THREADS
    out["target_met"] = numba_ms <= TARGET_MS if args.threads == TARGET_THREADS else None
    out["peak_rss_mb"] = round(peak_rss_mb(), 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
