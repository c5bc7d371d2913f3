"""The paper's evaluation on hil_sim: held-out views of dynamic Gaussians against natively magnified ground truth,
for the orders of the stages.

Records a capture (force held constant take to take), syncs it, magnifies every view in 2D (phase, alpha),
estimates poses with pycolmap and the tags, trains dynamic 3D Gaussians on all views but the held-out ones,
and renders the held-out views (at their estimated poses) at every timestep, magnified by alpha. The orders:
- paper: 2D-magnified views, a fit per timestep (Luiten et al.);
- paper_learned (not run by default): the same on views magnified by the learned network (Oh et al. 2018, the
  shipped weights or `--learned-weights`): the paper's own first stage;
- modal_magnified: 2D-magnified views, the modal model (reconstruction/modal.py);
- modal_raw: the unmagnified views, the modal model, magnified in 3D at render time;
- linear_raw: the unmagnified views at full resolution, every timestep in one linear solve on a node graph
  (reconstruction/linear.py), magnified in 3D at render time;
- paper_native (a control, not run by default): the paper order on hil_sim's noise-free renders of the true
  cameras with the motion multiplied by alpha, i.e. what a perfect 2D magnifier would give.
Ground truth: hil_sim's noise-free renders from the true camera with the structure's motion multiplied by alpha.
PSNR, SSIM and L2 are taken in the structure's box (the foreground), as the paper crops; `motion` scores the motion
alone there (each render less the render at rest, against the truth less the truth at rest: `motion_scores`).
Baseline in the same run: the rest state rendered at every time (what a static reconstruction would show).
Displacement: each model's physical 3D displacement (its frames' magnification divided out) at the accelerometer and
CAN-node points (read as the analysis reads them: the inverse-distance mean of the 16 nearest opaque Gaussians less
the outliers among them) against the truth over the trained window; `dominant_amplitude` is the least-squares
coefficient of the dominant mode when the model's displacement is regressed on every mode's true contribution (1 is
exact); `point_gains`, per point, the model's motion projected on the true motion over the window;
`dominant_amplitude_plain_readout`, the baseline readout (the 8 nearest, no outlier cut). Sensitivity, each varied
on its own: training views, pose noise on the training views, rgb noise on the training images. Speed: the
rasterizer (bench/raster.py).

`--seeds N` (default 3) records N captures (seeds seed..seed+N-1); the JSON line holds each run's figures (`runs`)
and every figure's worst and median over them (`spread`, bench/spread.py: PSNR, SSIM and poses registered the
smallest, errors, L2 and times the largest, gains and amplitudes the furthest from 1).

Prints one JSON line on stdout; progress goes to stderr.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from spread import run_seeds, spread  # noqa: E402

from odsplat.analysis.analyze import AnalyzeSettings  # noqa: E402
from odsplat.analysis.ods import SurfaceMotion  # noqa: E402
from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture  # noqa: E402
from odsplat.hil_sim.camera import SimCameraConfig  # noqa: E402
from odsplat.hil_sim.render import PinholeCamera, render, to_mono  # noqa: E402
from odsplat.hil_sim.rig import RigConfig, SimRig, TakeTruth, truth_path  # noqa: E402
from odsplat.hil_sim.scene import STRUCTURE, STRUCTURE_TAG  # noqa: E402
from odsplat.processing.magnify import MagnifySettings, magnify_capture, parse_options  # noqa: E402
from odsplat.processing.metrics import psnr, ssim  # noqa: E402
from odsplat.reconstruction.dynamic import FitSettings  # noqa: E402
from odsplat.reconstruction.modal import ModalSettings  # noqa: E402
from odsplat.reconstruction.model import ReconstructSettings, pose_camera, train  # noqa: E402
from odsplat.reconstruction.pose_result import PoseResult  # noqa: E402
from odsplat.reconstruction.poses import estimate_poses  # noqa: E402
from odsplat.reconstruction.sim3 import compare_poses  # noqa: E402
from odsplat.reconstruction.views import load_views  # noqa: E402
from odsplat.spine.store import Capture  # noqa: E402
from odsplat.sync import SyncSettings, sync_capture  # noqa: E402

log = logging.getLogger("bench.reconstruct")


class GroundTruth:
    """Noise-free renders of the rig from a take's true camera, motion x alpha, at the training resolution."""

    def __init__(self, rig: SimRig, truth: TakeTruth, width_px: int, camera: SimCameraConfig):
        self.rig, self.truth = rig, truth
        w, h = (int(v) for v in truth.camera_size_px)
        self.full = PinholeCamera(K=truth.camera_K, R=truth.camera_R, t=truth.camera_t, width_px=w, height_px=h)
        self.size = (width_px, max(1, round(h * width_px / w)))
        self.camera = camera  # the capture's: its background and supersampling

    def q(self, time_s: float) -> np.ndarray:
        """Modal coordinates at time_s after the impact onset (the sync grid's times), from the take's truth."""
        tr = self.truth
        x = float(np.ravel(tr.impact_daq_sample)[0]) + time_s * tr.daq_rate_hz  # the first (only) impact
        n = tr.modal_q_daq.shape[1]
        return np.array([np.interp(x, np.arange(n), row) for row in tr.modal_q_daq])

    def image(self, time_s: float, alpha: float) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) image in [0, 1] and the structure's mask, at the training size."""
        out = render(self.rig.scene.mesh(self.q(time_s), alpha), self.full, self.rig.scene.atlas,
                     supersample=self.camera.supersample, background=self.camera.background)
        img = out.image if out.image.ndim == 2 else to_mono(out.image)
        fg = np.isin(out.object_id, (STRUCTURE, STRUCTURE_TAG)).astype(np.float32)
        small = cv2.resize(img.astype(np.float32), self.size, interpolation=cv2.INTER_AREA)
        return small, cv2.resize(fg, self.size, interpolation=cv2.INTER_AREA) > 0


