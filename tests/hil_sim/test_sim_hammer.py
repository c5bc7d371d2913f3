"""The simulated automatic hammer, at the wire: a small host in this file speaks the hammer protocol to it over the
`simhammer://` PTY and over a `virtual` CAN bus, and every number it reads is checked against what the rig was struck
with (the rig's impacts and the model's ground truth)."""
from __future__ import annotations

import math
import struct
import time
import uuid
import zlib
from dataclasses import dataclass, field

import can
import numpy as np
import pytest
import serial

from odsplat.acquisition import hammerproto as hp
from odsplat.hil_sim.hammer import (
    HammerFaults,
    SimAutoHammer,
    SimHammerCAN,
    SimHammerSettings,
    hammer_url,
    model_from_url,
)
from odsplat.hil_sim.rig import SimRig
from odsplat.hil_sim.structure import Impact
from odsplat.spine.errors import InputError

pytestmark = pytest.mark.timeout(30)

F32 = 1e-6  # relative: floats travel as float32 on the serial line
# How long the host waits for a message: 10x the protocol's 1 s reply deadline, so that a loaded machine (a busy loop
# on every core) delays a reply without failing the test. Timings are asserted as lower bounds from the host's send
# time only (causality: nothing comes back before the device could have sent it); the bench measures speed.
WAIT_S = 10.0


@dataclass
class HammerHost:
    """The smallest honest host: every wait has a deadline; messages not yet asked for wait in the inbox, in order."""

    port: serial.SerialBase
    decoder: hp.dp.FrameDecoder = field(default_factory=lambda: hp.frame_decoder("test host"))
    inbox: list = field(default_factory=list)  # (host time received, device seq, message)
    seq: int = 0

    def __post_init__(self) -> None:
        self.port.write(b"\x00")  # ends whatever partial frame the device may hold

    def send(self, message) -> int:
        seq, self.seq = self.seq, (self.seq + 1) & 0xFFFF
        self.port.write(hp.encode_frame(message, seq))
        return seq

    def send_packet(self, version: int, type_: int, seq: int, body: bytes) -> None:
        head = struct.pack("<BBH", version, type_, seq) + body
        self.port.write(hp.dp.frame(head + struct.pack("<I", zlib.crc32(head))))

    def _read(self, deadline: float) -> None:
        self.port.timeout = max(0.0, min(0.02, deadline - time.monotonic()))
        data = self.port.read(max(1, self.port.in_waiting))
        now = time.monotonic()
        self.inbox += [(now, p.seq, p.message) for p in map(hp.parse_packet, self.decoder.feed_raw(data))]

    def expect(self, match, timeout_s: float = WAIT_S):
        """The first message (oldest first) for which match(message) is true; removes it from the inbox."""
        deadline = time.monotonic() + timeout_s
        while True:
            for i, (_, _, m) in enumerate(self.inbox):
                if match(m):
                    return self.inbox.pop(i)[2]
            if time.monotonic() > deadline:
                raise TimeoutError(f"no matching message within {timeout_s} s; inbox {[m for _, _, m in self.inbox]}")
            self._read(deadline)

    def silence(self, duration_s: float) -> list:
        """Everything that arrives within duration_s (and was waiting)."""
        deadline = time.monotonic() + duration_s
        while time.monotonic() < deadline:
            self._read(deadline)
        out = [m for _, _, m in self.inbox]
        self.inbox.clear()
        return out

    def request(self, message, timeout_s: float = WAIT_S):
        seq = self.send(message)
        return self.expect(lambda m: not isinstance(m, hp.Shot) and m.ref_seq == seq, timeout_s)

    def status_update(self, timeout_s: float = WAIT_S) -> hp.Status:
        return self.expect(lambda m: isinstance(m, hp.Status) and m.ref_seq == hp.NO_REF, timeout_s)

    def shot(self, shot_id: int, timeout_s: float = WAIT_S) -> hp.Shot:
        return self.expect(lambda m: isinstance(m, hp.Shot) and m.shot_id == shot_id, timeout_s)

    def fire(self, shot_id: int, level: float, mode=hp.LevelMode.FORCE_N, timeout_s: float = 1.0) -> hp.Shot:
        """ARM, FIRE, and the SHOT."""
        assert isinstance(self.request(hp.Arm()), hp.Ack)
        assert isinstance(self.request(hp.Fire(shot_id, mode, level, timeout_s)), hp.Ack)
        return self.shot(shot_id, timeout_s + WAIT_S)


