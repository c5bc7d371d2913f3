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


def test_motion_scores_read_the_motion_alone(sim_capture, bench_script):
    """The truth's own motion images (hil_sim's renders less the render at rest): exact reads inf dB and a
    correlation of 1; half the motion still correlates 1 and loses 20 log10 of the ratio it leaves; no motion at
    all (a static model) has no correlation, the PSNR of the motion's own rms (the baseline every result carries,
    `still_psnr_db`) and an SNR of 0 dB."""
    bench = bench_script("reconstruct")
    take = sorted(sim_capture.takes_dir.glob("*.h5"))[0]
    gt = bench.GroundTruth(SimRig(), TakeTruth.load(truth_path(take)), 64, SimCameraConfig(fps=2000.0))
    rest, _ = gt.image(0.0, 30.0)
    truth = [gt.image(t, 30.0)[0] - rest for t in np.arange(1, 12) * 0.5e-3]
    b = np.concatenate([np.ravel(t) for t in truth]).astype(float)
    peak, rms = np.abs(b).max(), np.sqrt(np.mean(b ** 2))
    assert peak > 0.01                                   # the structure moves visibly at alpha 30
    exact = bench.motion_scores(truth, truth)
    assert exact["psnr_db"] == float("inf") and exact["correlation"] == pytest.approx(1.0)
    half = bench.motion_scores([0.5 * t for t in truth], truth)
    assert half["correlation"] == pytest.approx(1.0)
    assert half["psnr_db"] == pytest.approx(20 * np.log10(peak / (0.5 * rms)), abs=1e-6)
    still = bench.motion_scores([np.zeros_like(t) for t in truth], truth)
    assert still["correlation"] is None and still["psnr_db"] == pytest.approx(20 * np.log10(peak / rms), abs=1e-6)
    # The baseline beside the PSNR: what the static model scores, and the motion's SNR (0 dB for no motion).
    assert still["still_psnr_db"] == pytest.approx(still["psnr_db"], abs=1e-9) and still["snr_db"] == pytest.approx(0.0)
    assert half["snr_db"] == pytest.approx(20 * np.log10(2), abs=1e-6)
    assert exact["snr_db"] == float("inf") and exact["still_psnr_db"] == pytest.approx(still["psnr_db"])
    noisy = bench.motion_scores([t + np.random.default_rng(0).normal(0, rms, t.shape) for t in truth], truth)
    assert 0.5 < noisy["correlation"] < 0.8 and noisy["psnr_db"] < half["psnr_db"]