def box(mask: np.ndarray, margin_px: int = 2) -> tuple[slice, slice]:
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    return (slice(max(0, ys.min() - margin_px), min(h, ys.max() + margin_px + 1)),
            slice(max(0, xs.min() - margin_px), min(w, xs.max() + margin_px + 1)))


def scores(img: np.ndarray, ref: np.ndarray, crop) -> tuple[float, float, float]:
    a, b = torch.as_tensor(img[crop]), torch.as_tensor(ref[crop])
    return psnr(a, b), ssim(a, b), float(torch.mean((a - b) ** 2))


def motion_scores(model: np.ndarray, truth: np.ndarray) -> dict:
    """The motion alone, each image less its rest image (render(t) - render(t0) against truth(t) - truth(t0)), over
    the timesteps and the structure's box pooled: PSNR against the truth's motion peak (its largest |change|, so the
    static texture both share weighs nothing), the same PSNR for a model that does not move (`still_psnr_db`, the
    baseline: the PSNR alone flatters a model that misses the motion), the truth motion's power over the error's
    (`snr_db`, 0 dB for no motion) and the correlation of the two (1: the same motion up to a scale; uncentred,
    since no change is the reference). `model`, `truth`: lists or arrays of equal-shape motion images."""
    a = np.concatenate([np.ravel(m) for m in model]).astype(float)
    b = np.concatenate([np.ravel(t) for t in truth]).astype(float)
    mse, peak = float(np.mean((a - b) ** 2)), float(np.abs(b).max(initial=0.0))
    norm = float(np.sqrt((a ** 2).sum() * (b ** 2).sum()))
    power = float(np.mean(b ** 2))

    def db(ratio: float) -> float | None:
        return float("inf") if ratio == np.inf else 10 * float(np.log10(ratio)) if ratio > 0 else None

    # A model that shows no motion at all scores still_psnr_db (most of the box barely changes, so the PSNR against
    # the peak is high for it too); snr_db is the truth motion's power over the error's: 0 dB for no motion.
    return dict(psnr_db=db(peak ** 2 / mse if mse > 0 else np.inf) if peak > 0 else None,
                still_psnr_db=db(peak ** 2 / power) if power > 0 else None,
                snr_db=db(power / mse if mse > 0 else np.inf) if power > 0 else None,
                correlation=float((a * b).sum() / norm) if norm > 0 else None, truth_peak=peak)


