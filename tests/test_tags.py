"""Tag detection and camera pose from tags, measured against the simulated rig's known corners and camera poses."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from odsplat.hil_sim.render import PinholeCamera, expose, render
from odsplat.hil_sim.scene import FLOOR_TAG, build_scene
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import TagLayout
from odsplat.spine.tags import (
    AUTO_ORDER,
    REFINEMENTS,
    CameraPose,
    TagDetection,
    camera_pose_from_tags,
    detect_tags,
    normalize_corners,
    rotation_angle_deg,
    tag_pose,
)

VIEWS = [((1.1, -1.3, 1.0), (0.15, 0.0, 0.3)),   # (eye, target) in metres
         ((-1.2, -0.9, 1.1), (0.1, 0.0, 0.25)),
         ((0.2, 1.5, 0.9), (0.0, 0.1, 0.3))]

# Corner error after normalisation over the three 640x480 views (median, 90th percentile, max; px). Measured:
#   apriltag 0.13-0.14 / 0.19-0.26 / 0.79   contour 0.09-0.12 / 0.29-0.37 / 0.74
#   subpix   0.31-0.43 / 0.72-1.31 / 1.54   none    0.45-0.46 / 0.75-1.08 / 1.36
# subpix and none are not limited by a convention: cornerSubPix is pulled inwards at the tag's L-shaped corners
# with the small windows these 20-55 px tags allow, and "none" corners are whole pixels.
#   auto (apriltag on the 2x image for every tag here) 0.05-0.07 / 0.11-0.17 / 0.37
CORNER_TOL_PX = {"apriltag": (0.15, 0.3, 1.0), "contour": (0.15, 0.45, 1.0),
                 "subpix": (0.5, 1.5, 2.0), "none": (0.55, 1.2, 1.6), "auto": (0.12, 0.25, 0.6)}
METHODS = [*REFINEMENTS, "auto"]
# Camera pose from all floor tags in a view (rotation deg, centre mm). Measured worst over the views:
#   apriltag 0.018 deg / 0.49 mm, contour 0.014 / 0.52, subpix 0.08 / 2.7, none 0.13 / 3.6, auto 0.013 / 0.36.
POSE_TOL = {"apriltag": (0.05, 1.5), "contour": (0.05, 1.5), "subpix": (0.2, 5.0), "none": (0.2, 5.0),
            "auto": (0.05, 1.5)}


@pytest.fixture(scope="module")
def scene():
    return build_scene()


@pytest.fixture(scope="module")
def views(scene):
    """(camera, uint8 image, ids of the floor tags fully in view and unoccluded) for each viewpoint."""
    out = []
    for eye, target in VIEWS:
        cam = PinholeCamera.look_at(eye, target, fov_deg=50, width_px=640, height_px=480)
        result = render(scene.mesh(), cam, scene.atlas, supersample=3)
        visible = []
        for tag in scene.tags.tags:
            if tag.on_structure:
                continue
            px = cam.project(np.array(tag.corners_m)).px
            probes = np.round(np.vstack([px + 0.15 * (px.mean(0) - px), px.mean(0)])).astype(int)
            inside = np.all(probes >= 3) and np.all(probes < [cam.width_px - 3, cam.height_px - 3])
            if inside and np.all(result.object_id[probes[:, 1], probes[:, 0]] == FLOOR_TAG):
                visible.append(tag.id)
        out.append((cam, _u8(result.image), visible))
    return out


@pytest.fixture(scope="module")
def detections(views):
    """detect_tags for every view and refinement, computed once."""
    return {m: [detect_tags(img, refinement=m) for _, img, _ in views] for m in METHODS}


def _u8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)


def _placements(scene):
    return {t.id: t for t in scene.tags.tags}


def _truth_px(cam, tag) -> np.ndarray:
    return cam.project(np.array(tag.corners_m)).px


def _raw_opencv(img: np.ndarray, refinement: str):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = REFINEMENTS[refinement]
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)
    corners, ids, _ = det.detectMarkers(img)
    return [(int(i), c.reshape(4, 2).astype(np.float64)) for c, i in zip(corners, ids.ravel())]


# ------------------------------------------------------------------------------------------ corners


@pytest.mark.parametrize("refinement", METHODS)
def test_every_visible_floor_tag_is_found_at_its_projected_corners(scene, views, detections, refinement):
    placed = _placements(scene)
    errors = []
    for (cam, _, visible), found in zip(views, detections[refinement]):
        ids = [d.id for d in found]
        assert ids == sorted(ids)
        assert set(visible) <= set(ids), (refinement, visible, ids)
        assert len(visible) >= 7
        for d in found:
            assert d.corners_px.shape == (4, 2) and d.corners_px.dtype == np.float64
            errors.append(d.corners_px - _truth_px(cam, placed[d.id]))
    err = np.concatenate(errors)
    norm = np.linalg.norm(err, axis=1)
    med, p90, worst = CORNER_TOL_PX[refinement]
    assert np.median(norm) < med, (refinement, np.median(norm))
    assert np.percentile(norm, 90) < p90, (refinement, np.percentile(norm, 90))
    assert norm.max() < worst, (refinement, norm.max())
    # No convention offset is left: the mean error is well under the half pixel the conventions differ by.
    assert np.all(np.abs(err.mean(axis=0)) < 0.1), (refinement, err.mean(axis=0))


def test_measured_refiner_offsets_are_the_ones_normalize_corners_removes(scene, views):
    """OpenCV's raw corners: apriltag is shifted by about +0.5 px in x and y, none/contour lie inside the tag."""
    placed = _placements(scene)
    shift, inward = {}, {}
    for m in REFINEMENTS:
        d, r = [], []
        for cam, img, _ in views:
            for tag_id, raw in _raw_opencv(img, m):
                truth = _truth_px(cam, placed[tag_id])
                out = truth - truth.mean(0)
                out /= np.linalg.norm(out, axis=1, keepdims=True)
                d.append(raw - truth)
                r.append(np.sum((raw - truth) * out, axis=1))
        shift[m], inward[m] = np.concatenate(d).mean(axis=0), -np.concatenate(r).mean()
    # Measured: apriltag +0.43 px (x and y) on these sharp renders, +0.49 with a 2 px blur; 0.5 is its convention.
    assert np.all((shift["apriltag"] > 0.35) & (shift["apriltag"] < 0.55)), shift["apriltag"]
    for m in ("none", "subpix", "contour"):
        assert np.all(np.abs(shift[m]) < 0.1), (m, shift[m])
    # Measured: contour corners 0.76 px inside the tag along its diagonals, none 0.54: half a pixel per edge.
    assert 0.6 < inward["contour"] < 0.9, inward["contour"]
    assert 0.35 < inward["none"] < 0.7, inward["none"]


