"""The DAQ wire protocol (docs/daq-protocol.md): COBS framing, CRC-checked packets, typed messages,
and the receive side's loss accounting. Shared by the simulated device and the real driver."""
from __future__ import annotations

import enum
import logging
import struct
import zlib
from dataclasses import dataclass, field
from typing import ClassVar, Mapping, Union

import numpy as np

from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
MAX_PACKET_BYTES = 8192  # version through CRC; a longer frame is line garbage
FULL_SCALE_COUNTS = 32767  # volts = counts / 32767 * range_v; -32768 is never sent
_HEADER = struct.Struct("<BBH")  # version, type, seq
_CRC = struct.Struct("<I")
_MIN_PACKET = _HEADER.size + _CRC.size
# COBS adds one byte per 254 plus one; the receiver gives up on a frame longer than this.
MAX_FRAME_BYTES = MAX_PACKET_BYTES + MAX_PACKET_BYTES // 254 + 1
_DATA_HEAD = struct.Struct("<QH")  # first_sample, n_samples


class DAQProtocolError(InputError):
    """The device (or host) broke the protocol: a NAK, a bad reply, a counter that went backwards."""

    reason: NakReason | None = None  # set by parse_packet: the NAK a device answers with


class MsgType(enum.IntEnum):
    # host -> device
    HELLO = 0x01
    CONFIGURE = 0x02
    START = 0x03
    STOP = 0x04
    # device -> host (high bit set, so a capture shows the direction)
    INFO = 0x81
    CONFIG_ACK = 0x82
    ACK = 0x83
    NAK = 0x84
    DATA = 0x85
    STATUS = 0x86


class NakReason(enum.IntEnum):
    UNSUPPORTED_VERSION = 1
    UNKNOWN_TYPE = 2
    MALFORMED = 3
    BUSY = 4  # not allowed while acquiring
    NOT_CONFIGURED = 5  # START before a successful CONFIGURE
    BAD_RATE = 6
    BAD_CHANNEL = 7
    BAD_RANGE = 8


class StatusFlag(enum.IntFlag):
    OVERRUN = 0x01  # the device discarded samples it could not send; they show as a sample gap
    CLIPPED = 0x02  # some sample saturated at +-32767 counts since START
    RUNNING = 0x04  # acquiring; clear in the STATUS that follows STOP


# ---------------------------------------------------------------------------------------- COBS

def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result holds no 0x00 (the frame delimiter is not added)."""
    out = bytearray()
    chunks = bytes(data).split(b"\x00")
    last = len(chunks) - 1
    for i, chunk in enumerate(chunks):
        pos = 0
        while len(chunk) - pos >= 254:
            out.append(0xFF)
            out += chunk[pos:pos + 254]
            pos += 254
        # A final run of exactly k*254 bytes needs no closing code byte (canonical COBS).
        if pos < len(chunk) or i < last or pos == 0:
            out.append(len(chunk) - pos + 1)
            out += chunk[pos:]
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of `cobs_encode`; raises ValueError on a zero byte or a code that runs past the end."""
    out = bytearray()
    n = len(data)
    i = 0
    while i < n:
        code = data[i]
        end = i + code
        if code == 0 or end > n:
            raise ValueError(f"bad COBS code {code} at byte {i} of {n}")
        block = data[i + 1:end]
        if 0 in block:
            raise ValueError(f"zero byte inside COBS block at byte {i}")
        out += block
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


# ------------------------------------------------------------------------------ body encoding

class BodyReader:
    """Cursor over a packet body; every read checks the length so a short body is MALFORMED, not a crash."""

    def __init__(self, body: bytes):
        self._body = body
        self._pos = 0

    def take(self, fmt: str):
        s = struct.Struct("<" + fmt)
        if self._pos + s.size > len(self._body):
            raise ValueError(f"body ends at byte {len(self._body)}, needed {self._pos + s.size}")
        values = s.unpack_from(self._body, self._pos)
        self._pos += s.size
        return values[0] if len(values) == 1 else values

    def raw(self, n: int) -> bytes:
        if self._pos + n > len(self._body):
            raise ValueError(f"body ends at byte {len(self._body)}, needed {self._pos + n}")
        out = self._body[self._pos:self._pos + n]
        self._pos += n
        return out

    def text(self) -> str:
        return self.raw(self.take("B")).decode("ascii")

    def rest(self) -> bytes:
        return self.raw(len(self._body) - self._pos)

    def end(self) -> None:
        if self._pos != len(self._body):
            raise ValueError(f"{len(self._body) - self._pos} unexpected bytes after the body")


