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

from odsplat.spine._deps import import_pycolmap
from odsplat.spine.checks import FRAME_INDEX, SEED, WORKERS, Range, check_choice, check_fields, maybe
from odsplat.spine.contract import CAPTURE_KEY, check, describe, numeric, plain, read_npz
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.geometry import camera_center_m, rotation_angle_deg
from odsplat.spine.manifest import TagLayout, load_json, load_toml
from odsplat.spine.space import check_free
from odsplat.spine.store import TAKE_SELECTIONS, Capture, atomic_open, atomic_write_text
from odsplat.spine.tags import TagDetection, camera_pose_from_tags, detect_tags

log = logging.getLogger(__name__)

KIND = "odsplat.poses"
SCHEMA = 2
MIN_SIM3_VIEWS = 3           # a similarity needs three non-collinear camera centres
_MAX_SIM3_HYPOTHESES = 2000  # LMedS tries every triple below this many, a random sample above
_LMEDS_INLIER_SIGMAS = 2.5   # inlier threshold in robust standard deviations of the best hypothesis
_STATIC_VIEW = re.compile(r"view_(\d+)$")
_PEAK_THRESHOLD = 0.02 / 3     # COLMAP's SIFT default
_MIN_PEAK_THRESHOLD = 0.002
_MIN_SIM3_CORNERS = 12       # three tags' corners: the Sim3 from SfM's tag corners, else from camera centres
_MIN_TAG_PAIR_CORNERS = 16     # a pair of images with no SIFT matches joins on four shared tags (COLMAP wants 15)


# ---------------------------------------------------------------------------------------------- the dataclasses


@dataclass
class PoseSettings:
    use_static: bool = True                # the photos in static/ join the takes' first frames
    fixed_intrinsics: bool | None = None   # None: fixed when the manifest has intrinsics
    masks_dir: Path | None = None          # DIR/<take>.png, DIR/static/<photo stem>.png; black = no features
    min_registered: int = 3                # fewer images registered by SfM: tag-only fallback
    max_features: int = 8192               # SIFT features per image (the 400x300 px sim frames give about 2500)
    peak_threshold: float | None = None    # SIFT's; None: COLMAP's 0.0067, lower for small images (_peak_threshold)
    tag_matches: bool = True               # floor tag corners (id, corner) join SfM as matches between the images
    frame: int = 0                         # which frame of each take (0: pretrigger, the structure at rest)
    seed: int = 0
    min_tags: int = 2                      # floor tags a view needs for a tag pose (one tag can flip, IPPE)
    fallback_min_tags: int = 1             # ... where SfM does not pose it (the fallback, unregistered views)
    threads: int | None = 1                # COLMAP's threads (None: every core): one gives the same poses on every run;
    #                                        more are faster, but the result then varies from run to run (docs/poses.md)
    takes: str = "all"                     # rejected takes too: their first frame shows the structure at rest
    from_file: Path | None = None          # known cameras (TOML or JSON, per view K, R, t): taken, not estimated

    def __post_init__(self) -> None:
        if self.masks_dir is not None:
            self.masks_dir = Path(self.masks_dir)
        if self.from_file is not None:
            self.from_file = Path(self.from_file)
        # max_features: COLMAP's default is 8192 and matching grows with its square; min_registered and the tag
        # counts: no capture has ten thousand images, no view a thousand tags.
        check_fields(self, {"min_registered": Range(at_least=2, at_most=10_000, integer=True),
                            "max_features": Range(at_least=64, at_most=65536, integer=True), "frame": FRAME_INDEX,
                            "min_tags": Range(at_least=1, at_most=1000, integer=True),
                            "fallback_min_tags": Range(at_least=1, at_most=1000, integer=True),
                            "peak_threshold": maybe(Range(above=0, below=1)), "threads": maybe(WORKERS),
                            "seed": SEED})
        check_choice("PoseSettings.takes", self.takes, TAKE_SELECTIONS)


