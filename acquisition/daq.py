"""The serial DAQ driver: speaks daqproto on any pyserial port, streams into a ring buffer in SI units.

Timestamps come from the device's sample counter (sample / rate), never from when the host received them.
Lost packets, bit errors (CRC failures), device overruns and disconnects are detected and reported; a gap
stays NaN in the buffer and is listed in `gaps`. Nothing is ever filled in.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import serial

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.manifest import CHANNEL_KINDS, ChannelInfo

from . import daqproto as dp
from .ring import SampleRing

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DAQChannel:
    """One DAQ input: which input, its range, and the sensor's sensitivity (V per SI unit of `kind`)."""

    name: str
    input: int
    kind: str = "voltage"
    sensitivity_v_per_unit: float = 1.0
    range_v: float = 10.0
    position_m: tuple[float, float, float] | None = None
    direction: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.kind not in CHANNEL_KINDS:
            raise InputError(f"DAQ channel {self.name!r}.kind",
                             f"expected one of {', '.join(CHANNEL_KINDS)}; got {self.kind!r}")
        if not self.sensitivity_v_per_unit > 0:
            raise InputError(f"DAQ channel {self.name!r}.sensitivity_v_per_unit",
                             f"must be positive, got {self.sensitivity_v_per_unit}")
        if self.input < 0:
            raise InputError(f"DAQ channel {self.name!r}.input", f"must be >= 0, got {self.input}")

    @property
    def unit(self) -> str:
        return CHANNEL_KINDS[self.kind]

    @property
    def full_scale(self) -> float:
        """The largest value the input can measure, in SI units."""
        return self.range_v / self.sensitivity_v_per_unit

    def info(self, device: str = "daq") -> ChannelInfo:
        return ChannelInfo(self.name, self.kind, self.unit, self.sensitivity_v_per_unit,
                           None if self.position_m is None else list(self.position_m),
                           None if self.direction is None else list(self.direction), device=device)


class DAQError(OdsplatError):
    """The DAQ stream failed: disconnect, timeout or a refused command."""


