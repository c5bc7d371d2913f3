"""Number checks for the settings dataclasses: finite, within its range, the field named, so that the command line,
`odsplat run --set` and the configuration file refuse the same nonsense (NaN, inf, 0 where a positive is needed,
1e12 where a hundred is plenty) with one line."""
from __future__ import annotations

import math
import reprlib
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from numbers import Real
from typing import Any

from odsplat.spine.errors import InputError


@dataclass(frozen=True)
class Range:
    """Where a number may lie: bounds open (`above`, `below`) or closed (`at_least`, `at_most`), always finite.
    `integer`: a whole number; `optional`: None is allowed (the setting left automatic)."""

    above: float | None = None
    at_least: float | None = None
    below: float | None = None
    at_most: float | None = None
    integer: bool = False
    optional: bool = False

    def describe(self) -> str:
        parts = [f"> {_number(self.above)}" if self.above is not None else "",
                 f">= {_number(self.at_least)}" if self.at_least is not None else "",
                 f"< {_number(self.below)}" if self.below is not None else "",
                 f"<= {_number(self.at_most)}" if self.at_most is not None else ""]
        kind = "an integer" if self.integer else "a finite number"
        bounds = " and ".join(p for p in parts if p)
        return f"{kind} {bounds}".strip() + (" (or leave it out)" if self.optional else "")

    def holds(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, Real):
            return False
        # math.isfinite would overflow on an int beyond a float's range: such an int is as good as infinite here.
        if not (abs(value) <= sys.float_info.max if isinstance(value, int) else math.isfinite(value)):
            return False
        if self.integer and value != int(value):
            return False
        return not ((self.above is not None and not value > self.above)
                    or (self.at_least is not None and not value >= self.at_least)
                    or (self.below is not None and not value < self.below)
                    or (self.at_most is not None and not value <= self.at_most))


def _number(x: float) -> str:
    """A bound as a person reads it: whole numbers in full (16777216, not 1.67772e+07), others with %g."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e12 else f"{x:g}"


# The upper bounds. No real test comes near them, but each stops a typo or a hostile value (1e12, 1e308) from
# becoming a MemoryError, an allocation failure inside OpenCV or a run that never ends. They are fixed numbers,
# not taken from the machine (its cores, its memory), so a configuration valid on one computer is valid on all.
MAX_WORKERS = 1024                        # processes or threads: more than the largest servers have cores
MAX_ITERATIONS = 1_000_000                # an optimiser's steps: the defaults are 150 to 2000
MAX_FRAMES = 100_000_000                  # a frame index or count: 100 s at a million frames/s
MAX_CHUNK_FRAMES = 1024                   # frames held in memory at a time (the defaults are 16 and 64)
MAX_WIDTH_PX = 16384                      # an image's width, trained or rendered
# The Nyquist frequencies of the fastest DAQ and camera a recording may have (io/limits.py; the spine's manifest
# imports this module, so it cannot import the io package, which imports the manifest).
MAX_FREQUENCY_HZ = 5e8                    # SAMPLE_RATE_HZ's top / 2
MAX_VIDEO_FREQUENCY_HZ = 5e7              # FRAME_RATE_HZ's top / 2
MAX_DURATION_S = 3600.0                   # a stretch of one take's record: impact responses last seconds
MAX_FORCE_N = 1e6                         # a force: the largest impact hammers reach about 100 kN
MAX_LENGTH_M = 1000.0                     # a length in the capture's world: cameras see a few metres
MAX_MAGNIFICATION = 1e4                   # motion magnification: far past where every method's output breaks up
MAX_ITEMS = 1000                          # values in a list of numbers (frequencies, ranks, views)

WORKERS = Range(at_least=1, at_most=MAX_WORKERS, integer=True)
ITERATIONS = Range(at_least=0, at_most=MAX_ITERATIONS, integer=True)
FRAME_INDEX = Range(at_least=0, at_most=MAX_FRAMES, integer=True)
CHUNK_FRAMES = Range(at_least=1, at_most=MAX_CHUNK_FRAMES, integer=True)
FREQUENCY_HZ = Range(above=0, at_most=MAX_FREQUENCY_HZ)
VIDEO_FREQUENCY_HZ = Range(above=0, at_most=MAX_VIDEO_FREQUENCY_HZ)
DURATION_S = Range(above=0, at_most=MAX_DURATION_S)
FORCE_N = Range(above=0, at_most=MAX_FORCE_N)
LENGTH_M = Range(above=0, at_most=MAX_LENGTH_M)
WIDTH_PX = Range(at_least=8, at_most=MAX_WIDTH_PX, integer=True)
# The 2D magnification of the motion (magnify's alpha, the flag, --set and odsplat.toml alike); render's 3D one
# takes 0 to the same top. At 1e4 every method's frames stay finite, in [0, 1] (tests/test_settings_abuse.py).
MAGNIFICATION = Range(above=0, at_most=MAX_MAGNIFICATION)
PLAYBACK_FPS = Range(at_least=0.1, at_most=1000)     # an mp4's playback rate, for a person to watch
SEED = Range(at_least=0, at_most=2**32 - 1, integer=True)   # what numpy and torch both take
LEARNING_RATE = Range(above=0, at_most=10)
WEIGHT = Range(at_least=0, at_most=1e6)              # a loss term's or a prior's weight, relative
NEIGHBOURS = Range(at_least=1, at_most=256, integer=True)   # k of a k-nearest-neighbour search
BLUR_PX = Range(at_least=0, at_most=100)             # a Gaussian blur's sd in pixels
RANK = Range(at_least=1, at_most=1024, integer=True)

POSITIVE = Range(above=0)
NON_NEGATIVE = Range(at_least=0)
FINITE = Range()
COUNT = Range(at_least=1, integer=True)
FRACTION = Range(at_least=0, at_most=1)


_SHOWN = reprlib.Repr()
_SHOWN.maxlevel, _SHOWN.maxstring, _SHOWN.maxother, _SHOWN.maxlist, _SHOWN.maxtuple, _SHOWN.maxdict = 3, 60, 60, 6, 6, 4


def shown(value: Any) -> str:
    """`value` as an error message quotes it: its repr, cut short. A hostile value may be a megabyte string, a list
    nested thousands deep or an integer of 5000 digits (whose repr Python refuses), and the message stays a line."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        digits = math.floor(value.bit_length() * math.log10(2)) + 1
        return f"{'a negative' if value < 0 else 'an'} integer of about {digits} digits"
    try:
        return _SHOWN.repr(value)
    except (ValueError, RecursionError):
        return f"a {type(value).__name__}"


