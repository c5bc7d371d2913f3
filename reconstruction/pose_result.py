"""The poses stage's settings and result: `PoseSettings`, `ViewPose` (one posed image) and `PoseResult`, saved as
derived/poses.json and derived/points.npz and read back (docs/poses.md)."""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine.atomic import atomic_open, atomic_write_text
from odsplat.spine.checks import FRAME_INDEX, SEED, WORKERS, Range, check_choice, check_fields, maybe
from odsplat.spine.contract import CAPTURE_KEY, check, describe, numeric, read_npz
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import camera_center_m
from odsplat.spine.manifest import load_json
from odsplat.spine.store import TAKE_SELECTIONS, Capture

from .sim3 import rms

log = logging.getLogger(__name__)

KIND = "odsplat.poses"
SCHEMA = 2


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
                lines.append(f"tags vs the file's poses over {len(rot)} views: rotation {rms(rot):.3f} deg rms "
                             f"({rot.max():.3f} max), centre {rms(mm):.1f} mm rms ({mm.max():.1f} max)")
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
            lines.append(f"tags vs final poses over {len(rot)} views: rotation {rms(rot):.3f} deg rms "
                         f"({rot.max():.3f} max), centre {rms(mm):.1f} mm rms ({mm.max():.1f} max)")
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


def _plain(value: Any) -> Any:
    return None if value is None else np.asarray(value, np.float64).tolist()
