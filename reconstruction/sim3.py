"""Similarity transforms: the robust Sim3 fit (least median of squares, then Umeyama) that puts SfM's model in the
tag layout's metric frame, and `compare_poses`, estimated poses against reference poses."""
from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.geometry import camera_center_m, rotation_angle_deg

MIN_SIM3_VIEWS = 3           # a similarity needs three non-collinear camera centres
_MAX_SIM3_HYPOTHESES = 2000  # LMedS tries every triple below this many, a random sample above
_LMEDS_INLIER_SIGMAS = 2.5   # inlier threshold in robust standard deviations of the best hypothesis


@dataclass
class PoseAccuracy:
    """Estimated poses against reference poses: rotation angle and camera-centre distance per view."""

    rotation_deg: dict[str, float]
    center_mm: dict[str, float]
    rotation_rms_deg: float
    rotation_max_deg: float
    center_rms_mm: float
    center_max_mm: float
    missing: list[str]            # in the reference, not estimated

    def summary(self) -> str:
        return (f"{len(self.rotation_deg)} views: rotation {self.rotation_rms_deg:.3f} deg rms "
                f"({self.rotation_max_deg:.3f} max), centre {self.center_rms_mm:.2f} mm rms "
                f"({self.center_max_mm:.2f} max)"
                + (f"; not estimated: {', '.join(self.missing)}" if self.missing else ""))


@dataclass
class Sim3:
    """X_dst = scale R X_src + t, fitted to matched points with outliers left out."""

    scale: float
    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray      # (N,) bool
    residuals_m: np.ndarray  # (N,) distance of each transformed source point from its target
    residual_m: float        # RMS over the inliers

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points, float) @ self.R.T + self.t


def compare_poses(estimated: Mapping[str, tuple[Any, Any]], truth: Mapping[str, tuple[Any, Any]]) -> PoseAccuracy:
    """Per view present in both: angle of R_est R_true^T and distance between the camera centres (mm)."""
    common = [name for name in truth if name in estimated]
    if not common:
        raise InputError("compare_poses", f"no view in common: estimated {sorted(estimated)}, truth {sorted(truth)}")
    rot, mm = {}, {}
    for name in common:
        (R_e, t_e), (R_t, t_t) = estimated[name], truth[name]
        rot[name] = rotation_angle_deg(R_e, R_t)
        mm[name] = 1e3 * float(np.linalg.norm(camera_center_m(R_e, t_e) - camera_center_m(R_t, t_t)))
    r, c = np.array(list(rot.values())), np.array(list(mm.values()))
    return PoseAccuracy(rot, mm, rms(r), float(r.max()), rms(c), float(c.max()),
                        [name for name in truth if name not in estimated])


def fit_sim3(src: np.ndarray, dst: np.ndarray, *, seed: int = 0) -> Sim3:
    """Similarity from src (N, 3) to dst (N, 3) robust to outliers: least median of squares over triples of
    points, inliers within 2.5 robust standard deviations, then Umeyama on the inliers (twice)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise InputError("fit_sim3", f"expected two (N, 3) arrays of matched points, got {src.shape} and {dst.shape}")
    if n < MIN_SIM3_VIEWS:
        raise InputError("fit_sim3", f"a similarity needs {MIN_SIM3_VIEWS} matched points, got {n}")
    if n == MIN_SIM3_VIEWS:
        triples: Sequence[tuple[int, ...]] = [(0, 1, 2)]
    elif math.comb(n, 3) <= _MAX_SIM3_HYPOTHESES:
        triples = list(itertools.combinations(range(n), 3))
    else:
        rng = np.random.default_rng(seed)
        triples = [tuple(rng.choice(n, 3, replace=False)) for _ in range(_MAX_SIM3_HYPOTHESES)]
    spread = float(np.sqrt(np.mean(np.sum((src - src.mean(0)) ** 2, axis=1)))) or 1.0
    best = None
    for tri in triples:
        idx = list(tri)
        a = src[idx]
        if np.linalg.norm(np.cross(a[1] - a[0], a[2] - a[0])) < 1e-6 * spread**2:
            continue  # collinear: the rotation about the line is free
        s, R, t = _umeyama(a, dst[idx])
        res = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
        med = float(np.median(res**2))
        if best is None or med < best[0]:
            best = (med, res)
    if best is None:
        raise InputError("fit_sim3", "the camera centres are collinear; a similarity is not determined")
    # Rousseeuw's robust standard deviation from the least median of squares, with its small-sample factor.
    sigma = 1.4826 * (1.0 + 5.0 / max(n - 3, 1)) * math.sqrt(best[0])
    inliers = best[1] <= max(_LMEDS_INLIER_SIGMAS * sigma, 1e-12)
    for _ in range(2):
        s, R, t = _umeyama(src[inliers], dst[inliers])
        res = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
        refined = res <= max(_LMEDS_INLIER_SIGMAS * sigma, 1e-12)
        if refined.sum() < MIN_SIM3_VIEWS or np.array_equal(refined, inliers):
            break
        inliers = refined
    return Sim3(float(s), R, t, inliers, res, rms(res[inliers]))


def _umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity dst = s R src + t (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(b.T @ a / len(src))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / np.mean(np.sum(a**2, axis=1)))
    return s, R, mu_d - s * R @ mu_s


def rms(values: np.ndarray) -> float:
    values = np.asarray(values, np.float64)
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")