def test_normalize_corners_conventions():
    square = np.array([[10.0, 20.0], [30.0, 20.0], [30.0, 40.0], [10.0, 40.0]])
    np.testing.assert_array_equal(normalize_corners(square, "subpix"), square)
    np.testing.assert_array_equal(normalize_corners(square, "apriltag"), square - 0.5)
    grown = np.array([[9.5, 19.5], [30.5, 19.5], [30.5, 40.5], [9.5, 40.5]])
    for m in ("none", "contour"):
        np.testing.assert_allclose(normalize_corners(square, m), grown, atol=1e-12)
        # Order and orientation do not matter; batches of quads work too.
        np.testing.assert_allclose(normalize_corners(square[::-1], m), grown[::-1], atol=1e-12)
        np.testing.assert_allclose(normalize_corners(np.stack([square, square + 5]), m), np.stack([grown, grown + 5]),
                                   atol=1e-12)
    # A tilted edge moves along its minor axis: the edge y = 0.5 x (mostly horizontal) moves by 0.5 in y.
    quad = np.array([[0.0, 0.0], [20.0, 10.0], [10.0, 30.0], [-10.0, 20.0]])
    out = normalize_corners(quad, "contour")
    top, before = out[1] - out[0], quad[1] - quad[0]
    assert abs(top[0] * before[1] - top[1] * before[0]) < 1e-9            # still parallel
    assert abs((out[0][1] - 0.5 * out[0][0]) - (-0.5)) < 1e-9              # y intercept moved from 0 to -0.5


# ------------------------------------------------------------------------------------------ image types


