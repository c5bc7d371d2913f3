"""The rig on one time base: a whole take through the PTY DAQ and the CAN bus, checked against its truth file."""
from __future__ import annotations

import time
import uuid

import can
import numpy as np
import pytest
from scipy.signal import find_peaks

from odsplat.acquisition import canproto as cp
from odsplat.acquisition import daqproto as dp
from odsplat.hil_sim.camera import SimCameraConfig
from odsplat.hil_sim.can_nodes import CANFaults, sim_nodes
from odsplat.hil_sim.daq import register_url_handler
from odsplat.hil_sim.render import PinholeCamera
from odsplat.hil_sim.rig import RigConfig, SimRig, TakeTruth, truth_path
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import Manifest
from odsplat.spine.store import Capture
from tests.hil_sim.daqhost import DAQHost, channels, open_port

pytestmark = pytest.mark.timeout(60)

FS_HZ = 25_600
N_SAMPLES = 25_600  # 1 s: 1 Hz resolution
HIT_S = 0.1
DAQ_DRIFT_PPM = 80.0
CAM_DRIFT_PPM = -40.0
CAM_OFFSET_S = 1.7e-4


@pytest.fixture(scope="module")
def view():
    return PinholeCamera.look_at((1.0, -1.1, 0.9), (0.15, 0.0, 0.35), fov_deg=45, width_px=96, height_px=80)


def _rig(scene, view, **config) -> SimRig:
    rig = SimRig(scene, RigConfig(**config))
    cam = rig.mount_camera(view, SimCameraConfig(fps=2000.0, shot_noise=False, read_noise_e=0.0),
                           clock_offset_s=CAM_OFFSET_S, clock_drift_ppm=CAM_DRIFT_PPM, drop_counters=(7,))
    cam.arm(n_frames=200, pretrigger=20, at_s=0.02)
    return rig


@pytest.fixture(scope="module")
def daq_take(scene, view):
    """One scripted take, acquired over the PTY from the rig with a drifting DAQ clock."""
    register_url_handler()
    rig = _rig(scene, view, daq_drift_ppm=DAQ_DRIFT_PPM)
    rig.hit(HIT_S)
    url = rig.daq_url(f"rig-{uuid.uuid4().hex[:8]}")
    with open_port(url) as port:
        take = DAQHost(port).take(channels(len(rig.channel_names)), FS_HZ, N_SAMPLES)
    assert take.gaps == [] and take.final.flags == 0
    return rig, take.volts(N_SAMPLES), rig.truth(N_SAMPLES)


def _lsb(range_v: float = 10.0) -> float:
    return range_v / dp.FULL_SCALE_COUNTS


def test_force_and_accelerometers_over_the_pty_equal_the_truth(daq_take):
    rig, volts, truth = daq_take
    c = rig.config
    assert truth.daq_rate_hz == pytest.approx(FS_HZ, rel=1e-12)
    assert truth.daq_true_rate_hz == pytest.approx(FS_HZ * (1 + DAQ_DRIFT_PPM * 1e-6), rel=1e-12)
    force = volts[0] / c.force_sensitivity_v_per_n
    assert np.max(np.abs(force - truth.force_n)) <= 0.5 * _lsb() / c.force_sensitivity_v_per_n + 1e-3
    # The pulse's peak sits half a pulse after the impact, in DAQ samples counted on the drifting clock.
    peak = truth.impact_daq_sample[0] + 0.5 * truth.impact_duration_s[0] * truth.daq_true_rate_hz
    assert abs(np.argmax(force) - peak) <= 0.5
    assert truth.impact_daq_sample[0] == pytest.approx(HIT_S * FS_HZ * (1 + DAQ_DRIFT_PPM * 1e-6))
    assert truth.impact_daq_time_s[0] == pytest.approx(HIT_S * (1 + DAQ_DRIFT_PPM * 1e-6))
    acc_truth = truth.sensor_acceleration_m_s2()
    for k, a in enumerate(c.accelerometers):
        measured = volts[1 + k] / a.sensitivity_v_per_m_s2
        expected = acc_truth[:, k] @ np.asarray(a.direction)
        assert truth.sensor_names[k] == a.name
        assert np.max(np.abs(measured - expected)) <= 0.5 * _lsb() / a.sensitivity_v_per_m_s2 + 1e-3, a.name
        assert np.max(np.abs(expected)) > 10.0  # the sensor really moved


def _peaks_hz(spectrum: np.ndarray, freqs: np.ndarray, f_max: float = 500.0) -> np.ndarray:
    sel = freqs < f_max
    peaks, _ = find_peaks(spectrum[sel], prominence=0.01 * spectrum[sel].max())
    return freqs[sel][peaks]


def test_every_mode_appears_in_the_daq_accelerometer_spectra(daq_take):
    rig, volts, truth = daq_take
    # Quadrature picking, as a modal engineer would: peaks of |Im(A/F)| summed over the accelerometers.
    n_acc = len(rig.config.accelerometers)
    accelerance = np.fft.rfft(volts[1:1 + n_acc], axis=1) / np.fft.rfft(volts[0])
    freqs = np.fft.rfftfreq(N_SAMPLES, 1.0 / truth.daq_rate_hz)  # as the host sees it: nominal rate
    peaks = _peaks_hz(np.abs(accelerance.imag).sum(axis=0), freqs)
    assert len(peaks) == len(truth.freqs_hz)
    np.testing.assert_allclose(peaks, truth.freqs_hz, atol=freqs[1])  # within the 1 Hz resolution