class SerialDAQ:
    """One DAQ on an open serial port. `configure()`, `start()`, then read by absolute sample index.

    A reader thread runs from construction to `close()`: it decodes every packet, answers the commands'
    waits, and writes DATA into the ring buffer.
    """

    def __init__(self, port: serial.SerialBase, channels: Sequence[DAQChannel], sample_rate_hz: float, *,
                 buffer_s: float = 30.0, reply_timeout_s: float = 2.0, name: str | None = None):
        if not channels:
            raise InputError(name or port.portstr, "no DAQ channels configured")
        names = [c.name for c in channels]
        if len(set(names)) != len(names):
            raise InputError(name or port.portstr, f"DAQ channel names must be distinct; got {names}")
        self.port = port
        self.name = name or port.portstr
        self.channels = tuple(channels)
        self.requested_rate_hz = float(sample_rate_hz)
        self.sample_rate_hz: float | None = None  # what the device runs at, from CONFIG_ACK
        self.buffer_s = buffer_s
        self.reply_timeout_s = reply_timeout_s
        self.info: dp.Info | None = None
        self.decoder = dp.FrameDecoder(self.name)
        self.checker: dp.DataStreamChecker | None = None
        self.gaps: list[dp.SampleGap] = []
        self.flags = dp.StatusFlag(0)
        self.clipped: set[str] = set()
        self.final_status: dp.Status | None = None
        self.error: DAQError | None = None
        self._ring: SampleRing | None = None
        self._scale: np.ndarray | None = None
        self._seq = 0
        self._start_seq: int | None = None
        self._replies: dict[int, dp.Packet] = {}
        self._cond = threading.Condition()
        self._closing = threading.Event()
        self._stopped = threading.Event()
        port.write(b"\x00")  # ends whatever partial frame the device may hold
        self._thread = threading.Thread(target=self._run, name=f"daq reader {self.name}", daemon=True)
        self._thread.start()

    @classmethod
    def from_url(cls, url: str, channels: Sequence[DAQChannel], sample_rate_hz: float, **kw) -> SerialDAQ:
        """Open a port by pyserial URL (a device path, `simdaq://...`, `socket://...`) at 0.05 s read timeout."""
        try:
            port = serial.serial_for_url(url, timeout=0.05, write_timeout=2.0)
        except (serial.SerialException, ValueError) as e:
            raise InputError(url, f"cannot open the DAQ port: {e}") from None
        try:
            return cls(port, channels, sample_rate_hz, name=url, **kw)
        except BaseException:
            port.close()
            raise

    # ------------------------------------------------------------------------------ commands

    def _request(self, message: dp.Message) -> dp.Packet:
        self._check_error()
        with self._cond:
            seq, self._seq = self._seq, (self._seq + 1) & 0xFFFF
            if isinstance(message, dp.Start):
                self._start_seq = seq
        self.port.write(dp.encode_frame(message, seq))
        deadline = time.monotonic() + self.reply_timeout_s
        with self._cond:
            while seq not in self._replies:
                left = deadline - time.monotonic()
                if left <= 0 or self.error is not None:
                    self._check_error()
                    raise DAQError(f"{self.name}: no reply to {message.TYPE.name} within {self.reply_timeout_s:g} s")
                self._cond.wait(left)
            packet = self._replies.pop(seq)
        if isinstance(packet.message, dp.Nak):
            raise packet.message.error(self.name)
        return packet

    def configure(self) -> dp.ConfigAck:
        """HELLO, then CONFIGURE with our channels; checks the echo. The device's actual rate is then known."""
        self.info = self._request(dp.Hello()).message
        for c in self.channels:
            if c.input >= self.info.n_inputs:
                raise InputError(f"{self.name}: channel {c.name!r}", f"input {c.input} does not exist; the device has "
                                 f"{self.info.n_inputs} inputs (0..{self.info.n_inputs - 1})")
            if not any(abs(r - c.range_v) <= 1e-6 * r for r in self.info.ranges_v):
                raise InputError(f"{self.name}: channel {c.name!r}", f"range +-{c.range_v:g} V not offered; the device "
                                 f"offers {list(self.info.ranges_v)}")
        request = dp.Configure(self.requested_rate_hz,
                               tuple(dp.ChannelConfig(c.input, c.range_v, c.name) for c in self.channels))
        ack = self._request(request).message
        dp.verify_config(request, ack, device=self.name)
        self.sample_rate_hz = ack.sample_rate_hz
        if abs(ack.sample_rate_hz - self.requested_rate_hz) > 1e-6 * self.requested_rate_hz:
            log.info("%s runs at %.6f Hz (asked %.6f Hz)", self.name, ack.sample_rate_hz, self.requested_rate_hz)
        ranges = np.array([c.range_v for c in ack.channels])
        sens = np.array([c.sensitivity_v_per_unit for c in self.channels])
        self._scale = (ranges / dp.FULL_SCALE_COUNTS / sens)[:, None]
        return ack

    def start(self) -> None:
        """START: the device's sample counter restarts at 0; the buffer and the gap list are cleared."""
        if self._scale is None:
            self.configure()
        self._ring = SampleRing(len(self.channels), max(1024, int(self.buffer_s * self.sample_rate_hz)), name=self.name,
                                error=DAQError)
        self.gaps, self.flags, self.clipped, self.final_status = [], dp.StatusFlag(0), set(), None
        self._stopped.clear()
        self._request(dp.Start())

    def stop(self, timeout_s: float = 2.0) -> dp.Status | None:
        """STOP; waits for the device's final status (its sample count closes any trailing gap)."""
        if self.error is not None:
            return None
        self._request(dp.Stop())
        if not self._stopped.wait(timeout_s):
            raise DAQError(f"{self.name}: no final status within {timeout_s:g} s of STOP")
        return self.final_status

    def close(self) -> None:
        self._closing.set()
        self._thread.join(timeout=2.0)
        self.port.close()

    def __enter__(self) -> SerialDAQ:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------ data

    @property
    def next_sample(self) -> int:
        """One past the newest sample received (or known lost)."""
        return 0 if self._ring is None else self._ring.stop

    def channel_index(self, name: str) -> int:
        for k, c in enumerate(self.channels):
            if c.name == name:
                return k
        raise InputError(self.name, f"no channel {name!r}; channels: {[c.name for c in self.channels]}")

    def wait_for(self, sample: int, timeout_s: float) -> None:
        """Block until samples before `sample` are in (received or known lost); raise on disconnect or timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self.next_sample < sample:
                self._check_error()
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DAQError(f"{self.name}: sample {sample} not received within {timeout_s:g} s "
                                   f"(have {self.next_sample})")
                self._cond.wait(min(left, 0.1))
        self._check_error(only_if_short=sample)

    def read(self, first: int, stop: int, channels: Sequence[str] | None = None) -> np.ndarray:
        """(n_channels, stop - first) in SI units; NaN where samples were lost."""
        if self._ring is None:
            raise DAQError(f"{self.name}: not started")
        with self._cond:
            data = self._ring.read(first, stop)
        if channels is not None:
            data = data[[self.channel_index(c) for c in channels]]
        return data

    def gaps_in(self, first: int, stop: int) -> list[dp.SampleGap]:
        return [g for g in self.gaps if g.first_sample < stop and g.stop > first]

    def _check_error(self, only_if_short: int | None = None) -> None:
        if self.error is not None and (only_if_short is None or self.next_sample < only_if_short):
            raise self.error

    # ------------------------------------------------------------------------------ reader thread

    def _run(self) -> None:
        try:
            while not self._closing.is_set():
                data = self.port.read(max(1, self.port.in_waiting))
                if data:
                    for packet in self.decoder.feed(data):
                        self._on_packet(packet)
        except (serial.SerialException, OSError) as e:
            if not self._closing.is_set():
                err = DAQError(f"{self.name}: disconnected after sample {self.next_sample}: {e}")
                log.error("%s", err)
                with self._cond:
                    self.error = err
                    self._cond.notify_all()

    def _on_packet(self, packet: dp.Packet) -> None:
        msg = packet.message
        with self._cond:
            ref = getattr(msg, "ref_seq", None)
            if ref is not None:
                self._replies[ref] = packet
            if isinstance(msg, dp.Ack) and ref == self._start_seq and msg.ref_type == dp.MsgType.START:
                self.checker = dp.DataStreamChecker(len(self.channels), device=self.name,
                                                    next_seq=(packet.seq + 1) & 0xFFFF)
            elif self.checker is not None:
                for event in self.checker.feed(packet):
                    self._on_event(event)
            if isinstance(msg, dp.Status):
                self._on_status(msg)
            self._cond.notify_all()

    def _on_event(self, event) -> None:
        if self._ring is None:
            return
        if isinstance(event, dp.SampleBlock):
            self._ring.write(event.first_sample, event.counts * self._scale, event.n_samples)
        else:
            self.gaps.append(event)
            self._ring.write(event.first_sample, None, event.n_samples)  # the checker has logged it

    def _on_status(self, status: dp.Status) -> None:
        self.flags |= status.flags
        for k, c in enumerate(self.channels):
            if status.clipped_channels >> k & 1 and c.name not in self.clipped:
                self.clipped.add(c.name)
                log.warning("%s: channel %r clipped at +-%g V", self.name, c.name, c.range_v)
        if not status.flags & dp.StatusFlag.RUNNING and self.checker is not None and self._ring is not None:
            for gap in self.checker.finish(status.sample_counter):
                self._on_event(gap)
            self.final_status = status
            self.checker = None
            self._stopped.set()

    @property
    def link_errors(self) -> dict[str, int]:
        """Counts of what went wrong on the link: CRC failures (bit errors), bad frames, lost packets."""
        s = self.decoder.stats
        lost = sum(g.lost_packets for g in self.gaps)
        return {"crc_errors": s.crc_errors, "cobs_errors": s.cobs_errors, "malformed": s.malformed,
                "lost_packets": lost}
