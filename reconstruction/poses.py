"""Camera poses of every view in metres, floor z = 0: COLMAP structure from motion on the still frames, scaled and
aligned to the floor's AprilTag layout by a robust Sim3, with tag-only poses when SfM fails (docs/poses.md)."""
from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import os
import re
import shutil
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from odsplat._deps import import_pycolmap
from odsplat.contract import check, describe, plain
from odsplat.errors import InputError, OdsplatError
from odsplat.geometry import camera_center_m, rotation_angle_deg
from odsplat.manifest import TagLayout, load_json
from odsplat.store import Capture, atomic_open, atomic_write_text
from odsplat.tags import TagDetection, camera_pose_from_tags, detect_tags

log = logging.getLogger(__name__)

KIND = "odsplat.poses"
SCHEMA = 2
MIN_SIM3_VIEWS = 3           # a similarity needs three non-collinear camera centres
_MAX_SIM3_HYPOTHESES = 2000  # LMedS tries every triple below this many, a random sample above
_LMEDS_INLIER_SIGMAS = 2.5   # inlier threshold in robust standard deviations of the best hypothesis
_STATIC_VIEW = re.compile(r"view_(\d+)$")


# ---------------------------------------------------------------------------------------------- the dataclasses


@dataclass
class PoseSettings:
    use_static: bool = True                # the photos in static/ join the takes' first frames
    fixed_intrinsics: bool | None = None   # None: fixed when the manifest has intrinsics
    masks_dir: Path | None = None          # DIR/<take>.png, DIR/static/<photo stem>.png; black = no features
    min_registered: int = 3                # fewer images registered by SfM: tag-only fallback
    max_features: int = 4096               # SIFT features per image (the 400x300 px sim frames give about 2500)
    frame: int = 0                         # which frame of each take (0: pretrigger, the structure at rest)
    seed: int = 0
    min_tags: int = 2                      # floor tags a view needs for a tag pose (one tag can flip, IPPE)
    threads: int | None = None             # COLMAP's threads; None: the cores this process may use
    takes: str = "all"                     # rejected takes too: their first frame shows the structure at rest

    def __post_init__(self) -> None:
        if self.masks_dir is not None:
            self.masks_dir = Path(self.masks_dir)
        for name, low in (("min_registered", 2), ("max_features", 64), ("frame", 0), ("min_tags", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InputError(f"PoseSettings.{name}", f"expected an integer >= {low}, got {value!r}")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise InputError("PoseSettings.threads", f"expected an integer >= 1 or None, got {self.threads!r}")


@dataclass
class ViewPose:
    """One posed image: a take's frame or a static photo; world = the tag layout's frame, metres."""

    name: str             # the take name, or "static/view_03" for a static photo
    kind: str             # "take" | "static"
    view: int             # view index (-1 for a static photo whose name carries none)
    source: str           # "sfm" | "tags"
    K: np.ndarray         # (3, 3) px, pixel (0, 0) centred at (0, 0)
    R: np.ndarray         # (3, 3) world to camera, X_cam = R X_world + t (OpenCV axes)
    t: np.ndarray         # (3,) metres
    width_px: int
    height_px: int
    reproj_rms_px: float | None   # SfM reprojection RMS of this image's points; tag corners' for a tag pose
    tag_rot_deg: float | None     # tag pose vs this pose: rotation angle
    tag_trans_mm: float | None    # tag pose vs this pose: distance between the camera centres
    dist: tuple[float, ...] = ()  # OpenCV distortion (k1, k2, p1, p2[, k3, k4, k5, k6]); () for none

    @property
    def center_m(self) -> np.ndarray:
        return camera_center_m(self.R, self.t)


@dataclass
class PoseResult:
    views: list[ViewPose]
    points_m: np.ndarray          # (P, 3) world, metres
    points_color: np.ndarray      # (P, C) in [0, 1], C = 1 (mono) or 3 (RGB)
    points_error_px: np.ndarray   # (P,) mean reprojection error of each point
    method: str                   # "sfm" | "tags"
    sim3_scale: float | None      # metres per SfM unit
    sim3_R: np.ndarray | None     # world from SfM: X_world = scale R X_sfm + t
    sim3_t: np.ndarray | None
    sim3_residual_m: float | None  # RMS camera-centre residual over the Sim3's inlier views
    registered: int               # images SfM registered (in its largest model)
    n_images: int                 # images given to SfM
    notes: list[str]
    reason: str = ""              # why this method
    reproj_mean_px: float | None = None  # SfM's mean reprojection error over all observations
    sim3_views: list[str] = field(default_factory=list)     # views whose centres fit the Sim3
    sim3_outliers: list[str] = field(default_factory=list)  # views left out of it as outliers
    timings_s: dict[str, float] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)   # the PoseSettings it was made with

    def view(self, name: str) -> ViewPose:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(f"no pose for {name!r}; posed are {[v.name for v in self.views]}")

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """name -> (R, t), world to camera, for `compare_poses`."""
        return {v.name: (v.R, v.t) for v in self.views}

    def tag_agreement(self) -> tuple[np.ndarray, np.ndarray]:
        """(rotation_deg, centre_mm) of the views that have a tag pose."""
        rot = np.array([v.tag_rot_deg for v in self.views if v.tag_rot_deg is not None], dtype=np.float64)
        mm = np.array([v.tag_trans_mm for v in self.views if v.tag_trans_mm is not None], dtype=np.float64)
        return rot, mm

    def report_lines(self) -> list[str]:
        by_source = {s: sum(v.source == s for v in self.views) for s in ("sfm", "tags")}
        lines = [f"poses: method {self.method} ({self.reason}); {len(self.views)}/{self.n_images} images posed "
                 f"({by_source['sfm']} by SfM, {by_source['tags']} by tags); SfM registered "
                 f"{self.registered}/{self.n_images}"]
        per_image = [v.reproj_rms_px for v in self.views if v.source == "sfm" and v.reproj_rms_px is not None]
        if self.reproj_mean_px is not None:
            spread = f", per image {min(per_image):.2f} to {max(per_image):.2f} px rms" if per_image else ""
            lines.append(f"reprojection: SfM mean {self.reproj_mean_px:.2f} px{spread}")
        if self.sim3_scale is not None:
            out = f"; outliers {', '.join(self.sim3_outliers)}" if self.sim3_outliers else ""
            lines.append(f"metric frame: Sim3 scale {self.sim3_scale:.5f} m per SfM unit, residual "
                         f"{1e3 * self.sim3_residual_m:.1f} mm rms over {len(self.sim3_views)} views{out}")
        rot, mm = self.tag_agreement()
        if len(rot) and self.method == "sfm":
            lines.append(f"tags vs final poses over {len(rot)} views: rotation {_rms(rot):.3f} deg rms "
                         f"({rot.max():.3f} max), centre {_rms(mm):.1f} mm rms ({mm.max():.1f} max)")
        if len(self.points_m):
            lines.append(f"points: {len(self.points_m)}, reprojection error median "
                         f"{float(np.median(self.points_error_px)):.2f} px")
        else:
            lines.append("points: none")
        lines += [f"note: {n}" for n in self.notes]
        return lines

    # -- files ------------------------------------------------------------------------------------

    def write(self, capture: Capture) -> None:
        """derived/poses.json (views, report, method, notes) and derived/points.npz, each written atomically."""
        paths = capture.paths
        paths.ensure(paths.root)
        doc = {
            **describe(capture.id, KIND, SCHEMA, self.settings).header(),
            "method": self.method,
            "reason": self.reason,
            "registered": self.registered,
            "n_images": self.n_images,
            "reproj_mean_px": self.reproj_mean_px,
            "sim3": None if self.sim3_scale is None else {
                "scale": self.sim3_scale, "R": _plain(self.sim3_R), "t": _plain(self.sim3_t),
                "residual_m": self.sim3_residual_m, "views": self.sim3_views, "outliers": self.sim3_outliers},
            "notes": self.notes,
            "timings_s": self.timings_s,
            "report": self.report_lines(),
            "views": [{
                "name": v.name, "kind": v.kind, "view": v.view, "source": v.source, "K": _plain(v.K), "R": _plain(v.R),
                "t": _plain(v.t), "dist": list(v.dist), "width_px": v.width_px, "height_px": v.height_px,
                "reproj_rms_px": v.reproj_rms_px, "tag_rot_deg": v.tag_rot_deg, "tag_trans_mm": v.tag_trans_mm,
                "center_m": _plain(v.center_m)} for v in self.views],
        }
        with atomic_open(paths.points_npz, "wb") as fh:
            np.savez(fh, points_m=self.points_m.astype(np.float64), points_color=self.points_color.astype(np.float32),
                     points_error_px=self.points_error_px.astype(np.float32))
        # The JSON goes last: a reader that finds it finds the points it describes.
        atomic_write_text(paths.poses_json, json.dumps(doc, indent=1) + "\n")
        log.info("poses: wrote %s and %s", paths.poses_json, paths.points_npz)

    @classmethod
    def read(cls, capture: Capture) -> PoseResult:
        """The capture's poses; a file of another kind, schema or capture is refused with one line."""
        path = capture.paths.poses_json
        doc = load_json(path, missing="no camera poses here; run `odsplat poses` first")
        prov = check(doc, path, kind=KIND, schema_version=SCHEMA, capture_id=capture.id)
        points_path = capture.paths.points_npz
        try:
            with np.load(points_path, allow_pickle=False) as npz:
                points = {k: npz[k] for k in ("points_m", "points_color", "points_error_px")}
        except FileNotFoundError:
            raise InputError(points_path, "missing beside poses.json; run `odsplat poses` again") from None
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(points_path, f"not a readable points file: {exc}") from None
        try:
            views = [ViewPose(name=v["name"], kind=v["kind"], view=int(v["view"]), source=v["source"],
                              K=np.array(v["K"], float), R=np.array(v["R"], float), t=np.array(v["t"], float),
                              width_px=int(v["width_px"]), height_px=int(v["height_px"]),
                              reproj_rms_px=v["reproj_rms_px"], tag_rot_deg=v["tag_rot_deg"],
                              tag_trans_mm=v["tag_trans_mm"], dist=tuple(v.get("dist", ())))
                     for v in doc["views"]]
            sim3 = doc["sim3"]
            return cls(views=views, **points, method=doc["method"], reason=doc.get("reason", ""),
                       sim3_scale=None if sim3 is None else float(sim3["scale"]),
                       sim3_R=None if sim3 is None else np.array(sim3["R"], float),
                       sim3_t=None if sim3 is None else np.array(sim3["t"], float),
                       sim3_residual_m=None if sim3 is None else sim3["residual_m"],
                       sim3_views=[] if sim3 is None else list(sim3["views"]),
                       sim3_outliers=[] if sim3 is None else list(sim3["outliers"]),
                       registered=int(doc["registered"]), n_images=int(doc["n_images"]), notes=list(doc["notes"]),
                       reproj_mean_px=doc.get("reproj_mean_px"), timings_s=dict(doc.get("timings_s", {})),
                       settings=prov.settings)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(path, f"malformed poses file ({exc!r}); run `odsplat poses` again") from None


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
    return PoseAccuracy(rot, mm, _rms(r), float(r.max()), _rms(c), float(c.max()),
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
    return Sim3(float(s), R, t, inliers, res, _rms(res[inliers]))


def _umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity dst = s R src + t (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(b.T @ a / len(src))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / np.mean(np.sum(a**2, axis=1)))
    return s, R, mu_d - s * R @ mu_s


# ---------------------------------------------------------------------------------------------- the images


@dataclass
class _Image:
    name: str            # the pose name: take name or "static/<stem>"
    kind: str            # "take" | "static"
    view: int
    colmap_name: str     # path under the work images folder: takes/NAME.png, static/STEM.png
    image: np.ndarray    # uint8, gray (H, W) or BGR (H, W, 3), as written for COLMAP
    group: tuple[int, int]  # (width, height): images of one size share one camera

    @property
    def gray(self) -> np.ndarray:
        return self.image if self.image.ndim == 2 else cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)


def _to_u8(frame: np.ndarray, bit_depth: int) -> np.ndarray:
    """A take frame as 8 bits by its recorded bit depth (12-bit data in uint16 is not scaled by 16 bits)."""
    if frame.dtype == np.uint8:
        return frame
    scale = 255.0 / (2 ** int(bit_depth) - 1)
    return np.clip(np.round(frame.astype(np.float32) * scale), 0, 255).astype(np.uint8)


def _collect_images(capture: Capture, settings: PoseSettings) -> tuple[list[_Image], list[str]]:
    images, notes = [], []
    for name in (t.name for t in capture.select_takes(settings.takes)):
        with capture.open_take(name) as reader:
            if not reader.has_frames or reader.n_frames == 0:
                notes.append(f"take {name} holds no frames; left out")
                continue
            if settings.frame >= reader.n_frames:
                raise InputError(reader.path, f"frame {settings.frame} asked for; the take has {reader.n_frames}")
            frame = reader.read_frames(settings.frame, settings.frame + 1)[0]
            u8 = _to_u8(frame, reader.bit_depth)
            view = reader.view
        if u8.ndim == 3:
            u8 = cv2.cvtColor(u8, cv2.COLOR_RGB2BGR)  # takes hold RGB, OpenCV writes BGR
        images.append(_Image(name, "take", -1 if view is None else view, f"takes/{name}.png", u8,
                             (u8.shape[1], u8.shape[0])))
    if settings.use_static and capture.static_dir.is_dir():
        for path in sorted(capture.static_dir.glob("*.png")):
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(path, "not a readable PNG image")
            if img.dtype == np.uint16:
                img = np.round(img / 257.0).astype(np.uint8)  # static photos are stored at 16-bit full scale
            if img.ndim == 3 and img.shape[2] == 4:
                img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
            match = _STATIC_VIEW.search(path.stem)
            images.append(_Image(f"static/{path.stem}", "static", int(match.group(1)) if match else -1,
                                 f"static/{path.name}", img, (img.shape[1], img.shape[0])))
    return images, notes


def _write_images(images: Sequence[_Image], work: Path, masks_dir: Path | None) -> Path | None:
    for im in tqdm(images, desc="poses: images", unit="image", disable=None, leave=False):
        path = work / "images" / im.colmap_name
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), im.image):
            raise OdsplatError(f"{path}: could not be written")
    if masks_dir is None:
        return None
    if not masks_dir.is_dir():
        raise InputError(masks_dir, "no such masks directory")
    found = 0
    for im in images:
        src = masks_dir / f"{im.name}.png"
        h, w = im.image.shape[:2]
        if src.exists():
            mask = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise InputError(src, "not a readable mask image")
            if mask.shape != (h, w):
                raise InputError(src, f"mask is {mask.shape[1]}x{mask.shape[0]} px; its image is {w}x{h}")
            found += 1
        else:
            mask = np.full((h, w), 255, np.uint8)  # no mask: features everywhere
        # COLMAP looks for MASKS/<image path>.png
        dst = work / "masks" / f"{im.colmap_name}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dst), mask)
    if not found:
        raise InputError(masks_dir, f"no mask matches an image; expected e.g. {images[0].name}.png"
                         if images else "no images to mask")
    log.info("poses: %d of %d images masked", found, len(images))
    return work / "masks"


