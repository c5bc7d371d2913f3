"""CAN accelerometer nodes: the DBC, byte-exact frames, and simulated nodes on a `virtual` bus read by the host."""
from __future__ import annotations

import threading
import time
import uuid

import can
import numpy as np
import pytest

from odsplat.acquisition import canproto as cp
from odsplat.hil_sim.can_nodes import CANFaults, SimAccelNode, SineSource, sim_nodes
from odsplat.spine.errors import InputError

pytestmark = pytest.mark.timeout(30)

RATE_HZ = 1000.0
RANGE_16G = cp.RANGES_M_S2[3]
LSB_16G = RANGE_16G / cp.FULL_SCALE_COUNTS
SRC = SineSource(freqs_hz=(31.0, 47.0, 73.0), amplitude_m_s2=50.0)


@pytest.fixture
def channel() -> str:
    return f"odsplat-test-{uuid.uuid4().hex}"


@pytest.fixture
def host(channel):
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def _collect(reader: cp.AccelNodeReader, until, limit_s: float = 10.0) -> list[cp.AccelBlock]:
    blocks: list[cp.AccelBlock] = []
    deadline = time.monotonic() + limit_s
    while not until(reader) and time.monotonic() < deadline:
        blocks += reader.read(0.05)
    assert until(reader), f"condition not met within {limit_s} s"
    return blocks


def _timed_out(*node_ids):
    return lambda r: {t.node_id for t in r.timeouts} >= set(node_ids)


def _stream(blocks, node_id) -> tuple[np.ndarray, np.ndarray]:
    """(sample indices, (n, 3) samples) of one node, in arrival order."""
    mine = [b for b in blocks if b.node_id == node_id]
    idx = np.concatenate([b.first_sample + np.arange(b.n_samples) for b in mine])
    return idx, np.concatenate([b.samples for b in mine])


def _lsb_error(src, node_id, idx, samples, rate_hz=RATE_HZ, lsb=LSB_16G) -> float:
    truth = src.acceleration(node_id, 0, int(idx.max()) + 1, rate_hz)[idx]
    return float(np.max(np.abs(samples - truth)) / lsb)


def _gaps_from(lost) -> list[tuple[int, int]]:
    runs: list[list[int]] = []
    for s in sorted(lost):
        if runs and runs[-1][0] + runs[-1][1] == s:
            runs[-1][1] += 1
        else:
            runs.append([s, 1])
    return [tuple(r) for r in runs]


def _scripted_node(bus: can.BusABC, node_id: int, then: list[can.Message]) -> tuple[threading.Thread, list]:
    """A node played by hand: waits for one NODE_CMD, answers RUNNING (ack, counter 0), then sends `then`."""
    commands: list[tuple[int, bytes]] = []
    status = cp.NodeStatus(node_id, cp.NodeState.RUNNING, RATE_HZ, RANGE_16G, False, False, True, (1, 0), 0)

    def run():
        cmd = bus.recv(timeout=2.0)
        commands.append((cmd.arbitration_id, bytes(cmd.data)))
        for msg in [cp.status_frame(status), *then]:
            bus.send(msg)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, commands


# --- the DBC and the codecs ---------------------------------------------------------------------------

def test_dbc_loads_and_every_message_round_trips():
    db = cp.load_dbc()
    assert len(db.messages) == 16 * 3 + 1
    node1 = {m.name[:-3]: m for m in db.messages if m.name.endswith("_01")}
    for msg in db.messages:
        values = {}
        for i, sig in enumerate(msg.signals):
            lo, hi = sig.minimum, sig.maximum
            values[sig.name] = lo + (hi - lo) * ((i * 0.37) % 1.0)  # a value between the limits, off-grid
        decoded = db.decode_message(msg.frame_id, db.encode_message(msg.frame_id, values), decode_choices=False)
        for sig in msg.signals:
            lsb = sig.scale if sig.scale != 1 else 1.0
            assert abs(decoded[sig.name] - values[sig.name]) <= lsb, (msg.name, sig.name)
        # All 16 nodes share one layout, so the per-node copies in the DBC cannot drift apart.
        if msg.name != "NODE_CMD_ALL":
            ref = node1[msg.name[:-3]]
            assert [(s.name, s.start, s.length, s.is_signed, s.scale) for s in msg.signals] == \
                   [(s.name, s.start, s.length, s.is_signed, s.scale) for s in ref.signals]
    assert cp.ACC_DATA_BASE + 16 == db.get_message_by_name("ACC_DATA_16").frame_id == 0x110
    assert db.get_message_by_name("NODE_CMD_ALL").frame_id == 0x600


