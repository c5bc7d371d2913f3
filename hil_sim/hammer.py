"""A simulated automatic impact hammer (a solenoid hammer fired on command) that speaks the hammer protocol on a
PTY or a CAN bus and strikes a `SimRig`, with injectable faults and the ground truth of every shot; and the
`simhammer://` URL registry."""
from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol, Sequence
from urllib.parse import urlsplit

import can
import numpy as np

from odsplat.acquisition import hammerproto as hp
from odsplat.spine.errors import InputError

from .daq import register_url_handler
from .pty import PtyDevice, parse_bool, split_url_options
from .structure import Impact, check_unit_vector

if TYPE_CHECKING:
    from .rig import SimRig

log = logging.getLogger(__name__)

FAULT_KINDS = ("rebound", "not_ready", "stuck", "no_response")
_IDLE_S = 0.5  # the serial loop's longest sleep when nothing is due (close() wakes it anyway)
_CAN_POLL_S = 0.01  # the CAN loop's longest wait in recv(): timed events are served at least this often


class HammerTarget(Protocol):
    """What the hammer strikes; `SimRig` is one. `impacts` carry times relative to the strike, which lands
    `delay_s` after the target's now."""

    def strike(self, impacts: Sequence[Impact], *, delay_s: float = 0.0) -> list[Impact]: ...


@dataclass(frozen=True)
class SimHammerSettings:
    """The hammer's mechanics and its scatter. Times are wall-clock seconds except the contact's own shape."""

    point_m: tuple[float, float, float] | None = None  # None: the target's manual hammer point (target.hammer)
    direction: tuple[float, float, float] | None = None  # likewise
    duration_s: float = 1.0e-3  # half-sine contact
    fire_delay_s: float = 0.015  # FIRE executed (drive ready) -> contact, mean
    fire_jitter_s: float = 0.001  # sd of that delay
    force_scatter: float = 0.01  # relative sd of the true peak force shot to shot
    force_gain: float = 1.0  # true peak = level * gain * (1 + scatter N(0,1)): calibrated on another structure
    load_cell_noise: float = 0.002  # relative sd of the hammer's own measurement of the peak
    rebound_probability: float = 0.0  # chance of a double hit per shot
    rebound_delay_s: float = 3.0e-3
    rebound_ratio: float = 0.4
    recharge_s: float = 0.05  # after a shot, before the drive is ready again
    tip_mass_kg: float = 0.1  # energy mode: E = m v^2 / 2; peak F = pi m v (1 + restitution) / (2 duration)
    restitution: float = 0.0
    min_force_n: float = 10.0
    max_force_n: float = 2000.0
    max_energy_j: float = 10.0
    device_id: str = "odsplat-simhammer"
    firmware: str = "1.0"
    seed: int = 0

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise InputError(f"SimHammerSettings.{name}", f"{what}; got {getattr(self, name)!r}")

        need(0.5e-3 <= self.duration_s <= 3e-3, "duration_s", "expected 0.5 to 3 ms (a half-sine Impact)")
        for name in ("fire_delay_s", "fire_jitter_s", "force_scatter", "load_cell_noise", "rebound_delay_s",
                     "recharge_s", "restitution"):
            need(getattr(self, name) >= 0, name, "must be >= 0")
        need(self.force_gain > 0, "force_gain", "must be > 0")
        need(0 <= self.rebound_probability <= 1, "rebound_probability", "must lie in [0, 1]")
        need(0 < self.rebound_ratio <= 1, "rebound_ratio", "must lie in (0, 1]")
        need(self.tip_mass_kg > 0, "tip_mass_kg", "must be > 0")
        need(0 < self.min_force_n < self.max_force_n, "max_force_n",
             f"must exceed min_force_n ({self.min_force_n}) > 0")
        need(self.max_energy_j > 0, "max_energy_j", "must be > 0")

    def energy_force_n(self, energy_j: float) -> float:
        """Peak of the half-sine whose impulse is the tip's momentum change: v = sqrt(2 E / m)."""
        v = math.sqrt(2.0 * energy_j / self.tip_mass_kg)
        return math.pi * self.tip_mass_kg * v * (1.0 + self.restitution) / (2.0 * self.duration_s)


