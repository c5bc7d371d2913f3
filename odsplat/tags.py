"""AprilTag detection and camera pose from tags, with corners in one convention: pixel (0, 0)'s centre at (0, 0).

That is the convention of OpenCV's camera matrix and of `hil_sim`'s renderer. OpenCV's corner refiners each report
corners in their own convention; `normalize_corners` is the one place that converts them (see docs/tags.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from odsplat.errors import InputError
from odsplat.geometry import rotation_angle_deg  # noqa: F401  (re-exported)
from odsplat.manifest import TagLayout

FAMILIES = {"tag36h11": cv2.aruco.DICT_APRILTAG_36h11}
REFINEMENTS = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}


@dataclass(frozen=True, eq=False)
class TagDetection:
    """One detected tag: its id and its four corners in px (normalised convention), order TL, TR, BR, BL."""

    id: int
    corners_px: np.ndarray  # (4, 2) float64

    def __post_init__(self) -> None:
        corners = np.array(self.corners_px, dtype=np.float64)
        if corners.shape != (4, 2) or not np.all(np.isfinite(corners)):
            raise InputError("TagDetection.corners_px", f"expected 4 finite (x, y) corners, got shape {corners.shape}")
        corners.setflags(write=False)
        object.__setattr__(self, "id", int(self.id))
        object.__setattr__(self, "corners_px", corners)


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


def _check_refinement(refinement: str) -> None:
    if refinement not in REFINEMENTS:
        raise InputError("refinement", f"expected one of {sorted(REFINEMENTS)}, got {refinement!r}")


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


def detect_tags(image: np.ndarray, *, family: str = "tag36h11", refinement: str = "apriltag") -> list[TagDetection]:
    """Detect tags in a mono (H, W) or RGB (H, W, 3) image; corners normalised, detections sorted by id.

    "apriltag" is the default because it is the most accurate refiner here, sharp or blurred (docs/tags.md); it
    finds fewer very small tags (under about 22 px a side) than the contour-based ones.

    Integer images are scaled by the bit depth their values use (12-bit data in uint16 included); float images
    in [0, 1] are taken as they are, other float ranges are scaled to their maximum.
    """
    if family not in FAMILIES:
        raise InputError("family", f"expected one of {sorted(FAMILIES)}, got {family!r}")
    _check_refinement(refinement)
    gray = _to_gray_u8(image)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = REFINEMENTS[refinement]
    # One detector per call: OpenCV's detector writes to its parameters while detecting.
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(FAMILIES[family]), params)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return []
    found = [TagDetection(int(i), normalize_corners(np.asarray(c, np.float64).reshape(4, 2), refinement))
             for c, i in zip(corners, ids.ravel())]
    return sorted(found, key=lambda d: d.id)


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
