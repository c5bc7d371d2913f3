"""AprilTag detection and camera pose from tags, with corners in one convention: pixel (0, 0)'s centre at (0, 0).

That is the convention of OpenCV's camera matrix and of `hil_sim`'s renderer. OpenCV's corner refiners each report
corners in their own convention; `normalize_corners` is the one place that converts them (see docs/tags.md).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.geometry import rotation_angle_deg  # noqa: F401  (re-exported)
from odsplat.spine.manifest import TagLayout

log = logging.getLogger(__name__)

FAMILIES = {"tag36h11": cv2.aruco.DICT_APRILTAG_36h11}
REFINEMENTS = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}
AUTO = "auto"
# The order "auto" prefers, most accurate first, by the corner errors measured on hil_sim renders with tags of
# 11 to 35 px (docs/tags.md): apriltag on the 2x image has a median error of 0.05-0.08 px, contour on it 0.07-0.16,
# apriltag at 1x 0.14-0.21, contour at 1x 0.12-0.20, none 0.4 and subpix 0.4-0.6.
AUTO_ORDER = (("apriltag", 2), ("contour", 2), ("apriltag", 1), ("contour", 1), ("none", 2), ("none", 1),
              ("subpix", 1))
MAX_UPSAMPLED_PX = 4_000_000  # "auto" upsamples images of up to this many pixels after upsampling (2x of 1 MP)
_CHECK_MAX_ERRORS = 3         # cells (of 64 in the tag and 36 of its quiet zone) read wrong at the final corners
_CHECK_MIN_CONTRAST = 0.12    # white minus black cells, as a fraction of the 8-bit range


@dataclass(frozen=True, eq=False)
class TagDetection:
    """One detected tag: its id and its four corners in px (normalised convention), order TL, TR, BR, BL."""

    id: int
    corners_px: np.ndarray  # (4, 2) float64
    method: str = ""        # which refiner found these corners, and on which image: "apriltag@2x", "contour@1x"

    def __post_init__(self) -> None:
        corners = np.array(self.corners_px, dtype=np.float64)
        if corners.shape != (4, 2) or not np.all(np.isfinite(corners)):
            raise InputError("TagDetection.corners_px", f"expected 4 finite (x, y) corners, got shape {corners.shape}")
        corners.setflags(write=False)
        object.__setattr__(self, "id", int(self.id))
        object.__setattr__(self, "corners_px", corners)
        object.__setattr__(self, "method", str(self.method))


@dataclass(frozen=True, eq=False)
class CameraPose:
    """World-to-camera pose (X_cam = R X_world + t, OpenCV axes) estimated from tags."""

    R: np.ndarray             # (3, 3)
    t: np.ndarray             # (3,)
    tag_ids: tuple[int, ...]  # the layout tags whose corners were used
    rms_px: float             # reprojection RMS over all used corners

    @property
    def center_m(self) -> np.ndarray:
        """Optical centre in world coordinates."""
        return -self.R.T @ self.t


def _check_refinement(refinement: str, *, auto: bool = False) -> None:
    allowed = sorted(REFINEMENTS) + ([AUTO] if auto else [])
    if refinement not in allowed:
        raise InputError("refinement", f"expected one of {allowed}, got {refinement!r}")


def normalize_corners(corners, refinement: str) -> np.ndarray:
    """Convert corners (..., 4, 2) as reported by OpenCV's `refinement` to the pixel-centre convention (float64).

    Offsets, measured against rendered tags with known corner projections (docs/tags.md):
    - "subpix": none. cornerSubPix samples the image with pixel centres at integer coordinates.
    - "apriltag": -0.5 px in x and y. The AprilTag quad fit adds half a pixel to its edge points, so its corners
      are in the "pixel (0, 0) spans [0, 1]" convention.
    - "none", "contour": the corners come from the contour of the thresholded dark square, i.e. from the centres
      of its outermost dark pixels. Each edge therefore lies half a pixel inside the true edge, measured along the
      pixel axis most nearly perpendicular to it. Each edge is moved out by that half pixel and the corners are
      re-intersected (this is not a plain translation: it enlarges the quad).
    """
    _check_refinement(refinement)
    c = np.array(corners, dtype=np.float64)
    if c.ndim < 2 or c.shape[-2:] != (4, 2):
        raise InputError("corners", f"expected an array of shape (..., 4, 2), got {c.shape}")
    if refinement == "subpix":
        return c
    if refinement == "apriltag":
        return c - 0.5
    return _grow_edges(c, 0.5)


def _grow_edges(c: np.ndarray, shift_px: float) -> np.ndarray:
    """Move each edge of the quads (..., 4, 2) outwards by shift_px along its minor pixel axis; re-intersect."""
    nxt = np.roll(c, -1, axis=-2)
    d = nxt - c                                   # edge k runs from corner k to corner k+1
    mid = 0.5 * (c + nxt)
    centre = c.mean(axis=-2, keepdims=True)
    horizontal = np.abs(d[..., 0]) >= np.abs(d[..., 1])
    axis = np.zeros_like(d)
    axis[..., 1] = horizontal                     # a mostly horizontal edge moves in y, a mostly vertical one in x
    axis[..., 0] = ~horizontal
    outward = np.sign(np.sum((mid - centre) * axis, axis=-1, keepdims=True))
    p = c + shift_px * outward * axis             # a point on each moved edge
    # Corner k is where edge k-1 (through p[k-1], direction d[k-1]) meets edge k (through p[k], direction d[k]).
    p0, d0 = np.roll(p, 1, axis=-2), np.roll(d, 1, axis=-2)
    cross = d0[..., 0] * d[..., 1] - d0[..., 1] * d[..., 0]
    w = p - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / cross
    out = p0 + s[..., None] * d0
    # Degenerate (parallel adjacent edges) cannot happen for a detected convex quad; keep the input there anyway.
    bad = ~np.isfinite(out).all(axis=-1, keepdims=True)
    return np.where(bad, c, out)


def _to_gray_u8(image) -> np.ndarray:
    """A 2D uint8 image for the detector from mono or RGB data of any real dtype (integers by their bit depth)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise InputError("image", f"expected a (H, W) mono or (H, W, 3) RGB array, got shape {img.shape}")
    if img.shape[0] < 8 or img.shape[1] < 8:
        raise InputError("image", f"expected at least 8x8 pixels, got {img.shape[1]}x{img.shape[0]}")
    if img.dtype == np.uint8:
        u8 = img
    elif img.dtype.kind == "u":
        # 10/12/14/16-bit data in uint16 containers: scale by the bit depth the data actually uses.
        bits = max(8, int(img.max()).bit_length())
        u8 = np.round(img * (255.0 / (2**bits - 1))).astype(np.uint8)
    elif img.dtype.kind in "fib":
        f = img.astype(np.float64)
        if not np.all(np.isfinite(f)):
            raise InputError("image", "contains NaN or inf")
        lo, hi = min(0.0, float(f.min())), max(1.0, float(f.max()))  # [0, 1] data keeps its scale
        u8 = np.round((f - lo) * (255.0 / (hi - lo))).astype(np.uint8)
    else:
        raise InputError("image", f"expected real pixel values, got dtype {img.dtype}")
    if u8.ndim == 3:
        u8 = cv2.cvtColor(np.ascontiguousarray(u8), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(u8)


def detect_tags(image: np.ndarray, *, family: str = "tag36h11", refinement: str = AUTO,
                upsample: int = 1) -> list[TagDetection]:
    """Detect tags in a mono (H, W) or RGB (H, W, 3) image; corners normalised, detections sorted by id.

    "auto" (the default) runs OpenCV's refiners on the image and on the image upsampled 2x, and keeps for every tag
    the corners of the most accurate of them (`AUTO_ORDER`) that pass a check: the tag's cells, read through the
    homography of those corners, must give the tag's code, a black border and a white quiet zone. That finds tags
    down to about 14 px a side; "apriltag" alone misses most under about 22 px (docs/tags.md). Each detection's
    `method` says which refiner and image it came from.

    A named refinement runs that refiner alone on the image upsampled by `upsample` (1 or 2), unchecked, as OpenCV
    reports it (corners normalised).

    Integer images are scaled by the bit depth their values use (12-bit data in uint16 included); float images
    in [0, 1] are taken as they are, other float ranges are scaled to their maximum.
    """
    if family not in FAMILIES:
        raise InputError("family", f"expected one of {sorted(FAMILIES)}, got {family!r}")
    _check_refinement(refinement, auto=True)
    if upsample not in (1, 2) or isinstance(upsample, bool):
        raise InputError("upsample", f"expected 1 or 2, got {upsample!r}")
    if refinement == AUTO and upsample != 1:
        raise InputError("upsample", "\"auto\" chooses the upsampling itself; give a named refinement with it")
    gray = _to_gray_u8(image)
    if refinement != AUTO:
        return sorted(_detect(gray, family, refinement, upsample), key=lambda d: d.id)
    return _detect_auto(gray, family)


def _detect(gray: np.ndarray, family: str, refinement: str, scale: int) -> list[TagDetection]:
    """One refiner on the image upsampled by scale; corners normalised, then mapped back to the image's pixels."""
    if scale != 1:
        # cv2.resize maps pixel centres: x_up = scale (x + 0.5) - 0.5, so corners map back by the inverse.
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = REFINEMENTS[refinement]
    # One detector per call: OpenCV's detector writes to its parameters while detecting.
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(FAMILIES[family]), params)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return []
    out = []
    for c, i in zip(corners, ids.ravel()):
        c = normalize_corners(np.asarray(c, np.float64).reshape(4, 2), refinement)
        if scale != 1:
            c = (c + 0.5) / scale - 0.5
        out.append(TagDetection(int(i), c, f"{refinement}@{scale}x"))
    return out


