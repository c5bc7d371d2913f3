"""The modal motion model on views rendered by hil_sim: the recovered 3D displacement against the truth, its principal
components, and magnification in 3D. (At a tenth of the amplitude the fit finds the motion but misses a quarter
of it, docs/reconstruction.md; that slower run is left to the bench's figures for the suite's time.)"""
import dataclasses

import cv2
import numpy as np
import pytest
import torch

from odsplat.hil_sim.render import PinholeCamera, render
from odsplat.hil_sim.scene import build_scene
from odsplat.reconstruction.dynamic import FitSettings, fit_static
from odsplat.reconstruction.gaussians import Gaussians
from odsplat.reconstruction.modal import ModalMotion, ModalSettings, fit_modal
from odsplat.reconstruction.model import DynamicScene
from odsplat.reconstruction.quaternion import quat_conjugate, quat_from_rotvec, quat_multiply, quat_to_rotvec
from odsplat.reconstruction.views import Camera, ViewSet
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import spherical_eye
from odsplat.spine.paths import DerivedPaths

from .test_dynamic import TARGET, _train_views, surface_points

N_T = 6
ENVELOPE = np.sin(np.linspace(0, 1.4 * np.pi, N_T)) * np.exp(-np.linspace(0, 1.0, N_T))  # a decaying swing


@pytest.fixture(scope="module")
def rig():
    """Eight 64 x 48 views of the rig with mode 1 swinging over six timesteps at a tip amplitude of 30 mm (1.5 px),
    and the rest fit."""
    scene = build_scene()
    sv = scene.structure_vertices()
    unit = 1.0 / np.abs(scene.shapes[sv, 0, :]).max()  # modal coordinate per metre of tip motion
    seqs = {0.03: []}
    cams = []
    for k in range(8):
        eye = spherical_eye(45 * k, 25 + 20 * (k % 2), 1.6, TARGET)
        pc = PinholeCamera.look_at(eye, TARGET, fov_deg=50, width_px=192, height_px=144)
        cams.append(Camera(pc.K, pc.R, pc.t, 192, 144, f"v{k}").resized(64))
        for tip, seq in seqs.items():
            frames = [render(scene.mesh(np.eye(scene.shapes.shape[1])[0] * unit * tip * e), pc, scene.atlas).image
                      for e in ENVELOPE]
            seq.append(np.stack([cv2.resize(f.astype(np.float32), (64, 48), interpolation=cv2.INTER_AREA)
                                 for f in frames])[..., None])
    views = {tip: _train_views(list(zip(cams, seq))) for tip, seq in seqs.items()}
    frame, tv = views[0.03]
    pts = surface_points(scene, 2500, np.random.default_rng(0))
    g = Gaussians.from_points(frame.to_scene(pts), np.full((len(pts), 1), 0.5))
    g0, stats = fit_static(g, [(v.camera, v.images[0]) for v in tv], FitSettings(iters_t0=300, progress=False))
    return scene, views, g0, torch.tensor(stats["background"]), unit


def _gain(scene, frame, g0, motion: ModalMotion, tip: float, unit: float):
    """Least-squares gain and relative error of the recovered displacement on the moving structure."""
    traj = motion.trajectory(g0)
    m = traj.means.double().numpy()
    rest = frame.to_world(m[0])
    disp = (m - m[:1]) * frame.radius
    shape = scene.structure.mode_shapes(rest)[:, 0, :] * unit * tip
    inside = np.zeros(len(rest), bool)
    for lo, hi in scene.structure.geometry.boxes().values():
        inside |= np.all((rest > np.asarray(lo) - 0.01) & (rest < np.asarray(hi) + 0.01), axis=1)
    sel = inside & (g0.opacities.numpy() > 0.3) & (np.linalg.norm(shape, axis=1) > 0.4 * tip)
    truth = ENVELOPE[:, None, None] * shape[None]
    gain = float((disp[:, sel] * truth[:, sel]).sum() / (truth[:, sel] ** 2).sum())
    err = float(np.linalg.norm(disp[:, sel] - truth[:, sel]) / np.linalg.norm(truth[:, sel]))
    floor = (rest[:, 2] < 0.005) & ~inside & (np.linalg.norm(rest[:, :2], axis=1) < 0.5)
    return gain, err, float(np.median(np.abs(disp[:, floor]).max(axis=0))), int(sel.sum()), int(floor.sum())


def test_modal_fit_recovers_the_displacement(rig):
    scene, views, g0, bg, unit = rig
    s = ModalSettings(iters=600, n_components=2, progress=False)   # the default 2000 in bench/analysis.py
    out = {}
    for tip, (frame, tv) in views.items():
        motion = fit_modal(g0, tv, s, bg)
        assert motion.basis.shape == (N_T, 2) and motion.shapes.shape == (len(g0), 2, 3)
        assert float(motion.basis[0].abs().max()) == 0.0  # timestep 0 is the rest state
        out[tip] = _gain(scene, frame, g0, motion, tip, unit)
    for tip, (_, _, floor, n_sel, n_floor) in out.items():
        assert n_sel >= 20 and n_floor >= 20
        assert floor < 0.1 * tip, out  # the floor stays still
    gain, err = out[0.03][:2]
    assert 0.85 < gain < 1.15 and err < 0.3, out  # measured 0.97 and 0.19 (1.02 and 0.17 after 2000 iterations)