@dataclass
class HammerFaults:
    """Faults the hammer injects. A fire index counts accepted FIRE commands from 0 since the device was built."""

    rebound_fires: Sequence[int] = ()  # these shots bounce (double hit), whatever the probability
    not_ready_fires: Sequence[int] = ()  # the drive is not ready for not_ready_s from acceptance: the FIRE expires
    stuck_fires: Sequence[int] = ()  # the plunger sticks: SHOT outcome FAULT, fault STUCK latched, nothing strikes
    stuck_persists: bool = False  # RESET cannot clear STUCK (NAK FAULTED): a hammer that needs a person
    # Silent on receiving this FIRE (no ACK, no SHOT, no strike), every packet ignored for silent_s, then back
    # DISARMED, as after a watchdog reboot.
    no_response_fires: Sequence[int] = ()
    not_ready_s: float = 5.0
    silent_s: float = 0.5

    def of_fire(self, index: int) -> set[str]:
        lists = (self.rebound_fires, self.not_ready_fires, self.stuck_fires, self.no_response_fires)
        return {kind for kind, fires in zip(FAULT_KINDS, lists) if index in fires}


@dataclass(frozen=True)
class SimShot:
    """Ground truth of one accepted FIRE: what the hammer really did, beside what it reported."""

    fire_index: int
    shot_id: int
    mode: hp.LevelMode
    level: float
    outcome: hp.Outcome | None  # None: the device went silent on this FIRE (no_response), no SHOT was sent
    true_peak_n: float = 0.0  # the force that reached the structure (0 unless FIRED)
    measured_peak_n: float = 0.0  # what SHOT reported
    rebound: bool = False
    impacts: tuple[Impact, ...] = ()  # as the target scheduled them (its times)
    wait_s: float = 0.0  # FIRE received -> the drive fired (ready), or -> expiry / abort
    delay_s: float = 0.0  # the drive fired -> contact (the drawn fire delay); SHOT.delay_s = wait_s + delay_s
    faults: frozenset[str] = frozenset()  # the injected faults this FIRE carried


@dataclass
class _Pending:
    seq: int
    fire: hp.Fire
    index: int
    faults: frozenset[str]
    received_s: float
    deadline_s: float
    # Set when the drive fires: the outcome is decided then, and reported once the contact is over.
    shot: SimShot | None = None
    report_s: float = math.inf


