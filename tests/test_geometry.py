"""odsplat.spine.geometry: look-at poses identical to hil_sim's camera, camera centres, rotation and viewing angles,
spherical camera positions."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from odsplat.hil_sim.render import PinholeCamera
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import (
    camera_center_m,
    direction,
    look_at,
    rotation_angle_deg,
    spherical_coords,
    spherical_eye,
    viewing_angle_deg,
)


def _eyes(n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        target = rng.uniform(-1, 1, 3)
        eye = target + rng.uniform(0.3, 3.0) * Rotation.random(random_state=rng).apply([1.0, 0.0, 0.0])
        up = rng.normal(size=3) if rng.random() < 0.3 else np.array([0.0, 0.0, 1.0])
        out.append((eye, target, up))
    return out


def test_look_at_is_bit_identical_to_hil_sim_camera():
    for eye, target, up in _eyes(200):
        R, t = look_at(eye, target, up)
        cam = PinholeCamera.look_at(eye, target, up, fov_deg=50.0, width_px=64, height_px=48)
        np.testing.assert_array_equal(R, cam.R)
        np.testing.assert_array_equal(t, cam.t)
    # plain tuples and the default up, as a caller in the field would pass them
    R, t = look_at((1.4, -0.3, 0.9), (0.2, 0.0, 0.3))
    cam = PinholeCamera.look_at((1.4, -0.3, 0.9), (0.2, 0.0, 0.3), fx_px=100.0, width_px=8, height_px=8)
    np.testing.assert_array_equal(R, cam.R)
    np.testing.assert_array_equal(t, cam.t)


def test_look_at_follows_the_opencv_convention():
    eye, target = np.array([2.0, 1.0, 1.5]), np.array([0.2, 0.0, 0.3])
    R, t = look_at(eye, target)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-15)
    # the target lies on the optical axis (+z) at its distance
    np.testing.assert_allclose(R @ target + t, [0.0, 0.0, np.linalg.norm(target - eye)], atol=1e-15)
    # world up points up in the image (camera -y), and camera x is horizontal
    assert (R @ [0.0, 0.0, 1.0])[1] < -0.5
    assert R[0, 2] == pytest.approx(0.0, abs=1e-15)
    np.testing.assert_allclose(camera_center_m(R, t), eye, atol=1e-15)


@pytest.mark.parametrize("eye, target", [((1.0, 2.0, 3.0), (1.0, 2.0, 3.0)), ((0.2, 0.0, 2.0), (0.2, 0.0, 0.3))])
def test_look_at_refuses_degenerate_views(eye, target):
    with pytest.raises(InputError, match="look_at"):
        look_at(eye, target)


def test_look_at_names_a_malformed_argument():
    with pytest.raises(InputError) as err:
        look_at((1.0, 2.0), (0.0, 0.0, 0.0))
    assert err.value.source == "look_at.eye_m"


def test_camera_center_round_trip():
    for eye, target, up in _eyes(50, seed=1):
        np.testing.assert_allclose(camera_center_m(*look_at(eye, target, up)), eye, atol=1e-14)


@pytest.mark.parametrize("angle_deg", [0.0, 1e-7, 1e-3, 0.5, 30.0, 90.0, 179.0, 179.9999, 180.0])
def test_rotation_angle_of_a_known_relative_rotation(angle_deg):
    rng = np.random.default_rng(2)
    for _ in range(10):
        R_b = Rotation.random(random_state=rng).as_matrix()
        axis = rng.normal(size=3)
        delta = Rotation.from_rotvec(math.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
        got = rotation_angle_deg(delta @ R_b, R_b)
        # atan2 keeps tiny angles to ~1e-14 deg; arccos of the trace would give 0 below ~1e-6 deg
        assert got == pytest.approx(angle_deg, abs=1e-9 if angle_deg < 1 else 1e-7)
    assert rotation_angle_deg(np.eye(3), np.eye(3)) == 0.0


def test_viewing_angle_at_the_target():
    target = np.array([0.2, 0.0, 0.3])
    assert viewing_angle_deg(target + [1, 0, 0], target + [0, 3, 0], target) == pytest.approx(90.0, abs=1e-12)
    assert viewing_angle_deg(target + [1, 0, 0], target + [-2, 0, 0], target) == pytest.approx(180.0, abs=1e-12)
    # distance along the ray does not change the angle
    assert viewing_angle_deg(target + [1, 0, 0], target + [5, 0, 0], target) == 0.0
    eps = 1e-6
    b = target + [math.cos(math.radians(eps)), math.sin(math.radians(eps)), 0.0]
    assert viewing_angle_deg(target + [1, 0, 0], b, target) == pytest.approx(eps, rel=1e-8)
    with pytest.raises(InputError, match="coincides"):
        viewing_angle_deg(target, target + 1, target)


def test_spherical_eye_conventions():
    target = (0.2, 0.0, 0.3)
    np.testing.assert_allclose(spherical_eye(0, 0, 1.6, target), [1.8, 0.0, 0.3], atol=1e-15)
    np.testing.assert_allclose(spherical_eye(90, 0, 1.6, target), [0.2, 1.6, 0.3], atol=1e-15)  # +x towards +y
    np.testing.assert_allclose(spherical_eye(0, 90, 1.6, target), [0.2, 0.0, 1.9], atol=1e-15)  # elevation: up
    np.testing.assert_allclose(spherical_eye(180, 30, 2.0, target), [0.2 - math.sqrt(3), 0.0, 1.3], atol=1e-15)
    eye = spherical_eye(137.0, 34.0, 1.6, target)
    assert np.linalg.norm(eye - target) == pytest.approx(1.6, abs=1e-15)
    assert np.linalg.norm(direction(137.0, 34.0)) == pytest.approx(1.0, abs=1e-15)
    az, el, d = spherical_coords(eye, target)
    assert (az, el, d) == pytest.approx((137.0, 34.0, 1.6), abs=1e-12)
    assert spherical_coords(spherical_eye(-30.0, 10.0, 1.0, target), target)[0] == pytest.approx(330.0, abs=1e-12)
    assert spherical_coords(spherical_eye(-1e-15, 10.0, 1.0, target), target)[0] < 360.0
    with pytest.raises(InputError) as err:
        spherical_eye(0, 10, 0.0, target)
    assert err.value.source == "spherical_eye.distance_m"
