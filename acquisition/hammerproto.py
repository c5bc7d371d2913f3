"""The automatic impact hammer's protocol (docs/hammer-protocol.md): typed messages, their serial packets
(framed exactly like the DAQ's: COBS, version/type/seq header, CRC-32) and their CAN frames (described by
`acquisition/auto_hammer.dbc`). Shared by the simulated device and the driver, so neither can drift from the spec."""
from __future__ import annotations

import enum
import functools
import logging
import math
import struct
from dataclasses import dataclass
from importlib import resources
from typing import ClassVar, Union

import can
import cantools

from odsplat.spine.errors import InputError, SchemaError

from . import daqproto as dp

log = logging.getLogger(__name__)

DBC_RESOURCE = "auto_hammer.dbc"  # package data of `odsplat.acquisition`
NO_REF = 0xFFFF  # ref_seq of an unsolicited STATUS (serial)
CAN_NO_REF = 0xFF  # the same on CAN
CAN_MAX_LEVEL = 16777.215  # Level on CAN: u24 in mN or mJ
MAX_TIMEOUT_S = 65.535  # fire timeouts travel in ms, u16 on CAN (u32 on serial, capped to the same)


class HammerProtocolError(dp.DAQProtocolError):
    """The hammer (or host) broke the protocol, or the hammer refused a command (NAK)."""


class MsgType(enum.IntEnum):
    # host -> hammer
    HELLO = 0x11
    ARM = 0x12
    DISARM = 0x13
    FIRE = 0x14
    ESTOP = 0x15
    RESET = 0x16
    GET_STATUS = 0x17
    # hammer -> host (high bit set)
    INFO = 0x91
    ACK = 0x93
    NAK = 0x94
    SHOT = 0x95
    STATUS = 0x96


class NakReason(enum.IntEnum):
    # 1-3 are the framing-level refusals, the same codes as the DAQ's
    UNSUPPORTED_VERSION = 1
    UNKNOWN_TYPE = 2
    MALFORMED = 3
    BUSY = 4          # a FIRE is already pending
    NOT_ARMED = 5     # FIRE without ARM (the hammer's own interlock)
    BAD_LEVEL = 6     # outside the hammer's force or energy range, or a bad mode
    FAULTED = 7       # a fault is latched: RESET first
    ESTOPPED = 8      # the emergency stop is latched: RESET first


class State(enum.IntEnum):
    DISARMED = 0
    ARMED = 1
    FIRING = 2   # a FIRE was accepted and waits for the mechanism (ready) or its timeout
    FAULT = 3
    ESTOP = 4


class Fault(enum.IntEnum):
    NONE = 0
    STUCK = 1        # the plunger did not move (or did not return): nothing reached the structure
    NOT_READY = 2    # the drive never became ready (capacitor not charged, mechanism not in position)
    OVERTEMP = 3     # the solenoid is too hot to fire


class Outcome(enum.IntEnum):
    FIRED = 1
    EXPIRED = 2   # not executed within the FIRE's timeout: nothing fired
    ABORTED = 3   # cancelled by DISARM or ESTOP before it fired
    FAULT = 4     # the mechanism faulted: see STATUS fault


class LevelMode(enum.IntEnum):
    FORCE_N = 0
    ENERGY_J = 1


class ShotFlag(enum.IntFlag):
    REBOUND = 0x01  # the hammer's own load cell saw a second contact


# ---------------------------------------------------------------------------------- messages

_Empty = dp.EmptyBody  # commands without a body encode as the DAQ's do


@dataclass(frozen=True)
class Hello(_Empty):
    """Who is there? Answered INFO."""
    TYPE: ClassVar[MsgType] = MsgType.HELLO


@dataclass(frozen=True)
class Arm(_Empty):
    """Arm for one shot; answered ACK, or NAK (FAULTED, ESTOPPED). A shot (or DISARM) disarms again."""
    TYPE: ClassVar[MsgType] = MsgType.ARM


@dataclass(frozen=True)
class Disarm(_Empty):
    """Disarm (idempotent, always ACKed); a pending FIRE ends with a SHOT of outcome ABORTED."""
    TYPE: ClassVar[MsgType] = MsgType.DISARM


@dataclass(frozen=True)
class Fire:
    """Fire once at `level` (N or J, by `mode`) when ready, or give up after `timeout_s`. ACK, then one SHOT."""
    TYPE: ClassVar[MsgType] = MsgType.FIRE
    shot_id: int          # the host's number for this shot, echoed in SHOT (u16 serial, u8 on CAN)
    mode: LevelMode
    level: float
    timeout_s: float

    def _body(self) -> bytes:
        _check_timeout(self.timeout_s)
        return struct.pack("<HBfI", self.shot_id & 0xFFFF, int(self.mode), self.level, round(self.timeout_s * 1000))

    @classmethod
    def _parse(cls, r: dp.BodyReader) -> Fire:
        shot_id, mode, level, timeout_ms = r.take("HBfI")
        return cls(shot_id, LevelMode(mode) if mode in LevelMode._value2member_map_ else mode, level, timeout_ms / 1000)