def _nak(reply, reason: hp.NakReason, ref_type: hp.MsgType) -> None:
    assert isinstance(reply, hp.Nak), reply
    assert (reply.reason, reply.ref_type) == (reason, ref_type), reply


@pytest.fixture
def rig() -> SimRig:
    return SimRig()


@pytest.fixture
def open_hammer(rig):
    """open_hammer(**url_options) -> (host, model) on `rig`; closed after the test."""
    ports = []

    def _open(**options) -> tuple[HammerHost, SimAutoHammer]:
        port = serial.serial_for_url(hammer_url(rig, **options), timeout=0.02)
        ports.append(port)
        return HammerHost(port), port.device.model

    yield _open
    for port in ports:
        port.close()


# ---------------------------------------------------------------------------------- the normal shot

def test_hello_and_the_order_of_replies(open_hammer, rig):
    host, model = open_hammer(seed=1)
    info = host.request(hp.Hello())
    assert info == hp.Info(0, "odsplat-simhammer", "1.0", 10.0, 2000.0, 10.0)
    st = host.request(hp.GetStatus())
    assert (st.ref_seq, st.state, st.ready, st.fault, st.shot_count) == (1, hp.State.DISARMED, True, hp.Fault.NONE, 0)

    sent = time.monotonic()
    host.send(hp.Arm())
    host.send(hp.Fire(42, hp.LevelMode.FORCE_N, 300.0, 1.0))
    got = []
    while len(got) < 7:
        host._read(time.monotonic() + 1.0)
        got = list(host.inbox)
        assert time.monotonic() - sent < WAIT_S, got
    seqs = [s for _, s, _ in got]
    assert seqs == list(range(seqs[0], seqs[0] + 7))  # one device counter, no gaps
    msgs = [m for _, _, m in got]
    # ARM: ACK then STATUS(ARMED); FIRE: ACK, STATUS(FIRING); SHOT, STATUS(DISARMED, not ready); STATUS(ready)
    assert msgs[0] == hp.Ack(2, hp.MsgType.ARM) and msgs[1].state is hp.State.ARMED and msgs[1].ref_seq == hp.NO_REF
    assert msgs[2] == hp.Ack(3, hp.MsgType.FIRE) and msgs[3].state is hp.State.FIRING
    shot, after, ready = msgs[4], msgs[5], msgs[6]
    truth = model.fires[0]
    assert (shot.shot_id, shot.outcome, shot.shot_count, shot.flags) == (42, hp.Outcome.FIRED, 1, hp.ShotFlag(0))
    assert shot.peak_force_n == pytest.approx(truth.measured_peak_n, rel=F32)
    assert (after.state, after.ready, after.shot_count) == (hp.State.DISARMED, False, 1)
    assert after.last_peak_force_n == pytest.approx(truth.measured_peak_n, rel=F32)
    assert (ready.state, ready.ready, ready.fault) == (hp.State.DISARMED, True, hp.Fault.NONE)
    # SHOT comes when the contact is over (delay + 1 ms after FIRE); ready again recharge_s (50 ms) later. Lower
    # bounds from `sent` (before ARM and FIRE left): a late reader may receive the replies together, never early.
    t_shot, t_ready = got[4][0] - sent, got[6][0] - sent
    assert t_shot >= truth.wait_s + truth.delay_s + 1e-3
    assert t_ready >= truth.wait_s + truth.delay_s + 1e-3 + model.settings.recharge_s
    # what struck the rig: one half-sine at the manual hammer's point, delay after the rig's now (0: no DAQ running)
    (imp,) = rig.impacts
    assert imp == truth.impacts[0]
    assert imp.point_m == tuple(rig.hammer.point_m) and imp.direction == pytest.approx(rig.hammer.direction)
    assert imp.time_s == pytest.approx(shot.delay_s, abs=1e-7) and imp.duration_s == 1e-3
    assert imp.peak_n == pytest.approx(300.0, rel=0.05)