def _detect_auto(gray: np.ndarray, family: str) -> list[TagDetection]:
    """Every tag any refiner finds, with the corners of the most accurate one that passes `_check_corners`.

    The runs are lazy: the 2x runs (when the image is small enough) and contour at 1x, the widest net, go first;
    the rest only run while some tag found so far has no corners that pass.
    """
    upsample = gray.size * 4 <= MAX_UPSAMPLED_PX
    order = [(m, s) for m, s in AUTO_ORDER if s == 1 or upsample]
    runs: dict[tuple[str, int], dict[int, TagDetection]] = {}

    def run(key: tuple[str, int]) -> dict[int, TagDetection]:
        if key not in runs:
            runs[key] = {d.id: d for d in _detect(gray, family, *key)}
        return runs[key]

    for key in [k for k in order if k[1] == 2][:2] + [("contour", 1)]:
        run(key)
    chosen: dict[int, TagDetection] = {}
    rejected: set[int] = set()
    for key in order:
        wanted = set().union(*(r.keys() for r in runs.values())) - set(chosen)
        if not wanted:
            break
        for tag_id, det in run(key).items():
            if tag_id in chosen:
                continue
            if _check_corners(gray, det.corners_px, tag_id, family):
                chosen[tag_id] = det
            else:
                rejected.add(tag_id)
    failed = rejected - set(chosen)
    if failed:
        log.debug("tags: %s found, but no refiner's corners pass the check; left out", sorted(failed))
    return sorted(chosen.values(), key=lambda d: d.id)