def surface_motion(scene) -> SurfaceMotion:
    """The model's physical motion over its Gaussians more than 30 % opaque, for reading at the sensor points."""
    opacity = scene.rest.opacities.numpy().reshape(-1)
    opaque = opacity > 0.3
    return SurfaceMotion(np.asarray(scene.times_s, float), scene.means_rest_m[opaque],
                         scene.physical_displacement_m()[:, opaque], opacity[opaque], 1.0)


def displacement_scores(scene, truth: TakeTruth, gt: GroundTruth) -> dict:
    """The model's sensor-point displacement against the truth's over the trained timesteps."""
    pts = np.asarray(truth.sensor_points_m, float)
    ok = np.all(np.isfinite(pts), axis=1)
    pts, phi = pts[ok], np.asarray(truth.sensor_mode_shapes, float)[ok]            # (S, M, 3)
    q = np.stack([gt.q(float(t)) for t in scene.times_s])                         # (T, M)
    q = q - q[:1]                                                                  # from timestep 0, as the model
    parts = np.einsum("smc,tm->mtsc", phi, q)                                       # each mode's contribution
    true = parts.sum(0)
    # Read as the analysis reads it (AnalyzeSettings' neighbours and outlier cut); the baseline readout is the
    # inverse-distance mean of the 8 nearest with no outlier cut.
    motion = surface_motion(scene)
    model = motion.at_points(pts, k=AnalyzeSettings.k_neighbours, outlier_factor=AnalyzeSettings.outlier_factor)
    plain = motion.at_points(pts, k=8, outlier_factor=None)
    energy = (parts ** 2).sum(axis=(1, 2, 3))
    dom = int(np.argmax(energy))
    basis = parts.reshape(len(parts), -1).T
    a, *_ = np.linalg.lstsq(basis, model.ravel(), rcond=None)
    a_plain, *_ = np.linalg.lstsq(basis, plain.ravel(), rcond=None)
    # per point: the model's motion projected on the true motion, over the window (1 is exact)
    gains = (model * true).sum(axis=(0, 2)) / np.maximum((true ** 2).sum(axis=(0, 2)), 1e-30)
    return dict(n_points=int(len(pts)), dominant_mode=dom, dominant_share=float(energy[dom] / energy.sum()),
                dominant_amplitude=float(a[dom]), dominant_amplitude_plain_readout=float(a_plain[dom]),
                point_gains=[float(g) for g in gains],
                rms_ratio=float(np.sqrt((model ** 2).sum() / (true ** 2).sum())),
                rel_error=float(np.linalg.norm(model - true) / np.linalg.norm(true)),
                peak_true_m=float(np.linalg.norm(true, axis=-1).max()))


