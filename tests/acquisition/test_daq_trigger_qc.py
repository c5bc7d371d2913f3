"""The DAQ driver, the hammer trigger and hit QC, on the simulated rig over a real PTY, against its truth."""
from __future__ import annotations

import uuid

import numpy as np
import pytest

from odsplat.acquisition.daq import DAQChannel, DAQError, SerialDAQ
from odsplat.acquisition.qc import QCLimits, check_hit
from odsplat.acquisition.trigger import HammerTrigger, NoTrigger, TriggeredRecord, first_crossing, wait_for_hit
from odsplat.hil_sim.daq import register_url_handler
from odsplat.hil_sim.rig import RigConfig, SimRig
from odsplat.hil_sim.structure import Hammer
from odsplat.spine.errors import InputError
from odsplat.spine.impulse import find_impacts

pytestmark = pytest.mark.timeout(60)
FS = 25_600


@pytest.fixture(scope="module", autouse=True)
def _handler():
    register_url_handler()


def _take(rig: SimRig, trigger: HammerTrigger, *, hit_delay_s=0.2, double=False, url_options=None, **chan_kw):
    url = rig.daq_url(f"acq-{uuid.uuid4().hex[:8]}", **(url_options or {}))
    with SerialDAQ.from_url(url, rig.daq_channels(**chan_kw), FS) as daq:
        daq.start()
        rig.hit(delay_s=hit_delay_s, double=double)
        record = wait_for_hit(daq, trigger, timeout_s=10)
        daq.stop()
        clipped = set(daq.clipped)
        errors = daq.link_errors
    return record, clipped, errors, rig.truth(record.stop_sample)


def test_trigger_keeps_the_pretrigger_and_stamps_by_sample_counter(scene):
    rig = SimRig(scene)
    trig = HammerTrigger(level_n=10.0, pretrigger_s=0.02, record_s=0.5)
    record, clipped, errors, truth = _take(rig, trig)
    # The crossing is the first sample at or above 10 N: exactly where the truth's pulse crosses it.
    t_cross = truth.impact_time_s[0] + truth.impact_duration_s[0] / np.pi * np.arcsin(10.0 / truth.impact_peak_n[0])
    assert record.trigger_sample == int(np.ceil(t_cross * truth.daq_true_rate_hz))
    assert record.pretrigger_samples == round(0.02 * FS) and record.stop_sample - record.first_sample == round(0.5 * FS)
    assert record.t0_s == record.first_sample / FS
    force = record.channel("force")
    truth_force = truth.force_n[record.first_sample:record.stop_sample]
    assert np.max(np.abs(force - truth_force)) < 0.5 * 10 / 32767 / 2.25e-3 + 1e-3
    acc = truth.sensor_acceleration_m_s2()[record.first_sample:record.stop_sample, 0] @ (0, 0, 1)
    assert np.max(np.abs(record.channel("acc_tip_z") - acc)) < 0.5 * 10 / 32767 / (0.1 / 9.80665) + 1e-3
    assert clipped == set() and errors["lost_packets"] == 0 and record.lost_samples == 0
    qc = check_hit(record, rig.daq_channels(), tags_seen=(0, 1, 2))
    assert qc.accepted, qc.details
    assert qc.peak_force_n == pytest.approx(truth.impact_peak_n[0], rel=0.01)
    assert len(qc.impact_times_s) == 1 and qc.to_qcinfo().status == "accepted"


@pytest.mark.parametrize("delay_ms", [1.0, 2.0, 5.0])
def test_double_hits_one_ms_or_more_apart_are_caught(scene, delay_ms):
    rig = SimRig(scene, hammer=Hammer((0.46, 0.03, 0.60), (-0.25, -0.45, -0.86), double_hit_delay_s=delay_ms * 1e-3,
                                      double_hit_ratio=0.3))
    record, *_ = _take(rig, HammerTrigger(pretrigger_s=0.01, record_s=0.2), double=True)
    qc = check_hit(record, rig.daq_channels())
    assert qc.reasons == ("double_hit",)
    assert np.diff(qc.impact_times_s)[0] == pytest.approx(delay_ms * 1e-3, abs=1.5 / FS)
    assert "double hit: 2 impacts" in qc.to_qcinfo().notes


def test_force_and_accelerometer_overload(scene):
    rig = SimRig(scene)
    record, clipped, *_ = _take(rig, HammerTrigger(pretrigger_s=0.01, record_s=0.2), force_range_v=0.2, acc_range_v=2.0,
                                url_options={"range": "0.2,2,10"})
    qc = check_hit(record, rig.daq_channels(force_range_v=0.2, acc_range_v=2.0), clipped=clipped)
    assert clipped == {"force", "acc_tip_z"}  # the device's own flags; the tip accelerometer peaks near 4.5 V
    assert set(qc.reasons) >= {"force_overload", "accel_overload"} and not qc.accepted
    assert "'acc_tip_z' reached its" in qc.to_qcinfo().notes


def test_dropped_packets_leave_nan_and_are_reported(scene):
    rig = SimRig(scene, hammer=Hammer((0.46, 0.03, 0.60), (-0.25, -0.45, -0.86), duration_s=3e-3))
    record, _, errors, truth = _take(rig, HammerTrigger(pretrigger_s=0.01, record_s=0.4),
                                     url_options={"drop_every": 7, "block": 32})
    assert errors["lost_packets"] > 0 and record.lost_samples > 0
    lost = np.isnan(record.data[0])
    expected = np.zeros_like(lost)
    for g in record.gaps:  # whole packets, never filled in
        assert g.n_samples == 32 and g.lost_packets == 1
        expected[max(0, g.first_sample - record.first_sample):g.stop - record.first_sample] = True
    assert np.array_equal(lost, expected) and lost.sum() == record.lost_samples
    assert not np.isnan(record.data[:, ~lost]).any()
    qc = check_hit(record, rig.daq_channels())
    assert "dropped_samples" in qc.reasons


