"""The automatic impact hammer driver: arm, fire at a force or energy level, status, emergency stop, over
serial or CAN (docs/hammer-protocol.md), behind interlocks, with every fire logged.

A link carries the protocol's messages: `SerialHammerLink` (any pyserial URL; `simhammer://` in tests) or
`CANHammerLink` (any python-can bus; `virtual` in tests), as python-can's interfaces share one bus API.
`AutoHammer` runs a reader thread on the link, so `estop()` works from any thread, even while `fire()` waits.

Interlocks, on the host side (the hammer adds its own: no FIRE unless armed, one shot per ARM):
- no FIRE unless this driver armed the hammer and the recording is armed (`recording_armed`, a callable the
  capture session sets while its camera and DAQ are armed);
- a FIRE carries a timeout: the hammer gives up when it cannot fire within it; if the driver hears nothing
  within the timeout plus `reply_timeout_s`, it sends ESTOP, so a late shot cannot land after the record;
- `estop()` disarms at once and latches until `reset()`;
- every fire attempt, refused ones too, is logged with its time and outcome (`records`, the log, and
  `fire_log`, a JSON-lines file flushed and fsynced per line).
"""
from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

import can
import serial

from odsplat.spine.errors import InputError, OdsplatError

from . import hammerproto as hp

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------- errors

class HammerError(OdsplatError):
    """A fire that did not happen as asked; `record` says what did."""

    def __init__(self, message: str, record: FireRecord | None = None):
        super().__init__(message)
        self.record = record


class InterlockError(HammerError):
    """The driver refused to send FIRE: the hammer or the recording is not armed, or the e-stop is latched."""


class HammerRefused(HammerError):
    """The hammer answered NAK."""

    def __init__(self, message: str, record: FireRecord | None = None, reason: int | None = None):
        super().__init__(message, record)
        self.reason = reason


class HammerNoResponse(HammerError):
    """No reply within the timeout."""


class HammerLinkLost(HammerNoResponse):
    """The link itself failed (port closed, cable pulled)."""


class ShotFailed(HammerError):
    """The hammer accepted the FIRE but did not fire: expired, aborted, or a fault (see `record.outcome`)."""


# ---------------------------------------------------------------------------------- links

class HammerLink(Protocol):
    """A transport for the hammer's messages."""

    name: str
    seq_modulus: int  # the hammer echoes seq modulo this (65536 serial, 256 CAN)

    def send(self, message: hp.Command, seq: int) -> None: ...

    def receive(self, timeout_s: float) -> hp.Reply | None:
        """The next message from the hammer, or None when none came within timeout_s."""

    def close(self) -> None: ...


class SerialHammerLink:
    """The protocol's serial packets on an open pyserial port."""

    seq_modulus = 1 << 16

    def __init__(self, port: serial.SerialBase, name: str | None = None):
        self.port = port
        self.name = name or port.portstr
        self.decoder = hp.frame_decoder(self.name)
        self._pending: list[hp.Reply] = []
        self._write_lock = threading.Lock()
        self._write(b"\x00")  # ends whatever partial frame the hammer may hold

    @classmethod
    def from_url(cls, url: str, *, baudrate: int = 115_200) -> SerialHammerLink:
        """Open a port by pyserial URL (a device path, `simhammer://...`, `socket://...`)."""
        try:
            port = serial.serial_for_url(url, baudrate=baudrate, timeout=0.02, write_timeout=1.0)
        except (serial.SerialException, ValueError) as e:
            raise InputError(url, f"cannot open the hammer's port: {e}") from None
        return cls(port, name=url)

    def _write(self, data: bytes) -> None:
        try:
            with self._write_lock:
                self.port.write(data)
        except (serial.SerialException, OSError) as e:
            raise HammerLinkLost(f"{self.name}: {e}") from e

    def send(self, message: hp.Command, seq: int) -> None:
        self._write(hp.encode_frame(message, seq))

    def receive(self, timeout_s: float) -> hp.Reply | None:
        deadline = time.monotonic() + timeout_s
        while not self._pending:
            try:
                data = self.port.read(max(1, self.port.in_waiting))
            except (serial.SerialException, OSError, TypeError) as e:  # TypeError: pyserial after close()
                raise HammerLinkLost(f"{self.name}: {e}") from e
            for packet in self.decoder.feed(data):
                if isinstance(packet.message, (hp.Info, hp.Ack, hp.Nak, hp.Shot, hp.Status)):
                    self._pending.append(packet.message)
                else:
                    log.warning("%s: ignored a %s from the hammer", self.name, type(packet.message).__name__)
            if not self._pending and time.monotonic() >= deadline:
                return None
        return self._pending.pop(0)

    def close(self) -> None:
        self.port.close()