def check_number(where: str, value: Any, rule: Range = POSITIVE) -> None:
    """Refuse `value` unless it is a finite number within `rule` (None too, when the rule is optional)."""
    if value is None and rule.optional:
        return
    if not rule.holds(value):
        raise InputError(where, f"expected {rule.describe()}; got {shown(value)}")


def check_fields(settings: Any, rules: Mapping[str, Range], *, name: str | None = None) -> None:
    """Check the named fields of a settings dataclass, each against its range; a tuple or list field is checked
    element by element, and may hold at most MAX_ITEMS. Errors name the field as `Class.field` (or `name.field`)."""
    prefix = name or type(settings).__name__
    for field, rule in rules.items():
        value = getattr(settings, field)
        if isinstance(value, (tuple, list)):
            if len(value) > MAX_ITEMS:
                raise InputError(f"{prefix}.{field}", f"expected at most {MAX_ITEMS} values; got {len(value)}")
            for i, v in enumerate(value):
                check_number(f"{prefix}.{field}[{i}]", v, rule)
        else:
            check_number(f"{prefix}.{field}", value, rule)


def check_choice(where: str, value: Any, choices: Iterable[str]) -> None:
    """Refuse `value` unless it is one of `choices` (a setting's enumerated strings)."""
    choices = tuple(choices)
    if not (isinstance(value, str) and value in choices):
        raise InputError(where, f"expected one of {', '.join(choices)}; got {shown(value)}")


def maybe(rule: Range) -> Range:
    """The same range, with None allowed (a setting left automatic)."""
    return Range(rule.above, rule.at_least, rule.below, rule.at_most, rule.integer, optional=True)


__all__ = ["BLUR_PX", "CHUNK_FRAMES", "COUNT", "DURATION_S", "FINITE", "FORCE_N", "FRACTION", "FRAME_INDEX",
           "FREQUENCY_HZ", "ITERATIONS", "LEARNING_RATE", "LENGTH_M", "MAGNIFICATION", "MAX_CHUNK_FRAMES",
           "MAX_DURATION_S", "MAX_FORCE_N", "MAX_FRAMES", "MAX_FREQUENCY_HZ", "MAX_ITEMS", "MAX_ITERATIONS",
           "MAX_LENGTH_M", "MAX_MAGNIFICATION", "MAX_VIDEO_FREQUENCY_HZ", "MAX_WIDTH_PX", "MAX_WORKERS", "NEIGHBOURS",
           "NON_NEGATIVE", "PLAYBACK_FPS", "POSITIVE", "RANK", "Range", "SEED", "VIDEO_FREQUENCY_HZ", "WEIGHT",
           "WIDTH_PX", "WORKERS", "check_choice", "check_fields", "check_number", "maybe", "shown"]
