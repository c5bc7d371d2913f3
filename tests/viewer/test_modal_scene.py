"""The viewer on a modal model's file (the linear model's default): its turns from rest come from the basis and the
rotation shapes the file holds (DynamicScene.turns_rad), and equal what the orientations multiplied out give."""
from __future__ import annotations

import numpy as np
import torch

from odsplat.app.viewer.load import _scene
from odsplat.reconstruction import DynamicScene, Gaussians, SceneFrame
from odsplat.reconstruction.model import modal_quats
from odsplat.spine.paths import DerivedPaths


def test_a_modal_models_motion_and_turns_reach_the_viewer(captures, tmp_path):
    cap = captures[0]
    rng = np.random.default_rng(3)
    n, t, k = 300, 12, 3
    points = np.column_stack([rng.uniform(-0.04, 0.04, n), rng.uniform(-0.04, 0.04, n), rng.uniform(0.1, 0.6, n)])
    basis = np.vstack([np.zeros((1, k)), rng.normal(size=(t - 1, k))])         # timestep 0 is the rest state
    shapes = rng.normal(0, 20e-6, (n, k, 3))
    rot = rng.normal(0, 1e-3, (n, k, 3))
    q_rest = rng.normal(size=(n, 4))
    q_rest /= np.linalg.norm(q_rest, axis=1, keepdims=True)
    frame = SceneFrame(np.array([0.0, 0.0, 0.3]), 1.0)
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    rest = Gaussians(means=f32(frame.to_scene(points)), quats=f32(q_rest), log_scales=f32(np.full((n, 3), -5.0)),
                     opacity_logits=f32(np.full(n, 3.0)), color_logits=f32(rng.normal(size=(n, 1))))
    alpha = 2.0
    scene = DynamicScene(np.arange(t) / 2000.0, np.arange(t), points, np.einsum("tk,nkc->tnc", basis, shapes),
                         modal_quats(basis, rot, q_rest), rest, frame, 8, np.array([0.0]), alpha, basis, shapes, rot)
    scene.save(DerivedPaths(tmp_path))
    back = DynamicScene.read(DerivedPaths(tmp_path).trajectories_npz)
    view = _scene(cap, back, None)
    assert np.allclose(view.rotvec_rad, np.einsum("tk,nkc->tnc", basis, rot) / alpha, atol=1e-7)
    # the same turns as the orientations multiplied out give, read as the per-timestep model reads them
    from_quats = DynamicScene(back.times_s, back.frame_index, points, back.displacement_m, back.quats, rest, frame, 8,
                              np.array([0.0]), alpha)
    assert np.allclose(view.rotvec_rad, from_quats.turns_rad() / alpha, atol=1e-7)
    assert np.allclose(view.displacement_m, np.einsum("tk,nkc->tnc", basis, shapes) / alpha, atol=1e-10)


def test_the_view_turns_each_gaussian_from_its_rest_orientation():
    """The render's turn of each Gaussian (reconstruction's quaternions): the rotation from rest applied after the
    rest orientation, as scipy composes them."""
    from scipy.spatial.transform import Rotation

    from odsplat.app.viewer.model import _turned

    rng = np.random.default_rng(4)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = rng.normal(0, 0.5, (50, 3))
    r[0] = 0.0                                                                  # no turn at all
    got = _turned(q.astype(np.float32), r.astype(np.float32))
    want = (Rotation.from_rotvec(r) * Rotation.from_quat(q[:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    assert got.dtype == np.float32 and got.shape == (50, 4)
    assert np.allclose(got * np.sign(np.sum(got * want, axis=1))[:, None], want, atol=2e-6)
    assert np.allclose(got[0], q[0], atol=1e-7)
