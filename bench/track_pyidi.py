"""Our 2D point tracker (analysis/tracking.py) against pyidi's Lucas-Kanade (LADISK's Python Image Displacement
Identification, `pyidi.LucasKanade`) on the same points of the same videos, at the same window: how far apart the two
trackers are, against our noise floor; how far each is from the truth where it is known; and their wall times.

The videos:
- simulated: a periodic band-limited speckle (white noise through a Gaussian of SPECKLE_PX) translated by known
  sub-pixel sinusoids along x and y (FFT phase ramp, processing/phase.py's `shift_image_px`: exact for such an
  image), with the camera noise measured on the real recording below (shot + read, var = READ_DN^2 + GAIN_DN * I)
  and 8-bit codes. The first --still frames do not move: our noise floor is the rms of our displacement there.
- simulated_brightening: the same with the scene brightening by --brighten (default 6 %, as the real recording
  does over its first 5 frames) over the first 5 moving frames. Our tracker solves each window's intensity gain
  and offset; pyidi's LK does not.
- showcase: pyidi's own sample, a real Photron SA-Z recording of a beam (../shared/data/pyidi-samples/
  data_showcase.cih, 640x40 px, 8-bit, 75 frames: every 100th of 15 kHz). pyidi reads the .cih itself (pyMRAW),
  we read it with `open_video`. The beam rings in every frame, so there is no still stretch. Our noise floor there is
  the vertical one from pairs of points at the same x (a beam end's two corners move together vertically:
  half the variance of their difference is one point's noise). The Cramér-Rao bound (analysis/crlb.py) comes with
  it, from the camera's noise fitted on the static background's pixels (rows BACKGROUND_ROWS).
- showcase_settled: the same from frame SETTLED_FRAME on (the reference frame too). The static background
  brightens over frames 0-5 (above the beam 81.5 -> 86.3 DN, 6 %), then holds within 0.5 %.

Both trackers get the same integer points (our `good_points` on the reference frame, rounded: pyidi's windows are
centred on whole pixels, and ours on the nearest one anyway), each tool's defaults otherwise (ours: --method,
20 iterations, 1e-4 px; pyidi: cubic spline, pad 2, 20 iterations, 1e-8). pyidi takes and returns (row, column) =
(y, x), displacements (points, frames, 2) of the content in the frame against the reference, as ours: the bench
turns them to (frames, points, (x, y)). Wall times are the shortest of --repeats runs, after each tracker has
run once on 3 frames (pyidi's numba kernels compile, or load from numba's cache, on their first call). pyidi's
kernel runs on --pyidi-threads of numba's threads (1 by default: ours runs on one core).

Figures per case: rms_diff_px (ours - pyidi, over the points, the frames after the reference and both axes;
rms_diff_xy_px per axis), noise_floor_px (showcase: noise_floor_y_px), rms_error_px (each against the truth, over
the moving frames), crlb_px, wall_s, speed_ratio_pyidi_over_ours. Measured with the defaults (11 px windows; 15 s
after the imports, on 2 cores loaded by others):
- simulated (40 points, 120 frames): the trackers 0.0038 px apart, our floor 0.013 px (the bound 0.008 px); each
  0.012 px from the truth (motion 0.21 / 0.50 px rms along x / y).
- simulated_brightening: ours 0.0125 px from the truth, pyidi 0.052 px; the trackers 0.046 px apart.
- showcase (7 points, 75 frames): vertically 0.0080 px apart, our floor 0.0079 px: not below it, because of the
  brightening (as simulated). Along x 0.033 px, mostly at points on the beam's long edges, where x is barely
  resolved (the bound 0.02-0.04 px there).
- showcase_settled (8 points, 70 frames): vertically 0.0045 px apart, our floor 0.0082 px, the motion 0.098 px rms.
- wall (4 runs): simulated, pyidi 0.08-0.45 s, ours 0.51-1.29 s; showcase 0.08-0.26 s against 0.28-0.39 s:
  pyidi's compiled kernel 1.1-6x faster (speed_ratio 0.16-0.95). The cores' load by others moves each figure 2-5x
  from run to run. With numba on both cores (--pyidi-threads 0) pyidi took 0.7-2 s there.

    bench/track_pyidi.py                              # both videos, 11 px windows
    bench/track_pyidi.py --window 15 --method lk      # OpenCV's LK as ours
    bench/track_pyidi.py --points 80 --frames 300     # a bigger simulated video, for the speed

One JSON line on stdout; progress on stderr.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.analysis.crlb import NoiseModel, fisher_2d, fit_noise_model, sigma_2d_px  # noqa: E402
from odsplat.analysis.tracking import good_points, track_points  # noqa: E402
from odsplat.spine.shared_data import shared_data_dir  # noqa: E402

log = logging.getLogger("bench.track_pyidi")

# The camera of data_showcase, as crlb.fit_noise_model reads it on the static background's pixels (showcase_noise:
# 75 frames, 7667 pixels): 0.0351 DN/e-, read noise 0.62 DN. The simulated video gets the same noise.
GAIN_DN, READ_DN = 0.0351, 0.62
SPECKLE_PX = 1.5                       # the simulated speckle's Gaussian (sigma, px): grains of about 3-4 px
AMPLITUDE_PX = (0.3, 0.7)              # the simulated motion's amplitude along x and y (px), sub-pixel
PERIOD_FRAMES = (13.7, 9.3)            # and its periods along x and y (frames): two different sinusoids, so that a
#                                        swapped axis or a flipped sign cannot match the truth
SHOWCASE = Path("pyidi-samples") / "data_showcase.cih"
BACKGROUND_ROWS = (slice(0, 8), slice(36, 40))   # data_showcase's static background: above and below the beam
SETTLED_FRAME = 5                      # data_showcase's background is within 0.5 % of its final brightness from here
PAIR_DX_PX = 2                         # points this close in x are a pair at the same beam cross-section


def import_pyidi():
    """pyidi, without its side effect on numba. On import it asks numba for the 'forksafe' threading layer (for its
    own worker processes) unless NUMBA_THREADING_LAYER is set; on a numba without TBB that is 'workqueue', for
    the whole process, from its first parallel kernel on, and 'workqueue' aborts the process when two threads
    launch parallel kernels at once. With the variable set to numba's own setting during the import, pyidi
    defers to it; the variable is restored after."""
    import numba

    saved = os.environ.get("NUMBA_THREADING_LAYER")
    os.environ["NUMBA_THREADING_LAYER"] = saved or str(numba.config.THREADING_LAYER)
    try:
        import pyidi
    finally:
        if saved is None:
            os.environ.pop("NUMBA_THREADING_LAYER", None)
    return pyidi


# ------------------------------------------------------------------------------------------- the videos

def speckle(height: int, width: int, rng: np.random.Generator, sigma_px: float = SPECKLE_PX) -> np.ndarray:
    """A periodic, band-limited speckle (H, W) in DN, about 30-220 (1st-99th percentile)."""
    spec = np.fft.fft2(rng.standard_normal((height, width)))
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.fftfreq(width)[None, :]
    img = np.fft.ifft2(spec * np.exp(-2 * (np.pi * sigma_px) ** 2 * (fx ** 2 + fy ** 2))).real
    lo, hi = np.percentile(img, (1, 99))
    return 30.0 + 190.0 * (img - lo) / (hi - lo)


def sinusoids(n_frames: int, n_still: int, amplitude_px=AMPLITUDE_PX, period_frames=PERIOD_FRAMES) -> np.ndarray:
    """The simulated motion (T, 2) (x, y) px: zero for the first n_still frames, then a sinusoid along each axis."""
    t = np.arange(n_frames) - n_still
    d = np.stack([a * np.sin(2 * np.pi * t / p + phase)
                  for a, p, phase in zip(amplitude_px, period_frames, (0.0, 0.6))], axis=1)
    d[:n_still] = 0.0
    return d


def simulated_video(truth_xy: np.ndarray, *, size=(256, 128), n_still: int = 0, brighten: float = 0.0,
                    seed: int = 0) -> np.ndarray:
    """8-bit frames (T, H, W) of speckle translated by truth_xy (T, 2) (x, y): the content of frame t at x is the
    reference's at x - truth[t]. Camera noise (GAIN_DN, READ_DN) is drawn anew per frame; the brightness rises
    by `brighten` over the 5 frames after n_still and stays there."""
    import torch

    from odsplat.processing.phase import shift_image_px

    rng = np.random.default_rng(seed)
    width, height = size
    texture = torch.from_numpy(speckle(height, width, rng))
    gain = 1.0 + brighten * np.clip((np.arange(len(truth_xy)) - n_still + 1) / 5.0, 0.0, 1.0)
    frames = np.empty((len(truth_xy), height, width), np.uint8)
    for i, (dx, dy) in enumerate(truth_xy):
        img = gain[i] * shift_image_px(texture, float(dx), float(dy)).numpy()
        noisy = img + rng.standard_normal(img.shape) * np.sqrt(READ_DN ** 2 + GAIN_DN * np.maximum(img, 0.0))
        frames[i] = np.clip(np.rint(noisy), 0, 255)
    return frames


# ------------------------------------------------------------------------------------------- the trackers

def pick_points(frame: np.ndarray, window_px: int, max_points: int, mask=None) -> np.ndarray:
    """Our `good_points` (x, y), rounded to whole pixels (pyidi's windows are centred on them), at least a
    window apart."""
    p = good_points(frame, mask, max_points=max_points, min_distance_px=window_px, window_px=window_px,
                    quality_level=0.01)
    return np.unique(np.rint(p), axis=0)


def track_ours(frames, points_xy: np.ndarray, window_px: int, method: str = "gradient") -> np.ndarray:
    """(T, P, 2) (x, y) px against frame 0."""
    return track_points(frames, points_xy, method=method, window_px=window_px).displacement_px


def track_pyidi(pyidi, video, points_xy: np.ndarray, window_px: int) -> np.ndarray:
    """pyidi's LucasKanade at points_xy (x, y) with roi_size window x window on a pyidi.VideoReader: (T, P, 2)
    (x, y) px against frame 0. pyidi takes (row, column) points and returns (P, T, 2) (row, column) = (y, x)."""
    lk = pyidi.LucasKanade(video)
    lk.configure(roi_size=(window_px, window_px), verbose=0, show_pbar=False)
    lk.set_points(np.rint(points_xy[:, ::-1]).astype(np.int64))
    d = lk.get_displacements(autosave=False)
    return np.transpose(d, (1, 0, 2))[..., ::-1].copy()


def pyidi_reader(pyidi, frames: np.ndarray, root: Path):
    """A pyidi.VideoReader on frames (T, H, W) in memory; pyidi keeps its temporary files under root."""
    return pyidi.VideoReader(np.ascontiguousarray(frames), root=str(root))


def timed(repeats: int, fn, *args) -> tuple[np.ndarray, float]:
    """fn(*args) and its shortest wall time over `repeats` runs (on shared cores the others' load only adds)."""
    best = np.inf
    for _ in range(max(int(repeats), 1)):
        t = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - t)
    return out, best


def run_both(pyidi, frames: np.ndarray, points_xy: np.ndarray, window_px: int, method: str, root: Path,
             video=None, repeats: int = 1) -> dict:
    """Both trackers on the same frames and points, each once on 3 frames first (pyidi's numba kernels compile
    on their first call), then timed. video: pyidi's own reader of the same frames (a .cih), else in memory."""
    track_ours(frames[:3], points_xy, window_px, method)
    track_pyidi(pyidi, pyidi_reader(pyidi, frames[:3], root), points_xy, window_px)
    video = pyidi_reader(pyidi, frames, root) if video is None else video
    ours, t_ours = timed(repeats, track_ours, frames, points_xy, window_px, method)
    theirs, t_pyidi = timed(repeats, track_pyidi, pyidi, video, points_xy, window_px)
    return {"ours": ours, "pyidi": theirs, "wall_s": {"ours": t_ours, "pyidi": t_pyidi}}


# ------------------------------------------------------------------------------------------- the figures

def rms(x, axis=None) -> np.ndarray:
    """Root mean square over finite values."""
    return np.sqrt(np.nanmean(np.square(x), axis=axis))


def _r(x, digits: int = 5):
    """JSON-ready rounding: floats and nested lists; NaN and inf as null."""
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_r(v, digits) for v in x]
    x = float(x)
    return round(x, digits) if np.isfinite(x) else None