class CANHammerLink:
    """The protocol's CAN frames (auto_hammer.dbc) on an open python-can bus; other devices' frames pass by."""

    seq_modulus = 1 << 8

    def __init__(self, bus: can.BusABC, name: str | None = None, *, close_bus: bool = False):
        self.bus = bus
        self.name = name or f"CAN hammer on {getattr(bus, 'channel_info', 'bus')}"
        self._close_bus = close_bus

    def send(self, message: hp.Command, seq: int) -> None:
        try:
            self.bus.send(hp.to_can(message, seq))
        except can.CanError as e:
            raise HammerLinkLost(f"{self.name}: {e}") from e

    def receive(self, timeout_s: float) -> hp.Reply | None:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                msg = self.bus.recv(left)
            except can.CanError as e:
                raise HammerLinkLost(f"{self.name}: {e}") from e
            if msg is None:
                return None
            try:
                decoded = hp.from_can(msg)
            except hp.HammerProtocolError as e:
                log.warning("%s: %s", self.name, e)
                continue
            if decoded is not None and not isinstance(decoded[1], hp.COMMANDS):  # our own commands, echoed
                return decoded[1]

    def close(self) -> None:
        if self._close_bus:
            self.bus.shutdown()


# ---------------------------------------------------------------------------------- the fire log