def test_fast_acc_codec_matches_cantools_within_one_lsb():
    db = cp.load_dbc()
    rng = np.random.default_rng(1)
    acc = rng.uniform(-1.2, 1.2, (200, 3)) * RANGE_16G
    counts, clipped = cp.to_counts(acc, RANGE_16G)
    assert counts.min() == -32767 and counts.max() == 32767  # saturates symmetrically, never -32768
    assert clipped.sum() == np.sum(np.abs(acc) > RANGE_16G * (1 + 0.5 / 32767))
    inside = ~clipped
    assert np.max(np.abs(cp.from_counts(counts, RANGE_16G) - acc)[inside]) <= 0.5 * LSB_16G * (1 + 1e-9)
    for node_id in (1, 7, 16):
        frames = cp.acc_data_frames(node_id, 65530, counts)
        for i, frame in enumerate(frames):
            fs = counts[i] / 32767
            ref = db.encode_message(frame.arbitration_id, {"Counter": (65530 + i) % 65536,
                                                           "AccX": fs[0], "AccY": fs[1], "AccZ": fs[2]})
            assert bytes(frame.data) == ref
            nid, counter, xyz = cp.decode_acc_data(frame)
            sig = db.decode_message(frame.arbitration_id, ref)
            assert (nid, counter) == (node_id, sig["Counter"]) == (node_id, (65530 + i) % 65536)
            assert np.allclose(np.array(xyz) * LSB_16G, np.array([sig["AccX"], sig["AccY"], sig["AccZ"]]) * RANGE_16G,
                               rtol=0, atol=1e-9)


def test_codes_and_bus_load():
    assert cp.range_code(156.9) == 3 and cp.RANGES_M_S2[3] == pytest.approx(156.9064, abs=1e-4)
    assert cp.rate_code(4000) == 4
    with pytest.raises(InputError, match="sample_rate_hz"):
        cp.rate_code(1234.0)
    with pytest.raises(InputError, match="node_id"):
        cp.check_node_id(17)
    # Four nodes at 1 kHz take 54 % of a 1 Mbit/s bus in the worst case.
    assert cp.bus_load(4, 1000.0) == pytest.approx(0.54)


def test_protocol_bytes_exact(host, channel):
    """pymeasure-style: every frame on the bus is listed, and nothing else arrives."""
    start = cp.command_frame(3, cp.Command.START, cp.rate_code(2000), cp.range_code(50 * 9.80665))
    assert (start.arbitration_id, bytes(start.data)) == (0x603, bytes([1, 3, 4, 0, 0, 0, 0, 0]))
    node_bus = can.Bus(interface="virtual", channel=channel)
    node = SimAccelNode(node_bus, 3, SRC, sample_rate_hz=1000.0, range_m_s2=156.9, firmware=(2, 5))
    node.start()
    try:
        host.send(cp.command_frame(3, cp.Command.QUERY))
        reply = host.recv(timeout=2.0)
        # IDLE, 1000 Hz (code 2), +-16 g (code 3), flags: Ack (bit 26), firmware 2.5, counter 0
        assert (reply.arbitration_id, bytes(reply.data)) == (0x703, bytes([0, 2, 3, 0x04, 2, 5, 0, 0]))
        host.send(cp.command_frame(4, cp.Command.QUERY))  # another node's address: no reply
        host.send(can.Message(arbitration_id=0x603, is_extended_id=False, data=bytes([1, 9, 3, 0, 0, 0, 0, 0])))
        reply = host.recv(timeout=2.0)  # START at an unknown rate code: FAULT, settings unchanged
        assert (reply.arbitration_id, bytes(reply.data)) == (0x703, bytes([2, 2, 3, 0x04, 2, 5, 0, 0]))
        assert host.recv(timeout=0.2) is None
        assert node.sent_samples == 0
    finally:
        node.stop()
        node_bus.shutdown()


