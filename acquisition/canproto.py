"""Host side of the CAN accelerometer-node protocol: the DBC, frame codecs, and a reader that turns
frames into gap-aware sample blocks timed by each node's own sample counter (docs/can-protocol.md)."""
from __future__ import annotations

import functools
import logging
import struct
import time
from dataclasses import dataclass, field
from enum import IntEnum
from importlib import resources
from typing import Any, Iterable, Mapping

import can
import cantools
import numpy as np

from odsplat.spine.errors import InputError, SchemaError
from odsplat.spine.units import STANDARD_GRAVITY_M_S2

log = logging.getLogger(__name__)

DBC_RESOURCE = "accel_nodes.dbc"  # package data of `odsplat.acquisition`
NODE_IDS = range(1, 17)
BROADCAST = 0  # NODE_CMD at NODE_CMD_BASE itself reaches every node
ACC_DATA_BASE, NODE_CMD_BASE, NODE_STATUS_BASE = 0x100, 0x600, 0x700
# Symmetric full scale: -32768 is never sent, so both signs saturate at the same magnitude.
FULL_SCALE_COUNTS = 32767
SAMPLE_RATES_HZ: dict[int, float] = {0: 250.0, 1: 500.0, 2: 1000.0, 3: 2000.0, 4: 4000.0}
RANGES_M_S2: dict[int, float] = {
    code: g * STANDARD_GRAVITY_M_S2 for code, g in enumerate((2, 4, 8, 16, 50, 100, 200, 500))
}
# Worst-case bit-stuffed length of a classic 11-bit-id frame with 8 data bytes, in bits.
FRAME_BITS_WORST = 135

_COUNTER_MOD = 1 << 16
_CODE_TOLERANCE = 1e-3  # "156.9 m/s^2" selects the +-16 g range (156.9064 m/s^2)
_ACC = struct.Struct("<Hhhh")
_ACC_DTYPE = np.dtype([("counter", "<u2"), ("acc", "<i2", (3,))])
_ERROR_FRAME_DATA = bytes([0, 0, 0x01, 0, 0, 0, 0, 0])  # SocketCAN layout: protocol violation, bit error


class NodeState(IntEnum):
    IDLE = 0
    RUNNING = 1
    FAULT = 2  # refused a START (unknown rate or range code); STOP clears it


class Command(IntEnum):
    QUERY = 0
    START = 1  # carries RateCode and RangeCode; resets the sample counter to 0
    STOP = 2


@dataclass(frozen=True)
class NodeStatus:
    """One NODE_STATUS frame, decoded."""

    node_id: int
    state: NodeState
    sample_rate_hz: float | None  # None for a code outside SAMPLE_RATES_HZ
    range_m_s2: float | None
    overrun: bool  # sticky until START: a sample could not be sent
    clipping: bool  # sticky until START: an axis was saturated at full scale
    ack: bool  # this frame answers a NODE_CMD
    firmware: tuple[int, int]
    counter: int  # 16-bit counter of the next sample the node will take


@dataclass(frozen=True)
class AccelBlock:
    """Contiguous samples of one node: sample k was taken at k / sample_rate_hz on the node's clock, since START."""

    node_id: int
    first_sample: int  # 64-bit sample index, 0 = the first sample after START
    sample_rate_hz: float  # nominal; the node's true clock may drift from it
    range_m_s2: float
    samples: np.ndarray  # (n, 3) float64 m/s^2 along the node's X, Y, Z

    @property
    def n_samples(self) -> int:
        return self.samples.shape[0]

    @property
    def t_s(self) -> np.ndarray:
        return (self.first_sample + np.arange(self.n_samples)) / self.sample_rate_hz

    @property
    def clipped(self) -> np.ndarray:
        """(n, 3) bool: values at full scale, i.e. saturated (or exactly at the range)."""
        return np.abs(self.samples) >= self.range_m_s2 * (1 - 0.5 / FULL_SCALE_COUNTS)