def test_principal_components_rebuild_the_motion():
    gen = torch.Generator().manual_seed(0)
    basis = torch.cat([torch.zeros(1, 3), torch.randn(7, 3, generator=gen, dtype=torch.float64).float()]).double()
    shapes = torch.randn(50, 3, 3, generator=gen, dtype=torch.float64)
    rot = torch.randn(50, 3, 3, generator=gen, dtype=torch.float64) * 1e-3
    m = ModalMotion(basis, shapes, rot, scale=1.0)
    b, phi, psi, energy = m.principal()
    assert np.allclose(np.einsum("tk,nkc->tnc", b, phi), np.einsum("tk,nkc->tnc", basis.numpy(), shapes.numpy()))
    assert np.allclose(np.einsum("tk,nkc->tnc", b, psi), np.einsum("tk,nkc->tnc", basis.numpy(), rot.numpy()))
    assert np.allclose(np.sqrt((b ** 2).mean(axis=0)), 1.0)
    assert energy.sum() == pytest.approx(1.0) and np.all(np.diff(energy) <= 1e-12)


def test_rotation_vectors_round_trip():
    gen = torch.Generator().manual_seed(3)
    axis = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen, dtype=torch.float64), dim=-1)
    v = axis * torch.rand(200, 1, generator=gen, dtype=torch.float64) * 3.1
    assert torch.allclose(quat_to_rotvec(quat_from_rotvec(v)), v, atol=1e-12)
    tiny = axis * 1e-7
    q = quat_from_rotvec(tiny)
    assert torch.allclose(q.norm(dim=-1), torch.ones(200, dtype=torch.float64), atol=1e-15)
    assert torch.allclose(quat_to_rotvec(q), tiny, rtol=1e-9, atol=0)


def test_scene_magnifies_in_3d_and_saves_the_modal_model(rig, tmp_path):
    scene_, views, g0, bg, _ = rig
    frame, tv = views[0.03]
    motion = fit_modal(g0, tv, ModalSettings(iters=20, n_components=2, progress=False), bg)
    vs = ViewSet(tv, [], np.arange(N_T), np.arange(N_T) / 2000.0, frame, 12, source_alpha=1.0)
    ds = DynamicScene.from_model(g0, motion.trajectory(g0), vs, bg, motion)
    assert ds.motion == "modal"
    t = float(vs.times_s[3])
    m1, q1 = ds.state(t)
    m5, q5 = ds.state(t, alpha=5.0)
    rest = torch.as_tensor(frame.to_scene(ds.means_rest_m), dtype=torch.float32)
    # the means are float32 scene coordinates under 1: rounded by 6e-8 each, the 5x by five times that
    assert torch.allclose(m5 - rest, 5 * (m1 - rest), atol=1e-5 * float((m1 - rest).abs().max()) + 6e-7)
    # rotations: the turn from rest is scaled too
    q0 = torch.as_tensor(ds.quats[0], dtype=torch.float64)
    turn = lambda q: quat_to_rotvec(quat_multiply(q.double(), quat_conjugate(q0)))  # noqa: E731
    assert torch.allclose(turn(q5), 5 * turn(q1), atol=1e-6)
    # alpha = 0 is the rest state
    m0, _ = ds.state(t, alpha=0.0)
    assert torch.allclose(m0, rest, atol=1e-6)
    ds.save(DerivedPaths(tmp_path))
    back = DynamicScene.read(DerivedPaths(tmp_path).trajectories_npz)
    assert back.motion == "modal" and back.source_alpha == 1.0
    assert np.allclose(back.shapes_m, ds.shapes_m) and np.allclose(back.basis, ds.basis)
    # The file holds the basis and shapes, not the (T, N, 3) and (T, N, 4) fields they multiply out to, and
    # reads back the same motion.
    with np.load(DerivedPaths(tmp_path).trajectories_npz) as z:
        assert "displacement_m" not in z.files and "quats" not in z.files and z["quats_rest"].shape == (len(g0), 4)
        arrays = {k: z[k] for k in z.files}
    assert np.array_equal(back.displacement_m, ds.displacement_m) and np.allclose(back.quats, ds.quats, atol=1e-12)
    assert np.allclose(ds.displacement_m, (motion.trajectory(g0).means.double().numpy() - rest.numpy()[None])
                       * frame.radius, atol=1e-6 * frame.radius)
    np.savez(tmp_path / "bad.npz", **{**arrays, "basis": arrays["basis"][1:]})
    with pytest.raises(InputError, match="basis, shapes_m"):
        DynamicScene.read(tmp_path / "bad.npz")
    mb, _ = back.state(t, alpha=5.0)
    assert torch.allclose(mb, m5, atol=1e-5)
    # A model trained on frames magnified 30x in 2D reports its physical displacement divided by 30.
    mag = dataclasses.replace(ds, source_alpha=30.0)
    assert np.allclose(mag.physical_displacement_m(), ds.displacement_m / 30.0)
    m30, _ = mag.state(t, alpha=30.0)
    assert torch.allclose(m30, m1, atol=1e-7)


def test_bad_settings_name_the_field():
    for kw, field in (({"n_components": 0}, "n_components"), ({"loss": "l3"}, "loss"), ({"iters": -1}, "iters"),
                      ({"k_neighbours": 0}, "k_neighbours")):
        with pytest.raises(InputError, match=field):
            ModalSettings(**kw)
