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
from typing import Any

import can
import numpy as np

from odsplat.errors import InputError, OdsplatError

from . import canproto as cp
from .ring import SampleRing

log = logging.getLogger(__name__)


class CANError(OdsplatError):
    """A node went silent, or a read timed out."""


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
                silent = [t for t in self.reader.timeouts if t.node_id == node_id]
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
