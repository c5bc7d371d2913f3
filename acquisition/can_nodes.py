"""The CAN accelerometer driver: starts nodes on any python-can bus and streams them into per-node ring buffers.

Frames are decoded through odsplat.acquisition.canproto (DBC for cantools). Timestamps come from each node's sample
counter (sample / nominal rate, on the node's clock); gaps, error frames and silent nodes are reported and
lost samples stay NaN.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.manifest import ChannelInfo, can_source

from . import canproto as cp
from .ring import SampleRing

log = logging.getLogger(__name__)


class CANError(OdsplatError):
    """A node went silent, or a read timed out."""


AXES = ("x", "y", "z")


@dataclass(frozen=True)
class CANNode:
    """A triaxial accelerometer node as mounted, and where its sample 0 falls on the DAQ's time base.

    Protocol 1 carries no time stamp shared with the DAQ: `t0_daq_s` is what the bench knows of it (its nodes'
    sampling starts with the DAQ's, or the delay was measured). A node's sample k is at DAQ time
    `t0_daq_s + k / sample_rate_hz`; the take file stores these times beside the samples."""

    node_id: int
    position_m: tuple[float, float, float] | None = None
    axes: tuple[tuple[float, float, float], ...] | None = None  # rows: the node's x, y, z axes in world coordinates
    t0_daq_s: float = 0.0

    def __post_init__(self) -> None:
        if self.node_id not in cp.NODE_IDS:
            raise InputError(f"CAN node {self.node_id}", f"unknown to {cp.DBC_RESOURCE}, which defines nodes "
                             f"{cp.NODE_IDS.start}..{cp.NODE_IDS.stop - 1}")
        if self.position_m is not None and len(self.position_m) != 3:
            raise InputError(f"CAN node {self.node_id}.position_m", f"expected 3 numbers; got {self.position_m!r}")
        if self.axes is not None:
            a = np.asarray(self.axes, float)
            if a.shape != (3, 3) or not np.allclose(a @ a.T, np.eye(3), atol=1e-6):
                raise InputError(f"CAN node {self.node_id}.axes", f"expected 3 orthonormal rows; got {self.axes!r}")
        if not np.isfinite(self.t0_daq_s):
            raise InputError(f"CAN node {self.node_id}.t0_daq_s", f"expected a time in s; got {self.t0_daq_s!r}")

    @property
    def name(self) -> str:
        """Its group in a take file and the stem of its channels' names: node1 -> node1_x, node1_y, node1_z."""
        return f"node{self.node_id}"

    def channels(self, sample_rate_hz: float) -> list[ChannelInfo]:
        """Its three axes as the manifest lists them (source "can:NODE", at the node's own rate)."""
        return [ChannelInfo(f"{self.name}_{axis}", "acceleration", "m/s^2",
                            position_m=None if self.position_m is None else [float(v) for v in self.position_m],
                            direction=None if self.axes is None else [float(v) for v in self.axes[i]],
                            node=self.node_id, device="can", source=can_source(self.name),
                            sample_rate_hz=float(sample_rate_hz))
                for i, axis in enumerate(AXES)]


@dataclass(frozen=True)
class CANSetup:
    """The CAN accelerometer nodes a session records into every take, and how."""

    nodes: tuple[CANNode, ...]
    sample_rate_hz: float = 1000.0
    range_m_s2: float = cp.RANGES_M_S2[4]       # +-50 g: a node near the hammer sees tens of g
    margin_samples: int = 32                    # kept beyond the DAQ's record at each end: the resampling kernel's
                                                # reach (odsplat.spine.timebase), so the whole record is band-limited
    timeout_s: float = 5.0                      # for the last samples of a take to arrive

    def __post_init__(self) -> None:
        if not self.nodes:
            raise InputError("CANSetup.nodes", "no CAN node given")
        ids = [n.node_id for n in self.nodes]
        if len(set(ids)) != len(ids):
            raise InputError("CANSetup.nodes", f"node ids must be distinct; got {ids}")
        try:
            cp.rate_code(self.sample_rate_hz)
        except InputError as e:
            raise InputError("CANSetup.sample_rate_hz", e.problem) from None
        try:
            cp.range_code(self.range_m_s2)
        except InputError as e:
            raise InputError("CANSetup.range_m_s2", e.problem) from None
        if self.margin_samples < 0:
            raise InputError("CANSetup.margin_samples", f"expected >= 0; got {self.margin_samples}")

    def channels(self) -> list[ChannelInfo]:
        return [c for n in self.nodes for c in n.channels(self.sample_rate_hz)]


class CANAccelerometers:
    """Triaxial nodes on one bus, read by a background thread into ring buffers of `buffer_s`."""

    def __init__(self, bus: can.BusABC, node_ids: Iterable[int], *, sample_rate_hz: float = 1000.0,
                 range_m_s2: float = cp.RANGES_M_S2[3], buffer_s: float = 30.0, node_timeout_s: float = 0.5,
                 name: str | None = None):
        self.bus = bus
        self.name = name or f"CAN {getattr(bus, 'channel_info', 'bus')}"
        self.node_ids = tuple(cp.check_node_id(n) for n in node_ids)
        if not self.node_ids:
            raise InputError(self.name, "no CAN nodes configured")
        self.sample_rate_hz = cp.SAMPLE_RATES_HZ[cp.rate_code(sample_rate_hz)]
        self.range_m_s2 = cp.RANGES_M_S2[cp.range_code(range_m_s2)]
        self.capacity = max(256, int(buffer_s * self.sample_rate_hz))
        self.reader = cp.AccelNodeReader(bus, node_timeout_s=node_timeout_s)
        self._rings = self._new_rings()
        self._gaps_seen = 0
        self._timeouts_seen = 0  # timeouts of earlier runs do not fail this one's waits
        self._cond = threading.Condition()
        self._running = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: Exception | None = None

    @classmethod
    def open(cls, node_ids: Iterable[int], *, interface: str | None = None, channel: Any = None,
             config: Mapping[str, Any] | None = None, **kw) -> CANAccelerometers:
        """Open the bus the configuration names (python-can's own config when it names none)."""
        bus = cp.open_bus(interface, channel, config=config)
        return cls(bus, node_ids, name=f"CAN {interface or '$CAN_INTERFACE'}:{channel}", **kw)

    def start(self) -> None:
        """START every node (each confirms or the call names the silent one), then stream in the background."""
        with self._cond:
            self._rings = self._new_rings()
            self._gaps_seen = len(self.reader.gaps)
            self._timeouts_seen = len(self.reader.timeouts)
        self.reader.start(self.node_ids, self.sample_rate_hz, self.range_m_s2)
        self._running.set()
        self._thread = threading.Thread(target=self._run, name=f"can reader {self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self.reader.stop()
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _run(self) -> None:
        try:
            while self._running.is_set():
                blocks = self.reader.read(0.02)
                with self._cond:
                    for b in blocks:
                        self._write(b.node_id, b.first_sample, b.samples)
                    for gap in self.reader.gaps[self._gaps_seen:]:
                        self._note_gap(gap)
                    self._gaps_seen = len(self.reader.gaps)
                    self._cond.notify_all()
        except Exception as e:  # the bus failed: report it to whoever waits
            log.exception("%s: reader failed", self.name)
            with self._cond:
                self.error = CANError(f"{self.name}: reader failed: {e}")
                self._cond.notify_all()

    def _new_rings(self) -> dict[int, SampleRing]:
        return {n: SampleRing(3, self.capacity, name=f"{self.name}: node {n}", error=CANError) for n in self.node_ids}

    def _write(self, node: int, first: int, samples: np.ndarray) -> None:
        if node in self._rings:
            self._rings[node].write(first, samples.T, len(samples))

    def _note_gap(self, gap: cp.Gap) -> None:
        if gap.node_id in self._rings:  # a lost sample is NaN, never what the ring held before
            self._rings[gap.node_id].write(gap.first_sample, None, gap.n_lost)

    # ------------------------------------------------------------------------------ data

    @property
    def gaps(self) -> list[cp.Gap]:
        return list(self.reader.gaps)

    @property
    def timeouts(self) -> list[cp.NodeTimeout]:
        return list(self.reader.timeouts)

    def next_sample(self, node_id: int) -> int:
        with self._cond:
            return self._rings[node_id].stop

    def clipping(self, node_id: int) -> bool:
        status = self.reader.status.get(node_id)
        return bool(status and status.clipping)

    def wait_for(self, node_id: int, sample: int, timeout_s: float) -> None:
        """Block until the node's samples before `sample` are in; a silent node raises CANError naming it."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._rings[node_id].stop < sample:
                if self.error is not None:
                    raise self.error
                silent = [t for t in self.reader.timeouts[self._timeouts_seen:] if t.node_id == node_id]
                if silent:
                    raise CANError(f"{self.name}: node {node_id} went silent at sample {silent[0].next_sample}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise CANError(f"{self.name}: node {node_id} sample {sample} not received within {timeout_s:g} s "
                                   f"(have {self._rings[node_id].stop})")
                self._cond.wait(min(left, 0.1))

    def read(self, node_id: int, first: int, stop: int) -> np.ndarray:
        """(stop - first, 3) m/s^2 along the node's axes; NaN where samples were lost."""
        with self._cond:
            return self._rings[node_id].read(first, stop).T

    def times_s(self, first: int, stop: int) -> np.ndarray:
        """Node-clock times of samples first..stop-1 (sample / nominal rate)."""
        return np.arange(first, stop) / self.sample_rate_hz


@dataclass(frozen=True)
class CANRecord:
    """One node's samples for a take: those covering the DAQ's record and `CANSetup.margin_samples` either side."""

    node: CANNode
    first_sample: int
    sample_rate_hz: float
    times_s: np.ndarray      # (n,) DAQ time base: t0_daq_s + sample / sample_rate_hz
    values: np.ndarray       # (n, 3) m/s^2 along the node's x, y, z; NaN where lost or never received
    problem: str | None = None  # why samples are missing (a silent node, a timeout), None when complete

    @property
    def lost_samples(self) -> int:
        return int(np.isnan(self.values).any(axis=1).sum())

    def block(self) -> dict[str, np.ndarray]:
        """The values by channel name (node1_x, ...), as the take file stores them."""
        return {f"{self.node.name}_{axis}": self.values[:, i] for i, axis in enumerate(AXES)}


def record_window(acc: CANAccelerometers, setup: CANSetup, t_first_s: float, t_stop_s: float, *,
                  wait: bool = True) -> list[CANRecord]:
    """Every node's samples from DAQ time `t_first_s` to `t_stop_s` (the DAQ's record), with the setup's margin
    either side; waits for them unless `wait` is False (a salvaged take). Samples that never came stay NaN."""
    rate = acc.sample_rate_hz
    out = []
    for node in setup.nodes:
        first = max(0, int(np.floor((t_first_s - node.t0_daq_s) * rate)) - setup.margin_samples)
        stop = max(first, int(np.ceil((t_stop_s - node.t0_daq_s) * rate)) + 1 + setup.margin_samples)
        problem = None
        if wait:
            try:
                acc.wait_for(node.node_id, stop, setup.timeout_s)
            except CANError as e:
                problem = str(e)
                log.error("%s", e)
        have = min(stop, acc.next_sample(node.node_id))
        values = np.full((stop - first, 3), np.nan)
        if have > first:
            try:
                values[:have - first] = acc.read(node.node_id, first, have)
            except CANError as e:  # the samples have left the ring: nothing to keep
                problem = str(e)
                log.error("%s", e)
        if problem is None and have < stop:
            problem = f"{acc.name}: node {node.node_id}: samples {have}..{stop - 1} not received"
        times = node.t0_daq_s + np.arange(first, stop) / rate
        out.append(CANRecord(node, first, rate, times, values, problem))
    return out