class SimAutoHammer:
    """The hammer's state machine, free of any transport. One thread drives it through `handle` (a command
    arrived) and `poll` (timed events); both return the replies to send, in order. `now` is time.monotonic().

    A FIRE executes when the drive is ready: the strike is scheduled on the target at once, `delay` after the
    target's now, and SHOT is sent when the contact is over in wall time (delay + contact later). From then on
    DISARM cannot abort it (it is ACKed) and ESTOP latches but the SHOT still reports what struck."""

    def __init__(self, target: HammerTarget, settings: SimHammerSettings | None = None,
                 faults: HammerFaults | None = None):
        s = settings or SimHammerSettings()
        manual = getattr(target, "hammer", None)
        point = s.point_m if s.point_m is not None else getattr(manual, "point_m", None)
        direction = s.direction if s.direction is not None else getattr(manual, "direction", None)
        if point is None or direction is None:
            raise InputError(s.device_id, "no point_m/direction given and the target has no manual hammer to copy")
        d = np.asarray(direction, float)
        self.point_m = tuple(float(x) for x in point)
        self.direction = tuple(float(x) for x in d / np.linalg.norm(d))
        check_unit_vector(self.direction, f"{s.device_id}.direction")
        self.target = target
        self.settings = s
        self.faults = faults or HammerFaults()
        self.fires: list[SimShot] = []  # ground truth, one per accepted FIRE, in order
        self.shot_count = 0
        self.last_peak_force_n = 0.0
        self.state = hp.State.DISARMED
        self._rng = np.random.default_rng(s.seed)
        self._lock = threading.RLock()  # the transport's thread drives it; tests and the bench inject and read
        self._fire_index = 0
        self._injected: set[str] = set()
        self._ready_at: float | None = None  # None: ready now
        self._ready_since = -math.inf
        self._not_ready = False  # the NOT_READY fault shows until the drive is ready
        self._stuck = False  # the latched STUCK fault
        self._silent_until: float | None = None
        self._pending: _Pending | None = None

    # ------------------------------------------------------------------------------ what the host can see

    @property
    def ready(self) -> bool:
        return self._ready_at is None

    @property
    def fault(self) -> hp.Fault:
        if self._stuck:
            return hp.Fault.STUCK
        return hp.Fault.NOT_READY if self._not_ready else hp.Fault.NONE

    def status(self, ref_seq: int = hp.NO_REF) -> hp.Status:
        with self._lock:
            return hp.Status(ref_seq, self.state, self.ready, self.fault, self.shot_count, self.last_peak_force_n)

    def is_silent(self, now: float) -> bool:
        with self._lock:
            return self._silent_until is not None and now < self._silent_until

    # ------------------------------------------------------------------------------ driving it

    def inject_next(self, kind: str) -> None:
        """Give the next accepted FIRE this fault (one of FAULT_KINDS); several kinds may be queued together."""
        if kind not in FAULT_KINDS:
            raise InputError(self.settings.device_id, f"fault kind {kind!r}; expected one of {FAULT_KINDS}")
        with self._lock:
            self._injected.add(kind)

    def poll(self, now: float) -> list[hp.Reply]:
        """Run the timed events due by `now`: ready after recharge, a pending FIRE executing, its expiry, its
        SHOT once the contact is over, the end of a silence."""
        with self._lock:
            return self._advance(now)

    def next_event_s(self, now: float) -> float | None:
        """Seconds until `poll` has something to do (0 if overdue); None if nothing is scheduled."""
        with self._lock:
            event = self._next_event()
            return None if event is None else max(0.0, event[0] - now)

    def handle(self, seq: int, message: hp.Command, now: float) -> list[hp.Reply]:
        """The replies to one command with sequence number `seq`: its answer, then a STATUS if it changed
        state, ready or fault. Nothing while silent."""
        with self._lock:
            out = self._advance(now)
            if self._silent_until is not None:
                log.debug("%s (silent) ignored %s", self.settings.device_id, type(message).__name__)
                return out
            before = self._snapshot()
            self._command(seq, message, now, out)
            self._announce(before, out)
            out += self._advance(now)  # a FIRE the drive is ready for executes at once
            return out

    def refuse(self, seq: int, ref_type: int, reason: int | None, text: str, now: float) -> list[hp.Reply]:
        """The NAK of a packet or frame that did not parse (the transport's decoding failed; no reason: MALFORMED);
        nothing while silent."""
        with self._lock:
            out = self._advance(now)
            if self._silent_until is None:
                ascii_text = text.encode("ascii", "replace").decode("ascii")
                reason = hp.NakReason.MALFORMED if reason is None else int(reason)
                out.append(hp.Nak(seq & 0xFFFF, ref_type & 0xFF, reason, ascii_text))
            return out

    # ------------------------------------------------------------------------------ commands

    def _command(self, seq: int, msg: Any, now: float, out: list) -> None:
        s, state = self.settings, self.state
        if isinstance(msg, hp.Hello):
            out.append(hp.Info(seq, s.device_id, s.firmware, s.min_force_n, s.max_force_n, s.max_energy_j))
        elif isinstance(msg, hp.GetStatus):
            out.append(self.status(seq))
        elif isinstance(msg, hp.Arm):
            refused = {hp.State.FIRING: hp.NakReason.BUSY, hp.State.FAULT: hp.NakReason.FAULTED,
                       hp.State.ESTOP: hp.NakReason.ESTOPPED}.get(state)
            if refused is not None:
                out.append(hp.Nak(seq, msg.TYPE, refused, f"cannot arm in {state.name}"))
                return
            self.state = hp.State.ARMED
            out.append(hp.Ack(seq, msg.TYPE))
        elif isinstance(msg, hp.Disarm):
            out.append(hp.Ack(seq, msg.TYPE))
            if state is hp.State.ARMED:
                self.state = hp.State.DISARMED
            elif state is hp.State.FIRING and self._pending.shot is None:
                self._abort(now, out)
                self.state = hp.State.DISARMED
        elif isinstance(msg, hp.Fire):
            self._fire(seq, msg, now, out)
        elif isinstance(msg, hp.EStop):
            out.append(hp.Ack(seq, msg.TYPE))
            if self._pending is not None and self._pending.shot is None:
                self._abort(now, out)
            if state is not hp.State.ESTOP:
                log.warning("%s: emergency stop (was %s)", s.device_id, state.name)
            self.state = hp.State.ESTOP
        elif isinstance(msg, hp.Reset):
            if state in (hp.State.ESTOP, hp.State.FAULT):
                if self._stuck and self.faults.stuck_persists:
                    self.state = hp.State.FAULT
                    out.append(hp.Nak(seq, msg.TYPE, hp.NakReason.FAULTED,
                                      "STUCK persists: the plunger needs a person"))
                    return
                self._stuck = False
                # A shot released before an ESTOP is still in flight: FIRING until its SHOT, as without the ESTOP.
                self.state = hp.State.DISARMED if self._pending is None else hp.State.FIRING
            out.append(hp.Ack(seq, msg.TYPE))
        else:
            type_ = getattr(msg, "TYPE", 0)
            what = getattr(type_, "name", type_)
            out.append(hp.Nak(seq, type_, hp.NakReason.UNKNOWN_TYPE, f"{what} is sent by hammers, not to them"))

    def _fire(self, seq: int, msg: hp.Fire, now: float, out: list) -> None:
        s, state = self.settings, self.state
        refused = {hp.State.DISARMED: hp.NakReason.NOT_ARMED, hp.State.FAULT: hp.NakReason.FAULTED,
                   hp.State.ESTOP: hp.NakReason.ESTOPPED, hp.State.FIRING: hp.NakReason.BUSY}.get(state)
        if refused is not None:
            out.append(hp.Nak(seq, msg.TYPE, refused, f"cannot fire in {state.name}"))
            return
        problem = self._level_problem(msg)
        if problem:
            out.append(hp.Nak(seq, msg.TYPE, hp.NakReason.BAD_LEVEL, problem))
            return
        index = self._fire_index
        self._fire_index += 1
        faults = frozenset(self._injected | self.faults.of_fire(index))
        self._injected.clear()
        if "no_response" in faults:
            self._silent_until = now + self.faults.silent_s
            self.fires.append(SimShot(index, msg.shot_id, hp.LevelMode(msg.mode), msg.level, None, faults=faults))
            log.warning("%s: silent for %.3g s on fire %d (injected fault)", s.device_id, self.faults.silent_s, index)
            return
        timeout_s = min(max(msg.timeout_s, 0.0), hp.MAX_TIMEOUT_S)
        self._pending = _Pending(seq, msg, index, faults, now, now + timeout_s)
        self.state = hp.State.FIRING
        out.append(hp.Ack(seq, msg.TYPE))
        if "not_ready" in faults:
            self._not_ready = True
            self._ready_at = max(self._ready_at or now, now + self.faults.not_ready_s)
            log.info("%s: drive not ready for %.3g s on fire %d (injected fault)", s.device_id,
                     self.faults.not_ready_s, index)

    def _level_problem(self, msg: hp.Fire) -> str:
        s = self.settings
        if msg.mode not in hp.LevelMode._value2member_map_:
            return f"mode {msg.mode!r}; expected one of {[m.value for m in hp.LevelMode]}"
        if hp.LevelMode(msg.mode) is hp.LevelMode.FORCE_N:
            if not s.min_force_n <= msg.level <= s.max_force_n:
                return f"{msg.level:g} N outside {s.min_force_n:g}..{s.max_force_n:g} N"
        elif not 0.0 < msg.level <= s.max_energy_j:
            return f"{msg.level:g} J outside (0, {s.max_energy_j:g}] J"
        return ""

    def _abort(self, now: float, out: list) -> None:
        p = self._pending
        self._pending = None
        wait = max(0.0, now - p.received_s)
        self.fires.append(SimShot(p.index, p.fire.shot_id, hp.LevelMode(p.fire.mode), p.fire.level, hp.Outcome.ABORTED,
                                  wait_s=wait, faults=p.faults))
        out.append(hp.Shot(p.fire.shot_id, hp.Outcome.ABORTED, self.shot_count, 0.0, wait))
        log.info("%s: fire %d aborted after %.3f s", self.settings.device_id, p.index, wait)

    # ------------------------------------------------------------------------------ timed events

    def _next_event(self) -> tuple[float, int, Callable[[float, list], None]] | None:
        """The earliest scheduled event as (time, tie-break order, action)."""
        if self._silent_until is not None:
            return self._silent_until, 0, self._wake
        events = []
        if self._ready_at is not None:
            events.append((self._ready_at, 1, self._become_ready))
        p = self._pending
        if p is not None:
            if p.shot is not None:
                events.append((p.report_s, 2, self._report))
            else:
                if self._ready_at is None:
                    events.append((max(p.received_s, self._ready_since), 3, self._release))
                events.append((p.deadline_s, 4, self._expire))
        return min(events, key=lambda e: e[:2]) if events else None

    def _advance(self, now: float) -> list[hp.Reply]:
        out: list[hp.Reply] = []
        while True:
            event = self._next_event()
            if event is None or event[0] > now:
                return out
            before = self._snapshot()
            event[2](event[0], out)
            self._announce(before, out)

    def _snapshot(self) -> tuple:
        return self.state, self.ready, self.fault

    def _announce(self, before: tuple, out: list) -> None:
        if self._snapshot() != before:
            out.append(self.status())

    def _wake(self, t: float, out: list) -> None:
        log.info("%s: back after silence (watchdog reboot), DISARMED", self.settings.device_id)
        self._silent_until = None
        self.state = hp.State.DISARMED
        self._pending = None
        self._ready_at, self._ready_since, self._not_ready = None, t, False

    def _become_ready(self, t: float, out: list) -> None:
        self._ready_at, self._ready_since, self._not_ready = None, t, False

    def _release(self, t: float, out: list) -> None:
        """The drive fires: draw the shot, strike the target (or stick), report once the contact is over."""
        s, p = self.settings, self._pending
        rng = self._rng  # four draws per shot whatever its path, so a fault does not shift later shots' draws
        z_force, u_rebound = rng.standard_normal(), rng.random()
        z_delay, z_cell = rng.standard_normal(), rng.standard_normal()
        delay = max(0.0, s.fire_delay_s + s.fire_jitter_s * z_delay)
        mode, wait = hp.LevelMode(p.fire.mode), t - p.received_s
        common = dict(fire_index=p.index, shot_id=p.fire.shot_id, mode=mode, level=p.fire.level, wait_s=wait,
                      delay_s=delay, faults=p.faults)
        if "stuck" in p.faults:
            p.shot = SimShot(outcome=hp.Outcome.FAULT, **common)
            p.report_s = t + delay  # the contact never comes: the hammer knows when it should have
            return
        nominal = p.fire.level if mode is hp.LevelMode.FORCE_N else s.energy_force_n(p.fire.level)
        peak = max(0.05 * nominal, nominal * s.force_gain * (1.0 + s.force_scatter * z_force))
        rebound = "rebound" in p.faults or u_rebound < s.rebound_probability
        impacts = [Impact(0.0, self.point_m, self.direction, peak, s.duration_s)]
        if rebound:
            impacts.append(Impact(s.rebound_delay_s, self.point_m, self.direction, peak * s.rebound_ratio,
                                  s.duration_s))
        struck = self.target.strike(impacts, delay_s=delay)
        measured = peak * (1.0 + s.load_cell_noise * z_cell)
        p.shot = SimShot(outcome=hp.Outcome.FIRED, true_peak_n=peak, measured_peak_n=measured, rebound=rebound,
                         impacts=tuple(struck), **common)
        p.report_s = t + delay + (s.rebound_delay_s if rebound else 0.0) + s.duration_s
        log.info("%s: fire %d struck %.1f N (measured %.1f N)%s, %.2f ms after FIRE", s.device_id, p.index, peak,
                 measured, " with a rebound" if rebound else "", (wait + delay) * 1e3)

    def _report(self, t: float, out: list) -> None:
        p, shot = self._pending, self._pending.shot
        self._pending = None
        self.fires.append(shot)
        flags = hp.ShotFlag.REBOUND if shot.rebound else hp.ShotFlag(0)
        if shot.outcome is hp.Outcome.FIRED:
            self.shot_count += 1
            self.last_peak_force_n = shot.measured_peak_n
            self._ready_at = t + self.settings.recharge_s
            if self.state is hp.State.FIRING:
                self.state = hp.State.DISARMED  # one shot per ARM
        else:
            self._stuck = True
            if self.state is hp.State.FIRING:
                self.state = hp.State.FAULT
            log.warning("%s: plunger stuck on fire %d (injected fault)", self.settings.device_id, p.index)
        out.append(hp.Shot(shot.shot_id, shot.outcome, self.shot_count, shot.measured_peak_n,
                           shot.wait_s + shot.delay_s, flags))

    def _expire(self, t: float, out: list) -> None:
        p = self._pending
        self._pending = None
        wait = t - p.received_s
        self.fires.append(SimShot(p.index, p.fire.shot_id, hp.LevelMode(p.fire.mode), p.fire.level, hp.Outcome.EXPIRED,
                                  wait_s=wait, faults=p.faults))
        self.state = hp.State.DISARMED
        out.append(hp.Shot(p.fire.shot_id, hp.Outcome.EXPIRED, self.shot_count, 0.0, wait))
        log.info("%s: fire %d expired after %.3f s", self.settings.device_id, p.index, wait)