# ---------------------------------------------------------------------------------------------- cameras


@dataclass
class _Intrinsics:
    K: np.ndarray                 # OpenCV convention: pixel (0, 0) centred at (0, 0)
    dist: tuple[float, ...] = ()  # OpenCV order

    def colmap(self, *, refined: bool = False) -> tuple[str, list[float]]:
        """COLMAP model name and parameters; COLMAP puts pixel (0, 0)'s centre at (0.5, 0.5). A square-pixel camera
        without distortion that SfM will refine becomes SIMPLE_RADIAL: one focal length and k1, as when estimated."""
        K, d = self.K, list(self.dist)
        base = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
        if refined and not any(d) and abs(K[0, 0] - K[1, 1]) <= 1e-6 * K[0, 0]:
            return "SIMPLE_RADIAL", [K[0, 0], base[2], base[3], 0.0]
        if not any(d):
            return "PINHOLE", base
        if len(d) == 4 or (len(d) == 5 and d[4] == 0):
            return "OPENCV", base + d[:4]
        if len(d) in (5, 8):
            return "FULL_OPENCV", base + (d + [0.0] * 3)[:8]
        raise InputError("capture.json: camera.intrinsics.dist",
                         f"COLMAP takes 4, 5 or 8 OpenCV distortion coefficients; got {len(d)}")

    @classmethod
    def from_colmap(cls, camera) -> _Intrinsics:
        p = [float(v) for v in camera.params]
        model = camera.model_name
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            f, cx, cy, extra = p[0], p[1], p[2], p[3:]
            K = np.array([[f, 0, cx - 0.5], [0, f, cy - 0.5], [0, 0, 1.0]])
            dist = () if model == "SIMPLE_PINHOLE" else tuple((extra + [0.0])[:2]) + (0.0, 0.0)
        elif model in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
            K = np.array([[p[0], 0, p[2] - 0.5], [0, p[1], p[3] - 0.5], [0, 0, 1.0]])
            dist = tuple(p[4:])
        else:
            raise OdsplatError(f"COLMAP camera model {model} is not converted to OpenCV here")
        return cls(K, dist)

    @property
    def cv_dist(self) -> np.ndarray | None:
        return np.asarray(self.dist, np.float64) if any(self.dist) else None