def test_thirty_shots_force_scatter_load_cell_and_delay_jitter(open_hammer, rig):
    host, model = open_hammer(seed=7, scatter=0.01, recharge_ms=0)
    shots = [host.fire(k, 200.0) for k in range(30)]
    peaks = np.array([i.peak_n for i in rig.impacts])
    assert len(peaks) == 30
    assert abs(peaks.mean() / 200.0 - 1) < 0.01
    assert 0.005 <= peaks.std(ddof=1) / 200.0 <= 0.02
    truth = {f.shot_id: f for f in model.fires}
    measured_err = []
    for shot in shots:
        t = truth[shot.shot_id]
        assert shot.outcome is hp.Outcome.FIRED and t.impacts[0] in rig.impacts
        assert shot.peak_force_n == pytest.approx(t.impacts[0].peak_n, rel=0.01)
        measured_err.append(shot.peak_force_n / t.impacts[0].peak_n - 1)
        assert shot.delay_s == pytest.approx(t.wait_s + t.delay_s, rel=F32)
        assert t.wait_s < 0.002  # the drive was ready: it fired on receipt
    assert 0.001 <= np.std(measured_err, ddof=1) <= 0.004  # load_cell_noise 0.002
    assert [s.shot_count for s in shots] == list(range(1, 31))
    delays = np.array([f.delay_s for f in model.fires])
    assert abs(delays.mean() - 0.015) < 0.0006
    assert 0.0006 <= delays.std(ddof=1) <= 0.0014  # fire_jitter 1 ms


def test_rebound_fires_and_injected_rebound(open_hammer, rig):
    host, model = open_hammer(seed=2, rebound_fires=1, recharge_ms=0)
    plain, bounced = host.fire(0, 500.0), host.fire(1, 500.0)
    model.inject_next("rebound")
    injected = host.fire(2, 500.0)
    assert plain.flags == hp.ShotFlag(0) and len(model.fires[0].impacts) == 1
    for shot, truth in ((bounced, model.fires[1]), (injected, model.fires[2])):
        assert shot.flags == hp.ShotFlag.REBOUND and truth.rebound and truth.faults >= {"rebound"}
        main, second = truth.impacts
        assert second.time_s - main.time_s == pytest.approx(3e-3, abs=1e-12)
        assert second.peak_n / main.peak_n == pytest.approx(0.4, rel=1e-12)
        assert shot.peak_force_n == pytest.approx(main.peak_n, rel=0.01)  # the load cell's peak is the main hit
    assert len(rig.impacts) == 5
    with pytest.raises(InputError, match="fault kind"):
        model.inject_next("overheat")


def test_energy_mode_and_gain_give_the_formula(open_hammer, rig):
    host, model = open_hammer(scatter=0, gain=1.1, recharge_ms=0)
    host.fire(0, 0.5, mode=hp.LevelMode.ENERGY_J)
    host.fire(1, 300.0)
    m, dur, v = 0.1, 1e-3, math.sqrt(2 * 0.5 / 0.1)
    expected = math.pi * m * v / (2 * dur) * 1.1  # 546.4 N
    assert model.fires[0].impacts[0].peak_n == pytest.approx(expected, rel=1e-12)
    assert model.fires[1].impacts[0].peak_n == pytest.approx(330.0, rel=1e-12)
    assert SimHammerSettings(restitution=0.5).energy_force_n(0.5) == pytest.approx(expected / 1.1 * 1.5, rel=1e-12)


# ---------------------------------------------------------------------------------- refusals