def test_the_strobe_channel_marks_every_exposure_even_dropped_ones(daq_take):
    rig, volts, truth = daq_take
    ttl = volts[-1]
    rising = np.flatnonzero((ttl[1:] > 2.5) & (ttl[:-1] <= 2.5)) + 1
    # Exposure starts in DAQ samples: frame 7 was dropped, but it was exposed, so it strobes too.
    period = 1.0 / (2000.0 * (1 + CAM_DRIFT_PPM * 1e-6))
    ticks = np.arange(truth.frame_counter[0], truth.frame_counter[-1] + 1)
    starts = truth.trigger_frame_time_s + ticks * period
    expected = np.ceil(starts * truth.daq_true_rate_hz - 1e-9).astype(int)
    in_recording = rising[(rising >= expected[0]) & (rising <= expected[-1])]
    assert np.array_equal(in_recording, expected)
    assert 7 not in truth.frame_counter and truth.dropped_counters.tolist() == [7]
    # Before the arm the strobe is low; after the last exposure it stops.
    assert ttl[: int(0.02 * FS_HZ) - 1].max() == 0.0
    assert ttl[expected[-1] + 10:].max() == 0.0


def test_the_camera_is_triggered_by_the_hammer_and_the_truth_says_when(daq_take):
    rig, _, truth = daq_take
    level = rig.config.trigger_level_n
    edge = HIT_S + truth.impact_duration_s[0] / np.pi * np.arcsin(level / truth.impact_peak_n[0])
    assert truth.trigger_time_s == pytest.approx(edge, abs=1e-12)
    # Frame 0 is the first exposure starting at or after the edge, on the camera's drifting clock.
    period = 1.0 / (2000.0 * (1 + CAM_DRIFT_PPM * 1e-6))
    assert 0 <= truth.trigger_frame_time_s - edge < period
    assert (truth.trigger_frame_time_s - CAM_OFFSET_S) / period == pytest.approx(
        round((truth.trigger_frame_time_s - CAM_OFFSET_S) / period), abs=1e-6)
    frame0 = truth.frame_time_s[truth.frame_counter == 0][0]
    assert truth.impact_camera_frame[0] == pytest.approx((HIT_S - frame0) / period)
    assert -1.0 < truth.impact_camera_frame[0] < 0.0  # the hit lies just before the trigger frame
    assert truth.impact_camera_time_s[0] == pytest.approx(truth.impact_camera_frame[0] / 2000.0)
    # Mid-exposure displacements of the surface points follow from the modal state.
    disp = truth.surface_displacement_m()
    assert disp.shape == (len(truth.frame_counter), rig.config.n_surface_points, 3)
    assert np.abs(disp[truth.frame_counter < -1]).max() == 0.0  # at rest before the hit
    assert 1e-5 < np.abs(disp).max() < 5e-3


def test_double_hit_is_two_pulses_and_two_impacts(scene, view):
    rig = _rig(scene, view)
    rig.hit(HIT_S, double=True)
    volts = rig.volts(0, 5000, 25_600.0)
    truth = rig.truth(5000)
    assert len(truth.impact_time_s) == 2
    force = volts[0] / rig.config.force_sensitivity_v_per_n
    above = force > 5.0
    assert np.count_nonzero(above[1:] & ~above[:-1]) == 2
    np.testing.assert_allclose(truth.impact_daq_sample[1] - truth.impact_daq_sample[0],
                               rig.hammer.double_hit_delay_s * 25_600.0)
    assert truth.trigger_time_s < truth.impact_time_s[1]  # the first pulse fired the camera


def test_clipping_at_a_small_adc_range_is_flagged(scene, view):
    register_url_handler()
    rig = _rig(scene, view)
    rig.hit(HIT_S)
    url = rig.daq_url(f"rig-{uuid.uuid4().hex[:8]}", range="2,10")
    chans = [dp.ChannelConfig(k, 10.0 if k != 1 else 2.0, n) for k, n in enumerate(rig.channel_names)]
    with open_port(url) as port:
        take = DAQHost(port).take(chans, FS_HZ, 8192)
    assert take.final.flags & dp.StatusFlag.CLIPPED and take.final.clipped_channels == 0b10
    acc = take.volts(8192)[1]
    assert acc.max() == pytest.approx(2.0, rel=1e-3)