def test_reader_counts_duplicates_and_gaps_from_scripted_frames(host, channel):
    """The reader alone, fed frames by hand: counter extension, duplicates, gaps, error frames."""
    node = can.Bus(interface="virtual", channel=channel)
    try:
        reader = cp.AccelNodeReader(host, node_timeout_s=5.0)
        counters = [0, 1, 1, 2, 5, 6]
        frames = [cp.acc_data_frames(9, c, np.array([[c, -c, 2 * c]], dtype=np.int16))[0] for c in counters]
        stale = cp.NodeStatus(9, cp.NodeState.RUNNING, RATE_HZ, RANGE_16G, False, False, True, (1, 0), 0)
        for msg in [cp.status_frame(stale), *frames, cp.error_frame()]:  # an earlier run, still queued
            node.send(msg)
        script, commands = _scripted_node(node, 9, [*frames, cp.error_frame()])
        # The stale frames queued before start() are handled first and ignored: node 9 had no stream yet.
        reader.start([9], RATE_HZ, RANGE_16G, confirm_timeout_s=2.0)
        script.join(2.0)
        assert commands == [(0x609, bytes([1, 2, 3, 0, 0, 0, 0, 0]))]
        blocks = reader.read(0.5)
        assert reader.duplicates == 1 and reader.error_frames == 2
        assert reader.gaps == [cp.Gap(9, 3, 2)] and reader.lost_samples(9) == 2
        assert [(b.first_sample, b.n_samples) for b in blocks] == [(0, 3), (5, 2)]
        assert np.allclose(blocks[1].samples / LSB_16G, [[5, -5, 10], [6, -6, 12]], atol=1e-9)
        assert np.allclose(blocks[1].t_s, [0.005, 0.006])
    finally:
        node.shutdown()


class _FakeClock:
    """Stands in for the `time` module inside canproto, so a long silence takes no test time."""

    def __init__(self):
        self.offset_s = 0.0

    def monotonic(self) -> float:
        return time.monotonic() + self.offset_s


def test_reader_resumes_after_a_silence_longer_than_a_counter_wrap(host, channel, monkeypatch):
    clock = _FakeClock()
    monkeypatch.setattr(cp, "time", clock)
    node = can.Bus(interface="virtual", channel=channel)
    try:
        reader = cp.AccelNodeReader(host, node_timeout_s=0.5)
        script, _ = _scripted_node(node, 2, cp.acc_data_frames(2, 0, np.zeros((3, 3), np.int16)))
        reader.start([2], RATE_HZ, RANGE_16G, confirm_timeout_s=2.0)
        script.join(2.0)
        assert sum(b.n_samples for b in reader.read(0.5)) == 3
        clock.offset_s += 70.0  # 70 s of silence: the node kept sampling, its counter wrapped once unseen
        assert reader.read(0.0) == [] and [(t.node_id, t.next_sample) for t in reader.timeouts] == [(2, 3)]
        node.send(cp.acc_data_frames(2, 70_002, np.zeros((1, 3), np.int16))[0])  # counter 70002 % 65536 = 4466
        (block,) = reader.read(0.5)
        assert block.first_sample == 70_002
        assert reader.gaps == [cp.Gap(2, 3, 69_999)]
    finally:
        node.shutdown()


# --- simulated nodes on a virtual bus ------------------------------------------------------------------

def test_two_nodes_stream_across_counter_wrap(host, channel):
    n = 66_000  # crosses the 16-bit wrap at 65536 once
    faults = {1: CANFaults(disconnect_after_samples=n), 2: CANFaults(disconnect_after_samples=n)}
    with sim_nodes(channel, [1, 2], SRC, faults=faults) as nodes:
        reader = cp.AccelNodeReader(host, node_timeout_s=0.5)
        reader.start([1, 2], RATE_HZ, RANGE_16G)
        blocks = _collect(reader, _timed_out(1, 2), limit_s=20.0)
        for node in nodes:
            idx, samples = _stream(blocks, node.node_id)
            assert idx.size == n and node.sent_samples == n
            assert np.array_equal(idx, np.arange(n))  # contiguous through 65535 -> 65536
            assert _lsb_error(SRC, node.node_id, idx, samples) <= 0.5 + 1e-6
            assert [b.sample_rate_hz for b in blocks if b.node_id == node.node_id][0] == RATE_HZ
        assert reader.gaps == [] and reader.error_frames == 0 and reader.duplicates == 0
        assert [(t.node_id, t.next_sample) for t in sorted(reader.timeouts, key=lambda t: t.node_id)] == \
               [(1, n), (2, n)]
        assert reader.status[1].state is cp.NodeState.RUNNING and not reader.status[1].clipping


