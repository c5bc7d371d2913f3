"""COLMAP structure from motion on the pose images: features, exhaustive matching (with the floor tag corners as
matches), incremental mapping, and points triangulated with the poses held fixed. pycolmap is handed in by the
stage, which loads it through odsplat.spine._deps only when poses are estimated."""
from __future__ import annotations

import contextlib
import itertools
import logging
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .pose_images import Intrinsics, PoseImage
from .pose_result import PoseSettings, ViewPose
from .sim3 import rms

log = logging.getLogger(__name__)

_PEAK_THRESHOLD = 0.02 / 3     # COLMAP's SIFT default
_MIN_PEAK_THRESHOLD = 0.002
_MIN_TAG_PAIR_CORNERS = 16     # a pair of images with no SIFT matches joins on four shared tags (COLMAP wants 15)


@contextlib.contextmanager
def quiet_colmap(pycolmap) -> Iterator[None]:
    """COLMAP logs every step at INFO to stderr; that is kept for odsplat's debug level."""
    old = pycolmap.logging.minloglevel
    if not log.isEnabledFor(logging.DEBUG):
        # glog levels: 0 info, 1 warning, 2 error, 3 fatal. What goes wrong is logged here in odsplat's words.
        pycolmap.logging.minloglevel = 1 if log.isEnabledFor(logging.INFO) else 3
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def colmap_threads(settings: PoseSettings) -> int:
    if settings.threads is not None:
        return settings.threads
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class Sfm:
    database: Path
    camera_ids: dict[tuple[int, int], int]  # image size -> COLMAP camera id
    rec: Any = None                          # the largest model, or None
    error: str | None = None
    tag_matches: int = 0                     # tag-corner matches added to the verified ones
    tag_keypoints: dict[str, dict[tuple[int, int], int]] = field(default_factory=dict)  # image -> (tag, k) -> kp


def _pipeline_options(pycolmap, settings: PoseSettings, constant: set[int], all_constant: bool):
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = colmap_threads(settings)
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


def run_sfm(pycolmap, images: Sequence[PoseImage], work: Path, masks: Path | None,
            priors: Mapping[tuple[int, int], Intrinsics], fixed: set[tuple[int, int]], settings: PoseSettings,
            timings: dict[str, float], tag_corners: Mapping[str, Mapping[int, np.ndarray]] | None = None) -> Sfm:
    """Features, exhaustive matching (plus the tag corners' matches) and incremental mapping; errors are caught
    into Sfm.error."""
    database = work / "database.db"
    sfm = Sfm(database, {})
    threads = colmap_threads(settings)
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


def image_reprojection(rec) -> dict[str, float]:
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
        out[image.name] = rms(np.linalg.norm(proj - xy, axis=1))
    return out


def model_points(rec, n_colors: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts = list(rec.points3D.values())
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, n_colors), np.float32), np.zeros(0, np.float32)
    xyz = np.array([p.xyz for p in pts], np.float64)
    color = np.array([p.color for p in pts], np.float32) / 255.0
    error = np.array([p.error for p in pts], np.float32)
    return xyz, (color[:, :1] if n_colors == 1 else color), error


def triangulate(pycolmap, sfm: Sfm, images: Sequence[PoseImage], views: Sequence[ViewPose], work: Path,
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
            model, params = Intrinsics(v.K, v.dist).colmap()
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


def verified_matches(pycolmap, database: Path) -> dict[str, tuple[int, int]]:
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
    except Exception as exc:  # as in run_sfm: a database COLMAP could not finish says nothing more
        log.debug("poses: no match counts from %s: %r", database, exc)
    return out


def matches_text(matched: tuple[int, int] | None) -> str:
    if not matched:
        return "no verified matches with any other image"
    return f"{matched[1]} verified matches with {matched[0]} other image(s)"