@dataclass
class ViewPose:
    """One posed image: a take's frame or a static photo; world = the tag layout's frame, metres."""

    name: str             # the take name, or "static/view_03" for a static photo
    kind: str             # "take" | "static"
    view: int             # view index (-1 for a static photo whose name carries none)
    source: str           # "sfm" | "tags" | "file"
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
    method: str                   # "sfm" | "tags" | "file"
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
    unposed: dict[str, str] = field(default_factory=dict)    # image name -> why it has no pose
    sim3_corners: int = 0         # tag corners the Sim3 was fitted to (0: fitted to camera centres)
    source: str = ""              # where the poses come from: "estimated", or the file they were read from

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
        if self.method == "file":
            rot, mm = self.tag_agreement()
            lines = [f"poses: method file ({self.reason}); {len(self.views)}/{self.n_images} images posed"]
            if len(rot):
                lines.append(f"tags vs the file's poses over {len(rot)} views: rotation {_rms(rot):.3f} deg rms "
                             f"({rot.max():.3f} max), centre {_rms(mm):.1f} mm rms ({mm.max():.1f} max)")
            lines += [f"not posed: {name}: {why}" for name, why in self.unposed.items()]
            return lines + [f"note: {n}" for n in self.notes]
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
            over = (f"{self.sim3_corners} triangulated tag corners" if self.sim3_corners
                    else f"{len(self.sim3_views)} views")
            lines.append(f"metric frame: Sim3 scale {self.sim3_scale:.5f} m per SfM unit, residual "
                         f"{1e3 * self.sim3_residual_m:.1f} mm rms over {over}{out}")
        rot, mm = self.tag_agreement()
        if len(rot) and self.method == "sfm":
            lines.append(f"tags vs final poses over {len(rot)} views: rotation {_rms(rot):.3f} deg rms "
                         f"({rot.max():.3f} max), centre {_rms(mm):.1f} mm rms ({mm.max():.1f} max)")
        if len(self.points_m):
            lines.append(f"points: {len(self.points_m)}, reprojection error median "
                         f"{float(np.median(self.points_error_px)):.2f} px")
        else:
            lines.append("points: none")
        lines += [f"not posed: {name}: {why}" for name, why in self.unposed.items()]
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
            "unposed": [{"name": name, "reason": why} for name, why in self.unposed.items()],
            "sim3_corners": self.sim3_corners,
            "source": self.source,
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
                     points_error_px=self.points_error_px.astype(np.float32), **{CAPTURE_KEY: np.asarray(capture.id)})
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
        arrays = read_npz(points_path, missing="missing beside poses.json; run `odsplat poses` again",
                          capture_id=capture.id)
        pts = numeric(arrays, "points_m", points_path, (None, 3))
        points = dict(points_m=pts, points_color=numeric(arrays, "points_color", points_path, (len(pts), None)),
                      points_error_px=numeric(arrays, "points_error_px", points_path, (len(pts),)))
        try:
            views = [ViewPose(name=str(v["name"]), kind=v["kind"], view=int(v["view"]), source=v["source"],
                              K=_matrix(v["K"], (3, 3)), R=_matrix(v["R"], (3, 3)), t=_matrix(v["t"], (3,)),
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
                       settings=prov.settings, unposed={u["name"]: u["reason"] for u in doc.get("unposed", [])},
                       sim3_corners=int(doc.get("sim3_corners", 0)), source=str(doc.get("source", "")))
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise InputError(path, f"malformed poses file ({type(exc).__name__}: {exc}); run `odsplat poses` "
                                   "again") from None


def _matrix(value: Any, shape: tuple[int, ...]) -> np.ndarray:
    """A camera matrix or vector from the poses file, of finite numbers and this shape (ValueError otherwise)."""
    a = np.array(value, float)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ValueError(f"expected {shape} finite numbers, got shape {a.shape}")
    return a


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
        # A camera below the floor is one tag's other IPPE solution: no pose rather than a flipped one.
        if pose is not None and pose.center_m[2] > 0:
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
    tag_matches: int = 0                     # tag-corner matches added to the verified ones
    tag_keypoints: dict[str, dict[tuple[int, int], int]] = field(default_factory=dict)  # image -> (tag, k) -> kp


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


def _peak_threshold(settings: PoseSettings, size: tuple[int, int]) -> float:
    """SIFT's peak threshold: the setting, or COLMAP's default (0.0067) for images of 640 px or more on their long
    side and proportionally less below (not under 0.002): small images give few features at the default."""
    if settings.peak_threshold is not None:
        return float(settings.peak_threshold)
    return max(_MIN_PEAK_THRESHOLD, _PEAK_THRESHOLD * min(1.0, max(size) / 640.0))


def _add_tag_matches(pycolmap, database: Path, corners: Mapping[str, Mapping[int, np.ndarray]],
                     keypoints: dict[str, dict[tuple[int, int], int]]) -> int:
    """Each floor tag corner seen in two images is a match: its id and corner index name it. The corners join
    each image's keypoints, and the matches each pair's verified ones (a new pair of images when they share at
    least four tags, which the mapper's 15-match minimum needs). `keypoints` gets, per image, the keypoint index
    of each (tag id, corner). Returns the matches added."""
    added = 0
    with contextlib.closing(pycolmap.Database.open(database)) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        index: dict[int, dict[tuple[int, int], int]] = {}
        for name, tags in corners.items():
            if name not in ids or not tags:
                continue
            image_id = ids[name]
            kp = db.read_keypoints(image_id)
            rows, where = [], {}
            for tag_id in sorted(tags):
                for k, (x, y) in enumerate(np.asarray(tags[tag_id], np.float64)):
                    where[(tag_id, k)] = len(kp) + len(rows)
                    rows.append([x + 0.5, y + 0.5, 1.0, 0.0, 0.0, 1.0])  # COLMAP: pixel (0, 0) centred at (0.5, 0.5)
            db.update_keypoints(image_id, np.vstack([kp.reshape(-1, 6), np.array(rows)]).astype(np.float32))
            index[image_id] = where
            keypoints[name] = where
        for a, b in itertools.combinations(sorted(index), 2):
            common = sorted(set(index[a]) & set(index[b]))
            if not common:
                continue
            pairs = np.array([[index[a][c], index[b][c]] for c in common], np.uint32)
            if db.exists_two_view_geometry(a, b):
                tvg = db.read_two_view_geometry(a, b)
                tvg.inlier_matches = np.vstack([tvg.inlier_matches.reshape(-1, 2), pairs]).astype(np.uint32)
                db.update_two_view_geometry(a, b, tvg)
            elif len(common) >= _MIN_TAG_PAIR_CORNERS:
                tvg = pycolmap.TwoViewGeometry()
                tvg.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
                tvg.inlier_matches = pairs
                db.write_two_view_geometry(a, b, tvg)
            else:
                continue
            added += len(pairs)
    return added


def _run_sfm(pycolmap, images: Sequence[_Image], work: Path, masks: Path | None,
             priors: Mapping[tuple[int, int], _Intrinsics], fixed: set[tuple[int, int]], settings: PoseSettings,
             timings: dict[str, float], tag_corners: Mapping[str, Mapping[int, np.ndarray]] | None = None) -> _Sfm:
    """Features, exhaustive matching (plus the tag corners' matches) and incremental mapping; errors are caught
    into _Sfm.error."""
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
            extraction.sift.peak_threshold = _peak_threshold(settings, size)
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
        if tag_corners:
            sfm.tag_matches = _add_tag_matches(pycolmap, database, tag_corners, sfm.tag_keypoints)
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
    if settings.from_file is not None:
        return poses_from_file(capture, settings.from_file, settings)
    pycolmap = import_pycolmap()
    layout = _floor_layout(capture)
    started = time.perf_counter()
    timings: dict[str, float] = {}
    images, notes = _collect_images(capture, settings)
    if not images:
        raise InputError(capture.root, "no take with frames and no static photo: nothing to pose")
    work = capture.paths.poses_work_dir
    if work.exists():
        shutil.rmtree(work)  # a stale database would mix old features in (a read-only folder: one line, not later)
    # COLMAP's images (PNG), its database of features and matches and its models: a few times the images' bytes.
    # pycolmap aborts the process on a full disk, so the space is checked first.
    check_free(work, 4 * sum(im.image.nbytes for im in images), "COLMAP's work files")
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
            corners = None
            if settings.tag_matches:
                floor = {t.id for t in layout.tags if not t.on_structure}
                corners = {im.colmap_name: {d.id: d.corners_px for d in detections[im.name] if d.id in floor}
                           for im in images}
            sfm = _run_sfm(pycolmap, images, work, masks, known, fixed, settings, timings, corners)
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


_FILE_KEYS = {"name", "K", "R", "t", "dist"}


def poses_from_file(capture: Capture, path: str | Path, settings: PoseSettings | None = None) -> PoseResult:
    """Known cameras (a calibrated rig, a robot-held camera) as the poses: a TOML or JSON file of `[[views]]`, each
    with `name` (a take, or "static/STEM" for a photo), `K` (3x3 px, pixel (0, 0) centred at (0, 0)), `R` (3x3) and
    `t` (3, metres), world to camera (X_cam = R X_world + t, OpenCV axes), and optionally `dist` (OpenCV's 4, 5 or 8
    coefficients). Every bad field is named on its own line of one InputError. Images the file does not name are
    listed as not posed; where a view sees floor tags, its tag pose is compared with the file's (tag_rot_deg)."""
    settings = settings or PoseSettings()
    path = Path(path)
    started = time.perf_counter()
    if path.suffix.lower() == ".toml":
        doc = load_toml(path, missing="no such poses file")
    elif path.suffix.lower() == ".json":
        doc = load_json(path, missing="no such poses file")
    else:
        raise InputError(path, "expected a .toml or .json file of per-view K, R, t")
    images, notes = _collect_images(capture, settings)
    by_name = {im.name: im for im in images}
    entries = doc.get("views") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        raise InputError(path, "expected a non-empty list `views` ([[views]] in TOML), each with name, K, R, t")
    problems: list[str] = []
    parsed: dict[str, tuple[_Intrinsics, np.ndarray, np.ndarray]] = {}
    for i, entry in enumerate(entries):
        where = f"views[{i}]"
        if not isinstance(entry, dict):
            problems.append(f"{where}: expected a table with name, K, R, t")
            continue
        name = entry.get("name")
        if not isinstance(name, str) or name not in by_name:
            problems.append(f"{where}.name: {name!r} is not an image of this capture (expected a take name or "
                            f"static/STEM, e.g. {images[0].name!r})" if images else f"{where}.name: no images")
        elif name in parsed:
            problems.append(f"{where}.name: {name!r} is given twice")
        where = f"{where} ({name})" if isinstance(name, str) else where
        for key in sorted(set(entry) - _FILE_KEYS):
            problems.append(f"{where}.{key}: unknown field; expected {sorted(_FILE_KEYS)}")
        K = _file_array(entry, "K", (3, 3), where, problems)
        R = _file_array(entry, "R", (3, 3), where, problems)
        t = _file_array(entry, "t", (3,), where, problems)
        dist = np.asarray(entry.get("dist", []), dtype=object).ravel()
        try:
            dist = dist.astype(np.float64)
            if dist.size not in (0, 4, 5, 8) or not np.all(np.isfinite(dist)):
                raise ValueError
        except (TypeError, ValueError):
            problems.append(f"{where}.dist: expected 0, 4, 5 or 8 finite OpenCV coefficients, got "
                            f"{entry.get('dist')!r}")
            dist = None
        if K is not None and (K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or np.any(K[2] != [0, 0, 1])):
            problems.append(f"{where}.K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
            K = None
        if R is not None and (not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0):
            problems.append(f"{where}.R: not a rotation (R R^T = I within 1e-6 and det +1 expected)")
            R = None
        if all(x is not None for x in (K, R, t, dist)) and name in by_name and name not in parsed:
            parsed[name] = (_Intrinsics(K, tuple(float(d) for d in dist)), R, t)
    if problems:
        raise InputError(path, f"{len(problems)} bad field(s):\n  " + "\n  ".join(problems))
    layout = capture.manifest.tags
    views, unposed = [], {}
    for im in images:
        if im.name not in parsed:
            unposed[im.name] = f"not in {path.name}"
            continue
        cam, R, t = parsed[im.name]
        tp = None
        if layout is not None:
            tp = _tag_poses([im], {im.name: detect_tags(im.gray, family=layout.family)}, layout, {im.group: cam},
                            settings.min_tags).get(im.name)
        view = _view(im, "file", cam, R, t, None, tp)
        if tp is not None:  # a file's pose against the tags: a check of the file
            view.tag_rot_deg = rotation_angle_deg(tp.R, R)
            view.tag_trans_mm = 1e3 * float(np.linalg.norm(camera_center_m(tp.R, tp.t) - camera_center_m(R, t)))
        views.append(view)
    result = PoseResult(views=views, points_m=np.zeros((0, 3)), points_color=np.zeros((0, 1), np.float32),
                        points_error_px=np.zeros(0, np.float32), method="file", sim3_scale=None, sim3_R=None,
                        sim3_t=None, sim3_residual_m=None, registered=0, n_images=len(images),
                        notes=notes + ["no points: the poses were read, not estimated"],
                        reason=f"known cameras from {path}", unposed=unposed, source=str(path))
    result.timings_s = {"total_s": round(time.perf_counter() - started, 3)}
    result.settings = plain(settings)
    return result


def _file_array(entry: Mapping[str, Any], key: str, shape: tuple[int, ...], where: str,
                problems: list[str]) -> np.ndarray | None:
    if key not in entry:
        problems.append(f"{where}.{key}: missing")
        return None
    try:
        a = np.array(entry[key], dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.all(np.isfinite(a)):
        want = "x".join(map(str, shape))
        problems.append(f"{where}.{key}: expected {want} finite numbers, got {entry[key]!r}")
        return None
    return a


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
    lone = _tag_poses([im for im in images if im.name not in registered and im.name not in tag], detections, layout,
                      intrinsics, settings.fallback_min_tags)
    both = [name for name in registered if name in tag]
    if len(both) < MIN_SIM3_VIEWS:
        return None, (f"only {len(both)} of the {len(registered)} SfM-registered images have a tag pose "
                      f"(>= {settings.min_tags} floor tags); the Sim3 needs {MIN_SIM3_VIEWS}")
    corners = _tag_corner_points(rec, sfm.tag_keypoints, layout)
    if len(corners) >= _MIN_SIM3_CORNERS:
        # The tag corners SfM triangulated, against where the layout puts them: many more and better points than
        # the camera centres of the views' own tag poses.
        src = np.array([xyz for xyz, _ in corners.values()])
        dst = np.array([world for _, world in corners.values()])
        try:
            sim = fit_sim3(src, dst, seed=settings.seed)
        except InputError as exc:
            return None, f"the Sim3 from SfM's tag corners to the layout failed: {exc.problem}"
        outliers = [f"tag {t} corner {k}" for (t, k), ok in zip(corners, sim.inliers) if not ok]
        if outliers:
            notes.append(f"tag corners left out of the Sim3: {', '.join(outliers)}")
        sim_views = [n for n in registered if n in tag]
        metric = f"{int(sim.inliers.sum())} triangulated tag corners"
    else:
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
        sim_views = [n for n, ok in zip(both, sim.inliers) if ok]
        metric = f"{int(sim.inliers.sum())} tag poses"
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.R), sim.t))
    if len(corners) >= _MIN_SIM3_CORNERS:
        kept = {key for key, ok in zip(corners, sim.inliers) if ok}
        constant = {sfm.camera_ids[size] for size in fixed}
        held = _adjust_on_tags(pycolmap, rec, sfm.tag_keypoints, layout, kept, constant, _threads(settings))
        notes.append(f"bundle adjustment with {len(kept)} floor tag corners ({held} points) held at their layout "
                     "positions")
    rec.write(_fresh(work / "model"))

    reproj = _image_reprojection(rec)
    views = []
    unposed: dict[str, str] = {}
    matched = _verified_matches(pycolmap, sfm.database)
    for im in images:
        img = registered.get(im.name)
        cam = intrinsics.get(im.group)
        tp = tag.get(im.name) or lone.get(im.name)
        if img is not None:
            pose = img.cam_from_world()
            R, t = pose.rotation.matrix(), np.asarray(pose.translation, np.float64)
            views.append(_view(im, "sfm", cam, R, t, reproj.get(img.name), tp))
        elif tp is not None:
            notes.append(f"{im.name}: not registered by SfM; posed from its tags")
            views.append(_view(im, "tags", cam, tp.R, tp.t, tp.rms_px, tp))
        else:
            unposed[im.name] = (f"not registered by SfM ({_matches_text(matched.get(im.colmap_name))}) and "
                                f"{_tags_text(im, detections, layout, cam, settings.fallback_min_tags)}")
    xyz, color, error = _points(rec, n_colors)
    reason = f"SfM registered {len(registered)}/{len(images)} images; metric by {metric}"
    return PoseResult(views=views, points_m=xyz, points_color=color, points_error_px=error, method="sfm",
                      sim3_scale=sim.scale, sim3_R=sim.R, sim3_t=sim.t, sim3_residual_m=sim.residual_m,
                      registered=len(registered), n_images=len(images), notes=notes, reason=reason,
                      reproj_mean_px=float(rec.compute_mean_reprojection_error()),
                      sim3_views=sim_views, sim3_outliers=outliers, unposed=unposed,
                      sim3_corners=int(sim.inliers.sum()) if len(corners) >= _MIN_SIM3_CORNERS else 0), ""


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
    tag = _tag_poses(images, detections, layout, intrinsics, settings.fallback_min_tags)
    views = [_view(im, "tags", intrinsics[im.group], tag[im.name].R, tag[im.name].t, tag[im.name].rms_px,
                   tag[im.name]) for im in images if im.name in tag]
    single = [im.name for im in images if im.name in tag and tag[im.name].n_tags == 1]
    if single:
        notes.append(f"{len(single)} image(s) posed from one floor tag alone (IPPE, less certain): "
                     + ", ".join(single))
    matched = _verified_matches(pycolmap, sfm.database) if sfm.database.exists() else {}
    unposed = {im.name: _tags_text(im, detections, layout, intrinsics.get(im.group), settings.fallback_min_tags)
               + f"; SfM: {_matches_text(matched.get(im.colmap_name))}" for im in images if im.name not in tag}
    if not views:
        raise OdsplatError(f"{work.parent.parent}: no pose for any view: {why}, and no view sees "
                           f"{settings.fallback_min_tags} floor tag(s) of the layout")
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
                      n_images=len(images), notes=notes, reason=f"fallback: {why}", unposed=unposed)


