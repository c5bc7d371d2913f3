"""Simulated CAN accelerometer nodes that speak odsplat's node protocol on any python-can bus,
with injectable faults and ground truth of every sample they lost."""
from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass
from typing import Iterator, Mapping, Protocol, Sequence

import can
import numpy as np

from odsplat.acquisition import canproto as cp

log = logging.getLogger(__name__)

_CHUNK = 64  # samples per source call; small enough that commands are answered within ~1 ms
_HEARTBEAT_S = 1.0  # NODE_STATUS period while running, in node time


class AccelSource(Protocol):
    """What a node measures. A source with its own clock (the rig, whose time is the DAQ's) also has
    `samples_available(node_id, sample_rate_hz) -> int`: how many samples of the node lie before its present;
    a `paced` node takes no more than that (its samples then never precede a hit scheduled later)."""

    def acceleration(self, node_id: int, start_sample: int, n: int, sample_rate_hz: float) -> np.ndarray:
        """(n, 3) m/s^2 in the node's axes for samples start_sample.., taken at sample_rate_hz (the node's true
        rate)."""


@dataclass(frozen=True)
class SineSource:
    """Ground-truth source: axis a of every node is amplitude * sin(2 pi freqs_hz[a] t + phase_rad * node_id)."""

    freqs_hz: tuple[float, float, float] = (31.0, 47.0, 73.0)
    amplitude_m_s2: float = 50.0
    phase_rad: float = 0.7

    def acceleration(self, node_id: int, start_sample: int, n: int, sample_rate_hz: float) -> np.ndarray:
        t = (start_sample + np.arange(n))[:, None] / sample_rate_hz
        return self.amplitude_m_s2 * np.sin(2 * np.pi * np.asarray(self.freqs_hz) * t + self.phase_rad * node_id)


@dataclass(frozen=True)
class CANFaults:
    """Faults a node injects. Sample s is the (s+1)-th data frame, so `every k` hits samples k-1, 2k-1, ..."""

    drop_every: int | None = None  # the frame is never sent (e.g. lost to a full transmit queue)
    drop_frames: Sequence[int] = ()  # sample numbers never sent
    drop_probability: float = 0.0  # random drops, seeded
    error_frame_every: int | None = None  # an error frame replaces the data frame: a bit error, the sample is lost
    clock_drift_ppm: float = 0.0  # the true rate is nominal * (1 + ppm 1e-6); the node does not know
    disconnect_after_samples: int | None = None  # silent (no frames, no replies) from this sample on
    seed: int = 0


