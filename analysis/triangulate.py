"""Several views, still 2D (after Gorjup et al. 2019, "Still-camera multiview spectral optical flow imaging for 3D
operating-deflection-shape identification"): surface points tracked in 2D in several posed, synced views,
triangulated to 3D motion by the cameras' projection Jacobians, as a check of the Gaussians' 3D motion and shapes
that owes them nothing but where the points are.

Each view v sees a point's 3D displacement D(t) to first order as d_v(t) = J_v D(t) (J_v: the pinhole's 2x3
Jacobian at the point, `crlb.projection_jacobian`); the takes are different hits of one linear structure, locked to
their impacts by sync, so each view's track is divided by its hit's impulse over the mean. With three views or more
on a point, D(t) is their least-squares solution. Each mode's 3D shape at the points then comes from the same
decay fit, at the same poles, as the Gaussians' (`ods.fit_decay`), and the two are compared by MAC and scale."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from odsplat.spine.store import Capture

from .correlation import mac, modal_scale_factor
from .crlb import projection_jacobian
from .crosscheck import PosedTakes, _to_pixels, _visible, box_frames, gain_correlation, posed_takes, track_noise
from .ods import SurfaceMotion, fit_decay
from .tracking import track_points

log = logging.getLogger(__name__)

MIN_VIEWS = 3          # views that must track a point for it to be triangulated
MIN_SPACING_M = 0.02   # between the points chosen
MAX_CONDITION = 50.0   # a point whose stacked Jacobian is worse conditioned than this is left out


@dataclass(frozen=True)
class Triangulation:
    """The triangulated points' 3D motion against the Gaussians' at the same points."""

    n_points: int
    n_views: int
    views_per_point: float       # median views that tracked a point
    gain: float                  # triangulated / Gaussians' motion, least squares over points, axes and time
    correlation: float
    motion_rms_m: float          # the Gaussians' motion at the points (how much there was to see)
    residual_rms_m: float        # triangulated - gain x Gaussians'
    mode_mac: tuple[float, ...]  # per fitted mode: MAC of the triangulated 3D shape against the Gaussians'
    mode_scale: tuple[float, ...]  # and the modal scale factor (triangulated over Gaussians')
    condition_median: float      # of the points' stacked Jacobians
    motion_px: float = float("nan")  # the Gaussians' motion at the points as the views see it (rms, px)
    noise_px: float = float("nan")   # the tracks' rms before the impact, where nothing moves (median over views)

    @property
    def expected_correlation(self) -> float:
        """The correlation exact 3D motion would reach against tracks this noisy: m / sqrt(m^2 + noise^2)."""
        m, n = self.motion_px, self.noise_px
        return float(m / np.hypot(m, n)) if np.isfinite(n) and m > 0 else float("nan")


def triangulate(tracks: list[np.ndarray], jacobians: list[np.ndarray], min_views: int = MIN_VIEWS
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3D displacements (T, P, 3) from each view's 2D tracks (T, P, 2) (NaN where the view does not track the
    point) and projection Jacobians (P, 2, 3): least squares over the views that track each point; NaN for points
    tracked by fewer than min_views. Also each point's view count (P,) and its stacked Jacobian's condition (P,)."""
    T, P = tracks[0].shape[:2]
    out = np.full((T, P, 3), np.nan)
    count = np.zeros(P, int)
    cond = np.full(P, np.inf)
    for p in range(P):
        seen = [v for v in range(len(tracks)) if np.isfinite(tracks[v][:, p]).all()]
        count[p] = len(seen)
        if len(seen) < min_views:
            continue
        A = np.concatenate([jacobians[v][p] for v in seen])                    # (2V, 3)
        b = np.concatenate([tracks[v][:, p] for v in seen], axis=1)            # (T, 2V)
        cond[p] = float(np.linalg.cond(A))
        out[:, p] = np.linalg.lstsq(A, b.T, rcond=None)[0].T
    return out, count, cond


def _candidates(motion: SurfaceMotion, n: int, k: int, outlier_factor: float | None) -> np.ndarray:
    """The surface points that move most (as read at the sensors), MIN_SPACING_M apart: up to n of them."""
    disp = motion.at_points(motion.points_m, k=k, outlier_factor=outlier_factor)        # (T, N, 3)
    order = np.argsort(-np.sqrt(np.nanmean((disp - disp[:1]) ** 2, axis=(0, 2))))
    chosen: list[int] = []
    for i in order:
        p = motion.points_m[i]
        if all(np.linalg.norm(motion.points_m[j] - p) >= MIN_SPACING_M for j in chosen):
            chosen.append(int(i))
            if len(chosen) == n:
                break
    return np.asarray(chosen, int)