def _check_timeout(timeout_s: float) -> None:
    if not 0.001 <= timeout_s <= MAX_TIMEOUT_S:  # it travels in whole ms
        raise InputError("FIRE", f"timeout {timeout_s!r} s must lie in [0.001, {MAX_TIMEOUT_S}]")


@dataclass(frozen=True)
class EStop(_Empty):
    """Emergency stop: disarm at once, abort a pending FIRE, latch ESTOP until RESET. Always ACKed."""
    TYPE: ClassVar[MsgType] = MsgType.ESTOP


@dataclass(frozen=True)
class Reset(_Empty):
    """Clear a latched fault or emergency stop (to DISARMED); NAK FAULTED if the fault persists."""
    TYPE: ClassVar[MsgType] = MsgType.RESET


@dataclass(frozen=True)
class GetStatus(_Empty):
    """Answered STATUS."""
    TYPE: ClassVar[MsgType] = MsgType.GET_STATUS


@dataclass(frozen=True)
class Info:
    TYPE: ClassVar[MsgType] = MsgType.INFO
    ref_seq: int
    device_id: str
    firmware: str
    min_force_n: float
    max_force_n: float
    max_energy_j: float

    def _body(self) -> bytes:
        return (struct.pack("<H", self.ref_seq) + dp.encode_text(self.device_id, "device id")
                + dp.encode_text(self.firmware, "firmware")
                + struct.pack("<fff", self.min_force_n, self.max_force_n, self.max_energy_j))

    @classmethod
    def _parse(cls, r: dp.BodyReader) -> Info:
        ref_seq, device_id, firmware = r.take("H"), r.text(), r.text()
        return cls(ref_seq, device_id, firmware, *r.take("fff"))


@dataclass(frozen=True)
class Ack(dp.Ack):
    """The DAQ protocol's ACK body (ref_seq u16, ref_type u8) under the hammer's type code."""
    TYPE: ClassVar[MsgType] = MsgType.ACK


@dataclass(frozen=True)
class Nak(dp.Nak):
    """The DAQ protocol's NAK body (ref_seq, ref_type, reason, text) under the hammer's type code and reasons."""
    TYPE: ClassVar[MsgType] = MsgType.NAK

    @property
    def reason_name(self) -> str:
        return NakReason(self.reason).name if self.reason in NakReason._value2member_map_ else str(self.reason)

    def error(self, device: str) -> HammerProtocolError:
        what = MsgType(self.ref_type).name if self.ref_type in MsgType._value2member_map_ else hex(self.ref_type)
        detail = f" ({self.text})" if self.text else ""
        err = HammerProtocolError(device, f"refused {what}: {self.reason_name}{detail}")
        err.reason = self.reason
        return err


@dataclass(frozen=True)
class Shot:
    """What became of one FIRE: sent once per accepted FIRE."""
    TYPE: ClassVar[MsgType] = MsgType.SHOT
    shot_id: int
    outcome: Outcome
    shot_count: int        # shots fired since power-on, this one included (u32 serial, u16 on CAN)
    peak_force_n: float    # the hammer's own load cell; 0 unless FIRED
    delay_s: float         # FIRE received -> contact (FIRED) or -> giving up
    flags: ShotFlag = ShotFlag(0)

    def _body(self) -> bytes:
        return struct.pack("<HBIffB", self.shot_id & 0xFFFF, int(self.outcome), self.shot_count, self.peak_force_n,
                           self.delay_s, int(self.flags))

    @classmethod
    def _parse(cls, r: dp.BodyReader) -> Shot:
        shot_id, outcome, count, peak, delay, flags = r.take("HBIffB")
        return cls(shot_id, Outcome(outcome), count, peak, delay, ShotFlag(flags))


@dataclass(frozen=True)
class Status:
    """The hammer's state; answers GET_STATUS (ref_seq) and is sent unsolicited (NO_REF) on every state change."""
    TYPE: ClassVar[MsgType] = MsgType.STATUS
    ref_seq: int
    state: State
    ready: bool
    fault: Fault
    shot_count: int
    last_peak_force_n: float

    def _body(self) -> bytes:
        return struct.pack("<HBBBIf", self.ref_seq, int(self.state), int(self.ready), int(self.fault), self.shot_count,
                           self.last_peak_force_n)

    @classmethod
    def _parse(cls, r: dp.BodyReader) -> Status:
        ref_seq, state, ready, fault, count, peak = r.take("HBBBIf")
        return cls(ref_seq, State(state), bool(ready), Fault(fault), count, peak)