def _verified_matches(pycolmap, database: Path) -> dict[str, tuple[int, int]]:
    """Image name (COLMAP's) -> (images it has verified matches with, those matches in all)."""
    out: dict[str, tuple[int, int]] = {}
    try:
        with contextlib.closing(pycolmap.Database.open(database)) as db:
            names = {im.image_id: im.name for im in db.read_all_images()}
            for pair_id, n in zip(*db.read_two_view_geometry_num_inliers()):
                if n <= 0:
                    continue
                for image_id in pycolmap.pair_id_to_image_pair(pair_id):
                    pairs, total = out.get(names[image_id], (0, 0))
                    out[names[image_id]] = (pairs + 1, total + int(n))
    except Exception as exc:  # as in _run_sfm: a database COLMAP could not finish says nothing more
        log.debug("poses: no match counts from %s: %r", database, exc)
    return out


def _matches_text(matched: tuple[int, int] | None) -> str:
    if not matched:
        return "no verified matches with any other image"
    return f"{matched[1]} verified matches with {matched[0]} other image(s)"


def _tags_text(im: _Image, detections: Mapping[str, list[TagDetection]], layout: TagLayout,
               cam: _Intrinsics | None, need: int) -> str:
    """Why the tags give this image no pose."""
    if cam is None:
        return f"no intrinsics for its size {im.group[0]}x{im.group[1]}"
    floor = {t.id for t in layout.tags if not t.on_structure}
    seen = sorted({d.id for d in detections[im.name] if d.id in floor})
    if not seen:
        return "no floor tag of the layout detected"
    if len(seen) < need:
        return f"{len(seen)} floor tag(s) detected ({seen}), {need} needed"
    return f"its floor tags {seen} give no pose in front of the camera above the floor"