def _known_intrinsics(capture: Capture, images: Sequence[_Image]) -> dict[tuple[int, int], _Intrinsics]:
    """The manifest's intrinsics, for the image size the manifest's camera has (the takes' size if unstated)."""
    cam = capture.manifest.camera
    if cam.intrinsics is None:
        return {}
    if cam.width_px and cam.height_px:
        size = (int(cam.width_px), int(cam.height_px))
    else:
        sizes = {im.group for im in images if im.kind == "take"}
        if len(sizes) != 1:
            return {}
        (size,) = sizes
    k = cam.intrinsics
    return {size: _Intrinsics(k.matrix(), tuple(float(d) for d in k.dist))}


def _floor_layout(capture: Capture) -> TagLayout:
    layout = capture.manifest.tags
    if layout is None or not any(not t.on_structure for t in layout.tags):
        raise InputError(capture.root / "capture.json", "tags: no floor tag layout; the poses take their metric "
                         "scale and floor from the AprilTags placed on the floor")
    return layout


@dataclass
class _TagPose:
    R: np.ndarray
    t: np.ndarray
    rms_px: float
    n_tags: int


def _tag_poses(images: Sequence[_Image], detections: Mapping[str, list[TagDetection]], layout: TagLayout,
               intrinsics: Mapping[tuple[int, int], _Intrinsics], min_tags: int) -> dict[str, _TagPose]:
    out = {}
    for im in images:
        cam = intrinsics.get(im.group)
        if cam is None:
            continue
        pose = camera_pose_from_tags(detections[im.name], layout, cam.K, cam.cv_dist, min_tags=min_tags)
        if pose is not None:
            out[im.name] = _TagPose(pose.R, pose.t, pose.rms_px, len(pose.tag_ids))
    return out