def test_any_image_type_gives_the_same_tags(views):
    cam, img, _ = views[0]
    ref, ref_auto = detect_tags(img, refinement="apriltag"), detect_tags(img)
    as_float = img.astype(np.float32) / 255.0
    as_12bit = ((img.astype(np.uint32) * 4095 + 127) // 255).astype(np.uint16)
    as_rgb = np.repeat(img[:, :, None], 3, axis=2)
    for other in (as_float, as_12bit, as_rgb, as_float[:, :, None], as_float * 1000.0):
        found = detect_tags(other, refinement="apriltag")
        assert [d.id for d in found] == [d.id for d in ref]
        for a, b in zip(found, ref):
            assert np.abs(a.corners_px - b.corners_px).max() < 0.05
        # "auto" reads the 2x image, whose 8-bit rounding follows the scaling: as_float * 1000 is stretched to its
        # maximum. Its corners then move by up to 0.22 px (measured), within their 0.37 px error from the truth.
        auto = detect_tags(other)
        assert [d.id for d in auto] == [d.id for d in ref_auto]
        for a, b in zip(auto, ref_auto):
            assert np.abs(a.corners_px - b.corners_px).max() < 0.35


def test_bad_input_names_the_argument(views):
    img = views[0][1]
    with pytest.raises(InputError, match="^image: expected a \\(H, W\\) mono or \\(H, W, 3\\) RGB"):
        detect_tags(np.zeros((48, 64, 4), np.uint8))
    with pytest.raises(InputError, match="^image: .*NaN"):
        detect_tags(np.full((48, 64), np.nan))
    with pytest.raises(InputError, match="^family: expected one of \\['tag36h11'\\], got 'tag25h9'"):
        detect_tags(img, family="tag25h9")
    with pytest.raises(InputError, match="^refinement: expected one of .*'subpix'.*got 'fancy'"):
        detect_tags(img, refinement="fancy")
    with pytest.raises(InputError, match="^refinement:"):
        normalize_corners(np.zeros((4, 2)), "fancy")
    with pytest.raises(InputError, match="^corners: expected an array of shape \\(..., 4, 2\\)"):
        normalize_corners(np.zeros((3, 2)), "subpix")
    det = TagDetection(0, np.array([[0.0, 0], [10, 0], [10, 10], [0, 10]]))
    with pytest.raises(InputError, match="^size_m:"):
        tag_pose(det, -0.1, np.eye(3))
    with pytest.raises(InputError, match="^K: expected a 3x3 camera matrix"):
        tag_pose(det, 0.1, np.eye(4))
    with pytest.raises(InputError, match="^dist:"):
        tag_pose(det, 0.1, np.eye(3), dist=[0.1, 0.2])
    with pytest.raises(InputError, match="^min_tags:"):
        camera_pose_from_tags([det], TagLayout(), np.eye(3), min_tags=0)
    with pytest.raises(InputError, match="^TagDetection.corners_px:"):
        TagDetection(1, np.zeros((3, 2)))


def test_an_image_without_tags_gives_no_detections_and_no_pose(scene):
    cam = PinholeCamera.look_at((0.6, -0.6, 0.8), (0.0, 0.0, 1.2), fov_deg=30, width_px=320, height_px=240)
    sky = render(scene.mesh(), cam, scene.atlas, supersample=1, background=0.3).image
    blank = np.random.default_rng(0).integers(100, 140, (240, 320)).astype(np.uint8)
    for img in (_u8(sky), blank):
        for m in METHODS:
            assert detect_tags(img, refinement=m) == []
    assert camera_pose_from_tags([], scene.tags, cam.K) is None


# ------------------------------------------------------------------------------------------ poses


@pytest.mark.parametrize("refinement", METHODS)
def test_camera_pose_from_tags_recovers_the_known_pose(scene, views, detections, refinement):
    max_rot_deg, max_centre_mm = POSE_TOL[refinement]
    for (cam, _, _), found in zip(views, detections[refinement]):
        pose = camera_pose_from_tags(found, scene.tags, cam.K)
        assert isinstance(pose, CameraPose)
        assert set(pose.tag_ids) == {d.id for d in found if d.id < 100}  # structure tags are left out
        assert rotation_angle_deg(pose.R, cam.R) < max_rot_deg
        assert np.linalg.norm(pose.center_m - cam.center_m) * 1e3 < max_centre_mm
        assert np.allclose(pose.center_m, -pose.R.T @ pose.t)
        assert 0 < pose.rms_px < CORNER_TOL_PX[refinement][1]


def test_pose_from_one_tag_and_the_tag_count_rules(scene, views, detections):
    cam, _, _ = views[0]
    found = detections["contour"][0]
    structure = [d for d in found if d.id >= 100]
    assert structure, "the column tag should be in view 0"
    # Structure tags only count when asked for.
    assert camera_pose_from_tags(structure, scene.tags, cam.K) is None
    with_structure = camera_pose_from_tags(found, scene.tags, cam.K, use_structure_tags=True)
    assert set(with_structure.tag_ids) == {d.id for d in found}
    # At rest the column tag is where the layout says. Measured: 0.005 deg.
    assert rotation_angle_deg(with_structure.R, cam.R) < 0.05
    floor = [d for d in found if d.id < 100]
    assert camera_pose_from_tags(floor, scene.tags, cam.K, min_tags=len(floor) + 1) is None
    # Tags missing from the layout are ignored.
    stranger = TagDetection(42, floor[0].corners_px)
    assert camera_pose_from_tags([stranger], scene.tags, cam.K) is None
    # One tag alone (the largest, 49 px across) still gives the pose, less precisely. Measured: 0.15 deg, 4.2 mm.
    biggest = max(floor, key=lambda d: cv2.contourArea(d.corners_px.astype(np.float32)))
    single = camera_pose_from_tags([biggest], scene.tags, cam.K)
    assert single.tag_ids == (biggest.id,)
    assert rotation_angle_deg(single.R, cam.R) < 0.5
    assert np.linalg.norm(single.center_m - cam.center_m) < 0.01


def test_single_tag_pose_matches_the_known_pose(scene, views, detections):
    placed = _placements(scene)
    rot, rel = [], []
    for (cam, _, _), found in zip(views, detections["apriltag"]):
        for d in found:
            tag = placed[d.id]
            R_tc, t_tc = tag_pose(d, tag.size_m, cam.K)
            # The tag's own frame from its layout corners: x to its right edge, y to its top edge, z out of it.
            tl, tr, br, bl = np.array(tag.corners_m)
            x, y = (tr - tl) / np.linalg.norm(tr - tl), (tl - bl) / np.linalg.norm(tl - bl)
            R_tw = np.stack([x, y, np.cross(x, y)], axis=1)
            centre_cam = cam.R @ np.mean(tag.corners_m, axis=0) + cam.t
            rot.append(rotation_angle_deg(R_tc, cam.R @ R_tw))
            rel.append(np.linalg.norm(t_tc - centre_cam) / np.linalg.norm(centre_cam))
    # Measured over 21 floor tags 22-56 px across: rotation median 0.14 deg, max 1.05 deg; position max 0.56 %.
    assert np.median(rot) < 0.3 and max(rot) < 1.5, rot
    assert max(rel) < 0.01, rel


def test_rotation_angle_deg():
    R = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(30.0)]))[0]
    assert abs(rotation_angle_deg(R, np.eye(3)) - 30.0) < 1e-9
    assert abs(rotation_angle_deg(np.eye(3), R) - 30.0) < 1e-9
    tiny = cv2.Rodrigues(np.array([1e-7, 0.0, 0.0]))[0]
    assert abs(rotation_angle_deg(tiny, np.eye(3)) - np.degrees(1e-7)) < 1e-12
    flip = cv2.Rodrigues(np.array([np.pi, 0.0, 0.0]))[0]
    assert abs(rotation_angle_deg(flip, np.eye(3)) - 180.0) < 1e-6