def test_refusals_not_armed_bad_level_busy_and_disarm_aborts(open_hammer, rig):
    host, model = open_hammer(not_ready_fires=0)
    _nak(host.request(hp.Fire(1, hp.LevelMode.FORCE_N, 200.0, 1.0)), hp.NakReason.NOT_ARMED, hp.MsgType.FIRE)
    assert isinstance(host.request(hp.Arm()), hp.Ack)
    for mode, level in ((hp.LevelMode.FORCE_N, 5.0), (hp.LevelMode.FORCE_N, 2500.0), (hp.LevelMode.ENERGY_J, 0.0),
                        (hp.LevelMode.ENERGY_J, 11.0), (7, 200.0), (hp.LevelMode.FORCE_N, float("nan"))):
        _nak(host.request(hp.Fire(1, mode, level, 1.0)), hp.NakReason.BAD_LEVEL, hp.MsgType.FIRE)
    assert host.request(hp.GetStatus()).state is hp.State.ARMED  # a bad level leaves it armed
    assert isinstance(host.request(hp.Arm()), hp.Ack)  # idempotent
    # fire 0: the drive is not ready (injected), so the FIRE stays pending
    assert isinstance(host.request(hp.Fire(3, hp.LevelMode.FORCE_N, 200.0, 2.0)), hp.Ack)
    st = host.request(hp.GetStatus())
    assert (st.state, st.ready, st.fault) == (hp.State.FIRING, False, hp.Fault.NOT_READY)
    _nak(host.request(hp.Fire(4, hp.LevelMode.FORCE_N, 200.0, 1.0)), hp.NakReason.BUSY, hp.MsgType.FIRE)
    _nak(host.request(hp.Arm()), hp.NakReason.BUSY, hp.MsgType.ARM)
    assert isinstance(host.request(hp.Disarm()), hp.Ack)
    shot = host.shot(3)
    assert (shot.outcome, shot.peak_force_n, shot.shot_count) == (hp.Outcome.ABORTED, 0.0, 0)
    assert host.request(hp.GetStatus()).state is hp.State.DISARMED
    assert rig.impacts == [] and [f.outcome for f in model.fires] == [hp.Outcome.ABORTED]


def test_estop_aborts_a_pending_fire_and_latches_until_reset(open_hammer, rig):
    host, model = open_hammer(not_ready_fires=0, not_ready_ms=300)
    assert isinstance(host.request(hp.Arm()), hp.Ack)
    assert isinstance(host.request(hp.Fire(9, hp.LevelMode.FORCE_N, 200.0, 2.0)), hp.Ack)
    host.status_update(), host.status_update()  # ARMED, FIRING
    assert host.request(hp.EStop()) == hp.Ack(host.seq - 1, hp.MsgType.ESTOP)
    shot = host.shot(9)
    assert shot.outcome is hp.Outcome.ABORTED and shot.peak_force_n == 0.0
    assert host.status_update().state is hp.State.ESTOP
    _nak(host.request(hp.Arm()), hp.NakReason.ESTOPPED, hp.MsgType.ARM)
    _nak(host.request(hp.Fire(10, hp.LevelMode.FORCE_N, 200.0, 1.0)), hp.NakReason.ESTOPPED, hp.MsgType.FIRE)
    assert isinstance(host.request(hp.Disarm()), hp.Ack)
    assert isinstance(host.request(hp.EStop()), hp.Ack)  # again: still latched
    time.sleep(0.35)  # the not-ready drive recovers meanwhile; the latch does not
    st = host.request(hp.GetStatus())
    assert (st.state, st.fault, st.ready) == (hp.State.ESTOP, hp.Fault.NONE, True)
    assert isinstance(host.request(hp.Reset()), hp.Ack)
    assert host.request(hp.GetStatus()).state is hp.State.DISARMED
    assert host.fire(11, 200.0).outcome is hp.Outcome.FIRED
    assert len(rig.impacts) == 1 and [f.outcome for f in model.fires] == [hp.Outcome.ABORTED, hp.Outcome.FIRED]


def test_fire_expires_when_the_drive_is_not_ready(open_hammer, rig):
    host, model = open_hammer(not_ready_fires=0, not_ready_ms=400)
    assert isinstance(host.request(hp.Arm()), hp.Ack)
    t0 = time.monotonic()
    assert isinstance(host.request(hp.Fire(5, hp.LevelMode.FORCE_N, 200.0, 0.15)), hp.Ack)
    shot = host.shot(5)
    waited = time.monotonic() - t0
    assert shot.outcome is hp.Outcome.EXPIRED and shot.peak_force_n == 0.0 and shot.shot_count == 0
    assert shot.delay_s == pytest.approx(0.15, abs=1e-6) and waited >= 0.15  # at the FIRE's timeout, never before
    updates = [host.status_update() for _ in range(3)]  # ARMED; FIRING not ready; DISARMED still not ready
    assert (updates[1].state, updates[1].ready, updates[1].fault) == (hp.State.FIRING, False, hp.Fault.NOT_READY)
    assert (updates[2].state, updates[2].fault) == (hp.State.DISARMED, hp.Fault.NOT_READY)
    recovered = host.status_update()  # by itself, not_ready_ms after the FIRE
    assert (recovered.ready, recovered.fault) == (True, hp.Fault.NONE)
    assert time.monotonic() - t0 >= 0.4
    assert rig.impacts == [] and model.fires[0].outcome is hp.Outcome.EXPIRED