@dataclass(frozen=True)
class Gap:
    """Samples first_sample .. first_sample + n_lost - 1 of a node never arrived; they are not filled."""

    node_id: int
    first_sample: int
    n_lost: int


@dataclass(frozen=True)
class NodeTimeout:
    """A running node sent no data frame for longer than the reader's node_timeout_s."""

    node_id: int
    next_sample: int  # the first sample not received
    silent_s: float  # host time since its last data frame, when detected


@functools.cache
def load_dbc() -> cantools.database.can.Database:
    """The node DBC shipped with odsplat; the fast ACC_DATA codec refuses a DBC whose layout it does not match."""
    text = resources.files("odsplat.acquisition").joinpath(DBC_RESOURCE).read_text(encoding="ascii")
    db = cantools.database.load_string(text, database_format="dbc")
    _check_fast_layout(db)
    return db


def _check_fast_layout(db: cantools.database.can.Database) -> None:
    # The hot path packs/unpacks "<Hhhh" instead of calling cantools per frame (~20x faster).
    want = {"Counter": (0, False, 1.0), "AccX": (16, True, 1 / FULL_SCALE_COUNTS),
            "AccY": (32, True, 1 / FULL_SCALE_COUNTS), "AccZ": (48, True, 1 / FULL_SCALE_COUNTS)}
    for node_id in NODE_IDS:
        msg = db.get_message_by_frame_id(ACC_DATA_BASE + node_id)
        got = {s.name: (s.start, s.is_signed, float(s.scale)) for s in msg.signals
               if s.length == 16 and s.byte_order == "little_endian" and s.offset == 0}
        ok = msg.length == 8 and got.keys() == want.keys() and all(
            got[k][:2] == v[:2] and abs(got[k][2] - v[2]) <= 1e-12 * v[2] for k, v in want.items())
        if not ok:
            raise SchemaError(DBC_RESOURCE, f"{msg.name} is not Counter u16, AccX/Y/Z int16 little-endian")


def _code(table: Mapping[int, float], value: float, what: str) -> int:
    for code, v in table.items():
        if abs(value - v) <= _CODE_TOLERANCE * v:
            return code
    raise InputError(what, f"{value:g} is not one of {sorted(round(v, 4) for v in table.values())}")


def rate_code(sample_rate_hz: float) -> int:
    return _code(SAMPLE_RATES_HZ, sample_rate_hz, "sample_rate_hz")


def range_code(range_m_s2: float) -> int:
    return _code(RANGES_M_S2, range_m_s2, "range_m_s2")


def check_node_id(node_id: int) -> int:
    if node_id not in NODE_IDS:
        raise InputError("node_id", f"{node_id} is outside {NODE_IDS.start}..{NODE_IDS.stop - 1}")
    return node_id


def bus_load(n_nodes: int, sample_rate_hz: float, bitrate: int = 1_000_000) -> float:
    """Worst-case fraction of the bus taken by the data frames; keep it under ~0.7 or frames queue up and drop."""
    return n_nodes * sample_rate_hz * FRAME_BITS_WORST / bitrate


