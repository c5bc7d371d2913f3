"""Benchmark of the viewer's 3D view: frames/s of `odsplat.app.viewer.render_view` at 640x480 on a capture's
reconstruction, against the straightforward baseline, `DynamicScene.render` (the training rasterizer, `rasterize`,
run under no_grad), in the same run.

Every figure but `fps_all_threads` and `fps_1thread` is taken on the thread count the window picks when it opens
(`best_threads`: all of torch's or one, whichever renders faster here), the baseline's too.

Prints one JSON line on stdout; progress goes to stderr. Each figure is the median frame time over at least
--min-time seconds (and 5 frames), each frame at another time of the measured motion (or phase of the mode), as
when the time plays; after one warm-up frame (numba compiles on first use and caches on disk). The median, not the
mean, so that other processes on a shared machine skew it less; the load average is reported beside it.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("bench.viewer")

REPO = Path(__file__).resolve().parents[1]
TARGET_FPS = 20.0
MIN_TIME_S = 2.0


def _fps(frame, min_time_s: float) -> tuple[float, int]:
    """Frames/s from the median time of frame(k), k = 0, 1, ..., over at least min_time_s and 5 frames."""
    frame(0)
    times = []
    t_end = time.perf_counter() + min_time_s
    while len(times) < 5 or time.perf_counter() < t_end:
        t0 = time.perf_counter()
        frame(len(times) + 1)
        times.append(time.perf_counter() - t0)
    return 1.0 / float(np.median(times)), len(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", nargs="?", default=str(REPO / "demo-out" / "sim-rig"),
                        help="a reconstructed and analysed capture (default demo-out/sim-rig)")
    parser.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    parser.add_argument("--alpha", type=float, default=100.0)
    parser.add_argument("--min-time", type=float, default=MIN_TIME_S, help="seconds timed per figure")
    parser.add_argument("--no-baseline", action="store_true", help="skip DynamicScene.render")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")

    import torch

    from odsplat.app.viewer import default_state, load_viewer, render_view
    from odsplat.app.viewer.model import best_threads, camera_for

    t0 = time.perf_counter()
    data = load_viewer(args.capture)
    load_s = time.perf_counter() - t0
    if data.scene is None:
        raise SystemExit(f"{args.capture}: no reconstruction to render")
    sc = data.scene
    w, h = args.size
    state = default_state(data, alpha=args.alpha, width_px=w, height_px=h)
    times = np.linspace(*data.time_range_s, 37)
    log.info("%s: %d Gaussians (%d the structure's), %dx%d, %d threads", data.name, sc.n, int(sc.structure.sum()), w,
             h, torch.get_num_threads())

    def view(k: int, **kw) -> None:
        render_view(data, replace(state, time_s=float(times[k % len(times)]), **kw))

    result: dict[str, Any] = {
        "bench": "viewer", "capture": data.name, "gaussians": sc.n, "structure_gaussians": int(sc.structure.sum()),
        "size": [w, h], "alpha": args.alpha, "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2), "load_s": round(load_s, 2),
        "view": "render_view: forward-only numba rasterizer (rasterize_image), cameras, sensors and caption drawn",
        "baseline": "DynamicScene.render under no_grad: rasterize(), the training path (autograd Functions, "
                    "buffers kept for backward)",
    }
    most = torch.get_num_threads()
    per_threads = {}
    for n_threads in sorted({most, 1}, reverse=True):
        torch.set_num_threads(n_threads)
        per_threads[n_threads], _ = _fps(view, args.min_time)
        log.info("view on %d thread(s): %.1f frames/s", n_threads, per_threads[n_threads])
    torch.set_num_threads(most)
    chosen = best_threads(data, state)         # what the window does when it opens; leaves torch at it
    try:
        fps, n = _fps(view, args.min_time)
        log.info("view on the %d thread(s) the viewer chooses here: %.1f frames/s (%d frames)", chosen, fps, n)
        fps_struct, _ = _fps(lambda k: view(k, structure_only=True), args.min_time)
        log.info("view, structure only: %.1f frames/s", fps_struct)
        fps_mode = None
        if data.modes and data.modes[0].gaussians is not None:
            mode_state = replace(state, mode=0)
            period = 1.0 / data.modes[0].freq_hz
            fps_mode, _ = _fps(lambda k: render_view(data, replace(mode_state, time_s=k * period / 24)),
                               args.min_time)
            log.info("view, mode 1: %.1f frames/s", fps_mode)
        result.update(viewer_threads=chosen, fps=round(fps, 2), frames=n, fps_structure_only=round(fps_struct, 2),
                      fps_mode=None if fps_mode is None else round(fps_mode, 2),
                      fps_all_threads=round(per_threads[most], 2), fps_1thread=round(per_threads[1], 2))
        if not args.no_baseline:
            from odsplat.reconstruction import DynamicScene

            scene = DynamicScene.load(data.capture)
            cam = camera_for(data, state)
            fps_base, _ = _fps(lambda k: scene.render(cam, float(times[k % len(times)]), alpha=args.alpha),
                               args.min_time)
            log.info("baseline on %d thread(s): %.1f frames/s", chosen, fps_base)
            # the ratios of the printed (rounded) figures, so that the line agrees with itself
            base = round(fps_base, 2)
            result.update(baseline_fps=base, ratio=round(result["fps"] / base, 2),
                          ratio_structure_only=round(result["fps_structure_only"] / base, 2))
    finally:
        torch.set_num_threads(most)
    result.update(target_fps=TARGET_FPS, meets_target=result["fps"] >= TARGET_FPS)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