def _calibrate_from_tags(images: Sequence[_Image], detections: Mapping[str, list[TagDetection]], layout: TagLayout,
                         size: tuple[int, int], min_tags: int) -> tuple[_Intrinsics, str] | None:
    """Focal length and k1 from the floor tags' corners over the views of one image size (Zhang's method with the
    principal point held at the centre); None with fewer than three views of min_tags tags."""
    placed = {t.id: np.asarray(t.corners_m, np.float64) for t in layout.tags if not t.on_structure}
    obj, img = [], []
    for im in images:
        if im.group != size:
            continue
        used = [d for d in detections[im.name] if d.id in placed]
        if len(used) >= min_tags:
            obj.append(np.concatenate([placed[d.id] for d in used]).astype(np.float32))
            img.append(np.concatenate([d.corners_px for d in used]).astype(np.float32))
    if len(obj) < 3:
        return None
    w, h = size
    K0 = np.array([[1.2 * max(w, h), 0, (w - 1) / 2], [0, 1.2 * max(w, h), (h - 1) / 2], [0, 0, 1.0]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    try:
        rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), K0, np.zeros(5), flags=flags)
    except cv2.error as exc:
        log.warning("poses: calibration from the tags failed: %s", exc)
        return None
    d = [float(v) for v in np.ravel(dist)[:4]]
    return _Intrinsics(K, tuple(d)), (f"intrinsics of the {w}x{h} images calibrated from the floor tags of "
                                      f"{len(obj)} views: f = {K[0, 0]:.1f} px, k1 = {d[0]:.4f}, rms {rms:.2f} px")