@dataclass(frozen=True)
class FireRecord:
    """One fire attempt as the driver saw it (written to the fire log)."""

    shot_id: int
    time_s: float                # host wall clock (time.time()) when the FIRE was sent or refused
    mode: str                    # "force_n" or "energy_j"
    level: float
    outcome: str                 # fired, expired, aborted, fault, refused, nak, no_response
    peak_force_n: float | None = None  # the hammer's own load cell
    delay_s: float | None = None
    shot_count: int | None = None
    rebound: bool = False        # the hammer's load cell saw a second contact
    detail: str = ""

    @property
    def fired(self) -> bool:
        return self.outcome == "fired"

    def to_json(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------------------------- the driver

class AutoHammer:
    """One automatic hammer on a link. `hello()` first; then `arm()` and `fire()` for each shot."""

    def __init__(self, link: HammerLink, *, reply_timeout_s: float = 0.5,
                 recording_armed: Callable[[], bool] | None = None, fire_log: str | Path | None = None):
        self.link = link
        self.name = link.name
        self.reply_timeout_s = reply_timeout_s
        self.recording_armed: Callable[[], bool] = recording_armed or (lambda: False)
        self.fire_log = Path(fire_log) if fire_log is not None else None
        self.info: hp.Info | None = None
        self.last_status: hp.Status | None = None
        self.records: list[FireRecord] = []
        self.error: Exception | None = None  # the reader thread's failure (link lost)
        self._armed = False
        self._estopped = False
        self._seq = 0
        self._shot_id = 0
        self._replies: dict[int, hp.Reply] = {}
        self._shots: dict[int, hp.Shot] = {}
        self._cond = threading.Condition()
        self._send_lock = threading.Lock()
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"hammer reader {self.name}", daemon=True)
        self._thread.start()

    @classmethod
    def open_serial(cls, url: str, **kw) -> AutoHammer:
        return cls(SerialHammerLink.from_url(url), **kw)

    # ------------------------------------------------------------------------------ the reader thread

    def _run(self) -> None:
        try:
            while not self._closing.is_set():
                msg = self.link.receive(0.05)
                if msg is not None:
                    self._on_message(msg)
        except Exception as e:
            if not self._closing.is_set():
                log.error("%s: hammer link failed: %s", self.name, e)
            with self._cond:
                self.error = e
                self._cond.notify_all()

    def _on_message(self, msg: hp.Reply) -> None:
        with self._cond:
            if isinstance(msg, hp.Shot):
                self._shots[msg.shot_id] = msg
            elif isinstance(msg, hp.Status) and msg.ref_seq == hp.NO_REF:
                self.last_status = msg
                if msg.state in (hp.State.DISARMED, hp.State.FAULT, hp.State.ESTOP):
                    self._armed = False
            else:
                self._replies[msg.ref_seq] = msg
            self._cond.notify_all()

    # ------------------------------------------------------------------------------ requests

    def _send(self, message: hp.Command) -> int:
        with self._send_lock:
            seq = self._seq
            self._seq = (self._seq + 1) % (self.link.seq_modulus - 1)  # never the last: it means "unsolicited"
            self.link.send(message, seq)
        return seq

    def _wait(self, what: str, ready: Callable[[], object], timeout_s: float) -> object:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                got = ready()
                if got is not None:
                    return got
                left = deadline - time.monotonic()
                if self.error is not None:
                    raise HammerNoResponse(f"{self.name}: link lost while waiting for {what}: {self.error}")
                if left <= 0:
                    raise HammerNoResponse(f"{self.name}: no {what} within {timeout_s:g} s")
                self._cond.wait(left)

    def _request(self, message: hp.Command) -> hp.Reply:
        seq = self._send(message)
        reply = self._wait(f"reply to {message.TYPE.name}", lambda: self._replies.pop(seq, None), self.reply_timeout_s)
        if isinstance(reply, hp.Nak):
            err = reply.error(self.name)
            raise HammerRefused(str(err), reason=reply.reason)
        return reply

    # ------------------------------------------------------------------------------ commands

    def hello(self) -> hp.Info:
        """Who is there; also reads the status, so a latched fault or e-stop shows at once."""
        self.info = self._request(hp.Hello())
        status = self.status()
        log.info("%s: %s firmware %s, %g..%g N, up to %g J; %s, %d shots", self.name, self.info.device_id or "hammer",
                 self.info.firmware, self.info.min_force_n, self.info.max_force_n, self.info.max_energy_j,
                 status.state.name, status.shot_count)
        return self.info

    def status(self) -> hp.Status:
        status = self._request(hp.GetStatus())
        with self._cond:
            self.last_status = status
            self._estopped = status.state is hp.State.ESTOP
            if status.state is not hp.State.ARMED:
                self._armed = False
        return status

    @property
    def armed(self) -> bool:
        return self._armed

    def arm(self) -> None:
        """Arm for one shot."""
        if self._estopped:
            raise InterlockError(f"{self.name}: the emergency stop is latched; reset() first")
        self._request(hp.Arm())
        self._armed = True

    def disarm(self) -> None:
        self._armed = False
        self._request(hp.Disarm())

    def estop(self) -> None:
        """Emergency stop: sent at once, from any thread; the hammer disarms and latches until `reset()`."""
        self._armed = False
        self._estopped = True
        log.warning("%s: EMERGENCY STOP", self.name)
        try:
            self._request(hp.EStop())
        except HammerNoResponse:
            log.error("%s: the hammer did not acknowledge the emergency stop: cut its power", self.name)
            raise

    def reset(self) -> None:
        """Clear a latched emergency stop or fault (the hammer refuses when the fault persists)."""
        self._request(hp.Reset())
        self._estopped = False

    def fire(self, *, force_n: float | None = None, energy_j: float | None = None,
             timeout_s: float = 1.0) -> FireRecord:
        """Fire once at a force (N) or an energy (J); returns the record of a shot that FIRED.

        Raises InterlockError (nothing sent), HammerRefused (NAK), ShotFailed (expired, aborted, fault) or
        HammerNoResponse (then ESTOP is sent). Every outcome is logged and recorded."""
        if (force_n is None) == (energy_j is None):
            raise InputError(f"{self.name}: fire()", "give exactly one of force_n or energy_j")
        if force_n is not None:
            mode, level = hp.LevelMode.FORCE_N, float(force_n)
        else:
            mode, level = hp.LevelMode.ENERGY_J, float(energy_j)
        shot_id = self._shot_id
        self._shot_id = (self._shot_id + 1) % self.link.seq_modulus
        base = dict(shot_id=shot_id, mode=mode.name.lower(), level=level)
        why = self._interlock()
        if why:
            record = self._record(FireRecord(time_s=time.time(), outcome="refused", detail=why, **base))
            raise InterlockError(f"{self.name}: fire refused: {why}", record)
        t_sent = time.time()
        message = hp.Fire(shot_id, mode, level, timeout_s)
        try:
            self._request(message)
        except HammerRefused as e:
            if e.reason == hp.NakReason.NOT_ARMED:
                self._armed = False
            record = self._record(FireRecord(time_s=t_sent, outcome="nak", detail=str(e), **base))
            raise HammerRefused(str(e), record, e.reason) from None
        except HammerNoResponse as e:
            record = self._record(FireRecord(time_s=t_sent, outcome="no_response", detail=str(e), **base))
            self._safe_estop()
            raise HammerNoResponse(str(e), record) from None
        try:
            shot = self._wait(f"SHOT {shot_id}", lambda: self._shots.pop(shot_id, None),
                              timeout_s + self.reply_timeout_s)
        except HammerNoResponse as e:
            record = self._record(FireRecord(time_s=t_sent, outcome="no_response", detail=str(e), **base))
            self._safe_estop()
            raise HammerNoResponse(str(e), record) from None
        self._armed = False  # one shot per ARM
        outcome = hp.Outcome(shot.outcome).name.lower()
        detail = ""
        if shot.outcome is hp.Outcome.FAULT:
            try:
                detail = self.status().fault.name
            except HammerError as e:
                detail = f"fault (status unavailable: {e})"
        record = self._record(FireRecord(
            time_s=t_sent, outcome=outcome,
            peak_force_n=shot.peak_force_n if shot.outcome is hp.Outcome.FIRED else None,
            delay_s=shot.delay_s, shot_count=shot.shot_count, rebound=bool(shot.flags & hp.ShotFlag.REBOUND),
            detail=detail, **base))
        if shot.outcome is not hp.Outcome.FIRED:
            raise ShotFailed(f"{self.name}: shot {shot_id} {outcome}" + (f" ({detail})" if detail else "") +
                             f" after {shot.delay_s:.3f} s", record)
        return record

    def _interlock(self) -> str | None:
        if self._estopped:
            return "the emergency stop is latched"
        if not self._armed:
            return "the hammer is not armed"
        try:
            recording = bool(self.recording_armed())
        except Exception as e:  # an interlock that cannot be read is open
            return f"the recording's state cannot be read ({e})"
        if not recording:
            return "the recording (camera and DAQ) is not armed"
        return None

    def _safe_estop(self) -> None:
        try:
            self.estop()
        except HammerError:
            pass

    def _record(self, record: FireRecord) -> FireRecord:
        self.records.append(record)
        level = logging.INFO if record.fired else logging.WARNING
        log.log(level, "%s: fire %d at %g %s: %s%s%s", self.name, record.shot_id, record.level, record.mode,
                record.outcome, f", {record.peak_force_n:.1f} N" if record.peak_force_n is not None else "",
                f" ({record.detail})" if record.detail else "")
        if self.fire_log is not None:
            line = json.dumps({"hammer": self.name, **record.to_json()}) + "\n"
            self.fire_log.parent.mkdir(parents=True, exist_ok=True)
            with open(self.fire_log, "a", encoding="utf-8") as fh:
                fh.write(line)
                fh.flush()
                os.fsync(fh.fileno())
        return record

    # ------------------------------------------------------------------------------ lifecycle

    def close(self) -> None:
        """Disarm (best effort) and close the link."""
        if self.error is None and self._armed:
            try:
                self.disarm()
            except HammerError as e:
                log.warning("%s: could not disarm on close: %s", self.name, e)
        self._closing.set()
        self._thread.join(timeout=2.0)
        self.link.close()

    def __enter__(self) -> AutoHammer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