def test_dropped_frames_are_counted_exactly_and_never_filled(host, channel):
    n = 6000
    faults = CANFaults(drop_every=997, drop_frames=(0, 5, 6, 7, 4000), drop_probability=0.002, seed=3,
                       disconnect_after_samples=n)
    with sim_nodes(channel, [4], SRC, faults={4: faults}) as (node,):
        reader = cp.AccelNodeReader(host, node_timeout_s=0.2)
        reader.start([4])
        blocks = _collect(reader, _timed_out(4))
    lost = set(node.dropped_samples)
    assert {0, 5, 6, 7, 4000, 996, 1993, 5981} <= lost and len(lost) > 8 + 6  # the random drops happened
    assert [(g.first_sample, g.n_lost) for g in reader.gaps] == _gaps_from(lost)
    assert reader.lost_samples(4) == len(lost) and reader.error_frames == 0
    idx, samples = _stream(blocks, 4)
    assert np.array_equal(idx, np.setdiff1d(np.arange(n), sorted(lost)))
    assert _lsb_error(SRC, 4, idx, samples) <= 0.5 + 1e-6


def test_error_frames_are_counted_and_their_samples_lost(host, channel):
    n = 5000
    with sim_nodes(channel, [2], SRC, faults={2: CANFaults(error_frame_every=250, disconnect_after_samples=n)}) \
            as (node,):
        reader = cp.AccelNodeReader(host, node_timeout_s=0.2)
        reader.start([2])
        blocks = _collect(reader, _timed_out(2))
    assert node.error_samples == list(range(249, n, 250))
    assert reader.error_frames == 20
    # The last sample (4999) is lost too, but nothing follows it: it shows only as where the stream stopped.
    assert reader.gaps == [cp.Gap(2, s, 1) for s in range(249, n - 1, 250)]
    assert reader.timeouts[0].next_sample == n - 1
    assert _stream(blocks, 2)[0].size == n - 20


def test_clipping_saturates_and_sets_the_status_flag(host, channel):
    loud = SineSource(amplitude_m_s2=30.0)  # beyond the +-2 g range (19.6 m/s^2)
    range_2g = cp.RANGES_M_S2[0]
    with sim_nodes(channel, [5], loud, faults={5: CANFaults(disconnect_after_samples=3000)}) as (node,):
        reader = cp.AccelNodeReader(host, node_timeout_s=0.2)
        reader.start([5], RATE_HZ, range_2g)
        blocks = _collect(reader, _timed_out(5))
    assert reader.status[5].clipping and not reader.status[5].overrun
    assert reader.status[5].range_m_s2 == range_2g
    idx, samples = _stream(blocks, 5)
    clipped_rows = np.concatenate([b.clipped for b in blocks]).any(axis=1)
    assert clipped_rows.sum() == node.clipped_samples > 100
    assert np.max(np.abs(samples)) == pytest.approx(range_2g, rel=1e-12)
    truth = loud.acceleration(5, 0, 3000, RATE_HZ)
    inside = np.abs(truth) < range_2g
    assert np.max(np.abs(samples - truth)[inside]) <= 0.5 * range_2g / 32767 * (1 + 1e-6)


def test_overrun_when_the_host_stops_reading(channel):
    small = can.Bus(interface="virtual", channel=channel, rx_queue_size=200)  # a host that falls behind
    try:
        with sim_nodes(channel, [3], SRC, faults={3: CANFaults(disconnect_after_samples=2500)}) as (node,):
            reader = cp.AccelNodeReader(small, node_timeout_s=0.2)
            reader.start([3])
            # the node's sends fail once the host queue is full: those samples are gone (waited for, not timed)
            deadline = time.monotonic() + 10.0
            while len(node.overrun_samples) < 5 and time.monotonic() < deadline:
                time.sleep(0.01)
            blocks = _collect(reader, _timed_out(3))
    finally:
        small.shutdown()
    assert len(node.overrun_samples) >= 5 and reader.status[3].overrun
    assert [(g.first_sample, g.n_lost) for g in reader.gaps] == _gaps_from(node.overrun_samples)
    assert _stream(blocks, 3)[0].size == 2500 - len(node.overrun_samples)


