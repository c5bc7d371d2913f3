"""The rig scene: tags detectable where the layout says, motion only on the structure, sub-pixel sensitivity."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from odsplat.hil_sim.render import PinholeCamera, render
from odsplat.hil_sim.scene import FLOOR, STRUCTURE


@pytest.fixture(scope="module")
def camera():
    return PinholeCamera.look_at((1.0, -1.1, 0.9), (0.1, 0.0, 0.3), fov_deg=50, width_px=512, height_px=512)


def test_tags_are_detected_at_their_layout_corners(scene, camera):
    image = render(scene.mesh(), camera, scene.atlas, background=0.5).image
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)
    corners, ids, _ = detector.detectMarkers((np.clip(image, 0, 1) * 255).astype(np.uint8))
    assert ids is not None and len(ids) >= 6
    placements = {t.id: t for t in scene.tags.tags}
    assert any(placements[int(i)].on_structure for i in ids.ravel())
    for found, tag_id in zip(corners, ids.ravel()):
        expected = camera.project(np.array(placements[int(tag_id)].corners_m))[0]
        # OpenCV's refiners differ by up to half a pixel in their corner convention.
        assert np.abs(found[0] - expected).max() < 1.0, (tag_id, found[0], expected)


def test_only_the_structure_moves(scene):
    q = np.linspace(1e-3, 2e-3, scene.structure.n_modes)
    moved = np.linalg.norm(scene.deformed(q) - scene.rest_m, axis=1)
    floor = np.unique(scene.faces[scene.object_id == FLOOR])
    assert moved[floor].max() == 0
    assert moved[scene.structure_vertices()].max() > 1e-4
    np.testing.assert_allclose(scene.deformed(q, alpha=50) - scene.rest_m, 50 * (scene.deformed(q) - scene.rest_m),
                               atol=1e-12)


def test_a_hundredth_of_a_pixel_changes_the_image(scene, camera):
    # Modal state whose largest image motion is 0.01 px.
    q = np.zeros(scene.structure.n_modes)
    q[0] = 1e-4
    idx = scene.structure_vertices()
    shift_px = np.abs(camera.project(scene.deformed(q)[idx])[0] - camera.project(scene.rest_m[idx])[0]).max()
    q *= 0.01 / shift_px
    still = render(scene.mesh(), camera, scene.atlas, background=0.5)
    moved = render(scene.mesh(q), camera, scene.atlas, background=0.5)
    diff = np.abs(moved.image - still.image)
    on_structure = still.object_id == STRUCTURE
    assert diff[on_structure].mean() > 1e-4  # about 1/2 LSB of a 12-bit camera on average
    # The floor does not move (away from edge pixels shared with the structure).
    floor = cv2.erode((still.object_id == FLOOR).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert diff[floor].max() < 1e-6
