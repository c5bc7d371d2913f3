"""Where the 2D path tracks (issue 45): a grid over what can be tracked, or the outlines, besides Shi-Tomasi's
points (tracking.grid_points, tracking.edge_points; Video2DSettings.layout)."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.analysis.tracking import edge_points, grid_points, track_points
from odsplat.analysis.video2d import Video2DSettings, pick_points
from odsplat.spine.errors import InputError

H, W = 120, 160
X0, X1, Y0, Y1 = 40, 120, 30, 90          # a speckled plate on a flat background


def _frame(shift_px: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(1)
    speckle = rng.random((H, W))
    img = np.full((H, W), 0.2)
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    inside = (xx >= X0 + shift_px) & (xx < X1 + shift_px) & (yy >= Y0) & (yy < Y1)
    img[inside] = 0.5 + 0.4 * np.roll(speckle, int(round(shift_px)), axis=1)[inside]
    return img


def test_the_grid_covers_what_can_be_tracked_and_nothing_else():
    p = grid_points(_frame(), spacing_px=8, window_px=11)
    assert len(p) > 40
    # every node is on the plate or within a window of its outline, and none on the flat background
    assert np.all((p[:, 0] >= X0 - 6) & (p[:, 0] <= X1 + 6) & (p[:, 1] >= Y0 - 6) & (p[:, 1] <= Y1 + 6))
    steps = np.diff(np.unique(p[:, 0]))
    assert np.allclose(steps, 8)
    # the spacing grows to hold max_points
    fewer = grid_points(_frame(), spacing_px=8, window_px=11, max_points=20)
    assert 0 < len(fewer) <= 20


def test_edge_points_lie_on_the_outline_a_spacing_apart():
    p = edge_points(_frame(), spacing_px=6, window_px=11, max_points=500)
    assert len(p) > 20
    # Canny on a speckled plate finds the speckle too; the strongest edges, first, are the outline
    first = p[:20]
    on_outline = (np.minimum(np.abs(first[:, 0] - X0), np.abs(first[:, 0] - X1)) <= 2) | \
                 (np.minimum(np.abs(first[:, 1] - Y0), np.abs(first[:, 1] - Y1)) <= 2)
    assert on_outline.mean() >= 0.8
    d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1)) + np.eye(len(p)) * 1e9
    assert d.min() >= 6 - 1e-9


def test_the_layout_is_a_setting_and_its_points_track():
    s = Video2DSettings(layout="grid", window_px=11, min_distance_px=10)
    p = pick_points(_frame(), s)
    tracks = track_points(np.stack([_frame(), _frame(1.0)]), p, window_px=11)
    d = tracks.displacement_px[1]
    ok = np.all(np.isfinite(d), axis=1)
    inner = ok & (p[:, 0] > X0 + 8) & (p[:, 0] < X1 - 8) & (p[:, 1] > Y0 + 8) & (p[:, 1] < Y1 - 8)
    assert inner.sum() > 10
    assert np.median(d[inner, 0]) == pytest.approx(1.0, abs=0.05)
    with pytest.raises(InputError, match="analyze.video2d.layout"):
        Video2DSettings(layout="mesh")