def encode_text(value: str, what: str) -> bytes:
    try:
        raw = value.encode("ascii")
    except UnicodeEncodeError:
        raise InputError(what, f"{value!r} must be ASCII") from None
    if len(raw) > 255:
        raise InputError(what, f"{value!r} is longer than 255 bytes")
    return bytes([len(raw)]) + raw


def wire_f32(x: float) -> float:
    """The value a float survives as on the wire; echoes are compared after this rounding."""
    return float(np.float32(x))


# ---------------------------------------------------------------------------------- messages

@dataclass(frozen=True)
class ChannelConfig:
    """One acquired channel: device input `index`, ADC full scale +-`range_v`, a name for the host."""

    index: int
    range_v: float
    name: str

    def _encode(self) -> bytes:
        return struct.pack("<Bf", self.index, self.range_v) + encode_text(self.name, "channel name")

    @classmethod
    def _decode(cls, r: BodyReader) -> ChannelConfig:
        index, range_v = r.take("Bf")
        return cls(index, range_v, r.text())

    def same_as(self, other: ChannelConfig) -> bool:
        return (self.index, wire_f32(self.range_v), self.name) == (other.index, wire_f32(other.range_v), other.name)


def _encode_channels(channels: tuple[ChannelConfig, ...]) -> bytes:
    if len(channels) > 255:
        raise InputError("CONFIGURE", f"{len(channels)} channels; at most 255")
    return bytes([len(channels)]) + b"".join(c._encode() for c in channels)


def _decode_channels(r: BodyReader) -> tuple[ChannelConfig, ...]:
    return tuple(ChannelConfig._decode(r) for _ in range(r.take("B")))


class EmptyBody:
    def _body(self) -> bytes:
        return b""

    @classmethod
    def _parse(cls, r: BodyReader):
        return cls()


@dataclass(frozen=True)
class Hello(EmptyBody):
    """Host asks who is there; the device answers INFO."""

    TYPE: ClassVar[MsgType] = MsgType.HELLO


@dataclass(frozen=True)
class Configure:
    """Host asks for a sample rate and a channel list; the device answers CONFIG_ACK or NAK."""

    TYPE: ClassVar[MsgType] = MsgType.CONFIGURE
    sample_rate_hz: int
    channels: tuple[ChannelConfig, ...]

    def _body(self) -> bytes:
        if self.sample_rate_hz != int(self.sample_rate_hz) or not 0 < self.sample_rate_hz < 2**32:
            raise InputError("CONFIGURE", f"sample rate {self.sample_rate_hz!r} Hz must be a whole number (u32)")
        return struct.pack("<I", int(self.sample_rate_hz)) + _encode_channels(tuple(self.channels))

    @classmethod
    def _parse(cls, r: BodyReader) -> Configure:
        return cls(r.take("I"), _decode_channels(r))


@dataclass(frozen=True)
class Start(EmptyBody):
    """Start acquiring; the sample counter restarts at 0. Answered ACK or NAK, then DATA flows."""

    TYPE: ClassVar[MsgType] = MsgType.START


@dataclass(frozen=True)
class Stop(EmptyBody):
    """Stop acquiring (idempotent); answered ACK, then a final STATUS with RUNNING clear."""

    TYPE: ClassVar[MsgType] = MsgType.STOP