def evaluate(model, poses: PoseResult, holdout: list[str], gts: dict[str, GroundTruth], alpha: float,
             width_px: int) -> dict:
    """PSNR/SSIM/L2 of held-out renders (and of the rest state held still) in the foreground box, over timesteps."""
    scene = model.scene()
    rows = {"dynamic": [], "rest": [], "truth_still": []}
    moved, moved_true = [], []                     # the motion images, the model's and the truth's (motion_scores)
    for name in holdout:
        cam = pose_camera(poses, name, width_px)
        ref0, mask0 = gts[name].image(float(scene.times_s[0]), alpha)
        still = scene.render(cam, float(scene.times_s[0]), alpha=alpha)[..., 0]
        for t in scene.times_s:
            ref, mask = gts[name].image(float(t), alpha)
            crop = box(mask0 | mask, 3)
            # The truth's own rest state against its moving state: how much the motion weighs in these metrics.
            rows["truth_still"].append(scores(ref0, ref, crop))
            rows["rest"].append(scores(still, ref, crop))
            img = scene.render(cam, float(t), alpha=alpha)[..., 0]
            rows["dynamic"].append(scores(img, ref, crop))
            if t != scene.times_s[0]:
                moved.append(np.asarray(img[crop], float) - np.asarray(still[crop], float))
                moved_true.append(np.asarray(ref[crop], float) - np.asarray(ref0[crop], float))
    out = {}
    for kind, r in rows.items():
        r = np.array(r)
        finite = np.isfinite(r[:, 0])
        out[kind] = dict(psnr_db=float(r[finite, 0].mean()) if finite.any() else float("inf"),
                         ssim=float(r[:, 1].mean()), l2=float(r[:, 2].mean()))
    out["motion"] = motion_scores(moved, moved_true) if moved else None
    name = holdout[0]
    out["displacement"] = displacement_scores(scene, gts[name].truth, gts[name])
    return out


def perturb_poses(poses: PoseResult, names: list[str], trans_mm: float, rot_deg: float, seed: int) -> PoseResult:
    """Random pose errors on `names`: a rotation of rot_deg about a random axis, a shift of trans_mm of the centre."""
    rng = np.random.default_rng(seed)
    views = []
    for v in poses.views:
        if v.name in names and (trans_mm or rot_deg):
            axis = rng.standard_normal(3)
            dR = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(rot_deg))[0]
            d = rng.standard_normal(3)
            c = v.center_m + d / np.linalg.norm(d) * trans_mm * 1e-3
            R = dR @ v.R
            v = dataclasses.replace(v, R=R, t=-R @ c)
        views.append(v)
    return dataclasses.replace(poses, views=views)


def native_frames(vs, truths: dict[str, TakeTruth], rig: SimRig, camera: SimCameraConfig, alpha: float) -> None:
    """Replace every training view's frames by hil_sim's noise-free renders of its true camera with the motion
    multiplied by alpha: what a perfect 2D magnifier would give (a control for the magnifier's share of the error)."""
    for v in vs.views:
        gt = GroundTruth(rig, truths[v.name], v.camera.width_px, camera)
        imgs = np.stack([gt.image(float(t), alpha)[0] for t in vs.times_s])[..., None]
        v.images = torch.as_tensor(imgs, dtype=v.images.dtype)
        v.rest = v.images[0]
    vs.source_alpha = alpha


def run_config(capture, poses, settings: ReconstructSettings, holdout, gts, alpha, *, train_names=None,
               rgb_noise=0.0, seed=0, native: dict | None = None) -> dict:
    vs = load_views(capture, poses, source=settings.source, width_px=settings.width_px,
                    n_timesteps=settings.n_timesteps, step=settings.step, holdout=tuple(holdout), use_static=False)
    if native is not None:
        native_frames(vs, native["truths"], native["rig"], native["camera"], alpha)
    if train_names is not None:
        vs.views = [v for v in vs.views if v.name in train_names]
    if rgb_noise:
        gen = torch.Generator().manual_seed(seed)
        for v in vs.views:
            v.images = (v.images + rgb_noise * torch.randn(v.images.shape, generator=gen)).clamp(0, 1)
    t0 = time.perf_counter()
    model = train(vs, poses, settings, capture)
    seconds = time.perf_counter() - t0
    res = evaluate(model, poses, holdout, gts, alpha, settings.width_px)
    res.update(n_views=len(vs.views), n_gaussians=len(model.g0), train_s=seconds,
               t0_s=model.stats_t0["seconds"], dynamic_s=model.seconds_dynamic)
    source = "native renders" if native is not None else settings.source
    print(f"  {settings.motion} on {source}, {len(vs.views)} views, rgb noise {rgb_noise}: held-out PSNR "
          f"{res['dynamic']['psnr_db']:.2f} dB (rest {res['rest']['psnr_db']:.2f}), motion alone "
          f"{(res['motion'] or {}).get('psnr_db')} dB, dominant mode amplitude "
          f"{res['displacement']['dominant_amplitude']:.3f}, in {seconds:.0f} s", file=sys.stderr)
    return res