def test_stuck_plunger_faults_and_reset_clears(open_hammer, rig):
    host, model = open_hammer(stuck_fires=0, recharge_ms=0)
    shot = host.fire(1, 200.0)
    assert (shot.outcome, shot.peak_force_n, shot.shot_count) == (hp.Outcome.FAULT, 0.0, 0)
    st = host.request(hp.GetStatus())
    assert (st.state, st.fault, st.shot_count) == (hp.State.FAULT, hp.Fault.STUCK, 0)
    _nak(host.request(hp.Arm()), hp.NakReason.FAULTED, hp.MsgType.ARM)
    _nak(host.request(hp.Fire(2, hp.LevelMode.FORCE_N, 200.0, 1.0)), hp.NakReason.FAULTED, hp.MsgType.FIRE)
    assert isinstance(host.request(hp.Disarm()), hp.Ack) and host.request(hp.GetStatus()).state is hp.State.FAULT
    assert isinstance(host.request(hp.Reset()), hp.Ack)
    st = host.request(hp.GetStatus())
    assert (st.state, st.fault) == (hp.State.DISARMED, hp.Fault.NONE)
    assert rig.impacts == []
    model.inject_next("stuck")  # the bench's way to fault a chosen take
    assert host.fire(3, 200.0).outcome is hp.Outcome.FAULT
    assert isinstance(host.request(hp.Reset()), hp.Ack)
    assert host.fire(4, 200.0).outcome is hp.Outcome.FIRED
    assert [f.fire_index for f in model.fires] == [0, 1, 2] and len(rig.impacts) == 1


def test_stuck_that_persists_refuses_reset(open_hammer, rig):
    host, model = open_hammer(stuck_fires=0, stuck_persists=1)
    assert host.fire(1, 200.0).outcome is hp.Outcome.FAULT
    _nak(host.request(hp.Reset()), hp.NakReason.FAULTED, hp.MsgType.RESET)
    assert isinstance(host.request(hp.EStop()), hp.Ack)  # ESTOP is taken even in FAULT
    assert host.request(hp.GetStatus()).state is hp.State.ESTOP
    _nak(host.request(hp.Reset()), hp.NakReason.FAULTED, hp.MsgType.RESET)
    st = host.request(hp.GetStatus())
    assert (st.state, st.fault) == (hp.State.FAULT, hp.Fault.STUCK)
    assert rig.impacts == []


def test_no_response_then_back_disarmed(open_hammer, rig):
    host, model = open_hammer(no_response_fires=0, silent_ms=500)
    assert isinstance(host.request(hp.Arm()), hp.Ack)
    t0 = time.monotonic()
    host.send(hp.Fire(1, hp.LevelMode.FORCE_N, 200.0, 1.0))
    host.send(hp.GetStatus())
    host.port.write(b"\x05\x01\x02")  # a partial frame, lost with the reboot
    got = host.silence(0.3)
    assert [m for m in got if not (isinstance(m, hp.Status) and m.state is hp.State.ARMED)] == []
    back = host.status_update()
    assert (back.state, back.ready, back.fault) == (hp.State.DISARMED, True, hp.Fault.NONE)
    assert time.monotonic() - t0 >= 0.5  # silent_ms after the FIRE, never before
    assert host.request(hp.GetStatus()).state is hp.State.DISARMED
    assert rig.impacts == [] and model.fires[0].outcome is None and model.fires[0].faults == {"no_response"}
    assert host.fire(2, 200.0).outcome is hp.Outcome.FIRED  # fire index 1: no fault
    assert len(rig.impacts) == 1


