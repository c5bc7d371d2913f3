"""A simulated DAQ that speaks odsplat.acquisition.daqproto on a PTY, with injectable faults (loss, bit errors, drift,
clipping, disconnect), and the `simdaq://` URL registry."""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence, Union
from urllib.parse import urlsplit

import numpy as np
import serial

from odsplat.acquisition import daqproto as dp
from odsplat.spine.errors import InputError

from .pty import PtyDevice, parse_bool, split_url_options

log = logging.getLogger(__name__)

FIRMWARE = "sim-1.0"
CLOCK_HZ = 13_107_200.0  # rates are CLOCK_HZ / k, as on sigma-delta DAQs: 51200, 25600, 10240 ... are exact
_LOW_WATER_BYTES = 32 * 1024  # non-realtime: generate only when this little is queued (the PTY gives backpressure)
_OVERRUN_S = 0.5  # realtime: a block due while this much is still queued is discarded (OVERRUN)
_DISCONNECT_FLUSH_S = 1.0


class SampleSource(Protocol):
    """Ground truth for the device's inputs: input i carries channel_names[i]."""

    channel_names: tuple[str, ...]

    def volts(self, start_sample: int, n: int, sample_rate_hz: float) -> np.ndarray:
        """(n_channels, n) float64 volts at the ADC input for samples start_sample .. start_sample + n - 1."""


@dataclass(frozen=True)
class SineSource:
    """Known sines: channel k is amplitudes_v[k] * sin(2 pi freqs_hz[k] t + phases_rad[k]), t = sample / rate."""

    amplitudes_v: tuple[float, ...]
    freqs_hz: tuple[float, ...]
    phases_rad: tuple[float, ...]

    @classmethod
    def default(cls, channels: int = 8, amp_v: float | None = None) -> SineSource:
        """Channel k: 117.0 * (k + 1) Hz, (0.5 + k) V (capped at 9.5) or amp_v for all, phase 0.3 k rad."""
        amps = [amp_v if amp_v is not None else min(0.5 + k, 9.5) for k in range(channels)]
        return cls(tuple(amps), tuple(117.0 * (k + 1) for k in range(channels)),
                   tuple(0.3 * k for k in range(channels)))

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(f"sine{k}" for k in range(len(self.freqs_hz)))

    def volts(self, start_sample: int, n: int, sample_rate_hz: float) -> np.ndarray:
        t = (start_sample + np.arange(n)) / sample_rate_hz
        f = np.asarray(self.freqs_hz)[:, None]
        return np.asarray(self.amplitudes_v)[:, None] * np.sin(2 * np.pi * f * t + np.asarray(self.phases_rad)[:, None])


@dataclass
class DAQFaults:
    """Faults the simulated device injects; DATA packet indices count from 0 at each START."""

    drop_packet_every: int | None = None  # every k-th DATA packet is lost on the wire (its seq is used up)
    drop_packets: Sequence[int] = ()  # or exactly these DATA packet indices
    bit_error_every: int | None = None  # every k-th DATA packet gets one bit flipped after its CRC was computed
    # The device does not know its clock drifts: CONFIG_ACK reports the nominal rate, samples come at
    # nominal * (1 + ppm 1e-6), so a host comparing against another clock can find the drift.
    clock_drift_ppm: float = 0.0
    disconnect_after_samples: int | None = None  # send this many samples, then close the PTY master
    seed: int = 0

    def drops(self, index: int) -> bool:
        k = self.drop_packet_every
        return bool(k and (index + 1) % k == 0) or index in self.drop_packets

    def corrupts(self, index: int) -> bool:
        k = self.bit_error_every
        return bool(k and (index + 1) % k == 0)


