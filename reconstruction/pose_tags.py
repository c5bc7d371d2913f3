"""Poses from the floor's AprilTags: each view's own tag pose, intrinsics calibrated from the tags, the tag-only
fallback when SfM poses too few views, and the bundle adjustment that holds SfM's tag corners at their layout
positions."""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.geometry import camera_center_m, rotation_angle_deg
from odsplat.spine.manifest import TagLayout
from odsplat.spine.store import Capture
from odsplat.spine.tags import TagDetection, camera_pose_from_tags

from .pose_images import Intrinsics, PoseImage
from .pose_result import PoseResult, PoseSettings, ViewPose
from .sfm import Sfm, matches_text, model_points, triangulate, verified_matches

log = logging.getLogger(__name__)


def floor_layout(capture: Capture) -> TagLayout:
    layout = capture.manifest.tags
    if layout is None or not any(not t.on_structure for t in layout.tags):
        raise InputError(capture.root / "capture.json", "tags: no floor tag layout; the poses take their metric "
                         "scale and floor from the AprilTags placed on the floor")
    return layout


@dataclass
class TagPose:
    R: np.ndarray
    t: np.ndarray
    rms_px: float
    n_tags: int


def tag_poses(images: Sequence[PoseImage], detections: Mapping[str, list[TagDetection]], layout: TagLayout,
              intrinsics: Mapping[tuple[int, int], Intrinsics], min_tags: int) -> dict[str, TagPose]:
    out = {}
    for im in images:
        cam = intrinsics.get(im.group)
        if cam is None:
            continue
        pose = camera_pose_from_tags(detections[im.name], layout, cam.K, cam.cv_dist, min_tags=min_tags)
        # A camera below the floor is one tag's other IPPE solution: no pose rather than a flipped one.
        if pose is not None and pose.center_m[2] > 0:
            out[im.name] = TagPose(pose.R, pose.t, pose.rms_px, len(pose.tag_ids))
    return out


def calibrate_from_tags(images: Sequence[PoseImage], detections: Mapping[str, list[TagDetection]], layout: TagLayout,
                        size: tuple[int, int], min_tags: int) -> tuple[Intrinsics, str] | None:
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
    return Intrinsics(K, tuple(d)), (f"intrinsics of the {w}x{h} images calibrated from the floor tags of "
                                     f"{len(obj)} views: f = {K[0, 0]:.1f} px, k1 = {d[0]:.4f}, rms {rms:.2f} px")


def tags_result(pycolmap, sfm: Sfm, images: Sequence[PoseImage], detections, layout: TagLayout,
                known: Mapping[tuple[int, int], Intrinsics], settings: PoseSettings, n_colors: int, work: Path,
                notes: list[str], why: str) -> PoseResult:
    """Each view's pose from its own floor tags; points triangulated with those poses held fixed, when the
    features were matched."""
    intrinsics = dict(known)
    for size in sorted({im.group for im in images} - set(known)):
        calibrated = calibrate_from_tags(images, detections, layout, size, settings.min_tags)
        if calibrated is not None:
            intrinsics[size] = calibrated[0]
            notes.append(calibrated[1])
        else:
            notes.append(f"the {size[0]}x{size[1]} images have no known intrinsics and too few views with tags to "
                         "calibrate them; not posed")
    tag = tag_poses(images, detections, layout, intrinsics, settings.fallback_min_tags)
    views = [view_pose(im, "tags", intrinsics[im.group], tag[im.name].R, tag[im.name].t, tag[im.name].rms_px,
                       tag[im.name]) for im in images if im.name in tag]
    single = [im.name for im in images if im.name in tag and tag[im.name].n_tags == 1]
    if single:
        notes.append(f"{len(single)} image(s) posed from one floor tag alone (IPPE, less certain): "
                     + ", ".join(single))
    matched = verified_matches(pycolmap, sfm.database) if sfm.database.exists() else {}
    unposed = {im.name: tags_text(im, detections, layout, intrinsics.get(im.group), settings.fallback_min_tags)
               + f"; SfM: {matches_text(matched.get(im.colmap_name))}" for im in images if im.name not in tag}
    if not views:
        raise OdsplatError(f"{work.parent.parent}: no pose for any view: {why}, and no view sees "
                           f"{settings.fallback_min_tags} floor tag(s) of the layout")
    xyz, color, error = np.zeros((0, 3)), np.zeros((0, n_colors), np.float32), np.zeros(0, np.float32)
    if sfm.camera_ids and sfm.database.exists():
        try:
            rec = triangulate(pycolmap, sfm, images, views, work, settings)
            xyz, color, error = model_points(rec, n_colors)
            notes.append("points triangulated from the matched features with the tag poses held fixed" if len(xyz)
                         else "no points: no matched features to triangulate with the tag poses")
        except Exception as exc:  # as in run_sfm: any error from COLMAP means no points, said in the notes
            log.warning("poses: triangulation with the tag poses failed: %r", exc)
            notes.append(f"no points: triangulation with the tag poses failed ({exc})")
    else:
        notes.append("no points: the features were never matched")
    return PoseResult(views=views, points_m=xyz, points_color=color, points_error_px=error, method="tags",
                      sim3_scale=None, sim3_R=None, sim3_t=None, sim3_residual_m=None, registered=0,
                      n_images=len(images), notes=notes, reason=f"fallback: {why}", unposed=unposed)


def tags_text(im: PoseImage, detections: Mapping[str, list[TagDetection]], layout: TagLayout,
              cam: Intrinsics | None, need: int) -> str:
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


def tag_corner_points(rec, keypoints: Mapping[str, Mapping[tuple[int, int], int]], layout: TagLayout,
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


def adjust_on_tags(pycolmap, rec, keypoints: Mapping[str, Mapping[tuple[int, int], int]], layout: TagLayout,
                   inliers: set[tuple[int, int]], constant_cameras: set[int], threads: int) -> int:
    """One bundle adjustment of the metric model with the tag corners held at their layout positions: the tags'
    corners are exact correspondences across the images and their positions are known, so they fix the model's
    scale and its frame and pull each camera to them. Returns the corner points held."""
    point_ids: dict[tuple[int, int], set[int]] = {}
    corners = tag_corner_points(rec, keypoints, layout, point_ids)
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


def view_pose(im: PoseImage, source: str, cam: Intrinsics, R: np.ndarray, t: np.ndarray, reproj: float | None,
              tag: TagPose | None) -> ViewPose:
    rot = mm = None
    if tag is not None and source != "tags":  # a tag pose against itself says nothing
        rot = rotation_angle_deg(tag.R, R)
        mm = 1e3 * float(np.linalg.norm(camera_center_m(tag.R, tag.t) - camera_center_m(R, t)))
    return ViewPose(name=im.name, kind=im.kind, view=im.view, source=source, K=np.array(cam.K, np.float64),
                    R=np.array(R, np.float64), t=np.array(t, np.float64).reshape(3), width_px=im.group[0],
                    height_px=im.group[1], reproj_rms_px=None if reproj is None else float(reproj),
                    tag_rot_deg=rot, tag_trans_mm=mm, dist=tuple(float(d) for d in cam.dist))
