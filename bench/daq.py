"""Benchmark of the serial DAQ driver: sustained lossless samples/s over a real PTY and its CPU cost, against baselines.

Prints one JSON line on stdout; progress goes to stderr. The simulated device (`simdaq://sine?channels=8`, truth
`SineSource.default`) runs in a child process that owns the PTY master (this script with --serve-device), so
`time.process_time()` here is the host's CPU alone; the child reports its own CPU (the device's share) on request.

Units. A "sample" is one instant of every channel (samples/s is per channel); a "value" is one channel's sample
(values/s = samples/s x channels). payload_mb_s counts the DATA counts, 2 bytes a value (1 MB = 1e6 bytes); wire
bytes add the headers and framing (~1 %). Every figure is over the stream span: from START (the driver's `start()`
returned; START's ACK read; START sent for the byte sink) until the target sample arrived, and counts only the
samples that arrived inside it. CPU % is of one core. host_cpu_s_per_m_values is host CPU seconds per million
values; cpu_pct_at_51200hz = host CPU s per value x 51200 x channels x 100: the share of one core the host needs at
51.2 kHz. host_limited_samples_per_s = samples / host CPU s: where the host would fill one core if its cost per
value held (an extrapolation). device_cpu_* are the device process's, over the same span plus its last few packets.

- sustained (realtime=0): the device makes samples as fast as the host reads them (PTY backpressure), so
  samples/s is the most this host and device sustain together. limited_by names what held it back: "device" or
  "host" when that process used >= 90 % of a core over the span, "cpus" when together they used >= 90 % of every
  core this process may run on (cpus_available; on one core they take turns), else "pty_handoff": they waited
  on each other (a Linux PTY hands over at most ~4 KB a read, less than one 8-channel DATA frame, so each packet
  costs wake-ups on both sides and the rate moves with scheduling). Only "host" makes samples/s the host's own
  limit; host_limited_samples_per_s and the CPU-per-value figures speak for the host in every case. Three hosts,
  each run `--repeats` times with a fresh device (the fastest run is reported whole, every rate in
  samples_per_s_runs):
  `driver`: SerialDAQ as a caller uses it (reader thread, FrameDecoder, DataStreamChecker, float32 ring buffer in SI
  units; the caller blocks in `wait_for`); its newest 4096 samples are checked against the sine truth
  (max_error_lsb, <= 0.5 plus float32 rounding).
  `decode_only`: one thread, the same pyserial reads, FrameDecoder.feed and DataStreamChecker.feed on every packet;
  no ring buffer, no SI conversion, no thread.
  `transport_ceiling`: the same pyserial reads into a byte sink that only counts frame delimiters: what the PTY and
  the device deliver. Ratios are driver / baseline. gaps and link errors (all runs) must be 0: no_loss.
- realtime (realtime=1, fs=51200, `--realtime-s`): the device paces at 51.2 kHz and discards samples (OVERRUN, a
  gap) once the host is 0.5 s behind. Achieved samples/s, overrun, gaps and host/device CPU % for the driver and
  decode_only; no_loss must hold.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import serial

from odsplat.acquisition import daqproto as dp
from odsplat.acquisition.daq import DAQChannel, SerialDAQ
from odsplat.hil_sim.daq import SineSource, device_from_url

log = logging.getLogger("bench.daq")

REPO = Path(__file__).resolve().parents[1]
RATE_HZ = 51_200  # the top rate the DAQ must sustain; also the realtime run's rate
RANGE_V = 10.0
MB = 1e6
READ_TIMEOUT_S = 0.05  # as SerialDAQ.from_url opens its port
CHECK_SAMPLES = 4096  # the driver's newest samples compared against the sine truth
SATURATED = 0.9  # a process using this much of a core over a span is what limits the rate


# ---------------------------------------------------------------------------------- the device

def serve_device(url: str) -> int:
    """Child process: serve the device of `url` on a PTY, print the slave's path; answer each `cpu` line on stdin
    with this process's CPU seconds; stop at EOF."""
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="bench.daq device: %(message)s")
    with device_from_url(url) as device:
        print(device.serve_pty(), flush=True)
        for line in sys.stdin:
            if line.strip() == "cpu":
                print(repr(time.process_time()), flush=True)
    return 0