@dataclass(frozen=True)
class Info:
    """Who the device is and what it can do."""

    TYPE: ClassVar[MsgType] = MsgType.INFO
    ref_seq: int  # seq of the HELLO answered
    device_id: str
    firmware: str
    n_inputs: int
    max_rate_hz: float
    ranges_v: tuple[float, ...]  # supported full-scale ranges, +-V

    def _body(self) -> bytes:
        return (struct.pack("<H", self.ref_seq) + encode_text(self.device_id, "device id")
                + encode_text(self.firmware, "firmware")
                + struct.pack("<BdB", self.n_inputs, self.max_rate_hz, len(self.ranges_v))
                + struct.pack(f"<{len(self.ranges_v)}f", *self.ranges_v))

    @classmethod
    def _parse(cls, r: BodyReader) -> Info:
        ref_seq, device_id, firmware = r.take("H"), r.text(), r.text()
        n_inputs, max_rate, n_ranges = r.take("BdB")
        ranges = struct.unpack(f"<{n_ranges}f", r.raw(4 * n_ranges))
        return cls(ref_seq, device_id, firmware, n_inputs, max_rate, tuple(ranges))


@dataclass(frozen=True)
class ConfigAck:
    """What the device will actually do: its true rate (may differ from the request) and the channel echo."""

    TYPE: ClassVar[MsgType] = MsgType.CONFIG_ACK
    ref_seq: int
    sample_rate_hz: float
    channels: tuple[ChannelConfig, ...]

    def _body(self) -> bytes:
        return struct.pack("<Hd", self.ref_seq, self.sample_rate_hz) + _encode_channels(tuple(self.channels))

    @classmethod
    def _parse(cls, r: BodyReader) -> ConfigAck:
        ref_seq, rate = r.take("Hd")
        return cls(ref_seq, rate, _decode_channels(r))


@dataclass(frozen=True)
class Ack:
    """A START or STOP was done."""

    TYPE: ClassVar[MsgType] = MsgType.ACK
    ref_seq: int
    ref_type: int

    def _body(self) -> bytes:
        return struct.pack("<HB", self.ref_seq, self.ref_type)

    @classmethod
    def _parse(cls, r: BodyReader) -> Ack:
        return cls(*r.take("HB"))


@dataclass(frozen=True)
class Nak:
    """A host packet was refused, with a reason code and a line of text for the user."""

    TYPE: ClassVar[MsgType] = MsgType.NAK
    ref_seq: int
    ref_type: int
    reason: int
    text: str = ""

    def _body(self) -> bytes:
        return struct.pack("<HBB", self.ref_seq, self.ref_type, self.reason) + encode_text(self.text[:255], "NAK text")

    @classmethod
    def _parse(cls, r: BodyReader) -> Nak:
        ref_seq, ref_type, reason = r.take("HBB")
        return cls(ref_seq, ref_type, reason, r.text())

    def error(self, device: str) -> DAQProtocolError:
        """The exception a host raises for this refusal."""
        reason = NakReason(self.reason).name if self.reason in NakReason._value2member_map_ else str(self.reason)
        what = MsgType(self.ref_type).name if self.ref_type in MsgType._value2member_map_ else hex(self.ref_type)
        return DAQProtocolError(device, f"refused {what}: {reason}" + (f" ({self.text})" if self.text else ""))


@dataclass(frozen=True, eq=False)
class Data:
    """A block of samples: `counts[c, k]` is channel c (configuration order) at device sample first_sample + k."""

    TYPE: ClassVar[MsgType] = MsgType.DATA
    first_sample: int
    counts: np.ndarray  # int16, shape (n_channels, n_samples)

    @property
    def n_samples(self) -> int:
        return self.counts.shape[1]

    def _body(self) -> bytes:
        counts = np.asarray(self.counts)
        if counts.ndim != 2 or not 1 <= counts.shape[1] <= 0xFFFF:
            raise InputError("DATA", f"counts must be (n_channels, 1..65535 samples); got shape {counts.shape}")
        # Wire order is sample-major: every channel of sample k, then sample k+1.
        return _DATA_HEAD.pack(self.first_sample, counts.shape[1]) + counts.T.astype("<i2").tobytes()

    @classmethod
    def _parse(cls, r: BodyReader) -> Data:
        first, n = r.take("QH")
        raw = r.rest()
        if n == 0 or len(raw) % (2 * n) or not raw:
            raise ValueError(f"{len(raw)} sample bytes do not hold {n} samples of whole channels")
        counts = np.frombuffer(raw, dtype="<i2").reshape(n, -1).T
        return cls(first, counts)


