"""CAN accelerometer nodes in the guided session on the simulated rig: each take holds their samples at their own
rate on the DAQ's time base, the DAQ-grid channel matches the rig's true acceleration, and the analysis finds the
rig's modes from a CAN node. Ground truth: hil_sim's modal model and each take's truth file."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from odsplat.acquisition import CaptureSession, HammerTrigger, PlanSettings, QCLimits, SessionSettings
from odsplat.analysis.analyze import AnalyzeSettings, analyze_capture
from odsplat.hil_sim.bench import SimBench, SimBenchSettings
from odsplat.hil_sim.rig import DEFAULT_CAN_NODES, RigConfig, SimRig, TakeTruth, truth_path
from odsplat.hil_sim.structure import Impact
from odsplat.spine.impulse import fit_pulse
from odsplat.spine.store import Capture

pytestmark = pytest.mark.timeout(120)

CAN_RATE_HZ = 1000.0
NODE2_T0_S = 0.0123   # node 2 starts 12.3 ms after the DAQ: a session that ignored it would be 12 samples off
RECORD_S = 0.5


@pytest.fixture(scope="module")
def can_capture(tmp_path_factory) -> tuple[Capture, SimRig]:
    """Three views, 8 small frames each (the camera is not under test), 0.5 s of DAQ record, both rig nodes at
    1 kHz; floor tags are not required at this size."""
    out = tmp_path_factory.mktemp("can") / "cap"
    nodes = (DEFAULT_CAN_NODES[0], dataclasses.replace(DEFAULT_CAN_NODES[1], t0_s=NODE2_T0_S))
    rig = SimRig(config=RigConfig(can_nodes=nodes, seed=4))
    settings = SimBenchSettings(width_px=160, height_px=120, can_rate_hz=CAN_RATE_HZ, seed=4)
    with SimBench(rig, settings) as bench:
        session = SessionSettings(name="can", plan=PlanSettings(n_views=3), n_frames=8, pretrigger_frames=2,
                                  trigger=HammerTrigger(pretrigger_s=0.02, record_s=RECORD_S),
                                  limits=QCLimits(min_tags=0))
        report = CaptureSession(out, session, bench).run()
        assert all(n.dropped_samples == [] and n.overrun_samples == [] for n in bench.can_nodes)
    assert report.complete, report.summary()
    return Capture.open(out), rig


def _node_truth(rig: SimRig, truth: TakeTruth, node_index: int, t_s: np.ndarray, shift_s: float = 0.0) -> np.ndarray:
    """(n, 3) the node's true acceleration along its axes at rig times t_s, its hits moved by shift_s."""
    impacts = [Impact(t + shift_s, tuple(p), tuple(d), pk, du) for t, p, d, pk, du in
               zip(truth.impact_time_s, truth.impact_point_m, truth.impact_direction, truth.impact_peak_n,
                   truth.impact_duration_s)]
    qdd = rig.structure.modal_response(impacts, np.asarray(t_s, float)).qdd
    phi = truth.sensor_mode_shapes[len(rig.config.accelerometers) + node_index]
    return np.einsum("kc,kt->tc", phi, qdd) @ np.asarray(rig.config.can_nodes[node_index].axes).T


def _fit_shift(rig: SimRig, truth: TakeTruth, node_index: int, t_s: np.ndarray, x: np.ndarray, guess_s: float) -> float:
    """How far the true response must slide along the stored times to fit the samples x (least squares)."""
    res = minimize_scalar(lambda d: np.sum((x - _node_truth(rig, truth, node_index, t_s, d)) ** 2),
                          bounds=(guess_s - 3e-3, guess_s + 3e-3), method="bounded", options={"xatol": 1e-8})
    return float(res.x)