class DeviceProcess:
    """The simulated device of a simdaq:// URL, served by a child process that owns the PTY master."""

    def __init__(self, url: str):
        self.url = url
        self._proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--serve-device", url],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO)
        self.path = self._proc.stdout.readline().strip()
        if not self.path:
            self._proc.kill()
            raise RuntimeError(f"{url}: the device process exited with {self._proc.wait()} before serving a PTY")

    def cpu_s(self) -> float:
        """The device process's CPU seconds so far (all its threads)."""
        self._proc.stdin.write("cpu\n")
        self._proc.stdin.flush()
        return float(self._proc.stdout.readline())

    def close(self) -> None:
        self._proc.stdin.close()
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()

    def __enter__(self) -> DeviceProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def device_url(*, channels: int, block: int, realtime: bool) -> str:
    return f"simdaq://sine?channels={channels}&fs={RATE_HZ}&block={block}&realtime={int(realtime)}"


def open_port(path: str) -> serial.Serial:
    return serial.Serial(path, timeout=READ_TIMEOUT_S, write_timeout=2.0)


# ---------------------------------------------------------------------------------- the hosts

class PlainHost:
    """The baselines' host: one thread, `port.read(max(1, in_waiting))` as the driver reads, replies matched by
    ref_seq; no ring buffer, no SI units, no reader thread."""

    def __init__(self, port: serial.SerialBase, n_channels: int, timeout_s: float = 5.0):
        self.port = port
        self.n_channels = n_channels
        self.timeout_s = timeout_s
        self.decoder = dp.FrameDecoder(port.portstr)
        self.backlog: list[dp.Packet] = []
        self._seq = 0
        port.write(b"\x00")

    def send(self, message: dp.Message) -> int:
        seq, self._seq = self._seq, (self._seq + 1) & 0xFFFF
        self.port.write(dp.encode_frame(message, seq))
        return seq

    def read(self) -> bytes:
        return self.port.read(max(1, self.port.in_waiting))

    def request(self, message: dp.Message) -> dp.Packet:
        seq = self.send(message)
        deadline = time.monotonic() + self.timeout_s
        while True:
            while not self.backlog:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{self.port.portstr}: no reply to {message.TYPE.name} in {self.timeout_s:g} s")
                self.backlog = self.decoder.feed(self.read())
            packet = self.backlog.pop(0)
            if getattr(packet.message, "ref_seq", None) == seq:
                if isinstance(packet.message, dp.Nak):
                    raise packet.message.error(self.port.portstr)
                return packet

    def configure(self) -> float:
        self.request(dp.Hello())
        request = dp.Configure(RATE_HZ, tuple(dp.ChannelConfig(k, RANGE_V, f"sine{k}") for k in range(self.n_channels)))
        ack = self.request(request).message
        dp.verify_config(request, ack, device=self.port.portstr)
        return ack.sample_rate_hz


def _cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _channels(n: int) -> list[DAQChannel]:
    return [DAQChannel(f"sine{k}", k, range_v=RANGE_V) for k in range(n)]