@lru_cache(maxsize=None)
def _expected_cells(family: str, tag_id: int) -> np.ndarray:
    """(10, 10) expected values, 0 black, 1 white: the tag's 8x8 cells inside a one-cell white quiet zone."""
    code = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(FAMILIES[family]), tag_id, 8)
    return np.pad(code > 127, 1, constant_values=True).astype(np.float64)


_SUB = (np.arange(3) - 1) * 0.25  # 3x3 samples per cell, a quarter cell apart: a mean over its middle half


def _check_corners(gray: np.ndarray, corners_px: np.ndarray, tag_id: int, family: str) -> bool:
    """Whether these corners read as this tag: a convex quad whose cells, sampled through the homography from the
    tag's 8x8 cell square to the corners, give the tag's code, its black border and a white quiet zone around it.

    A corner off by half a cell greys the border and quiet-zone cells along its edges, so this also checks that
    the four corners are consistent with the tag's grid."""
    c = np.asarray(corners_px, np.float64)
    e = np.roll(c, -1, axis=0) - c
    cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    if not (all(x > 0 for x in cross) or all(x < 0 for x in cross)):
        return False
    H = cv2.getPerspectiveTransform(np.float32([[0, 0], [8, 0], [8, 8], [0, 8]]), c.astype(np.float32))
    centres = np.arange(10) - 0.5  # cell centres of the quiet zone and the tag, in cells from the black square's TL
    gx = centres[None, :, None, None] + _SUB[None, None, None, :]
    gy = centres[:, None, None, None] + _SUB[None, None, :, None]
    gx, gy = np.broadcast_to(gx, (10, 10, 3, 3)), np.broadcast_to(gy, (10, 10, 3, 3))
    pts = cv2.perspectiveTransform(np.stack([gx, gy], -1).reshape(-1, 1, 2).astype(np.float32), H).reshape(-1, 2)
    h, w = gray.shape
    inside = ((pts[:, 0] >= -0.5) & (pts[:, 0] <= w - 0.5) & (pts[:, 1] >= -0.5) & (pts[:, 1] <= h - 0.5))
    inside = inside.reshape(10, 10, 9).all(-1)
    if not inside[1:-1, 1:-1].all():
        return False  # part of the tag itself is off the image
    values = cv2.remap(gray.astype(np.float32), pts[:, 0].reshape(1, -1).copy(), pts[:, 1].reshape(1, -1).copy(),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(10, 10, 9).mean(-1)
    expected = _expected_cells(family, tag_id)
    # Quiet-zone cells off the image are not read: a tag at the image's edge still counts.
    values, expected = values[inside], expected[inside]
    white, black = values[expected > 0.5].mean(), values[expected < 0.5].mean()
    if white - black < 255.0 * _CHECK_MIN_CONTRAST:
        return False
    read = values > 0.5 * (white + black)
    return int(np.sum(read != (expected > 0.5))) <= _CHECK_MAX_ERRORS


def _camera(K, dist) -> tuple[np.ndarray, np.ndarray]:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1:
        raise InputError("K", f"expected a 3x3 camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    if dist is None:
        return K, np.zeros(5)
    d = np.asarray(dist, dtype=np.float64).ravel()
    if d.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
        raise InputError("dist", f"expected 4, 5, 8, 12 or 14 finite OpenCV distortion coefficients, got {d.size}")
    return K, d


def _square_points(size_m: float) -> np.ndarray:
    """The tag's corners TL, TR, BR, BL in its own frame (x right, y up, z out of the tag), as IPPE_SQUARE wants."""
    h = 0.5 * size_m
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def _ippe_square(corners_px: np.ndarray, size_m: float, K, dist) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both IPPE solutions (R, t) tag-to-camera for one tag, best first."""
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(_square_points(size_m), corners_px.reshape(4, 1, 2), K, dist,
                                             flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return [(cv2.Rodrigues(r)[0], np.asarray(t, np.float64).ravel()) for r, t in zip(rvecs[:n], tvecs[:n])]


def tag_pose(detection: TagDetection, size_m: float, K: np.ndarray, dist=None) -> tuple[np.ndarray, np.ndarray]:
    """Pose (R (3, 3), t (3,)) of one tag in the camera, X_cam = R X_tag + t, by IPPE for squares.

    The tag frame has its origin at the tag's centre, x towards its right edge, y towards its top edge and z out of
    its printed face; size_m is the side of its black square.
    """
    if not (isinstance(size_m, (int, float)) and math.isfinite(size_m) and size_m > 0):
        raise InputError("size_m", f"expected the tag's side in metres (> 0), got {size_m!r}")
    K, dist = _camera(K, dist)
    R, t = _ippe_square(np.asarray(detection.corners_px), float(size_m), K, dist)[0]
    return R, t


def _tag_frame(corners_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Tag-to-world rotation, centre and side of a tag from its world corners TL, TR, BR, BL."""
    tl, tr, br, bl = corners_m
    x = (tr - tl) + (br - bl)
    y = (tl - bl) + (tr - br)
    x /= np.linalg.norm(x)
    y -= x * (x @ y)
    y /= np.linalg.norm(y)
    side = float(np.mean(np.linalg.norm(corners_m - np.roll(corners_m, -1, axis=0), axis=1)))
    return np.stack([x, y, np.cross(x, y)], axis=1), corners_m.mean(axis=0), side


def _rms_px(obj: np.ndarray, img: np.ndarray, R: np.ndarray, t: np.ndarray, K, dist) -> float:
    proj, _ = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))


