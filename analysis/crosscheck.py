"""The 3D motion checked against single views: the video's surface motion projected into a take's camera, and
the same points tracked in 2D in that take's synced (unmagnified) frames. Gain 1 means the 3D reconstruction
moves as much as the images show; it is independent of the 2D magnifier and of the Gaussians' fit."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from odsplat.reconstruction import PoseResult
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, load_sync

from .ods import SurfaceMotion
from .tracking import project_displacement, track_points

log = logging.getLogger(__name__)

DEPTH_TOL_M = 0.01     # a point is visible when within this of the nearest surface point on its pixel


@dataclass(frozen=True)
class ViewCheck:
    take: str
    n_points: int
    gain: float            # tracked / projected 3D motion, least squares over every point and time, divided by
                           # force_ratio (the 3D motion is the takes' mean; this take was hit a little harder or softer)
    correlation: float     # between the two, every point and time
    motion_rms_px: float   # rms of the projected 3D motion: how much there was to see
    residual_rms_px: float  # rms of tracked - gain x projected
    force_ratio: float = 1.0  # this take's impulse (as synced) / the synced takes' mean
    noise_px: float = float("nan")  # the tracks' rms on the same points before the impact, where nothing moves
    #                                 (NaN: fewer than 3 frames there)

    @property
    def expected_correlation(self) -> float:
        """The correlation an exact 3D motion would reach against tracks this noisy: m / sqrt(m^2 + noise^2)."""
        m, n = self.motion_rms_px, self.noise_px
        return float(m / np.hypot(m, n)) if np.isfinite(n) and m > 0 else float("nan")


def _poses(capture: Capture) -> dict[str, dict] | None:
    """The pose stage's cameras by take name (read through its contract, `PoseResult.read`); None when the capture
    has no poses.json. A poses file that is there but unreadable, damaged or another capture's is refused with its
    one line, never taken for no poses."""

    if not capture.paths.poses_json.exists():
        return None
    return {v.name: {"K": v.K, "R": v.R, "t": v.t} for v in PoseResult.read(capture).views}


def views_seeing(capture: Capture, points_m: np.ndarray) -> np.ndarray | None:
    """(N,) how many posed views hold each point inside their frame, in front of the camera (occlusion aside);
    None without poses. On the demo the floor's far edges are in 28-48 % fewer views than the structure."""
    poses = _poses(capture)
    if poses is None:
        log.info("no view coverage: %s not found", capture.paths.poses_json)
        return None
    cam = capture.manifest.camera
    pts = np.asarray(points_m, float).reshape(-1, 3)
    count = np.zeros(len(pts), int)
    for p in poses.values():
        K = np.asarray(p["K"], float)
        w, h = (cam.width_px, cam.height_px) if cam.width_px and cam.height_px else (2 * K[0, 2], 2 * K[1, 2])
        pc, uv = _to_pixels(pts, K, p["R"], p["t"])
        count += (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return count


def _to_pixels(points_m: np.ndarray, K, R, t) -> tuple[np.ndarray, np.ndarray]:
    """World points in a camera's frame (N, 3) and on its pixels (N, 2); those behind it get finite nonsense."""
    cam = np.asarray(points_m, float) @ np.asarray(R, float).T + np.asarray(t, float).reshape(3)
    z = cam[:, 2:3]
    return cam, (cam @ np.asarray(K, float).T)[:, :2] / np.where(z > 0, z, 1.0)


def _structure_box(points_m: np.ndarray, K, R, t, shape: tuple[int, int], pad_px: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the pixels of a frame of `shape` that the points in front of the camera fall on, padded;
    the whole frame when none do."""
    cam, uv = _to_pixels(points_m, K, R, t)
    h, w = shape
    on = (cam[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not on.any():
        return 0, h, 0, w
    lo, hi = np.floor(uv[on].min(axis=0)).astype(int) - pad_px, np.ceil(uv[on].max(axis=0)).astype(int) + pad_px
    return max(lo[1], 0), min(hi[1] + 1, h), max(lo[0], 0), min(hi[0] + 1, w)


def _visible(points_cam: np.ndarray, uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Points nearest the camera on their pixel (a z-buffer over the surface points, 3x3 neighbourhood)."""
    h, w = shape
    px = np.round(uv).astype(int)
    inside = (points_cam[:, 2] > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    zbuf = np.full((h + 2, w + 2), np.inf)
    z = points_cam[:, 2]
    np.minimum.at(zbuf, (px[inside, 1] + 1, px[inside, 0] + 1), z[inside])
    near = np.min(np.stack([zbuf[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]),
                  axis=0)
    vis = np.zeros(len(z), bool)
    vis[inside] = z[inside] <= near[px[inside, 1], px[inside, 0]] + DEPTH_TOL_M
    return vis


def _spread(order: np.ndarray, uv: np.ndarray, n: int, min_dist_px: float) -> np.ndarray:
    """Up to n of the indices in `order` (best first), at least min_dist_px apart in the image."""
    chosen: list[int] = []
    for i in order:
        if all(np.hypot(*(uv[i] - uv[j])) >= min_dist_px for j in chosen):
            chosen.append(int(i))
            if len(chosen) == n:
                break
    return np.array(chosen, int)


def check_view(frames: np.ndarray, frame_times_s: np.ndarray, motion: SurfaceMotion, K, R, t, *, take: str = "",
               n_points: int = 30, window_px: int = 15, method: str = "gradient",
               force_ratio: float = 1.0, k: int = 16, outlier_factor: float | None = 2.0) -> ViewCheck | None:
    """Compare one take's synced frames (T', H, W) at frame_times_s with the motion projected into its camera.
    The motion at each visible surface point is read as at the sensors (`SurfaceMotion.at_points` with k and
    outlier_factor); the n_points that move most, a window apart, are tracked."""
    K, R, t = (np.asarray(a, float) for a in (K, R, t))
    pick = np.array([int(np.argmin(np.abs(frame_times_s - ti))) for ti in motion.times_s])
    if np.max(np.abs(frame_times_s[pick] - motion.times_s)) > 1e-6 + 0.01 * np.median(np.diff(frame_times_s)):
        raise InputError(f"{take}: times_s", "the synced frames do not hold the reconstruction's timesteps")
    cam, uv = _to_pixels(motion.points_m, K, R, t)
    h, w = frames.shape[1:3]
    margin = window_px // 2 + 3
    ok = _visible(cam, uv, (h, w)) & (uv[:, 0] >= margin) & (uv[:, 0] < w - margin) & (uv[:, 1] >= margin) \
        & (uv[:, 1] < h - margin)
    if ok.sum() < 3:
        log.warning("%s: fewer than 3 visible surface points; no cross-check", take)
        return None
    idx = np.flatnonzero(ok)
    # each point's motion as its neighbours agree on it (as at the sensors): the points that move most in a real
    # reconstruction are otherwise the few Gaussians that wandered off
    disp = motion.at_points(motion.points_m[idx], k=k, outlier_factor=outlier_factor)
    proj = project_displacement(disp, motion.points_m[idx], K, R, t)                               # (T, n, 2)
    proj = proj - proj[:1]
    strongest = np.argsort(-np.sqrt(np.mean(proj ** 2, axis=(0, 2))))
    sel = _spread(strongest, uv[idx], n_points, window_px)
    tracks = track_points(frames[pick], uv[idx][sel], method=method, window_px=window_px)
    d_tr, d_pr = tracks.displacement_px, proj[:, sel]
    good = np.all(np.isfinite(d_tr), axis=(0, 2))
    if good.sum() < 3:
        log.warning("%s: fewer than 3 trackable points; no cross-check", take)
        return None
    a, b = d_tr[:, good].ravel(), d_pr[:, good].ravel()
    b = b * force_ratio
    gain, corr = gain_correlation(a, b)
    return ViewCheck(take, int(good.sum()), gain, corr, float(np.sqrt(np.mean(b ** 2))),
                     float(np.sqrt(np.mean((a - gain * b) ** 2))), float(force_ratio),
                     track_noise(frames, frame_times_s, uv[idx][sel][good], method, window_px))


def gain_correlation(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The least-squares gain of a on b (a = gain b) and their correlation (NaN where either is constant)."""
    gain = float(a @ b / max(b @ b, 1e-300))
    corr = float(np.corrcoef(a, b)[0, 1]) if np.std(a) > 0 and np.std(b) > 0 else float("nan")
    return gain, corr


def track_noise(frames: np.ndarray, frame_times_s: np.ndarray, uv: np.ndarray, method: str, window_px: int) -> float:
    """The tracks' rms displacement over the frames before the impact (t < 0), against the first of them: what
    the trackers read where nothing moves. NaN with fewer than 3 such frames."""
    pre = np.flatnonzero(np.asarray(frame_times_s) < 0)
    if len(pre) < 3:
        return float("nan")
    d = track_points(frames[pre], uv, method=method, window_px=window_px).displacement_px[1:]
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d ** 2))) if d.size else float("nan")


@dataclass(frozen=True)
class PosedTakes:
    """Synced takes with aligned frames and a pose, up to a number spread evenly over the capture, and each one's
    hit against the synced takes' mean (the 3D motion is their mean: a take hit harder moves more)."""

    sync: Any                       # odsplat.sync.SyncResult
    poses: dict[str, dict]          # by take name: K, R, t
    takes: list                     # the chosen odsplat.sync.TakeSync
    force_ratio: dict[str, float]   # impulse (as synced) / the synced takes' mean; 1 where unknown


def posed_takes(capture: Capture, max_views: int) -> PosedTakes | None:
    """Up to max_views synced takes with aligned frames and a pose, spread over the capture; None where the capture
    has no poses.json (one that is there must read) or no such take."""
    poses = _poses(capture)
    if poses is None:
        log.info("no 2D check: %s not found", capture.paths.poses_json)
        return None
    sync = load_sync(capture)
    takes = [tk for tk in sync.ok if tk.aligned_file and tk.name in poses
             and capture.paths.listed(tk.aligned_file).is_file()]
    if not takes:
        log.info("no 2D check: no synced take has aligned frames and a pose")
        return None
    impulse = {tk.name: (tk.impulse_n_s or np.nan) * (tk.impulse_scale or 1.0) for tk in sync.ok}
    mean_impulse = float(np.nanmean(list(impulse.values())))
    chosen = [takes[int(i)] for i in np.unique(np.linspace(0, len(takes) - 1, min(max_views, len(takes))).round())]
    ratio = {tk.name: float(np.nan_to_num(impulse[tk.name] / mean_impulse, nan=1.0)) for tk in chosen}
    return PosedTakes(sync, poses, chosen, ratio)


def box_frames(capture: Capture, posed: PosedTakes, take, points_m: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """A posed take's aligned frames (mono) in the box of the points (`_structure_box`, padded: sync filters only
    the pixels it is asked for, so memory is the box's), their times, the camera K moved to the box, and the box
    (y0, y1, x0, x1)."""
    p = posed.poses[take.name]
    with AlignedTake(capture, capture.paths.listed(take.aligned_file), posed.sync.generation) as ff:
        y0, y1, x0, x1 = _structure_box(points_m, p["K"], p["R"], p["t"], ff.frame_shape[:2], pad_px=32)

        def box(frame: np.ndarray, y0=y0, y1=y1, x0=x0, x1=x1) -> np.ndarray:
            frame = frame[y0:y1, x0:x1]
            return frame.mean(axis=-1) if frame.ndim == 3 else frame

        frames, times = ff.read_frames(spatial=box), ff.times_s
    K = np.asarray(p["K"], float).copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return frames, times, K, (y0, y1, x0, x1)


def crosscheck_views(capture: Capture, motion: SurfaceMotion, *, max_views: int = 6, n_points: int = 30,
                     method: str = "gradient", k: int = 16, outlier_factor: float | None = 2.0) -> list[ViewCheck]:
    """check_view on up to max_views synced takes spread over the capture (those with aligned frames and a
    pose); none when the capture has no aligned frames or no poses.json (one that is there must read)."""
    posed = posed_takes(capture, max_views)
    if posed is None:
        return []
    out = []
    for tk in posed.takes:
        frames, times, K, _ = box_frames(capture, posed, tk, motion.points_m)
        p = posed.poses[tk.name]
        check = check_view(frames, times, motion, K, p["R"], p["t"], take=tk.name, n_points=n_points,
                           method=method, force_ratio=posed.force_ratio[tk.name], k=k, outlier_factor=outlier_factor)
        if check is not None:
            log.info("%s: gain %.3f, correlation %.3f over %d points (%.3f px rms)", tk.name, check.gain,
                     check.correlation, check.n_points, check.motion_rms_px)
            out.append(check)
    return out
