"""The video's noise floor against its physical limit on hil_sim. A simulated capture is recorded (the
`odsplat capture --sim --auto` session, in process) and run through sync, poses and the reconstruction with the
defaults (the linear motion model on the raw frames), the rest fit shortened to 800 iterations. The analysis then
measures the noise floor, and `analysis.crlb.displacement_bound` gives the Cramér-Rao bound from the same takes'
frames at rest.

Figures: the camera's noise model as measured against the simulated sensor's truth (gain, read noise); per view,
its own 2D bound at the points it sees (median sigma along the image's x and y, in um at the points' depth, and in
px); the 3D bound over the structure's points (per world axis, the worst direction, the rms over the components);
the analysis' measured floor (per point, and per mode at the sensors) and their ratio. Baselines in the same run:
(a) the best single view's in-plane bound, with no 3D combination; (b) the bound were the quantisation the only
noise; (c) the same bound from fixed 7x7 px windows instead of each point's cell. Target: the measured floor within
2x of the bound (median over the structure's points).

Prints one JSON line on stdout; progress goes to stderr. The default size (9 views of 400x300 px, 64 frames at
2000 fps, 16 of them before the trigger) takes 48 s on 2 idle cores (record 19 s, sync 5 s, poses 4 s, reconstruct
14 s, the analysis and the bound 3 s), and 3.5 minutes on 2 busy cores shared with others.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.analysis.analyze import AnalyzeSettings, analyze_capture, structure_mask  # noqa: E402
from odsplat.analysis.crlb import displacement_bound  # noqa: E402
from odsplat.analysis.ods import SurfaceMotion  # noqa: E402
from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture  # noqa: E402
from odsplat.hil_sim.camera import SimCameraConfig  # noqa: E402
from odsplat.hil_sim.rig import RigConfig, SimRig  # noqa: E402
from odsplat.reconstruction.dynamic import FitSettings  # noqa: E402
from odsplat.reconstruction.linear import LinearSettings  # noqa: E402
from odsplat.reconstruction.model import ReconstructSettings, reconstruct  # noqa: E402
from odsplat.reconstruction.poses import estimate_poses  # noqa: E402
from odsplat.spine.store import Capture  # noqa: E402
from odsplat.sync import SyncSettings, sync_capture  # noqa: E402

log = logging.getLogger("bench.crlb")

MAX_RATIO = 2.0      # the target: the measured floor within 2x of the bound


def stage(times: dict, name: str, done: bool, fn) -> None:
    """Run fn unless its output exists (a kept capture), timing it."""
    if done:
        print(f"{name}: kept", file=sys.stderr)
        return
    t = time.perf_counter()
    fn()
    times[name] = round(time.perf_counter() - t, 1)
    print(f"{name}: {times[name]:.0f} s", file=sys.stderr)


def record_and_process(out: Path, args, times: dict) -> Capture:
    camera = SimCameraConfig(fps=args.fps, bit_depth=args.bit_depth, full_well_e=args.full_well_e,
                             read_noise_e=args.read_noise_e)
    stage(times, "record", (out / "capture.json").exists(), lambda: simulate_capture(
        out, n_views=args.views, n_frames=args.frames, pretrigger_frames=args.pretrigger, record_s=args.record_s,
        settings=SimBenchSettings(camera=camera, seed=args.seed), rig=SimRig(config=RigConfig(seed=args.seed))))
    cap = Capture.open(out)
    stage(times, "sync", cap.paths.sync_json.exists(), lambda: sync_capture(cap, SyncSettings(), progress=False))
    stage(times, "poses", cap.paths.poses_json.exists(), lambda: estimate_poses(cap).write(cap))
    settings = ReconstructSettings(width_px=args.width, threads=args.threads,
                                   fit=FitSettings(iters_t0=args.iters_t0, seed=args.seed, progress=False),
                                   linear=LinearSettings(progress=False))
    stage(times, "reconstruct", cap.paths.reconstruction_json.exists(), lambda: reconstruct(cap, settings))
    return cap


def _um(x) -> float | None:
    x = float(x)
    return round(1e6 * x, 4) if np.isfinite(x) else None


def evaluate(cap: Capture, args, times: dict) -> dict:
    s = AnalyzeSettings(plots=False, crosscheck_views=0, image_poles=False)
    t = time.perf_counter()
    res = analyze_capture(cap, s)
    times["analyze"] = round(time.perf_counter() - t, 1)
    video = res.video
    if video is None or video.noise is None:
        return {"error": "the analysis has no video side (no reconstruction, or too few timesteps)"}
    nf = video.noise
    # the points the noise floor is per: the motion the analysis fitted (video_modes reads it the same way)
    measured = video.shapes_from == "measured"
    path = cap.paths.measured_motion_npz if measured else cap.paths.trajectories_npz
    motion = SurfaceMotion.read(path, min_opacity=0.0 if measured else s.min_opacity, capture_id=cap.id)
    points = motion.points_m
    if len(points) != len(nf.point_sigma_m):
        return {"error": f"{len(points)} points in {path.name}, {len(nf.point_sigma_m)} in the noise floor"}
    keep, rule = structure_mask(cap, points, s, moving=nf.moving)
    placed = [sn for sn in res.sensors if sn.position_m is not None and sn.direction is not None]
    pos = np.stack([sn.position_m for sn in placed])
    dirs = np.stack([sn.direction for sn in placed])
    t = time.perf_counter()
    bound = displacement_bound(cap, points, nf.point_sigma_m, structure=keep, noise=nf, sensors_m=pos,
                               sensor_dirs=dirs, k=s.k_neighbours, outlier_factor=s.outlier_factor)
    times["bound"] = round(time.perf_counter() - t, 2)
    fixed = displacement_bound(cap, points, nf.point_sigma_m, structure=keep, window_px=7)
    summary, fixed_summary = bound.summary(), fixed.summary()
    gain = (2 ** args.bit_depth - 1) / args.full_well_e
    ratio = summary["ratio"]
    return {
        "points": {"source": video.shapes_from, "n": int(len(points)), "structure": int(keep.sum()), "rule": rule},
        "camera_truth": {"gain_dn_per_e": gain, "read_dn": args.read_noise_e * gain},
        "camera_measured": summary["noise"],
        "views": summary["views"],
        "bound": {k: summary[k] for k in ("bound_um", "bound_axis_um", "worst_um", "n_resolved", "n_unresolved",
                                          "median_views", "window_px")},
        "measured": {"point_um": summary["measured_um"], "sigma_um": _um(nf.sigma_m),
                     "pre_impact_um": _um(nf.pre_impact_sigma_m), "static_um": _um(nf.static_sigma_m),
                     "sensor_um": [_um(x) for x in nf.sensor_sigma_m]},
        "ratio": ratio, "ratio_p10_p90": summary["ratio_p10_p90"],
        "modes": {"freq_hz": [round(float(f), 2) for f in np.abs(video.poles_rad_s.imag) / (2 * np.pi)],
                  "below_floor": [bool(b) for b in nf.below], **(summary["modes"] or {})},
        "baselines": {"single_view_um": summary["single_view_um"], "quantisation_um": summary["quantisation_um"],
                      "window_7px_um": fixed_summary["bound_um"], "window_7px_ratio": fixed_summary["ratio"]},
        "targets": {"floor_within_2x_of_bound": ratio is not None and ratio <= MAX_RATIO},
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=9)
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--pretrigger", type=int, default=16, help="frames before the trigger: the noise is measured there")
    ap.add_argument("--record-s", type=float, default=0.3)
    ap.add_argument("--fps", type=float, default=2000.0)
    ap.add_argument("--bit-depth", type=int, default=12)
    ap.add_argument("--full-well-e", type=float, default=SimCameraConfig.full_well_e)
    ap.add_argument("--read-noise-e", type=float, default=SimCameraConfig.read_noise_e)
    ap.add_argument("--width", type=int, default=128, help="the reconstruction's training width")
    ap.add_argument("--iters-t0", type=int, default=800, help="the rest fit's iterations (as bench/analysis.py; "
                    "400 leaves the arm without nodes)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--keep", type=Path, default=None, help="record the capture here, keep it, reuse what is there")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(name)s: %(message)s")
    logging.getLogger("odsplat.analysis.crlb").setLevel(logging.INFO)
    times: dict = {}
    with tempfile.TemporaryDirectory(prefix="bench-crlb-") as tmp:
        out = args.keep or Path(tmp) / "cap"
        cap = record_and_process(out, args, times)
        figures = {"bench": "crlb", **evaluate(cap, args, times), "stages_s": times,
                   "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    print(json.dumps(figures, default=float))
    return figures


if __name__ == "__main__":
    main()