def test_takes_hold_the_can_nodes_at_their_rate_on_the_daq_time_base(can_capture):
    cap, rig = can_capture
    chans = {c.name: c for c in cap.manifest.channels}
    assert chans["node2_x"].source == "can:node2" and chans["node2_x"].sample_rate_hz == CAN_RATE_HZ
    assert chans["node2_x"].kind == "acceleration" and chans["node2_x"].unit == "m/s^2"
    assert chans["node2_x"].direction == [0.0, 1.0, 0.0] and chans["node2_x"].position_m == [0.0, 0.045, 0.5]
    lsb = SimBenchSettings().can_range_m_s2 / 32767
    worst_shift = 0.0
    for take in cap.select_takes():
        truth = TakeTruth.load(truth_path(cap.root / take.file))
        with cap.open_take(take.name) as r:
            assert r.can_nodes == ["node1", "node2"] and r.can_sample_rate_hz("node2") == CAN_RATE_HZ
            daq_start, daq_stop = r.daq_t0_s, r.daq_t0_s + r.n_samples / r.sample_rate_hz
            onset = fit_pulse(r.channel("force").astype(float), r.sample_rate_hz)
            hit_daq_s = r.daq_t0_s + onset.onset_s                # the hit as the DAQ's load cell saw it
            assert hit_daq_s == pytest.approx(truth.impact_daq_time_s[0], abs=2e-6)
            for i, node in enumerate(("node1", "node2")):
                t, _ = r.can_channel(f"{node}_x")
                x = np.stack([r.can_channel(f"{node}_{a}")[1] for a in "xyz"], axis=1).astype(float)
                # its own rate, covering the DAQ's record with the resampling kernel's reach to spare
                np.testing.assert_allclose(np.diff(t), 1 / CAN_RATE_HZ, rtol=1e-9)
                assert t[0] <= daq_start - 16 / CAN_RATE_HZ and t[-1] >= daq_stop + 16 / CAN_RATE_HZ
                assert not np.isnan(x).any()
                # the samples are the rig's at the stored times, to the node's quantisation
                assert np.max(np.abs(x - _node_truth(rig, truth, i, t))) <= 0.5 * lsb + 1e-6
                # the hit, timed from the CAN samples alone (the true response slid along the stored times),
                # falls where the DAQ's force put it
                hit_can_s = truth.impact_time_s[0] + _fit_shift(rig, truth, i, t, x, hit_daq_s - truth.impact_time_s[0])
                worst_shift = max(worst_shift, abs(hit_can_s - hit_daq_s))
    print(f"hit time CAN vs DAQ: worst {worst_shift * 1e6:.2f} us = {worst_shift * CAN_RATE_HZ:.4f} CAN periods")
    assert worst_shift < 0.02 / CAN_RATE_HZ


def test_a_can_channel_on_the_daq_grid_is_the_true_acceleration(can_capture):
    cap, rig = can_capture
    take = cap.select_takes()[0]
    truth = TakeTruth.load(truth_path(cap.root / take.file))
    with cap.open_take(take.name) as r:
        grid = r.daq_t0_s + np.arange(r.n_samples) / r.sample_rate_hz
        for i, node in enumerate(("node1", "node2")):
            got = np.stack([r.channel(f"{node}_{a}") for a in "xyz"], axis=1).astype(float)
            assert got.shape == (r.n_samples, 3) and not np.isnan(got).any()
            want = _node_truth(rig, truth, i, grid)
            peak = np.abs(want).max()
            err = np.abs(got - want)
            # The 1 ms half-sine's own share of the acceleration reaches past the 500 Hz Nyquist: the node's samples
            # alias it, and no resampler can give it back. 20 ms from the pulse (the kernel's 16 samples and the
            # pulse) only the six modes (<= 371 Hz, below the kernel's flat band of 0.42 x 1 kHz) are left, which
            # it reproduces to its ripple (< 1e-4) and the node's quantisation (one LSB: 0.015 m/s^2).
            away = np.abs(grid - truth.impact_time_s[0]) > 0.02
            rel_all = np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(want ** 2))
            print(f"{node}: peak {peak:.1f} m/s^2; 20 ms from the pulse: max error {err[away].max():.4f} m/s^2 "
                  f"({err[away].max() / peak:.2e} of peak); whole record incl. the aliased pulse: rms error "
                  f"{rel_all:.2e} of the signal's rms")
            assert err[away].max() < 1e-3 * peak


def test_the_analysis_finds_the_rigs_modes_from_a_can_node(can_capture):
    cap, rig = can_capture
    s = AnalyzeSettings(response_channels=("node1_x", "node1_y", "node1_z"), video=False, fmax_hz=0.45 * CAN_RATE_HZ)
    res = analyze_capture(cap, s)
    assert res.frf.n_averages == 3
    f_true = np.asarray(rig.structure.freqs_hz)
    in_band = f_true[f_true < 0.45 * CAN_RATE_HZ]
    found = np.asarray(res.modes.freq_hz)
    errors = [np.min(np.abs(found - f)) / f for f in in_band]
    print("true", np.round(in_band, 2), "found", np.round(found, 2), "worst rel error", f"{max(errors):.2e}")
    # every true mode in the node's band, within 0.5 % (the DAQ accelerometers' tolerance in tests/analysis)
    assert max(errors) < 0.005
