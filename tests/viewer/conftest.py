"""One small capture for the viewer's tests, built once: two views on the simulated rig, synced, the true cameras as
poses, a reconstruction file holding hil_sim's exact motion on Gaussians over the column, the arm and a still floor,
and the real analysis of it; and a copy analysed before the reconstruction existed (accelerometers only)."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from odsplat.analysis import AnalyzeSettings, analyze_capture
from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture
from odsplat.hil_sim.structure import ModalStructure
from odsplat.reconstruction import DynamicScene, Gaussians, SceneFrame
from odsplat.spine.store import Capture
from odsplat.sync import SyncSettings, load_sync, sync_capture

from ..analysis.test_run import _surface_points as surface_points
from ..analysis.test_run import _truth, write_true_poses

# the viewer reads none of the analysis's figures (most of its time here); an ODS line off the modes
SETTINGS = AnalyzeSettings(image_poles=False, crosscheck_views=0, ods_freq_hz=(23.5, 60.0), plots=False)
FLOOR_HALF_M = 0.5


def floor_points(n_side: int = 40) -> np.ndarray:
    """A still floor at z = 0 around the structure (the capture has floor tags: the analysis's floor rule)."""
    g = np.linspace(-FLOOR_HALF_M, FLOOR_HALF_M, n_side)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def write_scene(cap: Capture, n_steps: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """derived/reconstruction/trajectories.npz as a perfect reconstruction would leave it (DynamicScene.save): the
    structure's Gaussians moving with hil_sim's exact modal motion (mean over the synced takes, impact-locked
    timeline), the floor's still. Returns (the means at rest, which are the floor's)."""
    grid = load_sync(cap).times_s
    k0 = int(np.searchsorted(grid, 0.0)) - 1
    times = grid[k0:k0 + n_steps]
    qs = []
    for take in load_sync(cap).ok:
        tr = _truth(cap, take.name)
        x = float(np.ravel(tr.impact_daq_sample)[0]) + times * tr.daq_rate_hz
        n = tr.modal_q_daq.shape[1]
        qs.append(np.stack([np.interp(x, np.arange(n), row) for row in tr.modal_q_daq]))
    q = np.mean(qs, axis=0)
    struct, floor = surface_points(120), floor_points()   # points over the column's and the arm's faces
    points = np.concatenate([struct, floor])
    disp = np.zeros((len(times), len(points), 3))
    disp[:, :len(struct)] = np.einsum("prc,rt->tpc", ModalStructure().mode_shapes(struct), q)
    n = len(points)
    frame = SceneFrame(np.array([0.0, 0.0, 0.3]), 1.0)
    rng = np.random.default_rng(5)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    scale = np.where(np.arange(n) < len(struct), 0.008, 0.012)
    rest = Gaussians(means=t(frame.to_scene(points)), quats=t(np.tile([1.0, 0, 0, 0], (n, 1))),
                     log_scales=t(np.log(np.repeat(scale[:, None], 3, axis=1))),
                     opacity_logits=t(np.full(n, 3.0)), color_logits=t(rng.normal(0, 1.5, (n, 1))))
    quats = np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(times), n, 1))
    scene = DynamicScene(np.asarray(times, float), np.arange(k0, k0 + len(times)), points, disp, quats, rest, frame, 8,
                         np.array([0.0]), 1.0)
    scene.save(cap.paths)
    return points, np.arange(n) >= len(struct)


@pytest.fixture(scope="session")
def captures(tmp_path_factory):
    """(the reconstructed and analysed capture, its floor mask, the accelerometer-only copy)."""
    root = tmp_path_factory.mktemp("viewer")
    out = root / "cap"
    report = simulate_capture(out, n_views=2, n_frames=30, pretrigger_frames=4, record_s=0.3,
                              settings=SimBenchSettings(seed=11))
    assert report.complete
    cap = Capture.open(out)
    sync_capture(cap, SyncSettings())
    write_true_poses(cap)
    analyze_capture(cap, SETTINGS)                   # accelerometers only: no reconstruction yet
    shutil.copytree(out, root / "accel_only")
    _, floor = write_scene(cap, n_steps=24)
    analyze_capture(cap, SETTINGS)
    return cap, floor, Capture.open(root / "accel_only")
