"""bench/reconstruct.py's displacement figures on exact motion: they must read 1 for the truth and scale with it."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from odsplat.hil_sim.camera import SimCameraConfig
from odsplat.hil_sim.rig import SimRig, TakeTruth, truth_path


def _exact_scene(rig: SimRig, gt, times_s: np.ndarray, gain: float):
    """The structure's mesh vertices as Gaussians moving exactly as hil_sim's modes say, times `gain`."""
    pts = rig.scene.rest_m[rig.scene.structure_vertices()]
    q = np.stack([gt.q(float(t)) for t in times_s])
    disp = gain * np.einsum("pmc,tm->tpc", rig.structure.mode_shapes(pts), q - q[:1])
    return SimpleNamespace(times_s=times_s, means_rest_m=pts, rest=SimpleNamespace(opacities=torch.ones(len(pts))),
                           physical_displacement_m=lambda: disp)


@pytest.mark.parametrize("gain", [1.0, 0.5])
def test_displacement_scores_read_the_truth(sim_capture, gain, bench_script):
    bench = bench_script("reconstruct")
    take = sorted(sim_capture.takes_dir.glob("*.h5"))[0]
    truth = TakeTruth.load(truth_path(take))
    rig = SimRig()
    gt = bench.GroundTruth(rig, truth, 64, SimCameraConfig(fps=2000.0))
    times = np.arange(-1, 40) * 0.5e-3
    res = bench.displacement_scores(_exact_scene(rig, gt, times, gain), truth, gt)
    assert res["n_points"] >= 6 and res["dominant_share"] > 0.3
    # the 8 nearest vertices are within a cell (1 cm) of each sensor, where the shapes barely change
    assert res["dominant_amplitude"] == pytest.approx(gain, rel=0.03)
    assert np.allclose(res["point_gains"], gain, rtol=0.05), res["point_gains"]
    assert res["rms_ratio"] == pytest.approx(gain, rel=0.05)
    assert res["rel_error"] == pytest.approx(1 - gain, abs=0.05)