def test_disconnect_raises_a_timeout_for_that_node_only(host, channel):
    timeout_s = 0.25
    with sim_nodes(channel, [1, 2], SRC, realtime=True,
                   faults={2: CANFaults(disconnect_after_samples=300)}) as (node1, node2):
        reader = cp.AccelNodeReader(host, node_timeout_s=timeout_s)
        reader.start([1, 2])
        _collect(reader, _timed_out(2), limit_s=5.0)
        detected = time.monotonic()
        reader.read(0.05)
        assert [t.node_id for t in reader.timeouts] == [2]  # node 1 keeps streaming
        (event,) = reader.timeouts
        assert event.next_sample == 300 and event.silent_s > timeout_s
        # silent_since_s is a hair after its last frame left, so allow 20 ms below the timeout; above it, 10x the
        # timeout, so that a loaded machine (a busy loop on every core) does not fail it
        assert timeout_s - 0.02 <= detected - node2.silent_since_s <= 10 * timeout_s
        reader.stop()
    assert node1.sent_samples > 300


@pytest.mark.parametrize("ppm", [0.0, 250.0, -400.0])
def test_clock_drift_shifts_the_measured_frequency(host, channel, ppm):
    src = SineSource(freqs_hz=(50.0, 80.0, 125.0), amplitude_m_s2=100.0)
    n = 20_000
    with sim_nodes(channel, [6], src, faults={6: CANFaults(clock_drift_ppm=ppm, disconnect_after_samples=n)}):
        reader = cp.AccelNodeReader(host, node_timeout_s=0.2)
        reader.start([6])
        blocks = _collect(reader, _timed_out(6))
    idx, samples = _stream(blocks, 6)
    assert idx.size == n
    f_meas = _sine_freq_hz(samples[:, 0], RATE_HZ, 50.0)  # timed by the counter at the nominal rate
    measured_ppm = (50.0 / f_meas - 1) * 1e6
    assert measured_ppm == pytest.approx(ppm, abs=2.0)


def _sine_freq_hz(x: np.ndarray, fs_hz: float, f0_hz: float) -> float:
    # Demodulate at f0; block means over whole periods reject the 2 f0 image; the phase slope is the offset.
    k = np.arange(x.size)
    z = x * np.exp(-2j * np.pi * f0_hz * k / fs_hz)
    blk = int(round(10 * fs_hz / f0_hz))
    m = z.size // blk
    phase = np.unwrap(np.angle(z[: m * blk].reshape(m, blk).mean(axis=1)))
    slope = np.polyfit(np.arange(m) * blk, phase, 1)[0]
    return f0_hz + slope * fs_hz / (2 * np.pi)


def test_realtime_node_paces_to_its_sample_rate(host, channel):
    with sim_nodes(channel, [8], SRC, realtime=True, sample_rate_hz=500.0):
        reader = cp.AccelNodeReader(host)
        t0 = time.monotonic()  # before START: the node cannot have sampled earlier
        reader.start([8], 500.0)
        got, deadline = 0, t0 + 10.0
        while got < 300 and time.monotonic() < deadline:
            got += sum(b.n_samples for b in reader.read(0.05))
        elapsed = time.monotonic() - t0
        reader.stop()
    # Paced: never more than 500 Hz allows since START (plus what is in flight), however slow the host; every
    # sample arrives. How fast a loaded host receives them is not asserted.
    assert 300 <= got <= 500 * elapsed + 64 + 5
    assert reader.gaps == []


def test_start_names_a_silent_node(host):
    reader = cp.AccelNodeReader(host)
    t0 = time.monotonic()
    with pytest.raises(InputError, match="CAN node 11"):
        reader.start([11], confirm_timeout_s=0.2)
    assert 0.2 <= time.monotonic() - t0 < 10 * 0.2  # the confirm timeout, never before; 10x above for a loaded machine


def test_open_bus_takes_the_interface_from_configuration(monkeypatch, channel):
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", channel)
    a = cp.open_bus()
    b = cp.open_bus(config={"interface": "virtual", "channel": channel})
    try:
        assert a.channel_info == b.channel_info == f"Virtual bus channel {channel}"
        for i in range(3):
            a.send(cp.command_frame(i + 1, cp.Command.QUERY))
        assert [b.recv(timeout=1.0).arbitration_id for _ in range(3)] == [0x601, 0x602, 0x603]
    finally:
        a.shutdown()
        b.shutdown()
    with pytest.raises(InputError, match="CAN bus no_such_interface"):
        cp.open_bus("no_such_interface", "x")