# ---------------------------------------------------------------------------------- serial transport

class SimHammerSerial(PtyDevice):
    """Serves the hammer on one PTY: a daemon thread decodes packets on the master and sends the model's replies."""

    def __init__(self, model: SimAutoHammer):
        super().__init__(model.settings.device_id)
        self.model = model
        self._decoder = hp.frame_decoder(f"{self.pty_name} (device side)")
        self._tx_seq = 0

    def _tick(self) -> float:
        now = time.monotonic()
        self._queue(self.model.poll(now))
        wait = self.model.next_event_s(now)
        return _IDLE_S if wait is None else min(wait, _IDLE_S)

    def _on_bytes(self, data: bytes) -> None:
        now = time.monotonic()
        if not self.model.is_silent(now):
            for raw in self._decoder.feed_raw(data):
                try:
                    packet = hp.parse_packet(raw)
                except hp.HammerProtocolError as e:
                    self._queue(self.model.refuse(raw.seq, raw.type, e.reason, str(e), now))
                    continue
                self._queue(self.model.handle(packet.seq, packet.message, now))  # nothing once it went silent
        if self.model.is_silent(now):
            # Rebooting: bytes are lost, and so is a partial frame, as in a real UART's buffer.
            self._decoder = hp.frame_decoder(f"{self.pty_name} (device side)")

    def _queue(self, replies: Sequence[hp.Reply]) -> None:
        for reply in replies:
            self._out += hp.encode_frame(reply, self._tx_seq)
            self._tx_seq = (self._tx_seq + 1) & 0xFFFF
        if replies and self._master >= 0:
            self._send()  # replies are small: write now rather than after the next select