# ---------------------------------------------------------------------------------------------- COLMAP


@contextlib.contextmanager
def _quiet_colmap(pycolmap) -> Iterator[None]:
    """COLMAP logs every step at INFO to stderr; that is kept for odsplat's debug level."""
    old = pycolmap.logging.minloglevel
    if not log.isEnabledFor(logging.DEBUG):
        # glog levels: 0 info, 1 warning, 2 error, 3 fatal. What goes wrong is logged here in odsplat's words.
        pycolmap.logging.minloglevel = 1 if log.isEnabledFor(logging.INFO) else 3
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _threads(settings: PoseSettings) -> int:
    if settings.threads is not None:
        return settings.threads
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class _Sfm:
    database: Path
    camera_ids: dict[tuple[int, int], int]  # image size -> COLMAP camera id
    rec: Any = None                          # the largest model, or None
    error: str | None = None


def _pipeline_options(pycolmap, settings: PoseSettings, constant: set[int], all_constant: bool):
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = _threads(settings)
    opts.random_seed = settings.seed
    opts.mapper.random_seed = settings.seed
    opts.triangulation.random_seed = settings.seed
    if all_constant:
        opts.ba_refine_focal_length = False
        opts.ba_refine_extra_params = False
        opts.ba_refine_principal_point = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    elif constant:
        opts.constant_cameras = set(constant)
    return opts


def _run_sfm(pycolmap, images: Sequence[_Image], work: Path, masks: Path | None,
             priors: Mapping[tuple[int, int], _Intrinsics], fixed: set[tuple[int, int]], settings: PoseSettings,
             timings: dict[str, float]) -> _Sfm:
    """Features, exhaustive matching and incremental mapping; errors are caught into _Sfm.error."""
    database = work / "database.db"
    sfm = _Sfm(database, {})
    threads = _threads(settings)
    pycolmap.set_random_seed(settings.seed)
    try:
        t0 = time.perf_counter()
        groups: dict[tuple[int, int], list[str]] = {}
        for im in images:
            groups.setdefault(im.group, []).append(im.colmap_name)
        for size, names in groups.items():
            reader = pycolmap.ImageReaderOptions()
            if masks is not None:
                reader.mask_path = str(masks)
            if size in priors:
                model, params = priors[size].colmap(refined=size not in fixed)
                reader.camera_model = model
                reader.camera_params = ",".join(f"{p:.17g}" for p in params)
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.num_threads = threads
            extraction.sift.max_num_features = settings.max_features
            # One call per image size, each with one camera: the images of one size come from one camera.
            pycolmap.extract_features(database, work / "images", image_names=names,
                                      camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                      extraction_options=extraction)
        with contextlib.closing(pycolmap.Database.open(database)) as db:
            by_name = {im.name: im.camera_id for im in db.read_all_images()}
        for size, names in groups.items():
            sfm.camera_ids[size] = by_name[names[0]]
        timings["features_s"] = time.perf_counter() - t0
        log.info("poses: features of %d images in %.1f s", len(images), timings["features_s"])

        t0 = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = threads
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = settings.seed
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification)
        timings["matching_s"] = time.perf_counter() - t0
        log.info("poses: exhaustive matching in %.1f s", timings["matching_s"])

        t0 = time.perf_counter()
        constant = {sfm.camera_ids[s] for s in fixed}
        opts = _pipeline_options(pycolmap, settings, constant, all_constant=constant == set(sfm.camera_ids.values()))
        sparse = work / "sparse"
        sparse.mkdir()
        models = pycolmap.incremental_mapping(database, work / "images", sparse, options=opts)
        timings["mapping_s"] = time.perf_counter() - t0
        log.info("poses: incremental mapping in %.1f s: %d model(s)", timings["mapping_s"], len(models))
        if not models:
            sfm.error = "SfM built no model (too few matches between the images)"
        else:
            sfm.rec = max(models.values(), key=lambda r: r.num_reg_images())
    except Exception as exc:  # pycolmap raises plain RuntimeErrors (and worse) from C++; any of them means no SfM
        log.warning("poses: structure from motion failed: %r", exc)
        sfm.error = f"SfM failed: {exc}"
    return sfm


