"""Camera-pose geometry shared by the stages: world z up, floor z = 0, world-to-camera poses X_cam = R X_world + t
in the OpenCV/COLMAP convention (camera x right, y down, z forward); azimuth from +x towards +y, elevation up."""
from __future__ import annotations

import math

import numpy as np

from odsplat.spine.errors import InputError


def _vec3(source: str, value) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise InputError(source, f"expected 3 numbers (x, y, z), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(source, "contains NaN or inf")
    return arr


def _mat3(source: str, value) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3, 3):
        raise InputError(source, f"expected a 3x3 matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(source, "contains NaN or inf")
    return arr


def look_at(eye_m, target_m, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at eye_m looking at target_m with `up` pointing up in the image.

    `odsplat.hil_sim.render.PinholeCamera.look_at` uses it, so simulated and planned poses agree exactly.
    """
    eye = _vec3("look_at.eye_m", eye_m)
    forward = _vec3("look_at.target_m", target_m) - eye
    right = np.cross(forward, _vec3("look_at.up", up))
    if np.linalg.norm(forward) == 0 or np.linalg.norm(right) < 1e-12 * np.linalg.norm(forward):
        raise InputError("look_at", "eye and target coincide, or the view direction is parallel to up")
    z = forward / np.linalg.norm(forward)
    x = right / np.linalg.norm(right)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera x (right), y (down = z cross x), z (forward)
    return R, -R @ eye


def camera_center_m(R, t) -> np.ndarray:
    """Optical centre in world coordinates of the world-to-camera pose (R, t): C = -R^T t."""
    R = _mat3("camera_center_m.R", R)
    return -R.T @ _vec3("camera_center_m.t", t)


def rotation_angle_deg(R_a, R_b) -> float:
    """Angle in degrees, in [0, 180], of the relative rotation R_a R_b^T."""
    M = _mat3("rotation_angle_deg.R_a", R_a) @ _mat3("rotation_angle_deg.R_b", R_b).T
    # atan2 of the sine (from the skew part) and cosine (from the trace) stays accurate near 0 and 180 degrees,
    # where arccos of the trace alone loses half the digits.
    sin = 0.5 * math.hypot(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])
    cos = 0.5 * (M[0, 0] + M[1, 1] + M[2, 2] - 1.0)
    return math.degrees(math.atan2(sin, cos))


def viewing_angle_deg(center_a, center_b, target) -> float:
    """Angle in degrees at `target` between the rays to the two camera centres."""
    target = _vec3("viewing_angle_deg.target", target)
    u = _vec3("viewing_angle_deg.center_a", center_a) - target
    v = _vec3("viewing_angle_deg.center_b", center_b) - target
    if not np.any(u) or not np.any(v):
        raise InputError("viewing_angle_deg", "a camera centre coincides with the target")
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(u, v))), float(np.dot(u, v))))


def direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector from the target towards azimuth/elevation (degrees)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def spherical_eye(azimuth_deg: float, elevation_deg: float, distance_m: float, target_m) -> np.ndarray:
    """Camera position at distance_m from target_m in the direction azimuth/elevation (degrees): azimuth in the
    world x-y plane from +x towards +y, elevation up from the horizontal plane through the target."""
    if not math.isfinite(distance_m) or distance_m <= 0:
        raise InputError("spherical_eye.distance_m", f"expected a finite distance > 0, got {distance_m}")
    return _vec3("spherical_eye.target_m", target_m) + distance_m * direction(azimuth_deg, elevation_deg)


def spherical_coords(eye_m, target_m) -> tuple[float, float, float]:
    """Inverse of `spherical_eye`: (azimuth_deg in [0, 360), elevation_deg, distance_m) of eye_m seen from target_m."""
    d = _vec3("spherical_coords.eye_m", eye_m) - _vec3("spherical_coords.target_m", target_m)
    horizontal = math.hypot(d[0], d[1])
    distance = math.hypot(horizontal, d[2])
    if distance == 0:
        raise InputError("spherical_coords", "the eye coincides with the target")
    azimuth = math.degrees(math.atan2(d[1], d[0])) % 360.0
    if azimuth == 360.0:  # a tiny negative angle modulo 360 rounds up to 360
        azimuth = 0.0
    return azimuth, math.degrees(math.atan2(d[2], horizontal)), distance