# ---------------------------------------------------------------------------------- CAN transport

class SimHammerCAN:
    """Serves the hammer on a python-can bus (give it its own bus instance, as a real node has its own controller).

    Only HAMMER_ESTOP and HAMMER_CMD frames are read; every other id, the hammer's own replies included, is
    ignored, and so are remote frames except on the e-stop id (any frame there stops the hammer). A command frame
    that does not decode is NAKed with the decoder's reason, its Seq byte and its Command nibble as RefCommand
    (0 for Seq and RefCommand where the frame is too short to hold them)."""

    def __init__(self, bus: can.BusABC, model: SimAutoHammer):
        self.bus = bus
        self.model = model
        self._name = model.settings.device_id
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"simhammer-can {self._name}", daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("%s: CAN thread did not stop within %g s", self._name, timeout_s)
            self._thread = None

    def __enter__(self) -> SimHammerCAN:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                self._send(self.model.poll(now))
                wait = self.model.next_event_s(now)
                msg = self.bus.recv(timeout=_CAN_POLL_S if wait is None else min(wait, _CAN_POLL_S))
                if msg is not None:
                    self._on_frame(msg, time.monotonic())
        except Exception:  # a dead hammer must show in the log, the host sees only silence
            log.exception("%s: CAN thread failed", self._name)

    def _on_frame(self, msg: can.Message, now: float) -> None:
        if (msg.is_error_frame or msg.is_extended_id or msg.arbitration_id not in (hp.ESTOP_ID, hp.CMD_ID)
                or (msg.is_remote_frame and msg.arbitration_id != hp.ESTOP_ID)):
            return
        try:
            decoded = hp.from_can(msg)
        except hp.HammerProtocolError as e:
            seq, ref_type = _raw_command(msg)
            self._send(self.model.refuse(seq, ref_type, e.reason, str(e), now))
            return
        if decoded is not None:
            seq, command = decoded
            self._send(self.model.handle(seq, command, now))

    def _send(self, replies: Sequence[hp.Reply]) -> None:
        for reply in replies:
            try:
                self.bus.send(hp.to_can(reply))
            except can.CanError as e:
                log.warning("%s: reply %s lost: %s", self._name, type(reply).__name__, e)