class _Span:
    """Wall, host CPU and device CPU over one stream span."""

    def __init__(self, device: DeviceProcess):
        self.device = device
        self.dev0 = device.cpu_s()  # the device is idle until START: asking costs it nothing that matters

    def begin(self) -> None:
        self.t0, self.cpu0 = time.perf_counter(), time.process_time()

    def end(self) -> None:
        self.wall_s, self.cpu_s = time.perf_counter() - self.t0, time.process_time() - self.cpu0

    def _limit(self, dev_cpu_s: float, paced: bool) -> str:
        busy = SATURATED * self.wall_s
        if paced:
            return "device_clock"
        if dev_cpu_s >= busy:
            return "device"
        if self.cpu_s >= busy:
            return "host"
        if self.cpu_s + dev_cpu_s >= busy * _cpus():
            return "cpus"  # both together fill every core this process may use (one core: they take turns)
        return "pty_handoff"

    def figures(self, samples: int, n_channels: int, *, paced: bool = False) -> dict[str, Any]:
        dev_cpu_s = self.device.cpu_s() - self.dev0  # after STOP: includes the few packets sent after the span
        values = samples * n_channels
        return {
            "samples": samples,
            "wall_s": round(self.wall_s, 4),
            "samples_per_s": round(samples / self.wall_s, 1),
            "values_per_s": round(values / self.wall_s, 1),
            "payload_mb_s": round(2 * values / MB / self.wall_s, 3),
            "host_cpu_s": round(self.cpu_s, 4),
            "host_cpu_pct": round(100 * self.cpu_s / self.wall_s, 1),
            "host_cpu_s_per_m_values": round(self.cpu_s / values * 1e6, 4),
            # Where this host would fill one core, if its cost per value held at higher rates.
            "host_limited_samples_per_s": round(samples / self.cpu_s, 1) if self.cpu_s > 0 else None,
            "cpu_pct_at_51200hz": round(100 * self.cpu_s / values * RATE_HZ * n_channels, 2),
            "device_cpu_s": round(dev_cpu_s, 4),
            "device_cpu_pct": round(100 * dev_cpu_s / self.wall_s, 1),
            "device_cpu_s_per_m_values": round(dev_cpu_s / values * 1e6, 4),
            "limited_by": self._limit(dev_cpu_s, paced),
        }


def run_driver(n_samples: int, *, n_channels: int, block: int, realtime: bool, timeout_s: float) -> dict[str, Any]:
    """SerialDAQ as a caller uses it: start(), wait_for(n), stop(); rates over start() returned .. wait_for returned."""
    with DeviceProcess(device_url(channels=n_channels, block=block, realtime=realtime)) as device:
        with SerialDAQ.from_url(device.path, _channels(n_channels), RATE_HZ) as daq:
            daq.configure()
            span = _Span(device)
            daq.start()
            span.begin()
            s0 = daq.next_sample
            daq.wait_for(n_samples, timeout_s)
            s1 = daq.next_sample
            span.end()
            daq.stop()
            result = span.figures(s1 - s0, n_channels, paced=realtime)
            k = min(CHECK_SAMPLES, s1)
            got = daq.read(s1 - k, s1)
            truth = SineSource.default(n_channels).volts(s1 - k, k, daq.sample_rate_hz)
            result.update(
                gaps=len(daq.gaps), lost_samples=sum(g.n_samples for g in daq.gaps), link_errors=daq.link_errors,
                overrun=bool(daq.flags & dp.StatusFlag.OVERRUN), sample_rate_hz=daq.sample_rate_hz,
                max_error_lsb=round(float(np.max(np.abs(got - truth))) / (RANGE_V / dp.FULL_SCALE_COUNTS), 3),
            )
    return result


def run_decode_only(n_samples: int, *, n_channels: int, block: int, realtime: bool, timeout_s: float) -> dict[str, Any]:
    """PlainHost decoding every packet (FrameDecoder.feed + DataStreamChecker.feed) and keeping nothing."""
    with DeviceProcess(device_url(channels=n_channels, block=block, realtime=realtime)) as device, \
            open_port(device.path) as port:
        host = PlainHost(port, n_channels)
        host.configure()
        span = _Span(device)
        ack = host.request(dp.Start())
        span.begin()
        checker = dp.DataStreamChecker(n_channels, device=port.portstr, next_seq=(ack.seq + 1) & 0xFFFF)
        flags = dp.StatusFlag(0)
        wire_bytes = 0
        s0, s1, stop_seq, final = None, None, None, None
        deadline = time.monotonic() + timeout_s
        while final is None:
            for packet in host.backlog:
                checker.feed(packet)  # the blocks are dropped: this host keeps nothing
                msg = packet.message
                if isinstance(msg, dp.Status):
                    flags |= msg.flags
                    if stop_seq is not None and not msg.flags & dp.StatusFlag.RUNNING:
                        final = msg
                        break
            if final is not None:
                break
            if s0 is None:  # the packets that came with START's ACK are before the span
                s0 = checker.next_sample
            if stop_seq is None and checker.next_sample >= n_samples:
                s1 = checker.next_sample
                span.end()
                stop_seq = host.send(dp.Stop())
            if time.monotonic() > deadline:
                raise TimeoutError(f"{port.portstr}: {n_samples} samples and a final STATUS not received in "
                                   f"{timeout_s:g} s")
            data = host.read()
            wire_bytes += len(data)
            host.backlog = host.decoder.feed(data)
        checker.finish(final.sample_counter)
        result = span.figures(s1 - s0, n_channels, paced=realtime)
        stats, dec = checker.stats, host.decoder.stats
        result.update(gaps=len(stats.gaps), lost_samples=stats.lost_samples,
                      link_errors={"crc_errors": dec.crc_errors, "cobs_errors": dec.cobs_errors,
                                   "malformed": dec.malformed, "lost_packets": stats.lost_packets},
                      overrun=bool(flags & dp.StatusFlag.OVERRUN), wire_bytes=wire_bytes)
    return result


