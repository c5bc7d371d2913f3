"""Several views, still 2D: 2D tracks triangulated to 3D by the views' projection Jacobians
(analysis/triangulate.py)."""
from __future__ import annotations

import numpy as np

from odsplat.analysis.crlb import projection_jacobian
from odsplat.analysis.tracking import project_displacement
from odsplat.analysis.triangulate import triangulate
from odsplat.spine.geometry import look_at


def _camera(eye):
    R, t = look_at(eye, (0.0, 0.0, 0.3))
    return np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]]), R, t


def test_tracks_from_three_views_triangulate_to_the_3d_motion_within_their_noise():
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.1, 0.1, (12, 3)) + [0, 0, 0.3]
    t = np.arange(200) / 1000.0
    motion = (np.sin(2 * np.pi * 31 * t)[:, None, None] * rng.normal(0, 1e-4, (1, 12, 3))
              + np.sin(2 * np.pi * 86 * t)[:, None, None] * rng.normal(0, 5e-5, (1, 12, 3)))      # (T, P, 3) m
    cams = [_camera(e) for e in ((1.5, 0.0, 0.8), (0.0, 1.5, 0.8), (-1.0, -1.0, 1.2), (1.0, -1.2, 0.2))]
    noise_px = 0.01
    tracks, jac = [], []
    for K, R, tr in cams:
        d = project_displacement(motion, points, K, R, tr) + rng.normal(0, noise_px, (len(t), 12, 2))
        tracks.append(d)
        jac.append(projection_jacobian(points, K, R, tr))
    tracks[3][:, :4] = np.nan                      # the fourth view does not see four of the points
    out, count, cond = triangulate(tracks, jac)
    assert count.tolist() == [3] * 4 + [4] * 8
    assert np.isfinite(out).all() and np.all(cond < 10)
    err = np.sqrt(np.mean((out - motion) ** 2))
    # the noise's share: px noise over the Jacobian's scale (~800 px / 1.6 m = 500 px/m), less with more views
    assert err < 2.5 * noise_px / 500.0, err
    assert np.corrcoef(out.ravel(), motion.ravel())[0, 1] > 0.97   # 0.988: 0.05 px of motion against 0.01 px


def test_a_point_seen_by_two_views_only_is_not_triangulated():
    points = np.array([[0.0, 0.0, 0.3]])
    cams = [_camera(e) for e in ((1.5, 0.0, 0.8), (0.0, 1.5, 0.8), (-1.0, -1.0, 1.2))]
    tracks = [np.zeros((5, 1, 2)) for _ in cams]
    tracks[2][:] = np.nan
    out, count, _ = triangulate(tracks, [projection_jacobian(points, *c) for c in cams])
    assert count.tolist() == [2] and np.isnan(out).all()