def _raw_command(msg: can.Message) -> tuple[int, int]:
    """(seq, serial type) of an undecodable HAMMER_CMD frame, as far as its bytes go: Seq is byte 1, the Command
    the low nibble of byte 0 (type = 0x10 + Command, which to_can sends as RefCommand); 0 where the frame is too
    short."""
    data = bytes(msg.data)
    return (data[1] if len(data) > 1 else 0), (0x10 + (data[0] & 0x0F) if data else 0)


# ---------------------------------------------------------------------------------- registry and URL

_TARGETS: dict[str, HammerTarget] = {}


def register_target(name: str, target: HammerTarget) -> None:
    """Make `simhammer://NAME` strike `target`."""
    _TARGETS[name.lower()] = target
    register_url_handler()


def _ms(value: str) -> float:
    return float(value) * 1e-3


def _ints(value: str) -> tuple[int, ...]:
    return tuple(int(x) for x in value.split(",") if x.strip())


# URL option -> (SimHammerSettings or HammerFaults field, parser)
_URL_OPTIONS: dict[str, tuple[str, Callable[[str], Any]]] = {
    "seed": ("seed", int),
    "scatter": ("force_scatter", float),
    "gain": ("force_gain", float),
    "noise": ("load_cell_noise", float),
    "duration_ms": ("duration_s", _ms),
    "delay_ms": ("fire_delay_s", _ms),
    "jitter_ms": ("fire_jitter_s", _ms),
    "rebound": ("rebound_probability", float),
    "recharge_ms": ("recharge_s", _ms),
    "rebound_fires": ("rebound_fires", _ints),
    "not_ready_fires": ("not_ready_fires", _ints),
    "stuck_fires": ("stuck_fires", _ints),
    "no_response_fires": ("no_response_fires", _ints),
    "stuck_persists": ("stuck_persists", parse_bool),
    "silent_ms": ("silent_s", _ms),
    "not_ready_ms": ("not_ready_s", _ms),
}
_FAULT_FIELDS = {f.name for f in dataclasses.fields(HammerFaults)}