Command = Union[Hello, Arm, Disarm, Fire, EStop, Reset, GetStatus]
Reply = Union[Info, Ack, Nak, Shot, Status]
Message = Union[Command, Reply]
MESSAGES: dict[int, type] = {m.TYPE: m for m in (Hello, Arm, Disarm, Fire, EStop, Reset, GetStatus,
                                                 Info, Ack, Nak, Shot, Status)}
COMMANDS = (Hello, Arm, Disarm, Fire, EStop, Reset, GetStatus)


# ---------------------------------------------------------------------------------- serial

def encode_frame(message: Message, seq: int) -> bytes:
    """One serial frame: the DAQ protocol's packet (version 1, type, seq, body, CRC-32), COBS, 0x00."""
    return dp.encode_frame(message, seq)


def frame_decoder(device: str) -> dp.FrameDecoder:
    """A stream decoder for hammer packets (the DAQ's framing with the hammer's message types)."""
    return dp.FrameDecoder(device, MESSAGES, HammerProtocolError)


def parse_packet(raw: dp.RawPacket) -> dp.Packet:
    return dp.parse_packet(raw, MESSAGES, HammerProtocolError)


# ---------------------------------------------------------------------------------- CAN

ESTOP_ID, CMD_ID, REPLY_ID, STATUS_ID, SHOT_ID, INFO_ID = 0x010, 0x300, 0x301, 0x302, 0x303, 0x304
CAN_IDS = (ESTOP_ID, CMD_ID, REPLY_ID, STATUS_ID, SHOT_ID, INFO_ID)


@functools.cache
def load_dbc() -> cantools.database.can.Database:
    """The hammer's DBC shipped with odsplat; refused if it lacks a frame this codec uses."""
    text = resources.files("odsplat.acquisition").joinpath(DBC_RESOURCE).read_text(encoding="ascii")
    db = cantools.database.load_string(text, database_format="dbc")
    for frame_id in CAN_IDS:
        try:
            db.get_message_by_frame_id(frame_id)
        except KeyError:
            raise SchemaError(DBC_RESOURCE, f"no frame with id 0x{frame_id:03x}") from None
    return db


def _clamp(value: float, hi: float) -> float:
    return min(max(float(value), 0.0), hi)


def to_can(message: Message, seq: int = 0) -> can.Message:
    """The CAN frame of a message. `seq` numbers host commands (mod 256); replies carry their ref_seq.

    CAN frames are narrower than serial packets: shot ids wrap mod 256 and shot counts mod 65536, forces
    and delays are rounded to the DBC's scales, INFO's device id is not sent, and a FIRE level outside the
    frame's range is refused."""
    db = load_dbc()
    m = message
    if isinstance(m, EStop):
        frame_id, sig = ESTOP_ID, {"Seq": seq & 0xFF}
    elif isinstance(m, COMMANDS):
        sig = {"Command": int(m.TYPE) - 0x10, "Mode": 0, "Seq": seq & 0xFF, "ShotId": 0, "Timeout": 0.0, "Level": 0.0}
        if isinstance(m, Fire):
            _check_timeout(m.timeout_s)
            if not 0.0 <= m.level <= CAN_MAX_LEVEL:
                raise InputError("FIRE", f"level {m.level!r} does not fit the CAN frame's 0..{CAN_MAX_LEVEL}")
            sig.update(Mode=int(m.mode), ShotId=m.shot_id & 0xFF, Timeout=m.timeout_s, Level=m.level)
        frame_id = CMD_ID
    elif isinstance(m, (Ack, Nak)):
        frame_id = REPLY_ID
        sig = {"RefSeq": m.ref_seq & 0xFF, "RefCommand": int(m.ref_type) - 0x10 if 0x10 <= m.ref_type <= 0x1F else 0,
               "Accepted": int(isinstance(m, Ack)), "NakReason": m.reason if isinstance(m, Nak) else 0}
    elif isinstance(m, Status):
        frame_id = STATUS_ID
        sig = {"RefSeq": CAN_NO_REF if m.ref_seq == NO_REF else m.ref_seq & 0xFF, "State": int(m.state),
               "Ready": int(m.ready), "Fault": int(m.fault), "ShotCount": m.shot_count & 0xFFFF,
               "LastPeakForce": _clamp(m.last_peak_force_n, 6553.5)}
    elif isinstance(m, Shot):
        frame_id = SHOT_ID
        sig = {"ShotId": m.shot_id & 0xFF, "Outcome": int(m.outcome), "Rebound": int(bool(m.flags & ShotFlag.REBOUND)),
               "Delay": _clamp(m.delay_s, 0.4095), "ShotCount": m.shot_count & 0xFFFF,
               "PeakForce": _clamp(m.peak_force_n, CAN_MAX_LEVEL)}
    elif isinstance(m, Info):
        major, minor = ([_small_int(p) for p in m.firmware.split(".")] + [0, 0])[:2]
        frame_id = INFO_ID
        sig = {"RefSeq": m.ref_seq & 0xFF, "FwMajor": major, "FwMinor": minor,
               # limits rounded inwards, so a host never believes the hammer accepts more than it does
               "MinForce": math.ceil(_clamp(m.min_force_n, 65535) - 1e-9),
               "MaxForce": math.floor(_clamp(m.max_force_n, 65535) + 1e-9),
               "MaxEnergy": math.floor(_clamp(m.max_energy_j, 25.5) * 10 + 1e-9) / 10}
    else:
        raise InputError("hammer CAN codec", f"no CAN frame for {type(m).__name__}")
    return can.Message(arbitration_id=frame_id, is_extended_id=False, data=db.encode_message(frame_id, sig))