# ------------------------------------------------------------------------------------------ small tags

# Eight viewpoints around the rig, 1.6-1.9 m from its middle, 9-32 deg above it, rendered at four small sizes
# (12-bit, with sensor noise): the floor tags are then 9 to 50 px a side.
SMALL_VIEWS = [((1.6 * np.cos(a), 1.6 * np.sin(a), 0.55 + 0.15 * k % 0.9), (0.05, 0.0, 0.3))
               for k, a in enumerate(np.linspace(0.3, 2 * np.pi + 0.3, 8, endpoint=False))]
SMALL_SIZES = [(256, 192), (320, 240), (400, 300), (512, 384)]
# Tag size bins (px, the square root of the projected area) and what "auto" must do in each: detection rate,
# median / max corner error (px). Measured (docs/tags.md): 14 px 40/43 found, median 0.081, max 0.26;
# 20 px 44/45, 0.069, 0.21; 30 px 20/20, 0.053, 0.16. apriltag alone finds 12/43, 43/45 and 20/20.
SMALL_BINS = {14: ((12.5, 16.0), 0.85, 0.15, 0.6), 20: ((18.0, 22.0), 0.95, 0.12, 0.5),
              30: ((27.0, 33.0), 0.95, 0.10, 0.4)}


@pytest.fixture(scope="module")
def small_tags(scene):
    """(size px, tag id, true corners, auto detection or None, apriltag detection or None) per visible floor tag."""
    rng = np.random.default_rng(7)
    out = []
    for width, height in SMALL_SIZES:
        for eye, target in SMALL_VIEWS:
            cam = PinholeCamera.look_at(eye, target, fov_deg=50, width_px=width, height_px=height)
            result = render(scene.mesh(), cam, scene.atlas, supersample=3)
            frame = expose(result.image, bit_depth=12, rng=rng)
            auto = {d.id: d for d in detect_tags(frame)}
            plain = {d.id: d for d in detect_tags(frame, refinement="apriltag")}
            for tag in scene.tags.tags:
                if tag.on_structure:
                    continue
                px = _truth_px(cam, tag)
                probes = np.round(np.vstack([px + 0.15 * (px.mean(0) - px), px.mean(0)])).astype(int)
                inside = np.all(probes >= 3) and np.all(probes < [width - 3, height - 3])
                if not inside or not np.all(result.object_id[probes[:, 1], probes[:, 0]] == FLOOR_TAG):
                    continue
                d = px[2] - px[0], px[3] - px[1]
                size = float(np.sqrt(0.5 * abs(d[0][0] * d[1][1] - d[0][1] * d[1][0])))
                out.append((size, tag.id, px, auto.get(tag.id), plain.get(tag.id)))
    return out