def model_from_url(url: str) -> SimAutoHammer:
    """The hammer a `simhammer://NAME?option=value&...` URL describes, on the registered target NAME."""
    parts = urlsplit(url)
    if parts.scheme.lower() != "simhammer" or not parts.netloc:
        raise InputError(url, "expected simhammer://TARGET[?option=value&...]")
    try:
        target = _TARGETS[parts.netloc.lower()]
    except KeyError:
        raise InputError(url, f"no target {parts.netloc!r}; registered: {sorted(_TARGETS)}") from None
    settings_kw, fault_kw = split_url_options(url, parts.query, _URL_OPTIONS, _FAULT_FIELDS)
    try:
        settings = SimHammerSettings(**settings_kw)
    except InputError as e:
        raise InputError(url, str(e)) from None
    return SimAutoHammer(target, settings, HammerFaults(**fault_kw))


def device_from_url(url: str) -> SimHammerSerial:
    """Build (not yet serve) the serial device a `simhammer://` URL describes."""
    return SimHammerSerial(model_from_url(url))


def _url_value(value: Any) -> str:
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, (list, tuple, set, frozenset)):
        return ",".join(str(int(v)) for v in value)
    return str(value)


def hammer_url(rig: SimRig, name: str | None = None, **options) -> str:
    """Register `rig` as a hammer target (default name `rig.name`) and return its `simhammer://` URL with
    `options` (the URL's: seed, scatter, gain, delay_ms, ..., sequences for the *_fires lists)."""
    unknown = sorted(set(options) - set(_URL_OPTIONS))
    if unknown:
        raise InputError("hammer_url", f"unknown options {unknown}; expected some of {sorted(_URL_OPTIONS)}")
    name = name or rig.name
    register_target(name, rig)
    query = "&".join(f"{k}={_url_value(v)}" for k, v in options.items())
    return f"simhammer://{name}" + (f"?{query}" if query else "")


__all__ = ["FAULT_KINDS", "HammerFaults", "HammerTarget", "SimAutoHammer", "SimHammerCAN", "SimHammerSerial",
           "SimHammerSettings", "SimShot", "device_from_url", "hammer_url", "model_from_url", "register_target"]
