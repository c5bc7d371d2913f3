"""Camera poses of every view in metres, floor z = 0: COLMAP structure from motion on the still frames, scaled and
aligned to the floor's AprilTag layout by a robust Sim3, with tag-only poses when SfM fails (docs/poses.md).

The stage's entry; the parts: pose_result.py (settings, result, its files), pose_images.py (the images and their
intrinsics), sfm.py (COLMAP), sim3.py (the metric alignment), pose_tags.py (tag poses, the fallback, the tag-held
bundle adjustment), known_poses.py (known cameras read from a file)."""
from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine._deps import import_pycolmap
from odsplat.spine.contract import plain
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import camera_center_m
from odsplat.spine.manifest import TagLayout
from odsplat.spine.space import check_free
from odsplat.spine.store import Capture
from odsplat.spine.tags import detect_tags

from .known_poses import poses_from_file
from .pose_images import Intrinsics, PoseImage, collect_images, known_intrinsics, write_images
from .pose_result import PoseResult, PoseSettings
from .pose_tags import (
    TagPose,
    adjust_on_tags,
    calibrate_from_tags,
    floor_layout,
    tag_corner_points,
    tag_poses,
    tags_result,
    tags_text,
    view_pose,
)
from .sfm import (
    Sfm,
    colmap_threads,
    image_reprojection,
    matches_text,
    model_points,
    quiet_colmap,
    run_sfm,
    verified_matches,
)
from .sim3 import MIN_SIM3_VIEWS, Sim3, fit_sim3

log = logging.getLogger(__name__)

_MIN_SIM3_CORNERS = 12       # three tags' corners: the Sim3 from SfM's tag corners, else from camera centres


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
    layout = floor_layout(capture)
    started = time.perf_counter()
    timings: dict[str, float] = {}
    images, notes = collect_images(capture, settings)
    if not images:
        raise InputError(capture.root, "no take with frames and no static photo: nothing to pose")
    work = capture.paths.poses_work_dir
    if work.exists():
        shutil.rmtree(work)  # a stale database would mix old features in (a read-only folder: one line, not later)
    # COLMAP's images (PNG), its database of features and matches and its models: a few times the images' bytes.
    # pycolmap aborts the process on a full disk, so the space is checked first.
    check_free(work, 4 * sum(im.image.nbytes for im in images), "COLMAP's work files")
    work.mkdir(parents=True)
    masks = write_images(images, work, settings.masks_dir)

    known = known_intrinsics(capture, images)
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

    with quiet_colmap(pycolmap):
        if n_images >= 2:
            corners = None
            if settings.tag_matches:
                floor = {t.id for t in layout.tags if not t.on_structure}
                corners = {im.colmap_name: {d.id: d.corners_px for d in detections[im.name] if d.id in floor}
                           for im in images}
            sfm = run_sfm(pycolmap, images, work, masks, known, fixed, settings, timings, corners)
        else:
            sfm = Sfm(work / "database.db", {}, error="one image only: SfM needs two or more")
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
            result = tags_result(pycolmap, sfm, images, detections, layout, known, settings, n_colors, work, notes,
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


def _sfm_result(pycolmap, sfm: Sfm, images: Sequence[PoseImage], detections, layout: TagLayout,
                known: Mapping[tuple[int, int], Intrinsics], fixed: set[tuple[int, int]], settings: PoseSettings,
                n_colors: int, work: Path, notes: list[str]) -> tuple[PoseResult | None, str]:
    """The SfM poses scaled and aligned to the tags; (None, why) when the Sim3 cannot be fitted."""
    rec = sfm.rec
    by_colmap = {im.colmap_name: im for im in images}
    registered = {by_colmap[img.name].name: img for img in rec.images.values() if img.has_pose}
    registered_sizes = {by_colmap[img.name].group for img in registered.values()}
    intrinsics: dict[tuple[int, int], Intrinsics] = {}
    for size, camera_id in sfm.camera_ids.items():
        if size in fixed:
            intrinsics[size] = known[size]
        elif size in registered_sizes:
            intrinsics[size] = Intrinsics.from_colmap(rec.cameras[camera_id])
        else:  # SfM never refined this camera: its parameters are COLMAP's first guess
            calibrated = calibrate_from_tags(images, detections, layout, size, settings.min_tags)
            if calibrated is not None:
                intrinsics[size] = calibrated[0]
                notes.append(calibrated[1])
    tag = tag_poses(images, detections, layout, intrinsics, settings.min_tags)
    lone = tag_poses([im for im in images if im.name not in registered and im.name not in tag], detections, layout,
                     intrinsics, settings.fallback_min_tags)
    both = [name for name in registered if name in tag]
    if len(both) < MIN_SIM3_VIEWS:
        return None, (f"only {len(both)} of the {len(registered)} SfM-registered images have a tag pose "
                      f"(>= {settings.min_tags} floor tags); the Sim3 needs {MIN_SIM3_VIEWS}")
    metric, why = _fit_metric(rec, sfm, layout, registered, tag, both, settings.seed, notes)
    if metric is None:
        return None, why
    sim = metric.sim
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.R), sim.t))
    if metric.on_corners:
        kept = {key for key, ok in zip(metric.corners, sim.inliers) if ok}
        constant = {sfm.camera_ids[size] for size in fixed}
        held = adjust_on_tags(pycolmap, rec, sfm.tag_keypoints, layout, kept, constant, colmap_threads(settings))
        notes.append(f"bundle adjustment with {len(kept)} floor tag corners ({held} points) held at their layout "
                     "positions")
    rec.write(_fresh(work / "model"))

    reproj = image_reprojection(rec)
    views = []
    unposed: dict[str, str] = {}
    matched = verified_matches(pycolmap, sfm.database)
    for im in images:
        img = registered.get(im.name)
        cam = intrinsics.get(im.group)
        tp = tag.get(im.name) or lone.get(im.name)
        if img is not None:
            pose = img.cam_from_world()
            R, t = pose.rotation.matrix(), np.asarray(pose.translation, np.float64)
            views.append(view_pose(im, "sfm", cam, R, t, reproj.get(img.name), tp))
        elif tp is not None:
            notes.append(f"{im.name}: not registered by SfM; posed from its tags")
            views.append(view_pose(im, "tags", cam, tp.R, tp.t, tp.rms_px, tp))
        else:
            unposed[im.name] = (f"not registered by SfM ({matches_text(matched.get(im.colmap_name))}) and "
                                f"{tags_text(im, detections, layout, cam, settings.fallback_min_tags)}")
    xyz, color, error = model_points(rec, n_colors)
    reason = f"SfM registered {len(registered)}/{len(images)} images; metric by {metric.fitted_to}"
    return PoseResult(views=views, points_m=xyz, points_color=color, points_error_px=error, method="sfm",
                      sim3_scale=sim.scale, sim3_R=sim.R, sim3_t=sim.t, sim3_residual_m=sim.residual_m,
                      registered=len(registered), n_images=len(images), notes=notes, reason=reason,
                      reproj_mean_px=float(rec.compute_mean_reprojection_error()),
                      sim3_views=metric.views, sim3_outliers=metric.outliers, unposed=unposed,
                      sim3_corners=int(sim.inliers.sum()) if metric.on_corners else 0), ""


