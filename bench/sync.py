"""Benchmark of sync against ground truth on the simulated rig, with the straightforward answers beside it.

Records a capture on hil_sim (random sub-frame phase per take, a camera trigger that lags half a frame
and jitters, hits that vary in force), then syncs it twice: with the exposure strobe, and with the
trigger frame refined by the images alone. Baselines from the same data:
- impact onset: the DAQ's trigger sample (first sample over the level), against the half-sine fit;
- frame timing: the trigger frame alone (counter 0 starts half a frame after the trigger plus delay);
- alignment: the whole take shifted in memory at once, against sync's band-by-band stream (time, memory).

Prints one JSON line on stdout; progress goes to stderr.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture  # noqa: E402
from odsplat.hil_sim.camera import SimCameraConfig  # noqa: E402
from odsplat.hil_sim.rig import TakeTruth, truth_path  # noqa: E402
from odsplat.spine.store import Capture  # noqa: E402
from odsplat.sync import AlignedTake, SyncSettings, sync_capture  # noqa: E402
from odsplat.sync.resample import fractional_shift  # noqa: E402

log = logging.getLogger("bench.sync")


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def _alignment(cap: Capture, delay_s: float):
    """Sync writes how each take is aligned, and a reader computes the frames as it streams them (32-tap windowed
    sinc, chunks of 16 frames); the baseline is the whole take shifted in memory by the FFT (what sync stored before
    issue 44). The two agree to within the interpolators' difference near the Nyquist frequency. Returns the times,
    traced peaks, the differences (DN) on a sample of pixels and sync's result."""
    aligned = sync_capture(cap, SyncSettings(method="ttl", camera_trigger_delay_s=delay_s, check_with_image=False))
    tracemalloc.start()
    t = time.perf_counter()
    streamed = {}
    for tk in aligned.ok:
        with AlignedTake(cap, cap.paths.listed(tk.aligned_file)) as a:
            streamed[tk.name] = [x[:, ::8, ::8].copy() for x in a.iter_frames(16)]   # a sample to compare
    stream_s = time.perf_counter() - t
    _, stream_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    tracemalloc.start()
    t = time.perf_counter()
    diff = []
    for tk in aligned.ok:
        with cap.open_take(tk.name) as r:
            whole = r.read_frames().astype(np.float64)
            shifted = fractional_shift(whole, tk.grid_shift_frames % 1.0, axis=0)
        if not tk.dropped_counters:
            k = int(np.floor(tk.grid_shift_frames))
            y = shifted[k:k + aligned.n_frames, ::8, ::8]
            diff.append((np.concatenate(streamed[tk.name]) - y).ravel())
    whole_s = time.perf_counter() - t
    _, whole_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    diff = np.concatenate(diff) if diff else np.zeros(0)
    return stream_s, stream_peak, whole_s, whole_peak, diff, aligned


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=27)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--fps", type=float, default=2000.0)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--keep", type=Path, default=None, help="record the capture here and keep it")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(name)s: %(message)s")
    fps = args.fps
    delay_s, jitter_s = 0.5 / fps, 0.25 / fps
    tmp = tempfile.TemporaryDirectory(prefix="bench-sync-")
    out = args.keep or Path(tmp.name) / "cap"
    camera = SimCameraConfig(fps=fps, trigger_delay_s=delay_s, trigger_jitter_s=jitter_s)
    t = time.perf_counter()
    report = simulate_capture(out, n_views=args.views, n_frames=args.frames, pretrigger_frames=10, record_s=0.2,
                              settings=SimBenchSettings(camera=camera, force_scatter=0.3, seed=args.seed))
    record_s = time.perf_counter() - t
    print(f"recorded {len(report.outcomes)} takes in {record_s:.0f} s", file=sys.stderr)
    cap = Capture.open(out)
    takes = [t.name for t in cap.manifest.takes if t.qc == "accepted"]
    truth = {n: TakeTruth.load(truth_path(cap.takes_dir / f"{n}.h5")) for n in takes}

    def true_offset(n: str) -> float:
        tr = truth[n]
        return tr.trigger_frame_time_s + 0.5 * tr.camera_exposure_s - tr.impact_time_s[0]

    runs = {}
    for method in ("ttl", "image"):
        t = time.perf_counter()
        res = sync_capture(cap, SyncSettings(method=method, write_frames=False, camera_trigger_delay_s=delay_s,
                                             check_with_image=False))
        runs[method] = (res, time.perf_counter() - t)
    ttl, ttl_s = runs["ttl"]
    image, image_s = runs["image"]
    err_ttl = [(t.offset_s - true_offset(t.name)) * fps for t in ttl.ok]
    err_image = [(t.offset_s - true_offset(t.name)) * fps for t in image.ok]
    onset_err, trigger_err, frame_base_err = [], [], []
    exposure = cap.manifest.camera.exposure_s
    for t in ttl.ok:
        tr = truth[t.name]
        with cap.open_take(t.name) as r:
            fs = r.sample_rate_hz
            trig = r.trigger.trigger_time_s
        onset_err.append((t.hit_daq_time_s - tr.impact_time_s[0]) * fs)
        trigger_err.append((trig - tr.impact_time_s[0]) * fs)
        base_start = trig + delay_s + 0.5 / fps  # the trigger frame alone: somewhere in the frame after the trigger
        frame_base_err.append((base_start + 0.5 * exposure - tr.impact_time_s[0] - true_offset(t.name)) * fps)

    stream_s, stream_peak, whole_s, whole_peak, diff, aligned = _alignment(cap, delay_s)
    n_px = int(np.prod(aligned.frame_shape)) * args.frames * len(aligned.ok)
    print(json.dumps({
        "bench": "sync",
        "takes": len(takes),
        "frames": args.frames,
        "fps": fps,
        "trigger_delay_frames": delay_s * fps,
        "trigger_jitter_frames": jitter_s * fps,
        "onset_rms_samples": round(rms(onset_err), 4),
        "baseline_trigger_sample_rms_samples": round(rms(trigger_err), 3),
        "ttl_synced": len(ttl.ok),
        "ttl_rms_frames": round(rms(err_ttl), 4),
        "ttl_max_frames": round(float(np.max(np.abs(err_ttl))), 4),
        "image_synced": len(image.ok),
        "image_rms_frames": round(rms(err_image), 4),
        "image_max_frames": round(float(np.max(np.abs(err_image))), 4),
        "baseline_trigger_frame_rms_frames": round(rms(frame_base_err), 3),
        "ttl_s_per_take": round(ttl_s / len(takes), 3),
        "image_s_per_take": round(image_s / len(takes), 3),
        "align_stream_s": round(stream_s, 2),
        "align_stream_peak_mb": round(stream_peak / 1e6, 1),
        "align_whole_in_memory_s": round(whole_s, 2),
        "align_whole_peak_mb": round(whole_peak / 1e6, 1),
        "align_mpx_per_s": round(n_px / 1e6 / stream_s, 1),
        "align_vs_fft_rms_dn": round(rms(diff), 4),
        "align_vs_fft_max_dn": round(float(np.max(np.abs(diff))), 3) if diff.size else None,
        "record_s": round(record_s, 1),
    }))
    tmp.cleanup()


if __name__ == "__main__":
    main()