@dataclass(frozen=True)
class Status:
    """Sticky flags since START and the device's sample counter (samples acquired, sent or not)."""

    TYPE: ClassVar[MsgType] = MsgType.STATUS
    flags: StatusFlag
    clipped_channels: int  # bit c set: channel c (configuration order) clipped since START
    sample_counter: int

    def _body(self) -> bytes:
        return struct.pack("<BIQ", int(self.flags), self.clipped_channels, self.sample_counter)

    @classmethod
    def _parse(cls, r: BodyReader) -> Status:
        flags, mask, counter = r.take("BIQ")
        return cls(StatusFlag(flags), mask, counter)


Message = Union[Hello, Configure, Start, Stop, Info, ConfigAck, Ack, Nak, Data, Status]
_MESSAGES: dict[int, type] = {m.TYPE: m for m in (Hello, Configure, Start, Stop, Info, ConfigAck, Ack, Nak, Data,
                                                   Status)}


# ----------------------------------------------------------------------------------- packets

@dataclass(frozen=True)
class RawPacket:
    """A packet whose CRC passed, body not yet parsed (a device NAKs what it cannot parse)."""

    version: int
    type: int
    seq: int
    body: bytes


@dataclass(frozen=True)
class Packet:
    """A parsed packet: its sender's sequence number and the message."""

    seq: int
    message: Message


def encode_packet(message: Message, seq: int) -> bytes:
    """version | type | seq | body | CRC32, all little-endian; no framing."""
    head = _HEADER.pack(PROTOCOL_VERSION, message.TYPE, seq & 0xFFFF) + message._body()
    if len(head) + _CRC.size > MAX_PACKET_BYTES:
        raise InputError(message.TYPE.name, f"packet of {len(head) + _CRC.size} bytes exceeds {MAX_PACKET_BYTES}")
    return head + _CRC.pack(zlib.crc32(head))


def frame(packet: bytes) -> bytes:
    """COBS-encode a packet and append the 0x00 delimiter."""
    return cobs_encode(packet) + b"\x00"


def encode_frame(message: Message, seq: int) -> bytes:
    return frame(encode_packet(message, seq))


def check_packet(packet: bytes) -> RawPacket:
    """Verify length and CRC of an unframed packet; raises ValueError saying which check failed."""
    if len(packet) < _MIN_PACKET:
        raise ValueError(f"{len(packet)}-byte packet is shorter than {_MIN_PACKET}")
    if zlib.crc32(packet[:-4]) != _CRC.unpack_from(packet, len(packet) - 4)[0]:
        raise ValueError("CRC mismatch")
    version, type_, seq = _HEADER.unpack_from(packet)
    return RawPacket(version, type_, seq, bytes(packet[_HEADER.size:-4]))


def parse_packet(raw: RawPacket, messages: Mapping[int, type] | None = None,
                 error: type[DAQProtocolError] | None = None) -> Packet:
    """Parse a CRC-checked packet's body; raises DAQProtocolError (or `error`) with the NakReason as `reason`.

    `messages` maps type codes to message classes: the DAQ's by default. Another protocol framed the same
    way (the automatic hammer's, odsplat.acquisition.hammerproto) passes its own, and its error class."""
    def fail(reason: NakReason, problem: str) -> DAQProtocolError:
        err = (error or DAQProtocolError)(f"packet seq {raw.seq}", problem)
        err.reason = reason
        return err

    if raw.version != PROTOCOL_VERSION:
        raise fail(NakReason.UNSUPPORTED_VERSION, f"protocol version {raw.version}, expected {PROTOCOL_VERSION}")
    cls = (_MESSAGES if messages is None else messages).get(raw.type)
    if cls is None:
        raise fail(NakReason.UNKNOWN_TYPE, f"unknown message type 0x{raw.type:02x}")
    try:
        r = BodyReader(raw.body)
        message = cls._parse(r)
        r.end()
    except (ValueError, struct.error, UnicodeDecodeError) as e:
        raise fail(NakReason.MALFORMED, f"malformed {cls.TYPE.name}: {e}") from None
    return Packet(raw.seq, message)


