"""The hammer-threshold trigger: watch the force in the DAQ stream, keep a pretrigger, cut a record of fixed length."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from odsplat.spine.errors import InputError

from . import daqproto as dp
from .daq import DAQError, SerialDAQ

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HammerTrigger:
    """Trigger when `channel` rises through `level_n`; keep `pretrigger_s` before it, `record_s` in all."""

    channel: str = "force"
    level_n: float = 10.0
    pretrigger_s: float = 0.05
    record_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.level_n > 0:
            raise InputError("HammerTrigger.level_n", f"must be positive, got {self.level_n}")
        if not 0 <= self.pretrigger_s < self.record_s:
            raise InputError("HammerTrigger.pretrigger_s",
                             f"must lie in [0, record_s = {self.record_s:g} s), got {self.pretrigger_s}")

    def samples(self, sample_rate_hz: float) -> tuple[int, int]:
        """(pretrigger samples, record samples) at this rate."""
        return round(self.pretrigger_s * sample_rate_hz), round(self.record_s * sample_rate_hz)


def first_crossing(x: np.ndarray, level: float, *, previous: float = -np.inf) -> int | None:
    """Index of the first sample at or above `level` whose predecessor is below it (NaN counts as below).
    `previous` is the sample before x[0]."""
    above = np.nan_to_num(np.asarray(x, float), nan=-np.inf) >= level
    before = np.concatenate([[previous >= level], above[:-1]])
    hits = np.flatnonzero(above & ~before)
    return int(hits[0]) if hits.size else None


def lost_between(gaps: Iterable[dp.SampleGap], first: int, stop: int) -> int:
    """How many of samples first..stop-1 the gaps (each overlapping that range) lost."""
    return int(sum(min(g.stop, stop) - max(g.first_sample, first) for g in gaps))


@dataclass
class TriggeredRecord:
    """A record cut around a trigger: samples first_sample..stop_sample-1 of every DAQ channel, in SI units."""

    trigger_sample: int
    first_sample: int
    stop_sample: int
    sample_rate_hz: float
    channels: tuple[str, ...]
    data: np.ndarray                       # (n_channels, n), NaN where lost
    gaps: list[dp.SampleGap] = field(default_factory=list)

    @property
    def pretrigger_samples(self) -> int:
        return self.trigger_sample - self.first_sample

    @property
    def t0_s(self) -> float:
        """DAQ time (sample counter / rate) of the first sample."""
        return self.first_sample / self.sample_rate_hz

    @property
    def lost_samples(self) -> int:
        return lost_between(self.gaps, self.first_sample, self.stop_sample)

    def channel(self, name: str) -> np.ndarray:
        try:
            return self.data[self.channels.index(name)]
        except ValueError:
            raise InputError("record", f"no channel {name!r}; channels: {list(self.channels)}") from None


class NoTrigger(DAQError):
    """The force never crossed the trigger level in time; `lost_samples` were lost on the link while waiting (a
    hit there is never seen: the take counts as one with dropped samples)."""

    def __init__(self, message: str, lost_samples: int = 0):
        super().__init__(message)
        self.lost_samples = lost_samples


def wait_for_hit(daq: SerialDAQ, trigger: HammerTrigger, timeout_s: float, *, start_sample: int = 0,
                 on_trigger: Callable[[int], None] | None = None, poll_s: float = 0.02) -> TriggeredRecord:
    """Scan the stream from `start_sample` for the trigger, then wait for the whole record and cut it out.

    `on_trigger(sample)` runs as soon as the crossing is seen (e.g. a camera's software trigger). When the
    hit comes sooner after START than the pretrigger, the record starts at sample 0 and keeps less.
    """
    fs = daq.sample_rate_hz
    pre, length = trigger.samples(fs)
    k = daq.channel_index(trigger.channel)
    deadline = time.monotonic() + timeout_s
    pos, previous = start_sample, -np.inf
    crossing = None
    while crossing is None:
        if time.monotonic() > deadline:
            lost = lost_between(daq.gaps_in(start_sample, pos), start_sample, pos)
            why = f"; {lost} samples were lost on the link meanwhile: the hit may be among them" if lost else ""
            raise NoTrigger(f"{daq.name}: {trigger.channel!r} did not reach {trigger.level_n:g} N within "
                            f"{timeout_s:g} s{why}", lost)
        try:
            daq.wait_for(pos + 1, timeout_s=poll_s)
        except DAQError:
            if daq.error is not None:
                raise
            continue
        stop = daq.next_sample
        force = daq.read(pos, stop)[k]
        hit = first_crossing(force, trigger.level_n, previous=previous)
        if hit is not None:
            crossing = pos + hit
        else:
            previous = force[-1] if np.isfinite(force[-1]) else -np.inf
            pos = stop
    if on_trigger is not None:
        on_trigger(crossing)
    first = max(0, crossing - pre)
    stop = first + length if first > 0 else crossing - pre + length
    log.info("%s: trigger at sample %d (%.4f s); record %d..%d", daq.name, crossing, crossing / fs, first, stop)
    daq.wait_for(stop, timeout_s=max(1.0, deadline - time.monotonic() + trigger.record_s * 10))
    return TriggeredRecord(crossing, first, stop, fs, tuple(c.name for c in daq.channels), daq.read(first, stop),
                           daq.gaps_in(first, stop))
