"""The bounds a recording's rates must lie within, checked wherever a rate enters (a file's header or the rig)."""
from __future__ import annotations

import math

from odsplat.spine.errors import InputError

# Wide enough for a time-lapse of a slow test and the fastest cameras and DAQs made, narrow enough that a garbled
# header (1e-300, 1e308, nan) is refused rather than turned into frame times of 0 or inf.
FRAME_RATE_HZ = (1e-3, 1e8)
SAMPLE_RATE_HZ = (1.0, 1e9)


def check_rate(value: float, where: str, bounds: tuple[float, float], what: str, unit: str) -> float:
    """`value` as a float, refused naming `where` unless finite and within `bounds` (inclusive)."""
    low, high = bounds
    try:
        rate = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"expected a {what} in {unit}; got {value!r}") from None
    if not (math.isfinite(rate) and low <= rate <= high):
        raise InputError(where, f"{rate:.6g} is not a {what} from {low:g} to {high:g} {unit}")
    return rate


def check_frame_rate(value: float, where: str) -> float:
    return check_rate(value, where, FRAME_RATE_HZ, "frame rate", "fps")


def check_sample_rate(value: float, where: str) -> float:
    return check_rate(value, where, SAMPLE_RATE_HZ, "sample rate", "Hz")