def _view_tracks(capture: Capture, posed: PosedTakes, take, motion: SurfaceMotion, points_m: np.ndarray,
                 window_px: int, method: str) -> tuple[np.ndarray, np.ndarray, float]:
    """One view's tracks (T, P, 2) at the motion's timesteps (NaN where the point is not visible or lost), its
    Jacobians (P, 2, 3), and its tracks' noise before the impact (`crosscheck.track_noise`)."""
    frames, times, K, (y0, y1, x0, x1) = box_frames(capture, posed, take, points_m)
    pose = posed.poses[take.name]
    R, t = np.asarray(pose["R"], float), np.asarray(pose["t"], float)
    pick = np.array([int(np.argmin(np.abs(times - ti))) for ti in motion.times_s])
    cam, uv = _to_pixels(points_m, K, R, t)                                     # in the box's pixels
    # visible: in front, in the box, and the nearest surface point on its pixel (the Gaussians' own occlusion)
    vis_all = _visible(*_to_pixels(motion.points_m, K, R, t), (y1 - y0, x1 - x0))
    near = np.array([int(np.argmin(np.linalg.norm(motion.points_m - p, axis=1))) for p in points_m])
    margin = window_px // 2 + 3
    ok = vis_all[near] & (uv[:, 0] >= margin) & (uv[:, 0] < x1 - x0 - margin) & (uv[:, 1] >= margin) \
        & (uv[:, 1] < y1 - y0 - margin) & (cam[:, 2] > 0)
    out = np.full((len(pick), len(points_m), 2), np.nan)
    noise = float("nan")
    if ok.sum():
        tr = track_points(frames[pick], uv[ok], method=method, window_px=window_px).displacement_px
        out[:, ok] = tr - tr[:1]
        noise = track_noise(frames, times, uv[ok], method, window_px)
    return out, projection_jacobian(points_m, K, R, t), noise


def triangulation_check(capture: Capture, motion: SurfaceMotion, poles_rad_s: np.ndarray, *, max_views: int = 8,
                        n_points: int = 24, window_px: int = 15, method: str = "gradient", k: int = 16,
                        outlier_factor: float | None = 2.0, t_min_s: float = 0.0) -> Triangulation | None:
    """Track up to n_points of the surface in up to max_views synced, posed takes spread over the capture
    (`crosscheck.posed_takes`), triangulate them, and compare with the Gaussians' motion there (see the module's
    doc); None where fewer than 3 points are seen by MIN_VIEWS views."""
    posed = posed_takes(capture, max_views)
    if posed is None or len(posed.takes) < MIN_VIEWS:
        return None
    idx = _candidates(motion, 3 * n_points, k, outlier_factor)
    points = motion.points_m[idx]
    tracks, jacobians, noises = [], [], []
    for tk in posed.takes:
        d, J, noise = _view_tracks(capture, posed, tk, motion, points, window_px, method)
        tracks.append(d / posed.force_ratio[tk.name])
        jacobians.append(J)
        noises.append(noise)
    tri, count, cond = triangulate(tracks, jacobians)
    good = np.isfinite(tri).all(axis=(0, 2)) & (cond <= MAX_CONDITION)
    good &= np.cumsum(good) <= n_points
    if good.sum() < 3:
        log.info("triangulation: %d points seen by %d views or more; no check", int(good.sum()), MIN_VIEWS)
        return None
    ref = motion.at_points(points[good], k=k, outlier_factor=outlier_factor)                 # (T, P, 3)
    ref = ref - ref[:1]
    a, b = tri[:, good].ravel(), ref.ravel()
    gain, corr = gain_correlation(a, b)
    T = len(motion.times_s)
    fit_tri = fit_decay(motion.times_s, tri[:, good].reshape(T, -1), poles_rad_s, t_min_s=t_min_s).amplitudes
    fit_ref = fit_decay(motion.times_s, ref.reshape(T, -1), poles_rad_s, t_min_s=t_min_s).amplitudes
    macs = tuple(float(mac(fit_tri[r], fit_ref[r])[0, 0]) for r in range(len(poles_rad_s)))
    scales = tuple(float(np.abs(modal_scale_factor(fit_tri[r], fit_ref[r])[0])) for r in range(len(poles_rad_s)))
    seen = [np.einsum("pij,tpj->tpi", J[good], ref) for J in jacobians]                 # (T, P, 2) per view
    motion_px = float(np.sqrt(np.mean([np.mean(v ** 2) for v in seen])))
    noise_px = float(np.nanmedian(noises)) if np.isfinite(noises).any() else float("nan")
    out = Triangulation(int(good.sum()), len(posed.takes), float(np.median(count[good])), gain, corr,
                        float(np.sqrt(np.mean(b ** 2))), float(np.sqrt(np.mean((a - gain * b) ** 2))), macs, scales,
                        float(np.median(cond[good])), motion_px, noise_px)
    log.info("triangulation: %d points in %d views: gain %.3f, correlation %.3f (%.3f expected from %.4f px of "
             "motion over %.4f px of track noise), mode MAC %s", out.n_points, out.n_views, gain, corr,
             out.expected_correlation, motion_px, noise_px, [round(m, 3) for m in macs])
    return out


__all__ = ["MIN_VIEWS", "Triangulation", "triangulate", "triangulation_check"]