ORDERS = {  # name: (training frames, motion model)
    "paper": ("magnified/phase", "timestep"),
    "paper_learned": ("magnified/learned", "timestep"),
    "modal_magnified": ("magnified/phase", "modal"),
    "modal_raw": ("sync", "modal"),
    "linear_raw": ("sync", "linear"),
    # control: the paper order on natively magnified renders of the true cameras (a perfect 2D magnifier)
    "paper_native": ("magnified/phase", "timestep"),
}
DEFAULT_ORDERS = ("paper", "modal_magnified", "modal_raw", "linear_raw")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=27, help="training views (3 more are recorded and held out)")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--timesteps", type=int, default=32)
    ap.add_argument("--step", type=int, default=2)
    ap.add_argument("--alpha", type=float, default=30.0)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--iters-t0", type=int, default=1500)
    ap.add_argument("--iters-step", type=int, default=60, help="per timestep (paper order)")
    ap.add_argument("--iters-modal", type=int, default=2000)
    ap.add_argument("--prior-fraction", type=float, default=FitSettings.prior_fraction,
                    help="of the neighbourhoods each per-timestep iteration evaluates (FitSettings.prior_fraction)")
    ap.add_argument("--orders", default=",".join(DEFAULT_ORDERS), help=f"comma-separated, of {', '.join(ORDERS)}")
    ap.add_argument("--sensitivity", action="store_true",
                    help="also vary views, pose noise and rgb noise (for the first of --orders)")
    ap.add_argument("--magnify-option", action="append", default=[], metavar="KEY=VALUE",
                    help="a keyword of the phase magnifier, e.g. warp=true (repeatable)")
    ap.add_argument("--learned-weights", type=Path, default=None,
                    help="the learned magnifier's weights for paper_learned (default: the shipped ones)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--keep", type=Path, default=None, help="record the capture here and keep it")
    ap.add_argument("--seeds", type=int, default=3,
                    help="captures recorded with seeds seed..seed+N-1; the JSON line gives each figure's worst and "
                         "median over them")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    seeds = [args.seed + i for i in range(args.seeds)]
    runs = run_seeds(args, seeds, run_seed, "bench-recon-")
    figures = {"bench": "reconstruct", "seeds": seeds, "spread": spread(runs), "runs": runs}
    print(json.dumps(figures, default=float))
    return figures