@dataclass
class DecoderStats:
    frames: int = 0  # non-empty frames seen
    packets: int = 0  # packets that passed CRC
    crc_errors: int = 0  # frames that decoded but failed CRC: bit errors on the line
    cobs_errors: int = 0  # frames that are not valid COBS or too short to be a packet
    oversize: int = 0  # runs of bytes longer than any frame, discarded up to the next delimiter
    malformed: int = 0  # CRC passed but the packet could not be parsed (version, type, body)


class FrameDecoder:
    """Splits a byte stream into packets. Garbage, partial frames and corrupted frames are counted and skipped,
    so one bad frame costs one packet and the next delimiter resynchronises."""

    def __init__(self, device: str = "daq", messages: Mapping[int, type] | None = None,
                 error: type[DAQProtocolError] | None = None):
        self.device = device
        self._messages = messages  # see parse_packet
        self._error = error or DAQProtocolError
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._skipping = False  # inside an oversize run: drop bytes until the next delimiter

    def feed_raw(self, data: bytes) -> list[RawPacket]:
        """Packets whose CRC passed, unparsed."""
        self._buf += data
        out: list[RawPacket] = []
        start = 0
        while True:
            end = self._buf.find(0, start)
            if end < 0:
                break
            chunk = bytes(self._buf[start:end])
            start = end + 1
            if self._skipping:
                self._skipping = False
                continue
            if chunk:
                packet = self._decode(chunk)
                if packet is not None:
                    out.append(packet)
        del self._buf[:start]
        if len(self._buf) > MAX_FRAME_BYTES:
            self.stats.oversize += 1
            log.warning("%s: %d bytes without a frame delimiter discarded", self.device, len(self._buf))
            self._buf.clear()
            self._skipping = True
        return out

    def feed(self, data: bytes) -> list[Packet]:
        """Parsed packets; packets that pass CRC but cannot be parsed are counted as malformed and logged."""
        out = []
        for raw in self.feed_raw(data):
            try:
                out.append(parse_packet(raw, self._messages, self._error))
            except DAQProtocolError as e:
                self.stats.malformed += 1
                log.warning("%s: %s", self.device, e)
        return out

    def _decode(self, chunk: bytes) -> RawPacket | None:
        self.stats.frames += 1
        if len(chunk) > MAX_FRAME_BYTES:
            self.stats.oversize += 1
            return None
        try:
            packet = cobs_decode(chunk)
        except ValueError as e:
            self.stats.cobs_errors += 1
            log.debug("%s: COBS error: %s", self.device, e)
            return None
        if len(packet) < _MIN_PACKET:
            self.stats.cobs_errors += 1
            return None
        try:
            raw = check_packet(packet)
        except ValueError:
            self.stats.crc_errors += 1
            log.debug("%s: CRC error in a %d-byte frame", self.device, len(chunk))
            return None
        self.stats.packets += 1
        return raw


# ------------------------------------------------------------------------------ host helpers

def counts_to_volts(counts: np.ndarray, ranges_v) -> np.ndarray:
    """(n_channels, n) counts -> volts at the ADC input, float64."""
    scale = np.asarray(ranges_v, dtype=np.float64).reshape(-1, 1) / FULL_SCALE_COUNTS
    return np.asarray(counts, dtype=np.float64) * scale


def verify_config(requested: Configure, ack: ConfigAck, *, device: str) -> None:
    """A CONFIG_ACK must echo the requested channels exactly; its rate may differ (use `ack.sample_rate_hz`)."""
    problems = []
    if len(requested.channels) != len(ack.channels):
        problems.append(f"asked for {len(requested.channels)} channels, device runs {len(ack.channels)}")
    for want, got in zip(requested.channels, ack.channels):
        if not want.same_as(got):
            problems.append(f"asked for {want}, device runs {got}")
    if not ack.sample_rate_hz > 0:
        problems.append(f"device reports sample rate {ack.sample_rate_hz}")
    if problems:
        raise DAQProtocolError(device, "configuration mismatch: " + "; ".join(problems))