@pytest.mark.parametrize("size_px", list(SMALL_BINS))
def test_small_tags_are_found_with_accurate_corners(small_tags, size_px):
    (lo, hi), min_rate, max_median, max_err = SMALL_BINS[size_px]
    rows = [r for r in small_tags if lo <= r[0] < hi]
    assert len(rows) >= 10, f"only {len(rows)} tags of {lo}-{hi} px in the views"
    found = [r for r in rows if r[3] is not None]
    err = np.concatenate([np.linalg.norm(r[3].corners_px - r[2], axis=1) for r in found])
    bias = np.concatenate([r[3].corners_px - r[2] for r in found]).mean(axis=0)
    plain = sum(r[4] is not None for r in rows)
    methods = sorted({r[3].method for r in found})
    print(f"{size_px} px tags ({lo}-{hi}): auto found {len(found)}/{len(rows)} (apriltag alone {plain}), corner "
          f"error median {np.median(err):.3f} px, 90 % {np.percentile(err, 90):.3f}, max {err.max():.3f}, "
          f"mean ({bias[0]:+.3f}, {bias[1]:+.3f}); by {methods}")
    assert len(found) >= min_rate * len(rows) and len(found) >= plain
    assert np.median(err) < max_median and err.max() < max_err
    # The upsampled corners are mapped back to the image's pixel centres: no half-pixel (or quarter-pixel) offset.
    assert np.all(np.abs(bias) < 0.08), bias
    assert set(methods) <= {f"{m}@{s}x" for m, s in AUTO_ORDER}


def test_auto_leaves_out_corners_that_do_not_read_as_the_tag(scene, views):
    """The check behind "auto": true corners pass, corners off by half a cell or turned by one corner do not."""
    from odsplat.spine.tags import _check_corners, _to_gray_u8

    cam, img, visible = views[0]
    gray = _to_gray_u8(img)
    placed = _placements(scene)
    for tag_id in visible:
        truth = _truth_px(cam, placed[tag_id])
        assert _check_corners(gray, truth, tag_id, "tag36h11")
        assert not _check_corners(gray, np.roll(truth, 1, axis=0), tag_id, "tag36h11")
        assert not _check_corners(gray, truth, (tag_id + 1) % 8, "tag36h11")
        shifted = truth + 0.6 * (truth[1] - truth[0]) / 8   # the whole quad half a cell to the side
        assert not _check_corners(gray, shifted, tag_id, "tag36h11")


def test_named_refinement_with_upsampling_and_bad_arguments(views):
    _, img, _ = views[0]
    up = detect_tags(img, refinement="contour", upsample=2)
    assert up and all(d.method == "contour@2x" for d in up)
    assert all(d.method == "none@1x" for d in detect_tags(img, refinement="none"))
    with pytest.raises(InputError, match="^upsample: expected 1 or 2, got 3"):
        detect_tags(img, refinement="contour", upsample=3)
    with pytest.raises(InputError, match="^upsample: \"auto\" chooses"):
        detect_tags(img, upsample=2)