def _tag_corner_points(rec, keypoints: Mapping[str, Mapping[tuple[int, int], int]], layout: TagLayout,
                       point_ids: dict[tuple[int, int], set[int]] | None = None,
                       ) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """(tag id, corner) -> (its SfM point, its layout position) for the floor tag corners SfM triangulated;
    `point_ids` gets every SfM point of each corner (its track may have been split)."""
    placed = {t.id: np.asarray(t.corners_m, np.float64) for t in layout.tags if not t.on_structure}
    out: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        for (tag_id, k), idx in keypoints.get(image.name, {}).items():
            if tag_id not in placed or idx >= len(image.points2D):
                continue
            p2d = image.points2D[idx]
            if not p2d.has_point3D():
                continue
            if point_ids is not None:
                point_ids.setdefault((tag_id, k), set()).add(int(p2d.point3D_id))
            if (tag_id, k) not in out:
                out[(tag_id, k)] = (np.asarray(rec.points3D[p2d.point3D_id].xyz, np.float64), placed[tag_id][k])
    return out


def _adjust_on_tags(pycolmap, rec, keypoints: Mapping[str, Mapping[tuple[int, int], int]], layout: TagLayout,
                    inliers: set[tuple[int, int]], constant_cameras: set[int], threads: int) -> int:
    """One bundle adjustment of the metric model with the tag corners held at their layout positions: the tags'
    corners are exact correspondences across the images and their positions are known, so they fix the model's
    scale and its frame and pull each camera to them. Returns the corner points held."""
    point_ids: dict[tuple[int, int], set[int]] = {}
    corners = _tag_corner_points(rec, keypoints, layout, point_ids)
    config = pycolmap.BundleAdjustmentConfig()
    for image in rec.images.values():
        if image.has_pose:
            config.add_image(image.image_id)
    held = 0
    for key, ids in point_ids.items():
        if key not in inliers:
            continue
        for pid in ids:
            rec.points3D[pid].xyz = corners[key][1]
            config.add_constant_point(pid)
            held += 1
    for camera_id in constant_cameras:
        config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)  # the held corners fix it
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point = False
    options.ceres.solver_options.num_threads = threads
    pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    return held


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
    if path.exists():
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path


def _rms(values: np.ndarray) -> float:
    values = np.asarray(values, np.float64)
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def _plain(value: Any) -> Any:
    return None if value is None else np.asarray(value, np.float64).tolist()
