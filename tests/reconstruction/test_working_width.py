"""The rest fit's working width follows the views: at most half a motion node per working pixel, whatever the
cameras' size, within [128 px, the views' width]; as set when set."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.reconstruction import ReconstructSettings, working_width
from odsplat.reconstruction.linear import NODE_PX
from odsplat.reconstruction.pose_result import PoseResult, ViewPose
from odsplat.spine.geometry import look_at


def _poses(width_px: int, n_points: int = 400, distance_m: float = 1.6) -> PoseResult:
    """Twelve views of a 0.5 m structure from distance_m, 50 degrees across, width_px x 3/4 of it."""
    h = width_px * 3 // 4
    fx = 0.5 * width_px / np.tan(np.radians(25))
    K = np.array([[fx, 0, (width_px - 1) / 2], [0, fx, (h - 1) / 2], [0, 0, 1.0]])
    views = []
    for k, az in enumerate(np.radians(np.arange(0, 360, 30))):
        eye = np.array([distance_m * np.cos(az), distance_m * np.sin(az), 0.6])
        R, t = look_at(eye, np.array([0.0, 0.0, 0.25]))
        views.append(ViewPose(f"v{k:02d}_000", "take", k, "tags", K, R, t, width_px, h, None, None, None))
    pts = np.random.default_rng(0).uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.5], (n_points, 3))
    return PoseResult(views, pts, np.full((n_points, 1), 0.5), np.zeros(n_points), "tags", None, None, None, None,
                      len(views), len(views), [])


@pytest.mark.parametrize("n_points", [400, 0])     # with the pose stage's points, and tag-only poses without
def test_working_width_follows_the_views_footprint(n_points):
    s = ReconstructSettings()
    assert s.width_px is None
    widths = {w: working_width(_poses(w, n_points), s) for w in (256, 320, 512, 1024, 2048)}
    assert widths[256].width_px == 128 and widths[320].width_px == 128     # 5 px a node: 2 working px at 128
    for w, got in widths.items():
        assert got.width_px % 16 == 0 and 128 <= got.width_px <= max(w, 128)
        spacing_px = float(got.why.split(" = ")[1].split(" px")[0])
        assert spacing_px >= NODE_PX - 0.05
        assert spacing_px * got.width_px / w >= 2 - 1e-9 or got.width_px == w, (w, got)
    assert widths[512].width_px > 128                       # 5 px of 512 is 2 px of 205: finer than 128
    # Past the footprint where the scene's radius / 100 sets the spacing, the width stops growing with the pixels:
    # a 1024 px camera needs no more than the spacing asks for.
    assert widths[2048].width_px == widths[1024].width_px < 1024
    assert widths[2048].why.startswith("node spacing")


def test_working_width_as_set_and_for_the_other_models():
    poses = _poses(1024)
    assert working_width(poses, ReconstructSettings(width_px=96)).width_px == 96
    assert working_width(poses, ReconstructSettings(motion="modal")).width_px == 128
    assert working_width(poses, ReconstructSettings(motion="timestep")).width_px == 128