# ------------------------------------------------------------------------- stream accounting

@dataclass(frozen=True, eq=False)
class SampleBlock:
    """Samples first_sample .. first_sample + n_samples - 1, contiguous, in counts (n_channels, n)."""

    first_sample: int
    counts: np.ndarray

    @property
    def n_samples(self) -> int:
        return self.counts.shape[1]

    @property
    def stop(self) -> int:
        return self.first_sample + self.n_samples


@dataclass(frozen=True)
class SampleGap:
    """Samples first_sample .. stop - 1 never arrived. `lost_packets`: packets missing from the sequence since
    the last DATA; > 0: lost on the link (dropped or corrupted), 0: the device itself skipped them (overrun)."""

    first_sample: int
    n_samples: int
    lost_packets: int

    @property
    def stop(self) -> int:
        return self.first_sample + self.n_samples


@dataclass
class StreamStats:
    packets: int = 0  # device packets seen
    data_packets: int = 0
    lost_packets: int = 0  # from sequence gaps, any type
    samples: int = 0  # received
    lost_samples: int = 0  # in reported gaps
    gaps: list[SampleGap] = field(default_factory=list)


class DataStreamChecker:
    """Follows the device's packet sequence and sample counter from START on. Feed it every device packet in
    order; it returns DATA as `SampleBlock`s and each hole as a `SampleGap` with its exact sample range. Nothing
    is ever filled in."""

    def __init__(self, n_channels: int, *, device: str = "daq", next_seq: int | None = None):
        self.n_channels = n_channels
        self.device = device
        self.stats = StreamStats()
        self.next_sample = 0  # the device counts samples from 0 at START
        self._next_seq = next_seq  # None: taken from the first packet
        self._lost_since_data = 0  # packets missing since the last DATA: they explain the next sample gap

    def feed(self, packet: Packet) -> list[SampleBlock | SampleGap]:
        missing = 0 if self._next_seq is None else (packet.seq - self._next_seq) & 0xFFFF
        self._next_seq = (packet.seq + 1) & 0xFFFF
        self.stats.packets += 1
        # A gap of >= 65536 packets aliases; the sample counter below still gives the exact sample loss.
        self.stats.lost_packets += missing
        self._lost_since_data += missing
        msg = packet.message
        if not isinstance(msg, Data):
            return []
        if msg.counts.shape[0] != self.n_channels:
            raise DAQProtocolError(self.device,
                                   f"DATA with {msg.counts.shape[0]} channels, configured {self.n_channels}")
        if msg.first_sample < self.next_sample:
            raise DAQProtocolError(
                self.device,
                f"sample counter went back: DATA starts at {msg.first_sample}, expected {self.next_sample}")
        events: list[SampleBlock | SampleGap] = []
        if msg.first_sample > self.next_sample:
            events.append(self._gap(msg.first_sample))
        elif self._lost_since_data:
            log.warning("%s: %d packet(s) without samples lost before seq %d", self.device, self._lost_since_data,
                        packet.seq)
        self._lost_since_data = 0
        block = SampleBlock(msg.first_sample, msg.counts)
        self.stats.data_packets += 1
        self.stats.samples += block.n_samples
        self.next_sample = block.stop
        events.append(block)
        return events

    def finish(self, sample_counter: int) -> list[SampleGap]:
        """Close the stream with the counter from the final STATUS: samples after the last DATA are a gap too."""
        if sample_counter < self.next_sample:
            raise DAQProtocolError(self.device,
                                   f"final sample counter {sample_counter} < samples received {self.next_sample}")
        return [self._gap(sample_counter)] if sample_counter > self.next_sample else []

    def _gap(self, stop: int) -> SampleGap:
        gap = SampleGap(self.next_sample, stop - self.next_sample, self._lost_since_data)
        self._lost_since_data = 0
        self.stats.lost_samples += gap.n_samples
        self.stats.gaps.append(gap)
        self.next_sample = stop
        log.warning("%s: samples %d..%d lost (%d packets missing)", self.device, gap.first_sample, gap.stop - 1,
                    gap.lost_packets)
        return gap