def common_figures(run: dict, points_xy: np.ndarray) -> dict:
    """The difference between the trackers over all frames after the reference, and their wall times."""
    diff = run["ours"][1:] - run["pyidi"][1:]
    lost = {k: int(np.isnan(run[k]).any(axis=(0, 2)).sum()) for k in ("ours", "pyidi")}
    w = run["wall_s"]
    return {"points": int(len(points_xy)), "frames": int(len(run["ours"])), "lost_points": lost,
            "rms_diff_px": _r(rms(diff)), "rms_diff_xy_px": _r(rms(diff, axis=(0, 1))),
            "max_point_rms_diff_xy_px": _r(np.nanmax(rms(diff, axis=0), axis=0)),
            "wall_s": {k: round(v, 3) for k, v in w.items()},
            "speed_ratio_pyidi_over_ours": round(w["pyidi"] / w["ours"], 3)}


def simulated_case(pyidi, args, root: Path, brighten: float = 0.0) -> dict:
    """The simulated video: the trackers' difference against our noise floor (the still frames), each one's error
    against the truth over the moving frames, and the Cramér-Rao bound at the points."""
    width, height = (int(v) for v in args.size.split("x"))
    truth = sinusoids(args.frames, args.still)
    frames = simulated_video(truth, size=(width, height), n_still=args.still, brighten=brighten, seed=args.seed)
    points = pick_points(frames[0], args.window, args.points)
    run = run_both(pyidi, frames, points, args.window, args.method, root, repeats=args.repeats)
    out = {"size": args.size, "still_frames": args.still, "brighten": brighten, **common_figures(run, points)}
    still, moving = slice(1, args.still), slice(args.still, None)
    noiseless = speckle(height, width, np.random.default_rng(args.seed))   # frame 0 without noise: the bound's image
    crlb = sigma_2d_px(fisher_2d(noiseless, NoiseModel(GAIN_DN, READ_DN, 1.0, 10 ** 6, 0), points, args.window))
    out.update({
        "noise_floor_px": _r(rms(run["ours"][still])), "noise_floor_xy_px": _r(rms(run["ours"][still], axis=(0, 1))),
        "pyidi_noise_floor_px": _r(rms(run["pyidi"][still])),
        "crlb_px": _r(rms(crlb)),
        "rms_error_px": {k: _r(rms(run[k][moving] - truth[moving, None])) for k in ("ours", "pyidi")},
        "rms_error_xy_px": {k: _r(rms(run[k][moving] - truth[moving, None], axis=(0, 1))) for k in ("ours", "pyidi")},
        "truth_rms_px": _r(rms(truth[moving], axis=0)),
    })
    out["diff_below_floor"] = bool(out["rms_diff_px"] < out["noise_floor_px"])
    return out