def _image_reprojection(rec) -> dict[str, float]:
    """RMS reprojection error (px) of each registered image over its triangulated points."""
    out = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in image.points2D if p.has_point3D()]
        if not obs:
            continue
        xy = np.array([o[0] for o in obs])
        world = np.array([o[1] for o in obs])
        pose = image.cam_from_world()
        cam = world @ pose.rotation.matrix().T + pose.translation
        proj = image.camera.img_from_cam(cam, check_cheirality=False)
        out[image.name] = _rms(np.linalg.norm(proj - xy, axis=1))
    return out


def _points(rec, n_colors: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts = list(rec.points3D.values())
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, n_colors), np.float32), np.zeros(0, np.float32)
    xyz = np.array([p.xyz for p in pts], np.float64)
    color = np.array([p.color for p in pts], np.float32) / 255.0
    error = np.array([p.error for p in pts], np.float32)
    return xyz, (color[:, :1] if n_colors == 1 else color), error


def _triangulate(pycolmap, sfm: _Sfm, images: Sequence[_Image], views: Sequence[ViewPose], work: Path,
                 settings: PoseSettings):
    """Points from the matched features with the poses held fixed (COLMAP's point triangulator)."""
    by_pose = {v.name: v for v in views}
    sizes = {im.colmap_name: im.group for im in images}
    poses = {im.colmap_name: by_pose[im.name] for im in images if im.name in by_pose}
    rec = pycolmap.Reconstruction()
    with contextlib.closing(pycolmap.Database.open(sfm.database)) as db:
        for size, camera_id in sfm.camera_ids.items():
            v = next((p for name, p in poses.items() if sizes[name] == size), None)
            if v is None:
                continue
            model, params = _Intrinsics(v.K, v.dist).colmap()
            camera = pycolmap.Camera(model=model, width=size[0], height=size[1], params=params, camera_id=camera_id)
            # The triangulator checks the model against the database's: the database gets the posing intrinsics.
            db.update_camera(camera)
            rec.add_camera_with_trivial_rig(camera)
        db_images = db.read_all_images()
    for db_image in db_images:
        v = poses.get(db_image.name)
        if v is None or not rec.exists_camera(db_image.camera_id):
            continue
        image = pycolmap.Image(name=db_image.name, camera_id=db_image.camera_id, image_id=db_image.image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(v.R), v.t))
    opts = _pipeline_options(pycolmap, settings, set(), all_constant=True)
    out = work / "model"
    out.mkdir(exist_ok=True)
    return pycolmap.triangulate_points(rec, sfm.database, work / "images", out, options=opts)


# ---------------------------------------------------------------------------------------------- the stage