def camera_pose_from_tags(detections, layout: TagLayout, K, dist=None, *, use_structure_tags: bool = False,
                          min_tags: int = 1) -> CameraPose | None:
    """The camera's world pose from the detected tags that the layout places; None below min_tags such tags.

    Tags on the structure move with it and are left out unless use_structure_tags. The pose starts from the best
    single-tag IPPE solution (lowest reprojection error over all used corners) and is refined over all corners
    by Levenberg-Marquardt.
    """
    if int(min_tags) < 1:
        raise InputError("min_tags", f"expected >= 1, got {min_tags}")
    K, dist = _camera(K, dist)
    placed = {t.id: t for t in layout.tags}
    used, obj, img = [], [], []
    for det in detections:
        tag = placed.get(det.id)
        if tag is None or (tag.on_structure and not use_structure_tags) or det.id in used:
            continue
        corners_m = np.asarray(tag.corners_m, dtype=np.float64)
        if corners_m.shape != (4, 3):
            raise InputError(f"layout.tags[id={tag.id}].corners_m",
                             f"expected 4 (x, y, z) corners, got shape {corners_m.shape}")
        used.append(det.id)
        obj.append(corners_m)
        img.append(np.asarray(det.corners_px, dtype=np.float64))
    if len(used) < int(min_tags):
        return None
    obj_all, img_all = np.concatenate(obj), np.concatenate(img)

    best = None
    for corners_m, corners_px in zip(obj, img):
        R_tw, centre, side = _tag_frame(corners_m)
        for R_tc, t_tc in _ippe_square(corners_px, side, K, dist):
            R = R_tc @ R_tw.T                         # world-to-camera
            t = t_tc - R @ centre
            err = _rms_px(obj_all, img_all, R, t, K, dist)
            if best is None or err < best[0]:
                best = (err, R, t)
    _, R, t = best
    rvec, tvec = cv2.solvePnPRefineLM(obj_all, img_all, K, dist, cv2.Rodrigues(R)[0], t.reshape(3, 1).copy())
    R, t = cv2.Rodrigues(rvec)[0], tvec.ravel()
    return CameraPose(R=R, t=t, tag_ids=tuple(used), rms_px=_rms_px(obj_all, img_all, R, t, K, dist))