def pair_noise_y(d: np.ndarray, points_xy: np.ndarray) -> tuple[float, list]:
    """One point's vertical noise (px) from pairs of points at the same x (within PAIR_DX_PX) on the beam, whose
    vertical motion is the same: rms over the pairs of rms(dy_a - dy_b) / sqrt(2). NaN without a pair."""
    pairs = [(i, j) for i in range(len(points_xy)) for j in range(i + 1, len(points_xy))
             if abs(points_xy[i, 0] - points_xy[j, 0]) <= PAIR_DX_PX]
    if not pairs:
        return float("nan"), []
    per_pair = [rms(d[1:, i, 1] - d[1:, j, 1]) / np.sqrt(2) for i, j in pairs]
    return float(rms(per_pair)), pairs


def load_showcase(path: Path) -> np.ndarray:
    """data_showcase's frames (75, 40, 640) uint8, read by our reader."""
    from odsplat.spine.io.video import open_video

    video = open_video(path)
    return video.read(0, video.n_frames)


def showcase_noise(frames: np.ndarray) -> NoiseModel:
    """The camera's noise, fitted on the static background's pixels over all frames."""
    return fit_noise_model(np.concatenate([frames[:, rows] for rows in BACKGROUND_ROWS], axis=1), bit_depth=8)


