"""A minimal host for the simulated DAQ, for tests: every read has a deadline, every reply is matched.

The acquisition stage has the real driver; this one stays small so the device can be tested alone."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import serial

from odsplat.acquisition import daqproto as dp


@dataclass
class DAQTake:
    info: dp.Info
    ack: dp.ConfigAck
    checker: dp.DataStreamChecker
    decoder: dp.FrameDecoder
    blocks: list[dp.SampleBlock] = field(default_factory=list)
    gaps: list[dp.SampleGap] = field(default_factory=list)
    statuses: list[dp.Status] = field(default_factory=list)
    elapsed_s: float = 0.0

    @property
    def final(self) -> dp.Status:
        return self.statuses[-1]

    def volts(self, n: int) -> np.ndarray:
        """The first n samples in volts; NaN where a gap was reported (only for comparing)."""
        out = np.full((len(self.ack.channels), n), np.nan)
        ranges = [c.range_v for c in self.ack.channels]
        for b in self.blocks:
            if b.first_sample < n:
                out[:, b.first_sample:b.stop] = dp.counts_to_volts(b.counts, ranges)[:, : n - b.first_sample]
        return out


class DAQHost:
    """The smallest honest host: every read has a deadline, every reply is matched by ref_seq."""

    def __init__(self, port: serial.SerialBase, timeout_s: float = 10.0):
        self.port = port
        self.timeout_s = timeout_s
        self.decoder = dp.FrameDecoder(port.portstr)
        self._seq = 0
        self._backlog: list[dp.Packet] = []
        port.write(b"\x00")  # ends whatever partial frame the device may hold

    def send(self, message: dp.Message) -> int:
        seq, self._seq = self._seq, (self._seq + 1) & 0xFFFF
        self.port.write(dp.encode_frame(message, seq))
        return seq

    def next_packet(self, deadline: float) -> dp.Packet:
        while not self._backlog:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.port.portstr}: no packet from the device in time")
            self._backlog = self.decoder.feed(self.port.read(max(1, self.port.in_waiting)))
        return self._backlog.pop(0)

    def request(self, message: dp.Message) -> dp.Packet:
        seq = self.send(message)
        deadline = time.monotonic() + self.timeout_s
        while True:
            packet = self.next_packet(deadline)
            if getattr(packet.message, "ref_seq", None) == seq:
                if isinstance(packet.message, dp.Nak):
                    raise packet.message.error(self.port.portstr)
                return packet

    def take(self, channels, rate_hz: int, n_samples: int, *, pause_s: float = 0.0) -> DAQTake:
        info = self.request(dp.Hello()).message
        request = dp.Configure(rate_hz, tuple(channels))
        ack = self.request(request).message
        dp.verify_config(request, ack, device=self.port.portstr)
        started = self.request(dp.Start())
        checker = dp.DataStreamChecker(len(channels), device=self.port.portstr, next_seq=started.seq + 1)
        take = DAQTake(info, ack, checker, self.decoder)
        t0 = time.monotonic()
        time.sleep(pause_s)  # a host that falls behind
        deadline = t0 + self.timeout_s
        stop_seq = None
        while True:
            packet = self.next_packet(deadline)
            if stop_seq is None and take.checker.next_sample >= n_samples:
                take.elapsed_s = time.monotonic() - t0
                stop_seq = self.send(dp.Stop())
            for event in take.checker.feed(packet):
                (take.blocks if isinstance(event, dp.SampleBlock) else take.gaps).append(event)
            if isinstance(packet.message, dp.Status):
                take.statuses.append(packet.message)
                if stop_seq is not None and not packet.message.flags & dp.StatusFlag.RUNNING:
                    take.gaps += take.checker.finish(packet.message.sample_counter)
                    return take


def channels(n: int, range_v: float = 10.0) -> list[dp.ChannelConfig]:
    return [dp.ChannelConfig(k, range_v, f"ch{k}") for k in range(n)]


def open_port(url: str) -> serial.SerialBase:
    return serial.serial_for_url(url, timeout=0.5, write_timeout=5)