def run_transport_ceiling(n_samples: int, *, n_channels: int, block: int, timeout_s: float) -> dict[str, Any]:
    """PlainHost's reads into a byte sink after START: counts bytes and frame delimiters (in C), decodes nothing.
    Each delimiter after START's ACK ends one DATA frame of `block` samples (no STATUS comes in a clean stream)."""
    with DeviceProcess(device_url(channels=n_channels, block=block, realtime=False)) as device, \
            open_port(device.path) as port:
        host = PlainHost(port, n_channels)
        host.configure()
        span = _Span(device)
        target_frames = 1 + -(-n_samples // block)  # START's ACK, then DATA
        frames = wire_bytes = 0
        deadline = time.monotonic() + timeout_s
        span.begin()
        host.send(dp.Start())
        while frames < target_frames:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{port.portstr}: {target_frames} frames not received in {timeout_s:g} s")
            data = host.read()
            wire_bytes += len(data)
            frames += data.count(0)
        span.end()
        # Stop cleanly: a fresh decoder (its first, partial frame is discarded) until the final STATUS.
        host.decoder, host.backlog = dp.FrameDecoder(port.portstr), []
        host.request(dp.Stop())
        while not any(isinstance(p.message, dp.Status) and not p.message.flags & dp.StatusFlag.RUNNING
                      for p in host.backlog):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{port.portstr}: no final STATUS after STOP")
            host.backlog += host.decoder.feed(host.read())
        result = span.figures((frames - 1) * block, n_channels)
        result.update(wire_bytes=wire_bytes, wire_mb_s=round(wire_bytes / MB / span.wall_s, 3))
    return result


# ---------------------------------------------------------------------------------- main

def _ratio(a: float, b: float) -> float | None:
    return round(a / b, 3) if b else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2_000_000,
                        help="samples per channel in each sustained run (default 2000000)")
    parser.add_argument("--realtime-s", type=float, default=3.0,
                        help=f"seconds of the realtime run at {RATE_HZ} Hz (default 3; 0 skips it)")
    parser.add_argument("--channels", type=int, default=8, help="channels acquired (default 8)")
    parser.add_argument("--block", type=int, default=256, help="samples per DATA packet (device default 256)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="sustained runs per host, the fastest reported (default 3)")
    parser.add_argument("--quick", action="store_true", help="a small run: --samples 100000 --realtime-s 1 --repeats 1")
    parser.add_argument("--serve-device", metavar="URL", help=argparse.SUPPRESS)  # the child process
    args = parser.parse_args(argv)
    if args.serve_device:
        return serve_device(args.serve_device)
    if args.quick:
        args.samples, args.realtime_s, args.repeats = 100_000, 1.0, 1
    max_block = (dp.MAX_PACKET_BYTES - 18) // (2 * max(args.channels, 1))
    if (args.samples < args.block or args.realtime_s < 0 or args.repeats < 1 or not 1 <= args.channels <= 8
            or not 1 <= args.block <= max_block):
        parser.error(f"need --samples >= --block, --realtime-s >= 0, --repeats >= 1, --channels 1..8, "
                     f"--block 1..{max_block}")
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
    kw = {"n_channels": args.channels, "block": args.block}
    timeout_s = 60.0 + args.samples / 20_000  # far beyond any sane rate: a hang fails, a slow host does not

    result: dict[str, Any] = {
        "bench": "daq", "channels": args.channels, "block_samples": args.block, "rate_hz": RATE_HZ,
        "cpu_count": os.cpu_count(),
        "cpus_available": _cpus(),
        "machine": platform.machine(), "python": platform.python_version(),
        "device": "simdaq sine in a child process owning the PTY master; host CPU is this process only",
    }
    sustained: dict[str, Any] = {"samples_target": args.samples, "repeats": args.repeats}
    for name, run in (("transport_ceiling", run_transport_ceiling), ("decode_only", run_decode_only),
                      ("driver", run_driver)):
        runs = []
        for rep in range(args.repeats):
            log.info("sustained, %s (%d/%d): %d samples x %d channels", name, rep + 1, args.repeats, args.samples,
                     args.channels)
            extra = {} if name == "transport_ceiling" else {"realtime": False}
            r = run(args.samples, timeout_s=timeout_s, **kw, **extra)
            log.info("  %.0f samples/s (%.1f MB/s payload), host CPU %.0f %% (%.2f %% at %d Hz), device CPU %.0f %%",
                     r["samples_per_s"], r["payload_mb_s"], r["host_cpu_pct"], r["cpu_pct_at_51200hz"], RATE_HZ,
                     r["device_cpu_pct"])
            runs.append(r)
        # The fastest run, whole, so that its figures belong together (as bench/store.py takes the best of 3);
        # every run's rate beside it, since the rate moves with how the scheduler places the two processes.
        best = max(runs, key=lambda r: r["samples_per_s"])
        sustained[name] = {**best, "samples_per_s_runs": [r["samples_per_s"] for r in runs],
                           "gaps_all_runs": sum(r.get("gaps", 0) for r in runs),
                           "link_errors_all_runs": sum(sum(r.get("link_errors", {}).values()) for r in runs)}
    drv, dec, ceil = sustained["driver"], sustained["decode_only"], sustained["transport_ceiling"]
    sustained["rate_ratio_vs_decode_only"] = _ratio(drv["samples_per_s"], dec["samples_per_s"])
    sustained["rate_ratio_vs_transport_ceiling"] = _ratio(drv["samples_per_s"], ceil["samples_per_s"])
    sustained["cpu_per_value_ratio_vs_decode_only"] = _ratio(drv["host_cpu_s_per_m_values"],
                                                             dec["host_cpu_s_per_m_values"])
    sustained["cpu_per_value_ratio_vs_transport_ceiling"] = _ratio(drv["host_cpu_s_per_m_values"],
                                                                   ceil["host_cpu_s_per_m_values"])
    sustained["no_loss"] = all(sustained[k]["gaps_all_runs"] == 0 and sustained[k]["link_errors_all_runs"] == 0
                               for k in ("driver", "decode_only"))
    sustained["realtime_margin_x"] = round(drv["samples_per_s"] / RATE_HZ, 2)  # sustained rate / 51.2 kHz
    result["sustained"] = sustained

    if args.realtime_s > 0:
        n_rt = round(args.realtime_s * RATE_HZ)
        realtime: dict[str, Any] = {"seconds": args.realtime_s}
        for name, run in (("decode_only", run_decode_only), ("driver", run_driver)):
            log.info("realtime %d Hz, %s: %.1f s", RATE_HZ, name, args.realtime_s)
            r = run(n_rt, timeout_s=args.realtime_s + 10.0, realtime=True, **kw)
            log.info("  %.0f samples/s, overrun %s, gaps %d, host CPU %.1f %%, device CPU %.1f %%", r["samples_per_s"],
                     r["overrun"], r["gaps"], r["host_cpu_pct"], r["device_cpu_pct"])
            realtime[name] = r
        realtime["host_cpu_ratio_vs_decode_only"] = _ratio(realtime["driver"]["host_cpu_pct"],
                                                           realtime["decode_only"]["host_cpu_pct"])
        realtime["no_loss"] = all(not realtime[k]["overrun"] and realtime[k]["gaps"] == 0
                                  for k in ("driver", "decode_only"))
        result["realtime"] = realtime
    else:
        result["realtime"] = None
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