@dataclass
class _Metric:
    """SfM's model put in the layout's metric frame: the Sim3 and what it was fitted to."""

    sim: Sim3
    on_corners: bool     # fitted to the tag corners SfM triangulated (else to the views' camera centres)
    corners: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]  # those corners: (SfM point, layout position)
    views: list[str]     # the views whose tag poses fit it
    outliers: list[str]  # the corners or views left out of it
    fitted_to: str       # "N triangulated tag corners" or "N tag poses"


def _fit_metric(rec, sfm: Sfm, layout: TagLayout, registered: Mapping[str, Any], tag: Mapping[str, TagPose],
                both: Sequence[str], seed: int, notes: list[str]) -> tuple[_Metric | None, str]:
    """The Sim3 from SfM's model to the layout: fitted to SfM's triangulated tag corners where there are enough of
    them, else to the camera centres of the views' own tag poses; (None, why) when it cannot be fitted."""
    corners = tag_corner_points(rec, sfm.tag_keypoints, layout)
    if len(corners) >= _MIN_SIM3_CORNERS:
        # The tag corners SfM triangulated, against where the layout puts them: many more and better points than
        # the camera centres of the views' own tag poses.
        src = np.array([xyz for xyz, _ in corners.values()])
        dst = np.array([world for _, world in corners.values()])
        try:
            sim = fit_sim3(src, dst, seed=seed)
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
            sim = fit_sim3(src, dst, seed=seed)
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
    return _Metric(sim, len(corners) >= _MIN_SIM3_CORNERS, corners, sim_views, outliers, metric), ""


def _fresh(path: Path) -> Path:
    if path.exists():
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path