def test_malformed_packets_are_naked(open_hammer):
    host, _ = open_hammer()
    host.send_packet(1, hp.MsgType.FIRE, 77, b"\x01\x02")
    reply = host.expect(lambda m: isinstance(m, hp.Nak))
    assert (reply.ref_seq, reply.ref_type, reply.reason) == (77, hp.MsgType.FIRE, hp.NakReason.MALFORMED)
    assert "malformed FIRE" in reply.text
    host.send_packet(1, 0x42, 78, b"")
    _nak(host.expect(lambda m: isinstance(m, hp.Nak)), hp.NakReason.UNKNOWN_TYPE, 0x42)
    host.send_packet(2, hp.MsgType.HELLO, 79, b"")
    _nak(host.expect(lambda m: isinstance(m, hp.Nak)), hp.NakReason.UNSUPPORTED_VERSION, hp.MsgType.HELLO)
    _nak(host.request(hp.Status(0, hp.State.ARMED, True, hp.Fault.NONE, 0, 0.0)), hp.NakReason.UNKNOWN_TYPE,
         hp.MsgType.STATUS)
    frame = bytearray(hp.encode_frame(hp.Arm(), 80))
    frame[3] ^= 0x10  # a bit error: the CRC fails, the device drops it silently
    host.port.write(bytes(frame))
    assert host.silence(0.1) == []
    assert isinstance(host.request(hp.Hello()), hp.Info)


def test_url_errors(rig):
    url = hammer_url(rig, seed=3)
    assert url == f"simhammer://{rig.name}?seed=3"
    with pytest.raises(InputError, match=r"simhammer://.*unknown option 'bogus'.*expected one of"):
        model_from_url(url + "&bogus=1")
    with pytest.raises(InputError, match="no target 'nosuchrig'"):
        serial.serial_for_url("simhammer://nosuchrig")
    with pytest.raises(InputError, match="option scatter='x'"):
        model_from_url(url + "&scatter=x")
    with pytest.raises(InputError, match="duration_s"):
        model_from_url(url + "&duration_ms=5")
    with pytest.raises(InputError, match="unknown options"):
        hammer_url(rig, scater=0.1)
    m = model_from_url(hammer_url(rig, delay_ms=20, jitter_ms=0, rebound_fires=(1, 4), stuck_persists=True,
                                  silent_ms=250))
    assert (m.settings.fire_delay_s, m.settings.fire_jitter_s) == (0.02, 0.0)
    assert (tuple(m.faults.rebound_fires), m.faults.stuck_persists, m.faults.silent_s) == ((1, 4), True, 0.25)


# ---------------------------------------------------------------------------------- the model alone

class _Recorder:
    """A target that records strikes, with a manual hammer to copy the point from."""

    class hammer:
        point_m, direction = (0.1, 0.2, 0.3), (0.0, 0.0, -1.0)

    def __init__(self):
        self.strikes: list[tuple[list[Impact], float]] = []

    def strike(self, impacts, *, delay_s=0.0):
        self.strikes.append((list(impacts), delay_s))
        return list(impacts)


def _run_model(seed: int) -> tuple[list, _Recorder]:
    target = _Recorder()
    m = SimAutoHammer(target, SimHammerSettings(seed=seed, rebound_probability=0.5), HammerFaults())
    t, out = 100.0, []
    for k in range(20):
        out += m.handle(2 * k, hp.Arm(), t)
        out += m.handle(2 * k + 1, hp.Fire(k, hp.LevelMode.FORCE_N, 100.0, 1.0), t)
        while (wait := m.next_event_s(t)) is not None:
            t += wait
            out += m.poll(t)
    return out, target


def test_model_is_reproducible_and_timed_by_next_event():
    a, target = _run_model(5)
    b, _ = _run_model(5)
    c, _ = _run_model(6)
    assert a == b and a != c
    shots = [m for m in a if isinstance(m, hp.Shot)]
    assert len(shots) == 20 and {s.outcome for s in shots} == {hp.Outcome.FIRED}
    assert 4 <= sum(bool(s.flags) for s in shots) <= 16  # rebound probability 0.5
    impacts, delay = target.strikes[0]
    assert impacts[0].point_m == (0.1, 0.2, 0.3) and impacts[0].time_s == 0.0
    assert shots[0].delay_s == pytest.approx(delay)