def test_can_nodes_on_the_rig_time_base(scene, view):
    rig = _rig(scene, view)
    rig.hit(0.1)
    channel = f"odsplat-rig-{uuid.uuid4().hex}"
    n, rate = 1000, 1000.0
    range_ = cp.RANGES_M_S2[4]  # 50 g: the arm node sees about 26 g
    faults = {i: CANFaults(disconnect_after_samples=n) for i in (1, 2)}
    host = can.Bus(interface="virtual", channel=channel)
    try:
        with sim_nodes(channel, [1, 2], rig, faults=faults, sample_rate_hz=rate, range_m_s2=range_):
            reader = cp.AccelNodeReader(host, node_timeout_s=0.3)
            reader.start([1, 2], rate, range_)
            blocks = []
            deadline = time.monotonic() + 20
            while {t.node_id for t in reader.timeouts} != {1, 2} and time.monotonic() < deadline:
                blocks += reader.read(0.05)
    finally:
        host.shutdown()
    assert reader.gaps == []
    truth = rig.truth(1, daq_rate_hz=rate)  # only the modal model is needed here
    lsb = range_ / cp.FULL_SCALE_COUNTS
    for i, mount in enumerate(rig.config.can_nodes):
        mine = [b for b in blocks if b.node_id == mount.node_id]
        samples = np.concatenate([b.samples for b in mine])
        assert samples.shape == (n, 3)
        t = mount.t0_s + np.arange(n) / rate
        qdd = scene.structure.modal_response(rig.impacts, t).qdd
        phi = truth.sensor_mode_shapes[len(rig.config.accelerometers) + i]
        expected = np.einsum("kc,kt->tc", phi, qdd) @ np.asarray(mount.axes).T
        assert np.max(np.abs(samples - expected)) <= 0.5 * lsb + 1e-9
        assert np.abs(expected).max() > 10 * lsb
    arm_node = np.concatenate([b.samples for b in blocks if b.node_id == 1])
    spec = np.abs(np.fft.rfft(arm_node, axis=0)).sum(axis=1)
    # No force on this bus: plain amplitude peaks, which neighbouring modes pull by up to a percent.
    peaks = _peaks_hz(spec, np.fft.rfftfreq(n, 1 / rate))
    assert len(peaks) == len(truth.freqs_hz)
    np.testing.assert_allclose(peaks, truth.freqs_hz, rtol=0.01, atol=1.0)


def test_truth_file_lives_beside_its_take(tmp_path, scene, view):
    rig = _rig(scene, view)
    rig.hit(HIT_S)
    rig.volts(0, 4096, 25_600.0)
    truth = rig.truth(4096)
    cap = Capture.create(tmp_path / "cap", Manifest(name="sim"))
    cam = rig.camera
    with cap.new_take("v00_t00", view=0, frame_shape=cam.frame_shape, dtype=cam.dtype, bit_depth=12, fps=2000.0) as w:
        for frame in list(cam.frames())[:5]:
            w.append_frames(frame.image[None], np.array([frame.time_s]), np.array([frame.counter]))
        record = w.finalize()
    take_file = cap.root / record.file
    path = truth.save(truth_path(take_file))
    assert path == take_file.with_name("v00_t00.truth.npz") and path.exists()
    assert cap.unlisted_takes() == []  # the truth file is not mistaken for a take
    back = TakeTruth.load(path)
    for name in ("impact_daq_sample", "impact_camera_frame", "force_n", "modal_q_frames", "camera_R", "frame_counter"):
        np.testing.assert_array_equal(getattr(back, name), getattr(truth, name))
    assert back.camera_fps == 2000.0 and back.mode_names.tolist() == [m.name for m in scene.structure.modes]
    cam_back = back.camera()
    p = np.array([[0.1, 0.2, 0.3]])
    np.testing.assert_allclose(cam_back.project(p)[0], view.project(p)[0])
    assert back.camera_info().intrinsics.fx_px == pytest.approx(view.K[0, 0])
    # Bad files say which file and what is wrong.
    bad = tmp_path / "bad.truth.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(InputError, match="bad.truth.npz: not a readable ground-truth file"):
        TakeTruth.load(bad)
    data = dict(np.load(path))
    del data["force_n"]
    np.savez(tmp_path / "short.truth.npz", **data)
    with pytest.raises(InputError, match="short.truth.npz: ground-truth field 'force_n' is missing"):
        TakeTruth.load(tmp_path / "short.truth.npz")


def test_bad_rig_config_names_the_field(scene):
    with pytest.raises(InputError, match="RigConfig: DAQ channel names must be distinct"):
        RigConfig(force_channel="acc_tip_z")
    with pytest.raises(InputError, match="RigConfig.trigger_level_n"):
        RigConfig(trigger_level_n=0)
    rig = SimRig(scene)
    with pytest.raises(InputError, match="CAN node 9: not mounted"):
        rig.acceleration(9, 0, 10, 1000.0)


def test_default_rig_url_and_unique_names(scene):
    register_url_handler()
    a, b = SimRig(scene), SimRig(scene)
    assert a.daq_url() != b.daq_url() and a.daq_url(fs_max_hz=25600).endswith("?fs=25600")
    with open_port("simdaq://rig?fs=25600&hit_s=0.05") as port:
        take = DAQHost(port).take(channels(6), 25600, 4096)
    force = take.volts(4096)[0] / RigConfig().force_sensitivity_v_per_n
    assert abs(np.argmax(force) / 25600 - 0.0505) < 1.5 / 25600 and force.max() > 100