def run_seed(args, out: Path) -> dict:
    """One capture recorded with args.seed through the stages and every order; its figures."""
    n_total = args.views + 3
    rig = SimRig(config=RigConfig(seed=args.seed))    # the rig's seed: its DAQ, hammer and camera noise
    t = time.perf_counter()
    camera = SimCameraConfig(fps=2000.0)
    if not (out / "capture.json").exists():
        simulate_capture(out, n_views=n_total, n_frames=args.frames, pretrigger_frames=6, record_s=0.1,
                         settings=SimBenchSettings(camera=camera, force_scatter=0.0,
                                                   seed=args.seed), rig=rig)
    figures: dict = {"record_s": time.perf_counter() - t}
    cap = Capture.open(out)
    t = time.perf_counter()
    if not cap.paths.sync_json.exists():
        sync_capture(cap, SyncSettings())
    if not cap.paths.magnified_dir("phase").exists():
        magnify_capture(cap, MagnifySettings(method="phase", alpha=args.alpha, every_view=True,
                                             options=parse_options(args.magnify_option)), progress=False)
    if "paper_learned" in args.orders and not cap.paths.magnified_dir("learned").exists():
        learned = (("weights", str(args.learned_weights)),) if args.learned_weights is not None else ()
        magnify_capture(cap, MagnifySettings(method="learned", alpha=args.alpha, every_view=True, options=learned),
                        progress=False)
    figures["sync_magnify_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if cap.paths.poses_json.exists():
        poses = PoseResult.read(cap)
    else:
        poses = estimate_poses(cap)
        poses.write(cap)
        figures["poses_s"] = time.perf_counter() - t
    names = [v.name for v in poses.views if v.kind == "take"]
    truth = {n: TakeTruth.load(truth_path(cap.takes_dir / f"{n}.h5")) for n in names}
    acc = compare_poses(poses.poses(), {n: (tr.camera_R, tr.camera_t) for n, tr in truth.items()})
    figures["poses"] = dict(method=poses.method, registered=poses.registered, n_images=poses.n_images,
                            rotation_rms_deg=acc.rotation_rms_deg, rotation_max_deg=acc.rotation_max_deg,
                            center_rms_mm=acc.center_rms_mm, center_max_mm=acc.center_max_mm)
    holdout = names[1::max(1, len(names) // 3)][:3]
    train_names = [n for n in names if n not in holdout]
    gts = {n: GroundTruth(rig, truth[n], args.width, camera) for n in holdout}
    fit = FitSettings(iters_t0=args.iters_t0, iters_per_step=args.iters_step, prior_fraction=args.prior_fraction,
                      seed=args.seed, progress=False)
    modal = ModalSettings(iters=args.iters_modal, seed=args.seed, progress=False)
    print(f"{len(train_names)} training views, held out {holdout}", file=sys.stderr)
    orders = [o.strip() for o in args.orders.split(",") if o.strip()]
    configs = {name: ReconstructSettings(source=ORDERS[name][0], width_px=args.width, n_timesteps=args.timesteps,
                                         step=args.step, use_static=False, motion=ORDERS[name][1], fit=fit,
                                         modal=modal) for name in orders}
    native = dict(truths=truth, rig=rig, camera=camera)
    figures["orders"] = {name: run_config(cap, poses, cfg, holdout, gts, args.alpha,
                                          native=native if name == "paper_native" else None)
                         for name, cfg in configs.items()}
    base = configs[orders[0]]
    if args.sensitivity:
        # Cheaper fits for the sweep (half the timesteps, half the t=0 iterations): compare within the sweep.
        quick = dataclasses.replace(base, n_timesteps=max(4, args.timesteps // 2),
                                    fit=dataclasses.replace(fit, iters_t0=args.iters_t0 // 2))
        rng = np.random.default_rng(args.seed)
        sens: dict = {"views": {}, "pose_noise": {}, "rgb_noise": {}}
        for n in sorted({3, 9, len(train_names)}):
            pick = list(rng.choice(train_names, size=min(n, len(train_names)), replace=False))
            sens["views"][str(n)] = run_config(cap, poses, quick, holdout, gts, args.alpha, train_names=pick)
        for mm, deg in ((5.0, 0.5), (20.0, 2.0)):
            noisy = perturb_poses(poses, train_names, mm, deg, args.seed)
            sens["pose_noise"][f"{mm:g}mm_{deg:g}deg"] = run_config(cap, noisy, quick, holdout, gts, args.alpha)
        for sd in (0.01, 0.05):
            sens["rgb_noise"][f"{sd:g}"] = run_config(cap, poses, quick, holdout, gts, args.alpha, rgb_noise=sd,
                                                      seed=args.seed)
        figures["sensitivity"] = sens
    figures.update(settings=dict(views=args.views, frames=args.frames, timesteps=args.timesteps, step=args.step,
                                 alpha=args.alpha, width_px=args.width, iters_t0=args.iters_t0,
                                 iters_step=args.iters_step, iters_modal=args.iters_modal,
                                 prior_fraction=args.prior_fraction, threads=args.threads,
                                 magnify_options=args.magnify_option, seed=args.seed,
                                 learned_weights=str(args.learned_weights) if args.learned_weights else None))
    return figures


if __name__ == "__main__":
    main()