# ---------------------------------------------------------------------------------- CAN

def _can_expect(bus: can.BusABC, match, timeout_s: float = WAIT_S):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        frame = bus.recv(timeout=max(0.0, deadline - time.monotonic()))
        decoded = hp.from_can(frame) if frame is not None else None
        if decoded is not None and match(decoded[1]):
            return decoded[1]
    raise TimeoutError(f"no matching CAN frame within {timeout_s} s")


def test_the_same_shot_over_can(rig):
    channel = f"odsplat-hammer-{uuid.uuid4().hex}"
    dev_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    host = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    model = SimAutoHammer(rig, SimHammerSettings(seed=4))
    try:
        with SimHammerCAN(dev_bus, model):
            host.send(hp.to_can(hp.Hello(), seq=1))
            info = _can_expect(host, lambda m: isinstance(m, hp.Info))
            assert (info.ref_seq, info.firmware, info.min_force_n, info.max_force_n, info.max_energy_j) == \
                (1, "1.0", 10.0, 2000.0, 10.0)
            # Another device's frame: ignored.
            host.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"))
            host.send(hp.to_can(hp.Arm(), seq=2))
            assert _can_expect(host, lambda m: isinstance(m, (hp.Ack, hp.Nak))) == hp.Ack(2, hp.MsgType.ARM)
            assert _can_expect(host, lambda m: isinstance(m, hp.Status)).state is hp.State.ARMED
            host.send(hp.to_can(hp.Fire(300, hp.LevelMode.FORCE_N, 400.0, 1.0), seq=3))
            assert _can_expect(host, lambda m: isinstance(m, (hp.Ack, hp.Nak))) == hp.Ack(3, hp.MsgType.FIRE)
            shot = _can_expect(host, lambda m: isinstance(m, hp.Shot))
            after = _can_expect(host, lambda m: isinstance(m, hp.Status) and m.state is hp.State.DISARMED)
            truth = model.fires[0]
            assert (shot.shot_id, shot.outcome, shot.shot_count) == (300 & 0xFF, hp.Outcome.FIRED, 1)
            assert shot.peak_force_n == pytest.approx(truth.measured_peak_n, abs=1e-3)
            assert shot.peak_force_n == pytest.approx(rig.impacts[0].peak_n, rel=0.01)
            assert shot.delay_s == pytest.approx(truth.wait_s + truth.delay_s, abs=1e-4)
            assert (after.ready, after.shot_count) == (False, 1)
            assert after.last_peak_force_n == pytest.approx(truth.measured_peak_n, abs=0.05)
            # a frame too short to decode, and an unknown command code
            host.send(can.Message(arbitration_id=hp.CMD_ID, is_extended_id=False, data=b"\x04\x07"))
            nak = _can_expect(host, lambda m: isinstance(m, hp.Nak))
            assert (nak.ref_seq, nak.ref_type, nak.reason) == (7, hp.MsgType.FIRE, hp.NakReason.MALFORMED)
            host.send(can.Message(arbitration_id=hp.CMD_ID, is_extended_id=False, data=b"\x09\x08" + bytes(6)))
            nak = _can_expect(host, lambda m: isinstance(m, hp.Nak))
            assert (nak.ref_seq, nak.ref_type, nak.reason) == (8, 0x19, hp.NakReason.UNKNOWN_TYPE)
            # any frame on the e-stop id stops it, a remote one too (Seq 0)
            host.send(can.Message(arbitration_id=hp.ESTOP_ID, is_extended_id=False, is_remote_frame=True, dlc=1))
            assert _can_expect(host, lambda m: isinstance(m, (hp.Ack, hp.Nak))) == hp.Ack(0, hp.MsgType.ESTOP)
            assert _can_expect(host, lambda m: isinstance(m, hp.Status)).state is hp.State.ESTOP
            host.send(hp.to_can(hp.Arm(), seq=10))
            assert _can_expect(host, lambda m: isinstance(m, (hp.Ack, hp.Nak))) == \
                hp.Nak(10, hp.MsgType.ARM, hp.NakReason.ESTOPPED)
        assert len(rig.impacts) == 1
    finally:
        dev_bus.shutdown()
        host.shutdown()