def estimate_poses(capture: Capture, settings: PoseSettings | None = None) -> PoseResult:
    """Poses of every take's frame `settings.frame` (and the static photos) in the tag layout's frame, metres.

    Work files (8-bit images, COLMAP's database, its sparse models, the final metric model in COLMAP's format)
    go to derived/poses/, replaced on each run. The result is not saved: call `PoseResult.write` (or use
    `run_poses`, the stage's entry, which does)
    """
    settings = settings or PoseSettings()
    pycolmap = import_pycolmap()
    layout = _floor_layout(capture)
    started = time.perf_counter()
    timings: dict[str, float] = {}
    images, notes = _collect_images(capture, settings)
    if not images:
        raise InputError(capture.root, "no take with frames and no static photo: nothing to pose")
    work = capture.paths.poses_work_dir
    shutil.rmtree(work, ignore_errors=True)  # a stale database would mix old features in
    work.mkdir(parents=True)
    masks = _write_images(images, work, settings.masks_dir)

    known = _known_intrinsics(capture, images)
    fixed_wanted = bool(known) if settings.fixed_intrinsics is None else settings.fixed_intrinsics
    if fixed_wanted and not known:
        raise InputError(capture.root / "capture.json", "camera.intrinsics: fixed intrinsics were asked for, but "
                         "the manifest has none for the takes' image size")
    fixed = set(known) if fixed_wanted else set()
    unknown_sizes = {im.group for im in images} - set(known)
    if unknown_sizes:
        sizes = ", ".join(f"{w}x{h}" for w, h in sorted(unknown_sizes))
        notes.append(f"intrinsics estimated for image size(s) {sizes}")
    elif not fixed:
        notes.append("intrinsics refined by SfM from the manifest's")

    t0 = time.perf_counter()
    detections = {im.name: detect_tags(im.gray, family=layout.family) for im in images}
    timings["tags_s"] = time.perf_counter() - t0
    n_images = len(images)
    n_colors = 3 if any(im.image.ndim == 3 for im in images) else 1

    with _quiet_colmap(pycolmap):
        if n_images >= 2:
            sfm = _run_sfm(pycolmap, images, work, masks, known, fixed, settings, timings)
        else:
            sfm = _Sfm(work / "database.db", {}, error="one image only: SfM needs two or more")
        registered = sfm.rec.num_reg_images() if sfm.rec is not None else 0
        result = None
        if sfm.rec is not None and registered >= settings.min_registered:
            # A copy of the notes: what _sfm_result notes is dropped if it gives up.
            result, why_not = _sfm_result(pycolmap, sfm, images, detections, layout, known, fixed, settings,
                                          n_colors, work, list(notes))
        else:
            why_not = sfm.error or (f"SfM registered {registered}/{n_images} images, fewer than min_registered = "
                                    f"{settings.min_registered}")
        if result is None:
            log.warning("poses: falling back to tag-only poses: %s", why_not)
            result = _tags_result(pycolmap, sfm, images, detections, layout, known, settings, n_colors, work, notes,
                                  why_not)
    result.registered = registered
    result.n_images = n_images
    timings["total_s"] = time.perf_counter() - started
    result.timings_s = {k: round(v, 3) for k, v in timings.items()}
    result.settings = plain(settings)
    for line in result.report_lines():
        log.info("%s", line)
    return result


def run_poses(capture: Capture, settings: PoseSettings | None = None) -> PoseResult:
    """The poses stage's entry: `estimate_poses`, saved to derived/poses.json and points.npz."""
    result = estimate_poses(capture, settings)
    result.write(capture)
    return result


def _sfm_result(pycolmap, sfm: _Sfm, images: Sequence[_Image], detections, layout: TagLayout,
                known: Mapping[tuple[int, int], _Intrinsics], fixed: set[tuple[int, int]], settings: PoseSettings,
                n_colors: int, work: Path, notes: list[str]) -> tuple[PoseResult | None, str]:
    """The SfM poses scaled and aligned to the tags; (None, why) when the Sim3 cannot be fitted."""
    rec = sfm.rec
    by_colmap = {im.colmap_name: im for im in images}
    registered = {by_colmap[img.name].name: img for img in rec.images.values() if img.has_pose}
    registered_sizes = {by_colmap[img.name].group for img in registered.values()}
    intrinsics: dict[tuple[int, int], _Intrinsics] = {}
    for size, camera_id in sfm.camera_ids.items():
        if size in fixed:
            intrinsics[size] = known[size]
        elif size in registered_sizes:
            intrinsics[size] = _Intrinsics.from_colmap(rec.cameras[camera_id])
        else:  # SfM never refined this camera: its parameters are COLMAP's first guess
            calibrated = _calibrate_from_tags(images, detections, layout, size, settings.min_tags)
            if calibrated is not None:
                intrinsics[size] = calibrated[0]
                notes.append(calibrated[1])
    tag = _tag_poses(images, detections, layout, intrinsics, settings.min_tags)
    both = [name for name in registered if name in tag]
    if len(both) < MIN_SIM3_VIEWS:
        return None, (f"only {len(both)} of the {len(registered)} SfM-registered images have a tag pose "
                      f"(>= {settings.min_tags} floor tags); the Sim3 needs {MIN_SIM3_VIEWS}")
    src = np.array([registered[n].projection_center() for n in both])
    dst = np.array([camera_center_m(tag[n].R, tag[n].t) for n in both])
    try:
        sim = fit_sim3(src, dst, seed=settings.seed)
    except InputError as exc:
        return None, f"the Sim3 from SfM to the tags failed: {exc.problem}"
    if int(sim.inliers.sum()) < MIN_SIM3_VIEWS:
        return None, "fewer than three views agree on the Sim3 from SfM to the tags"
    outliers = [n for n, ok in zip(both, sim.inliers) if not ok]
    for n, r in zip(both, sim.residuals_m):
        if n in outliers:
            notes.append(f"{n}: tag pose left out of the Sim3 (camera centre {1e3 * r:.0f} mm off)")
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.R), sim.t))
    rec.write(_fresh(work / "model"))

    reproj = _image_reprojection(rec)
    views = []
    for im in images:
        img = registered.get(im.name)
        cam = intrinsics.get(im.group)
        tp = tag.get(im.name)
        if img is not None:
            pose = img.cam_from_world()
            R, t = pose.rotation.matrix(), np.asarray(pose.translation, np.float64)
            views.append(_view(im, "sfm", cam, R, t, reproj.get(img.name), tp))
        elif tp is not None:
            notes.append(f"{im.name}: not registered by SfM; posed from its tags")
            views.append(_view(im, "tags", cam, tp.R, tp.t, tp.rms_px, tp))
        else:
            notes.append(f"{im.name}: not registered by SfM and sees fewer than {settings.min_tags} floor tags; "
                         "no pose")
    xyz, color, error = _points(rec, n_colors)
    reason = f"SfM registered {len(registered)}/{len(images)} images; metric by {int(sim.inliers.sum())} tag poses"
    return PoseResult(views=views, points_m=xyz, points_color=color, points_error_px=error, method="sfm",
                      sim3_scale=sim.scale, sim3_R=sim.R, sim3_t=sim.t, sim3_residual_m=sim.residual_m,
                      registered=len(registered), n_images=len(images), notes=notes, reason=reason,
                      reproj_mean_px=float(rec.compute_mean_reprojection_error()),
                      sim3_views=[n for n, ok in zip(both, sim.inliers) if ok], sim3_outliers=outliers), ""