def test_bit_errors_count_as_crc_failures(scene):
    # A 3 ms pulse over 32-sample packets spans three of them: one corrupted packet cannot hide the hit.
    rig = SimRig(scene, hammer=Hammer((0.46, 0.03, 0.60), (-0.25, -0.45, -0.86), duration_s=3e-3))
    record, _, errors, _ = _take(rig, HammerTrigger(pretrigger_s=0.01, record_s=0.3),
                                 url_options={"bit_error_every": 9, "block": 32})
    assert errors["crc_errors"] + errors["cobs_errors"] > 0 and record.lost_samples > 0


def test_disconnect_mid_take_names_the_port(scene):
    rig = SimRig(scene)
    url = rig.daq_url(f"acq-{uuid.uuid4().hex[:8]}", disconnect_after=20000)
    with SerialDAQ.from_url(url, rig.daq_channels(), FS) as daq:
        daq.start()
        rig.hit(delay_s=0.1)
        with pytest.raises(DAQError, match=r"simdaq://acq-.*disconnected after sample"):
            wait_for_hit(daq, HammerTrigger(pretrigger_s=0.01, record_s=1.5), timeout_s=10)


def test_no_hit_times_out_and_bad_configs_name_the_channel(scene):
    rig = SimRig(scene)
    with SerialDAQ.from_url(rig.daq_url(f"acq-{uuid.uuid4().hex[:8]}", realtime=1), rig.daq_channels(), FS) as daq:
        daq.start()
        with pytest.raises(NoTrigger, match="'force' did not reach 10 N"):
            wait_for_hit(daq, HammerTrigger(), timeout_s=0.3)
        daq.stop()
    bad = [DAQChannel("force", 9, "force", 2.25e-3)]
    with SerialDAQ.from_url(rig.daq_url(f"acq-{uuid.uuid4().hex[:8]}"), bad, FS) as daq:
        with pytest.raises(InputError, match="channel 'force': input 9 does not exist"):
            daq.configure()
    with pytest.raises(InputError, match="'force'.sensitivity_v_per_unit"):
        DAQChannel("force", 0, "force", 0.0)
    with pytest.raises(InputError, match="HammerTrigger.pretrigger_s"):
        HammerTrigger(pretrigger_s=2.0, record_s=1.0)


def test_a_hit_lost_on_the_link_times_out_saying_samples_were_lost(scene):
    # Packets 40-199 (50-250 ms) never arrive: the hit at ~0.1 s is in them, so the trigger cannot see it; the
    # session flags such a take dropped_samples (not only daq_error) from the count the timeout carries.
    rig = SimRig(scene)
    url = rig.daq_url(f"acq-{uuid.uuid4().hex[:8]}", realtime=1, block=32, drop=",".join(map(str, range(40, 200))))
    with SerialDAQ.from_url(url, rig.daq_channels(), FS) as daq:
        daq.start()
        rig.hit(delay_s=0.1)
        with pytest.raises(NoTrigger, match="5120 samples were lost on the link meanwhile") as e:
            wait_for_hit(daq, HammerTrigger(), timeout_s=0.6)
        daq.stop()
    assert e.value.lost_samples == 160 * 32


def test_first_crossing_and_find_impacts_on_plain_arrays():
    x = np.array([0, 5, np.nan, 12, 15, 3, 11])
    assert first_crossing(x, 10) == 3
    assert first_crossing(x, 10, previous=20) == 3  # previous above: x[0] is not a crossing, x[3] is
    assert first_crossing(np.array([11.0, 12.0]), 10, previous=11) is None
    t = np.arange(0, 0.01, 1 / FS)

    def pulse(t0, d, p):
        return np.where((t >= t0) & (t <= t0 + d), p * np.sin(np.pi * np.clip(t - t0, 0, d) / d), 0)

    one = pulse(0.002, 1e-3, 200) + 0.5 * np.random.default_rng(0).standard_normal(t.size)
    assert len(find_impacts(one)) == 1
    assert len(find_impacts(pulse(0.002, 1e-3, 200) + pulse(0.003, 1e-3, 60))) == 2
    rec = TriggeredRecord(10, 0, t.size, FS, ("force",), one[None])
    low = check_hit(rec, [DAQChannel("force", 0, "force", 2.25e-3)], limits=QCLimits(force_band_n=(250, 500)),
                    dropped_frames=(3,), tags_seen=(1,))
    assert set(low.reasons) == {"force_low", "dropped_frames", "tags_not_visible"}
    with pytest.raises(InputError, match="QCLimits.force_band_n"):
        QCLimits(force_band_n=(5, 1))


def test_ring_buffer_refuses_samples_that_left_it(scene):
    rig = SimRig(scene, RigConfig())
    with SerialDAQ.from_url(rig.daq_url(f"acq-{uuid.uuid4().hex[:8]}"), rig.daq_channels(), FS, buffer_s=0.05) as daq:
        daq.start()
        daq.wait_for(FS, timeout_s=10)
        with pytest.raises(DAQError, match="has left the"):
            daq.read(0, 100)
        daq.stop()