def to_counts(acc_m_s2: np.ndarray, range_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """m/s^2 -> int16 counts saturated at +-FULL_SCALE_COUNTS, and the mask of saturated values."""
    raw = np.rint(np.asarray(acc_m_s2, dtype=np.float64) * (FULL_SCALE_COUNTS / range_m_s2))
    return np.clip(raw, -FULL_SCALE_COUNTS, FULL_SCALE_COUNTS).astype(np.int16), np.abs(raw) > FULL_SCALE_COUNTS


def from_counts(counts: np.ndarray, range_m_s2: float) -> np.ndarray:
    return np.asarray(counts, dtype=np.float64) * (range_m_s2 / FULL_SCALE_COUNTS)


def acc_data_frames(node_id: int, first_sample: int, counts: np.ndarray) -> list[can.Message]:
    """ACC_DATA frames of consecutive samples first_sample.. of one node; counts is (n, 3) int16."""
    arb = ACC_DATA_BASE + node_id
    return [can.Message(arbitration_id=arb, is_extended_id=False,
                        data=_ACC.pack((first_sample + i) & 0xFFFF, *row))
            for i, row in enumerate(np.asarray(counts).tolist())]


def decode_acc_data(msg: can.Message) -> tuple[int, int, tuple[int, int, int]]:
    """(node_id, 16-bit counter, (x, y, z) counts) of one ACC_DATA frame."""
    counter, x, y, z = _ACC.unpack(bytes(msg.data))
    return msg.arbitration_id - ACC_DATA_BASE, counter, (x, y, z)


def error_frame() -> can.Message:
    return can.Message(is_error_frame=True, arbitration_id=0x8, is_extended_id=False, data=_ERROR_FRAME_DATA)


def command_frame(node_id: int, command: Command, rate: int = 0, range_: int = 0) -> can.Message:
    """NODE_CMD to node_id (BROADCAST for all); rate and range_ are codes, used by START."""
    frame_id = NODE_CMD_BASE + (node_id if node_id == BROADCAST else check_node_id(node_id))
    data = load_dbc().encode_message(frame_id, {"Command": int(command), "RateCode": rate, "RangeCode": range_})
    return can.Message(arbitration_id=frame_id, is_extended_id=False, data=data)


def decode_command(msg: can.Message) -> tuple[int, int, int, int]:
    """(target node id or BROADCAST, command, rate code, range code) as raw numbers; the node validates them."""
    sig = load_dbc().decode_message(msg.arbitration_id, bytes(msg.data), decode_choices=False)
    return msg.arbitration_id - NODE_CMD_BASE, int(sig["Command"]), int(sig["RateCode"]), int(sig["RangeCode"])


def status_frame(status: NodeStatus) -> can.Message:
    frame_id = NODE_STATUS_BASE + check_node_id(status.node_id)
    data = load_dbc().encode_message(frame_id, {
        "State": int(status.state), "RateCode": rate_code(status.sample_rate_hz),
        "RangeCode": range_code(status.range_m_s2), "Overrun": int(status.overrun),
        "Clipping": int(status.clipping), "Ack": int(status.ack), "FwMajor": status.firmware[0],
        "FwMinor": status.firmware[1], "Counter": status.counter & 0xFFFF})
    return can.Message(arbitration_id=frame_id, is_extended_id=False, data=data)


def decode_status(msg: can.Message) -> NodeStatus:
    sig = load_dbc().decode_message(msg.arbitration_id, bytes(msg.data), decode_choices=False)
    return NodeStatus(
        node_id=msg.arbitration_id - NODE_STATUS_BASE, state=NodeState(sig["State"]),
        sample_rate_hz=SAMPLE_RATES_HZ.get(sig["RateCode"]), range_m_s2=RANGES_M_S2.get(sig["RangeCode"]),
        overrun=bool(sig["Overrun"]), clipping=bool(sig["Clipping"]), ack=bool(sig["Ack"]),
        firmware=(int(sig["FwMajor"]), int(sig["FwMinor"])), counter=int(sig["Counter"]))


def open_bus(interface: str | None = None, channel: Any = None, *, config: Mapping[str, Any] | None = None,
             **kwargs: Any) -> can.BusABC:
    """can.Bus from a config dict and keywords; what neither names comes from python-can's own
    configuration (CAN_INTERFACE / CAN_CHANNEL / CAN_BITRATE, ~/.canrc), so one variable switches to `virtual`."""
    cfg = {**(config or {}), **kwargs}
    if interface is not None:
        cfg["interface"] = interface
    if channel is not None:
        cfg["channel"] = channel
    try:
        return can.Bus(**cfg)
    except (can.CanError, ValueError, ImportError, OSError) as exc:
        where = f"CAN bus {cfg.get('interface', '$CAN_INTERFACE')}:{cfg.get('channel', '$CAN_CHANNEL')}"
        raise InputError(where, f"cannot open: {exc}") from exc


@dataclass
class _Stream:
    node_id: int
    sample_rate_hz: float
    range_m_s2: float
    last_rx_s: float
    confirmed: bool = False  # its START reply arrived; data frames before it are stale
    stopped: bool = False
    timed_out: bool = False
    next_sample: int = 0
    run_first: int = 0
    run: bytearray = field(default_factory=bytearray)


class AccelNodeReader:
    """Starts accelerometer nodes on an open bus and reads their samples, counting gaps, error frames and
    silent nodes. Not thread-safe: one acquisition thread owns it. It never opens or closes the bus."""

    def __init__(self, bus: can.BusABC, *, node_timeout_s: float = 0.5):
        self._bus = bus
        self.node_timeout_s = node_timeout_s
        self._streams: dict[int, _Stream] = {}
        self._blocks: list[AccelBlock] = []
        self.status: dict[int, NodeStatus] = {}  # latest NODE_STATUS per node
        self.gaps: list[Gap] = []
        self.timeouts: list[NodeTimeout] = []
        self.error_frames = 0  # bus-wide: an error frame names no node; its lost sample shows as a Gap
        self.duplicates = 0  # CAN may deliver a frame twice (error in the last EOF bit); dropped
        self.malformed = 0
        load_dbc()  # fail here, not on the first status frame

    def lost_samples(self, node_id: int) -> int:
        return sum(g.n_lost for g in self.gaps if g.node_id == node_id)

    def start(self, node_ids: Iterable[int], sample_rate_hz: float = 1000.0,
              range_m_s2: float = RANGES_M_S2[3], *, confirm_timeout_s: float = 1.0) -> None:
        """START each node and wait for its RUNNING reply; raises InputError naming a node that refuses or is silent."""
        ids = [check_node_id(n) for n in node_ids]
        rate, range_ = rate_code(sample_rate_hz), range_code(range_m_s2)
        self._pump()
        now = time.monotonic()
        for n in ids:
            if n in self._streams:  # a restart: keep what the old run received
                self._close_run(self._streams[n])
            self.status.pop(n, None)  # an old FAULT reply must not fail this START
            self._streams[n] = _Stream(n, SAMPLE_RATES_HZ[rate], RANGES_M_S2[range_], last_rx_s=now)
            self._bus.send(command_frame(n, Command.START, rate, range_))
        deadline = now + confirm_timeout_s
        while (waiting := [n for n in ids if not self._streams[n].confirmed]):
            refused = [n for n in waiting if n in self.status and self.status[n].ack
                       and self.status[n].state is NodeState.FAULT]
            if refused:
                raise InputError(f"CAN node {refused[0]}", "refused START (state FAULT)")
            left = deadline - time.monotonic()
            if left <= 0:
                raise InputError(f"CAN node {waiting[0]}", f"no RUNNING reply to START within {confirm_timeout_s:g} s")
            msg = self._bus.recv(timeout=left)
            if msg is not None:
                self._handle(msg, time.monotonic())

    def stop(self) -> None:
        """STOP every started node; frames already on the bus still come out of read()."""
        for s in self._streams.values():
            s.stopped = True
            self._bus.send(command_frame(s.node_id, Command.STOP))

    def read(self, timeout_s: float = 0.1, max_frames: int = 50_000) -> list[AccelBlock]:
        """Wait up to timeout_s for a frame, then take what is queued (at most max_frames);
        returns the contiguous runs received, and updates gaps, error_frames and timeouts."""
        msg = self._bus.recv(timeout=timeout_s)
        n = 0
        while msg is not None:
            self._handle(msg, time.monotonic())
            n += 1
            if n >= max_frames:
                break
            msg = self._bus.recv(timeout=0.0)
        self._check_timeouts(time.monotonic())
        for s in self._streams.values():
            self._close_run(s)
        blocks, self._blocks = self._blocks, []
        return blocks

    def _pump(self, limit: int = 100_000) -> None:
        # Frames queued before a START belong to the old streams (or none): handle them before replacing any.
        for _ in range(limit):
            if (msg := self._bus.recv(timeout=0.0)) is None:
                return
            self._handle(msg, time.monotonic())

    def _handle(self, msg: can.Message, now: float) -> None:
        if msg.is_error_frame:
            self.error_frames += 1
            return
        if msg.is_remote_frame or msg.is_extended_id:
            return
        arb = msg.arbitration_id
        if arb - ACC_DATA_BASE in self._streams:
            self._on_data(self._streams[arb - ACC_DATA_BASE], msg.data, now)
        elif arb - NODE_STATUS_BASE in NODE_IDS:
            self._on_status(msg, now)

    def _on_data(self, s: _Stream, data: bytearray, now: float) -> None:
        if not s.confirmed:
            return
        if len(data) != 8:
            self.malformed += 1
            return
        delta = ((data[0] | data[1] << 8) - s.next_sample) & 0xFFFF
        if s.timed_out:
            # After a silence whole wraps may have passed unseen; only their number comes from host time.
            delta += max(0, round(((now - s.last_rx_s) * s.sample_rate_hz - delta) / _COUNTER_MOD)) * _COUNTER_MOD
            s.timed_out = False
            log.info("CAN node %d is back after %.2f s", s.node_id, now - s.last_rx_s)
        elif delta == 0xFFFF:
            self.duplicates += 1
            return
        if delta:
            self._close_run(s)
            self.gaps.append(Gap(s.node_id, s.next_sample, delta))
            s.next_sample += delta
        if not s.run:
            s.run_first = s.next_sample
        s.run += data
        s.next_sample += 1
        s.last_rx_s = now

    def _on_status(self, msg: can.Message, now: float) -> None:
        try:
            st = decode_status(msg)
        except (ValueError, KeyError, cantools.database.DecodeError):
            self.malformed += 1
            return
        old = self.status.get(st.node_id)
        self.status[st.node_id] = st
        for flag in ("overrun", "clipping"):
            if getattr(st, flag) and not (old and getattr(old, flag)):
                log.warning("CAN node %d reports %s", st.node_id, flag)
        s = self._streams.get(st.node_id)
        # The reply to our START is the only status that is RUNNING, an ack, and before sample 0.
        if s and not s.confirmed and st.ack and st.state is NodeState.RUNNING and st.counter == 0:
            if (st.sample_rate_hz, st.range_m_s2) != (s.sample_rate_hz, s.range_m_s2):
                log.warning("CAN node %d runs at %s Hz, %s m/s^2, not as commanded",
                            st.node_id, st.sample_rate_hz, st.range_m_s2)
                s.sample_rate_hz, s.range_m_s2 = st.sample_rate_hz, st.range_m_s2
            s.confirmed, s.last_rx_s = True, now

    def _check_timeouts(self, now: float) -> None:
        for s in self._streams.values():
            if s.confirmed and not s.stopped and not s.timed_out and now - s.last_rx_s > self.node_timeout_s:
                s.timed_out = True
                self.timeouts.append(NodeTimeout(s.node_id, s.next_sample, now - s.last_rx_s))
                log.warning("CAN node %d silent for %.2f s after sample %d", s.node_id, now - s.last_rx_s,
                            s.next_sample - 1)

    def _close_run(self, s: _Stream) -> None:
        if s.run:
            counts = np.frombuffer(bytes(s.run), dtype=_ACC_DTYPE)["acc"]
            self._blocks.append(AccelBlock(s.node_id, s.run_first, s.sample_rate_hz, s.range_m_s2,
                                           from_counts(counts, s.range_m_s2)))
            s.run = bytearray()