class SimDAQDevice(PtyDevice):
    """Serves one PTY; acquires from `source` on the inputs the host configures, one thread, non-blocking I/O."""

    def __init__(
        self,
        source: SampleSource,
        *,
        max_rate_hz: float = 102_400.0,
        block_samples: int = 256,
        realtime: bool = False,
        faults: DAQFaults | None = None,
        range_v: float | Sequence[float] = 10.0,
        device_id: str = "odsplat-simdaq",
    ):
        if block_samples < 1:
            raise InputError(device_id, f"block_samples must be >= 1, got {block_samples}")
        super().__init__(device_id)
        self.source = source
        self.max_rate_hz = float(max_rate_hz)
        self.block_samples = int(block_samples)
        self.realtime = realtime
        self.faults = faults or DAQFaults()
        ranges = (range_v,) if isinstance(range_v, (int, float)) else tuple(range_v)
        self.ranges_v = tuple(sorted(dp.wire_f32(r) for r in ranges))
        self.device_id = device_id
        self.n_inputs = len(source.channel_names)
        self.disconnected = False  # set when the disconnect fault fired
        self.sample_counter = 0
        self._rng = np.random.default_rng(self.faults.seed)
        self._decoder = dp.FrameDecoder(f"{device_id} (device side)")
        self._tx_seq = 0
        self._config: dp.ConfigAck | None = None
        self._running = False
        self._data_index = 0
        self._flags = dp.StatusFlag(0)
        self._clipped = 0
        self._t0 = 0.0
        self._disconnect_deadline: float | None = None

    # ------------------------------------------------------------------------------ event loop

    def _tick(self) -> float | None:
        return self._produce()

    def _after_io(self) -> None:
        if self._disconnect_deadline is not None and (not self._out or time.monotonic() > self._disconnect_deadline):
            self._disconnect()

    def _on_bytes(self, data: bytes) -> None:
        for raw in self._decoder.feed_raw(data):
            try:
                packet = dp.parse_packet(raw)
            except dp.DAQProtocolError as e:
                self._queue(dp.Nak(raw.seq, raw.type, e.reason, e.problem))
                continue
            self._handle(packet)

    def _queue(self, message: dp.Message, *, lose: bool = False, corrupt: bool = False) -> None:
        packet = dp.encode_packet(message, self._tx_seq)
        self._tx_seq = (self._tx_seq + 1) & 0xFFFF
        if lose:
            return
        if corrupt:
            bit = int(self._rng.integers(len(packet) * 8))
            packet = bytearray(packet)
            packet[bit // 8] ^= 1 << (bit % 8)
        self._out += dp.frame(bytes(packet))

    # ------------------------------------------------------------------------------ commands

    def _handle(self, packet: dp.Packet) -> None:
        msg, seq = packet.message, packet.seq
        if isinstance(msg, dp.Hello):
            self._queue(dp.Info(seq, self.device_id, FIRMWARE, self.n_inputs, self.max_rate_hz, self.ranges_v))
        elif isinstance(msg, dp.Configure):
            if self._running:
                self._queue(dp.Nak(seq, msg.TYPE, dp.NakReason.BUSY, "stop before configuring"))
                return
            try:
                self._config = self._configure(seq, msg)
            except _Refused as e:
                self._queue(dp.Nak(seq, msg.TYPE, e.reason, str(e)))
                return
            self._queue(self._config)
        elif isinstance(msg, dp.Start):
            if self._running:
                self._queue(dp.Nak(seq, msg.TYPE, dp.NakReason.BUSY, "already acquiring"))
            elif self._config is None:
                self._queue(dp.Nak(seq, msg.TYPE, dp.NakReason.NOT_CONFIGURED, "CONFIGURE first"))
            else:
                self._queue(dp.Ack(seq, msg.TYPE))
                self._start()
        elif isinstance(msg, dp.Stop):
            self._running = False
            self._flags &= ~dp.StatusFlag.RUNNING
            self._queue(dp.Ack(seq, msg.TYPE))
            self._queue(dp.Status(self._flags, self._clipped, self.sample_counter))
        else:
            self._queue(dp.Nak(seq, msg.TYPE, dp.NakReason.UNKNOWN_TYPE, f"{msg.TYPE.name} is sent by devices"))

    def _configure(self, seq: int, msg: dp.Configure) -> dp.ConfigAck:
        if not 0 < msg.sample_rate_hz <= self.max_rate_hz:
            raise _Refused(dp.NakReason.BAD_RATE, f"{msg.sample_rate_hz} Hz outside 1..{self.max_rate_hz:g} Hz")
        rate = CLOCK_HZ / max(1, round(CLOCK_HZ / msg.sample_rate_hz))
        if not msg.channels:
            raise _Refused(dp.NakReason.BAD_CHANNEL, "no channels")
        indices = [c.index for c in msg.channels]
        if len(set(indices)) != len(indices) or max(indices) >= self.n_inputs:
            raise _Refused(dp.NakReason.BAD_CHANNEL, f"inputs {indices}: must be distinct, 0..{self.n_inputs - 1}")
        channels = []
        for c in msg.channels:
            match = [r for r in self.ranges_v if abs(r - c.range_v) <= 1e-6 * r]
            if not match:
                raise _Refused(dp.NakReason.BAD_RANGE, f"+-{c.range_v:g} V; supported {list(self.ranges_v)}")
            channels.append(dp.ChannelConfig(c.index, match[0], c.name))
        return dp.ConfigAck(seq, rate, tuple(channels))

    # ------------------------------------------------------------------------------ acquisition

    def _start(self) -> None:
        self._running = True
        self.sample_counter = 0
        self._data_index = 0
        self._flags = dp.StatusFlag.RUNNING
        self._clipped = 0
        self._t0 = time.monotonic()
        cfg = self._config
        self._indices = np.array([c.index for c in cfg.channels])
        self._scale = (dp.FULL_SCALE_COUNTS / np.array([c.range_v for c in cfg.channels]))[:, None]
        self._true_rate = cfg.sample_rate_hz * (1 + self.faults.clock_drift_ppm * 1e-6)
        fit = (dp.MAX_PACKET_BYTES - 18) // (2 * len(cfg.channels))
        self._block = min(self.block_samples, fit, 0xFFFF)

    def _produce(self) -> float | None:
        """Generate DATA that is due; returns how long the loop may sleep."""
        if not self._running or self._disconnect_deadline is not None:
            return 0.5
        if not self.realtime:
            if len(self._out) < _LOW_WATER_BYTES:
                self._acquire_block()
            return 0 if len(self._out) < _LOW_WATER_BYTES else 0.5
        while self._running and self._disconnect_deadline is None:
            due = self._t0 + (self.sample_counter + self._block) / self._true_rate
            wait = due - time.monotonic()
            if wait > 0:
                return wait
            queued_s = len(self._out) / (2 * len(self._indices) * self._true_rate)
            self._acquire_block(discard=queued_s > _OVERRUN_S)
        return 0.5

    def _acquire_block(self, *, discard: bool = False) -> None:
        n = self._block
        limit = self.faults.disconnect_after_samples
        if limit is not None:
            n = min(n, limit - self.sample_counter)
        if n > 0:
            first = self.sample_counter
            self.sample_counter += n
            if discard:
                self._raise_flags(dp.StatusFlag.OVERRUN, 0)
            else:
                volts = np.asarray(self.source.volts(first, n, self._true_rate), dtype=np.float64)[self._indices]
                raw = np.rint(volts * self._scale)
                # A real ADC saturates at full scale; the clip is reported, never hidden.
                over = np.abs(raw) > dp.FULL_SCALE_COUNTS
                counts = np.clip(raw, -dp.FULL_SCALE_COUNTS, dp.FULL_SCALE_COUNTS).astype(np.int16)
                index = self._data_index
                self._data_index += 1
                self._queue(dp.Data(first, counts), lose=self.faults.drops(index), corrupt=self.faults.corrupts(index))
                if over.any():
                    mask = sum(1 << int(c) for c in np.flatnonzero(over.any(axis=1)) if c < 32)  # u32 on the wire
                    self._raise_flags(dp.StatusFlag.CLIPPED, mask)
        if limit is not None and self.sample_counter >= limit:
            log.info("%s: disconnecting after %d samples (fault injection)", self.device_id, self.sample_counter)
            self._disconnect_deadline = time.monotonic() + _DISCONNECT_FLUSH_S

    def _raise_flags(self, flags: dp.StatusFlag, clipped: int) -> None:
        if (self._flags | flags) != self._flags or (self._clipped | clipped) != self._clipped:
            self._flags |= flags
            self._clipped |= clipped
            self._queue(dp.Status(self._flags, self._clipped, self.sample_counter))

    def _disconnect(self) -> None:
        self.disconnected = True
        self._running = False
        self._disconnect_deadline = None
        os.close(self._master)
        self._master = -1


class _Refused(Exception):
    def __init__(self, reason: dp.NakReason, text: str):
        super().__init__(text)
        self.reason = reason


# ---------------------------------------------------------------------------------- registry

SourceOrFactory = Union[SampleSource, Callable[..., SampleSource]]
_SOURCES: dict[str, SourceOrFactory] = {}


def register_source(name: str, source: SourceOrFactory) -> None:
    """Make `simdaq://NAME` acquire from `source`, or from `source(**options)` built per open, where options
    are the URL's query parameters that the device itself does not use (as strings)."""
    _SOURCES[name.lower()] = source


def _sine_factory(channels: str = "8", amp_v: str | None = None) -> SineSource:
    return SineSource.default(int(channels), None if amp_v is None else float(amp_v))


register_source("sine", _sine_factory)


def _make_source(name: str, options: dict[str, str]) -> SampleSource:
    try:
        entry = _SOURCES[name.lower()]
    except KeyError:
        raise InputError(f"simdaq://{name}", f"no source {name!r}; registered: {sorted(_SOURCES)}") from None
    if not isinstance(entry, type) and hasattr(entry, "volts"):  # an instance, shared by every open
        if options:
            raise InputError(f"simdaq://{name}", f"unknown URL options {sorted(options)}")
        return entry
    try:
        return entry(**options)
    except (TypeError, ValueError) as e:
        raise InputError(f"simdaq://{name}", f"bad source options {options}: {e}") from None


def register_url_handler() -> None:
    """Let `serial.serial_for_url("simdaq://...")` find hil_sim/protocol_simdaq.py (idempotent)."""
    if "odsplat.hil_sim" not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append("odsplat.hil_sim")


# URL option -> (SimDAQDevice or DAQFaults keyword, parser)
_URL_OPTIONS: dict[str, tuple[str, Callable[[str], Any]]] = {
    "fs": ("max_rate_hz", float),
    "block": ("block_samples", int),
    "realtime": ("realtime", parse_bool),
    "range": ("range_v", lambda v: tuple(float(x) for x in v.split(","))),
    "id": ("device_id", str),
    "drop_every": ("drop_packet_every", int),
    "drop": ("drop_packets", lambda v: tuple(int(x) for x in v.split(",") if x)),
    "bit_error_every": ("bit_error_every", int),
    "drift_ppm": ("clock_drift_ppm", float),
    "disconnect_after": ("disconnect_after_samples", int),
    "seed": ("seed", int),
}
_FAULT_FIELDS = {"drop_packet_every", "drop_packets", "bit_error_every", "clock_drift_ppm", "disconnect_after_samples",
                 "seed"}


def device_from_url(url: str) -> SimDAQDevice:
    """Build (not yet serve) the device a `simdaq://NAME?option=value&...` URL describes."""
    parts = urlsplit(url)
    if parts.scheme.lower() != "simdaq" or not parts.netloc:
        raise InputError(url, "expected simdaq://SOURCE[?option=value&...]")
    source_options: dict[str, str] = {}  # the rest are the source's own
    device_kw, fault_kw = split_url_options(url, parts.query, _URL_OPTIONS, _FAULT_FIELDS, source_options)
    source = _make_source(parts.netloc, source_options)
    return SimDAQDevice(source, faults=DAQFaults(**fault_kw), **device_kw)