def _tags_result(pycolmap, sfm: _Sfm, images: Sequence[_Image], detections, layout: TagLayout,
                 known: Mapping[tuple[int, int], _Intrinsics], settings: PoseSettings, n_colors: int, work: Path,
                 notes: list[str], why: str) -> PoseResult:
    """Each view's pose from its own floor tags; points triangulated with those poses held fixed, when the
    features were matched."""
    intrinsics = dict(known)
    for size in sorted({im.group for im in images} - set(known)):
        calibrated = _calibrate_from_tags(images, detections, layout, size, settings.min_tags)
        if calibrated is not None:
            intrinsics[size] = calibrated[0]
            notes.append(calibrated[1])
        else:
            notes.append(f"the {size[0]}x{size[1]} images have no known intrinsics and too few views with tags to "
                         "calibrate them; not posed")
    tag = _tag_poses(images, detections, layout, intrinsics, settings.min_tags)
    views = [_view(im, "tags", intrinsics[im.group], tag[im.name].R, tag[im.name].t, tag[im.name].rms_px,
                   tag[im.name]) for im in images if im.name in tag]
    unposed = [im.name for im in images if im.name not in tag]
    if not views:
        raise OdsplatError(f"{work.parent.parent}: no pose for any view: {why}, and no view sees {settings.min_tags} "
                           "floor tags of the layout")
    if unposed:
        notes.append(f"{len(unposed)} image(s) see fewer than {settings.min_tags} floor tags and have no pose: "
                     + ", ".join(unposed))
    xyz, color, error = np.zeros((0, 3)), np.zeros((0, n_colors), np.float32), np.zeros(0, np.float32)
    if sfm.camera_ids and sfm.database.exists():
        try:
            rec = _triangulate(pycolmap, sfm, images, views, work, settings)
            xyz, color, error = _points(rec, n_colors)
            notes.append("points triangulated from the matched features with the tag poses held fixed" if len(xyz)
                         else "no points: no matched features to triangulate with the tag poses")
        except Exception as exc:  # as in _run_sfm: any error from COLMAP means no points, said in the notes
            log.warning("poses: triangulation with the tag poses failed: %r", exc)
            notes.append(f"no points: triangulation with the tag poses failed ({exc})")
    else:
        notes.append("no points: the features were never matched")
    return PoseResult(views=views, points_m=xyz, points_color=color, points_error_px=error, method="tags",
                      sim3_scale=None, sim3_R=None, sim3_t=None, sim3_residual_m=None, registered=0,
                      n_images=len(images), notes=notes, reason=f"fallback: {why}")


def _view(im: _Image, source: str, cam: _Intrinsics, R: np.ndarray, t: np.ndarray, reproj: float | None,
          tag: _TagPose | None) -> ViewPose:
    rot = mm = None
    if tag is not None and source != "tags":  # a tag pose against itself says nothing
        rot = rotation_angle_deg(tag.R, R)
        mm = 1e3 * float(np.linalg.norm(camera_center_m(tag.R, tag.t) - camera_center_m(R, t)))
    return ViewPose(name=im.name, kind=im.kind, view=im.view, source=source, K=np.array(cam.K, np.float64),
                    R=np.array(R, np.float64), t=np.array(t, np.float64).reshape(3), width_px=im.group[0],
                    height_px=im.group[1], reproj_rms_px=None if reproj is None else float(reproj),
                    tag_rot_deg=rot, tag_trans_mm=mm, dist=tuple(float(d) for d in cam.dist))


def _fresh(path: Path) -> Path:
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path


def _rms(values: np.ndarray) -> float:
    values = np.asarray(values, np.float64)
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def _plain(value: Any) -> Any:
    return None if value is None else np.asarray(value, np.float64).tolist()