def showcase_case(pyidi, frames: np.ndarray, start: int, args, root: Path, cih: Path | None = None) -> dict:
    """The real recording from frame `start` on (the reference): the trackers' difference per axis against our
    vertical noise floor (pairs at the same x) and the Cramér-Rao bound at the points. cih: let pyidi read the
    recording itself (only with start 0); else it gets our frames."""
    f = np.ascontiguousarray(frames[start:])
    points = pick_points(f[0], args.window, args.points)
    video = None
    if cih is not None and start == 0:
        link = root / "showcase"
        link.mkdir(exist_ok=True)                 # pyidi writes temporary files next to the video: not in shared/
        for ext in (".cih", ".mraw"):
            if not (link / f"v{ext}").exists():
                (link / f"v{ext}").symlink_to(cih.with_suffix(ext))
        video = pyidi.VideoReader(str(link / "v.cih"))
        if not np.array_equal(video.get_frames(), frames):
            raise RuntimeError("pyidi and our reader read different frames from the showcase")
    run = run_both(pyidi, f, points, args.window, args.method, root, video=video, repeats=args.repeats)
    out = {"start_frame": start, **common_figures(run, points)}
    floor, pairs = pair_noise_y(run["ours"], points)
    noise = showcase_noise(frames)
    crlb = sigma_2d_px(fisher_2d(f[0], noise, points, args.window))
    bg = np.concatenate([frames[:, rows] for rows in BACKGROUND_ROWS], axis=1).reshape(len(frames), -1).mean(axis=1)
    diff = run["ours"][1:] - run["pyidi"][1:]
    out.update({
        "noise_floor_y_px": _r(floor), "noise_floor_pairs": [[int(i), int(j)] for i, j in pairs],
        "pyidi_noise_floor_y_px": _r(pair_noise_y(run["pyidi"], points)[0]),
        "crlb_xy_px": _r(rms(crlb, axis=0)), "point_crlb_xy_px": _r(crlb, 4),
        "point_rms_diff_xy_px": _r(rms(diff, axis=0), 4), "points_xy": points.astype(int).tolist(),
        "motion_rms_y_px": _r(rms(run["ours"][1:, :, 1])),
        "background_brightness": _r(bg[start:start + 8] / np.median(bg) - 1.0, 4),
        "camera_noise": noise.describe(),
    })
    out["y_diff_below_floor"] = bool(np.isfinite(floor) and out["rms_diff_xy_px"][1] < floor)
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--window", type=int, default=11, help="the window's side (odd, px), both trackers")
    ap.add_argument("--method", default="gradient", help="our tracker's method: gradient, lk or phase")
    ap.add_argument("--points", type=int, default=40, help="at most this many points per video (good_points)")
    ap.add_argument("--frames", type=int, default=120, help="the simulated video's frames")
    ap.add_argument("--still", type=int, default=20, help="of which this many still ones first (the noise floor)")
    ap.add_argument("--size", default="256x128", help="the simulated video's WxH")
    ap.add_argument("--brighten", type=float, default=0.06, help="the brightening case's rise (0: no such case)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pyidi-threads", type=int, default=1, help="numba's threads for pyidi's kernel (0: numba's "
                    "default, every core); ours runs on one core, so one each by default")
    ap.add_argument("--repeats", type=int, default=3, help="wall times: the shortest of this many runs")
    ap.add_argument("--data", type=Path, default=None, help="the shared data folder (default ../shared/data or "
                    "$ODSPLAT_SHARED_DATA); without data_showcase in it the real cases are left out")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(name)s: %(message)s")
    pyidi = import_pyidi()
    import numba

    if args.pyidi_threads:
        numba.set_num_threads(args.pyidi_threads)
    figures = {"bench": "track_pyidi", "pyidi": pyidi.__version__, "method": args.method, "window_px": args.window,
               "numba_threads": int(numba.get_num_threads())}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-track-pyidi-") as tmp:
        root = Path(tmp)
        figures["simulated"] = simulated_case(pyidi, args, root)
        print(f"simulated: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        if args.brighten:
            figures["simulated_brightening"] = simulated_case(pyidi, args, root, brighten=args.brighten)
            print(f"simulated, brightening: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        cih = (args.data or shared_data_dir(REPO)) / SHOWCASE
        if cih.is_file():
            frames = load_showcase(cih)
            figures["showcase"] = showcase_case(pyidi, frames, 0, args, root, cih=cih)
            figures["showcase_settled"] = showcase_case(pyidi, frames, SETTLED_FRAME, args, root)
            print(f"showcase: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        else:
            figures["showcase"] = f"left out: {cih} not found"
    figures["total_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(figures, default=float))
    return figures


if __name__ == "__main__":
    main()