class SimAccelNode:
    """One node: a daemon thread answers NODE_CMD and, while running, sends one ACC_DATA frame per sample.
    Give each node its own bus instance, as each real node has its own CAN controller. `paced`: the node keeps
    to its source's clock (`samples_available`), as nodes on the rig beside the DAQ must."""

    def __init__(self, bus: can.BusABC, node_id: int, source: AccelSource, *, sample_rate_hz: float = 1000.0,
                 range_m_s2: float = 156.9, realtime: bool = False, faults: CANFaults = CANFaults(),
                 firmware: tuple[int, int] = (1, 0), paced: bool = False):
        self._bus, self.node_id, self._source = bus, cp.check_node_id(node_id), source
        self._rate, self._range = cp.rate_code(sample_rate_hz), cp.range_code(range_m_s2)  # power-on settings
        self._realtime, self.faults, self.firmware = realtime, faults, firmware
        self._available = source.samples_available if paced else None
        self._rng = np.random.default_rng(faults.seed)
        self._drop = frozenset(faults.drop_frames)
        self.state = cp.NodeState.IDLE
        self._next = 0  # index of the next sample to take
        self._t0 = 0.0
        self._overrun = self._clipping = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # Ground truth, for tests: what the node did, not what the host saw.
        self.sent_samples = 0
        self.dropped_samples: list[int] = []
        self.error_samples: list[int] = []
        self.overrun_samples: list[int] = []
        self.clipped_samples = 0
        self.silent_since_s: float | None = None  # time.monotonic() when it went silent

    @property
    def sample_rate_hz(self) -> float:
        return cp.SAMPLE_RATES_HZ[self._rate]

    @property
    def true_rate_hz(self) -> float:
        return self.sample_rate_hz * (1 + self.faults.clock_drift_ppm * 1e-6)

    @property
    def range_m_s2(self) -> float:
        return cp.RANGES_M_S2[self._range]

    @property
    def samples_taken(self) -> int:
        return self._next

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"sim-can-node-{self.node_id}", daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("sim CAN node %d did not stop within %g s", self.node_id, timeout_s)
            self._thread = None

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                streaming = self.state is cp.NodeState.RUNNING and self.silent_since_s is None
                self._poll(0.0 if streaming else 0.01)
                if streaming:
                    self._stream()
                    # Hand over the GIL: flooding nodes otherwise starve one another for ~0.4 s, a false timeout.
                    time.sleep(0)
        except Exception:  # a dead node must show in the log, the host sees only silence
            log.exception("sim CAN node %d crashed", self.node_id)

    def _poll(self, wait_s: float) -> None:
        # Drain the whole queue (other nodes' data lands here too on a shared bus); wait only for the first frame.
        msg = self._bus.recv(timeout=wait_s)
        while msg is not None and not self._stop.is_set():
            if self.silent_since_s is None:
                self._on_frame(msg)
            msg = self._bus.recv(timeout=0.0)

    def _on_frame(self, msg: can.Message) -> None:
        if (msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id
                or msg.arbitration_id not in (cp.NODE_CMD_BASE, cp.NODE_CMD_BASE + self.node_id)):
            return
        try:
            _, command, rate, range_ = cp.decode_command(msg)
        except Exception:  # a malformed command is ignored, as firmware would
            log.debug("sim CAN node %d ignored %s", self.node_id, msg)
            return
        if command == cp.Command.START:
            if rate in cp.SAMPLE_RATES_HZ and range_ in cp.RANGES_M_S2:
                self._rate, self._range = rate, range_
                self.state, self._next, self._t0 = cp.NodeState.RUNNING, 0, time.monotonic()
                self._overrun = self._clipping = False
            else:
                self.state = cp.NodeState.FAULT
        elif command == cp.Command.STOP:
            self.state = cp.NodeState.IDLE
        self._send_status(ack=True)

    def _stream(self) -> None:
        n = _CHUNK
        if self._available is not None:
            n = min(n, self._available(self.node_id, self.true_rate_hz) - self._next)
            if n <= 0:
                self._stop.wait(0.001)
                return
        if self._realtime:
            n = min(n, int((time.monotonic() - self._t0) * self.true_rate_hz) + 1 - self._next)
            if n <= 0:
                self._stop.wait(0.0005)
                return
        f = self.faults
        if f.disconnect_after_samples is not None:
            n = min(n, f.disconnect_after_samples - self._next)
            if n <= 0:
                self.silent_since_s = time.monotonic()
                log.info("sim CAN node %d goes silent at sample %d", self.node_id, self._next)
                return
        first = self._next
        counts, clipped = cp.to_counts(self._source.acceleration(self.node_id, first, n, self.true_rate_hz),
                                       self.range_m_s2)
        heartbeat = max(1, round(_HEARTBEAT_S * self.sample_rate_hz))
        for i, frame in enumerate(cp.acc_data_frames(self.node_id, first, counts)):
            s = first + i
            flag_raised = False
            if clipped[i].any():
                self.clipped_samples += 1
                flag_raised, self._clipping = not self._clipping, True
            if f.error_frame_every and (s + 1) % f.error_frame_every == 0:
                self.error_samples.append(s)
                self._send(cp.error_frame(), s)
            elif (s in self._drop or (f.drop_every and (s + 1) % f.drop_every == 0)
                  or (f.drop_probability and self._rng.random() < f.drop_probability)):
                self.dropped_samples.append(s)
            elif self._send(frame, s):
                self.sent_samples += 1
            self._next = s + 1
            if flag_raised or self._next % heartbeat == 0:
                self._send_status(ack=False)

    def _send(self, msg: can.Message, sample: int | None = None) -> bool:
        try:
            self._bus.send(msg, timeout=0.01)
            return True
        except can.CanError:
            # A full transmit queue: the sample is gone, as on a real node, and the host is told by a flag.
            if sample is not None:
                self.overrun_samples.append(sample)
            flag_raised, self._overrun = not self._overrun, True
            if flag_raised and sample is not None:
                self._send_status(ack=False)
            return False

    def _send_status(self, *, ack: bool) -> None:
        self._send(cp.status_frame(cp.NodeStatus(
            self.node_id, self.state, self.sample_rate_hz, self.range_m_s2, self._overrun, self._clipping,
            ack, self.firmware, self._next & 0xFFFF)))


@contextlib.contextmanager
def sim_nodes(channel: str, node_ids: Sequence[int], source: AccelSource, *, interface: str = "virtual",
              faults: Mapping[int, CANFaults] | None = None, **node_kw) -> Iterator[list[SimAccelNode]]:
    """Running nodes, each on its own bus instance of `channel`; stops them and closes their buses on exit."""
    buses: list[can.BusABC] = []
    nodes: list[SimAccelNode] = []
    try:
        for node_id in node_ids:
            buses.append(can.Bus(interface=interface, channel=channel))
            nodes.append(SimAccelNode(buses[-1], node_id, source, faults=(faults or {}).get(node_id, CANFaults()),
                                      **node_kw))
            nodes[-1].start()
        yield nodes
    finally:
        for node in nodes:
            node.stop()
        for bus in buses:
            bus.shutdown()