def _small_int(text: str) -> int:
    digits = "".join(ch for ch in text if ch.isdigit())
    return min(int(digits), 255) if digits else 0


def from_can(msg: can.Message) -> tuple[int, Message] | None:
    """(seq, message) of a hammer frame; None for frames of other devices. A command's seq is its own;
    a reply's is its ref_seq (CAN_NO_REF for SHOT and unsolicited STATUS). Raises HammerProtocolError for
    a frame that does not decode."""
    if msg.is_error_frame or msg.is_extended_id or msg.arbitration_id not in CAN_IDS:
        return None
    frame_id = msg.arbitration_id
    if frame_id == ESTOP_ID:  # any frame on the e-stop id stops, even an empty or remote one
        return (msg.data[0] if len(msg.data) and not msg.is_remote_frame else 0), EStop()
    where = f"CAN id 0x{frame_id:03x}"
    try:
        sig = load_dbc().decode_message(frame_id, bytes(msg.data), decode_choices=False)
    except Exception as e:  # cantools raises several types for short or odd frames
        err = HammerProtocolError(where, f"cannot decode {bytes(msg.data).hex()}: {e}")
        err.reason = NakReason.MALFORMED
        raise err from None
    try:
        if frame_id == CMD_ID:
            cls = MESSAGES.get(int(sig["Command"]) + 0x10)
            if cls not in COMMANDS:
                err = HammerProtocolError(where, f"unknown command {int(sig['Command'])}")
                err.reason = NakReason.UNKNOWN_TYPE
                raise err
            if cls is Fire:
                mode = int(sig["Mode"])
                return int(sig["Seq"]), Fire(int(sig["ShotId"]), LevelMode(mode) if mode in LevelMode._value2member_map_
                                             else mode, round(float(sig["Level"]), 3), round(float(sig["Timeout"]), 3))
            return int(sig["Seq"]), cls()
        if frame_id == REPLY_ID:
            ref, ref_type = int(sig["RefSeq"]), int(sig["RefCommand"]) + 0x10
            if sig["Accepted"]:
                return ref, Ack(ref, ref_type)
            return ref, Nak(ref, ref_type, int(sig["NakReason"]))
        if frame_id == STATUS_ID:
            ref = int(sig["RefSeq"])
            return ref, Status(NO_REF if ref == CAN_NO_REF else ref, State(int(sig["State"])), bool(sig["Ready"]),
                               Fault(int(sig["Fault"])), int(sig["ShotCount"]), round(float(sig["LastPeakForce"]), 1))
        if frame_id == SHOT_ID:
            return CAN_NO_REF, Shot(int(sig["ShotId"]), Outcome(int(sig["Outcome"])), int(sig["ShotCount"]),
                                    round(float(sig["PeakForce"]), 3), round(float(sig["Delay"]), 4),
                                    ShotFlag.REBOUND if sig["Rebound"] else ShotFlag(0))
        ref = int(sig["RefSeq"])
        return ref, Info(ref, "", f"{int(sig['FwMajor'])}.{int(sig['FwMinor'])}", float(sig["MinForce"]),
                         float(sig["MaxForce"]), round(float(sig["MaxEnergy"]), 1))
    except HammerProtocolError:
        raise
    except ValueError as e:  # an enum value the spec does not define
        err = HammerProtocolError(where, f"bad frame {bytes(msg.data).hex()}: {e}")
        err.reason = NakReason.MALFORMED
        raise err from None
