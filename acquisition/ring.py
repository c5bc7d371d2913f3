"""A ring buffer of multichannel samples addressed by absolute sample index, shared by the DAQ and CAN drivers."""
from __future__ import annotations

import numpy as np

from odsplat.spine.errors import OdsplatError


class SampleRing:
    """The last `capacity` samples of every channel, addressed by absolute sample index; NaN where lost.

    Out-of-range reads raise `error` (the driver's own error class), naming `name`."""

    def __init__(self, n_channels: int, capacity: int, *, name: str, error: type[OdsplatError] = OdsplatError):
        self.capacity = capacity
        self.name = name
        self.error = error
        self.data = np.full((n_channels, capacity), np.nan, np.float32)
        self.stop = 0  # one past the newest sample written

    def write(self, first: int, values: np.ndarray | None, n: int) -> None:
        """Samples first..first+n-1, as (n_channels, n); None marks them lost (NaN). A write may fill in an
        older stretch (a gap reported after later data) but never moves `stop` back."""
        if n <= 0:
            return
        keep = min(n, self.capacity)  # only the newest `capacity` of a huge write survive
        first, skip = first + n - keep, n - keep
        pos = np.arange(first, first + keep) % self.capacity
        self.data[:, pos] = np.nan if values is None else values[:, skip:]
        self.stop = max(self.stop, first + keep)

    def read(self, first: int, stop: int) -> np.ndarray:
        """(n_channels, stop - first) float64."""
        if stop > self.stop:
            raise self.error(f"{self.name}: samples up to {stop} requested, only {self.stop} received")
        if first < self.stop - self.capacity:
            raise self.error(f"{self.name}: sample {first} has left the {self.capacity}-sample ring buffer "
                             f"(oldest {self.stop - self.capacity})")
        return self.data[:, np.arange(first, stop) % self.capacity].astype(np.float64)
