"""Number checks for the settings dataclasses: finite, within its range, the field named, so that the command line,
`odsplat run --set` and the configuration file refuse the same nonsense (NaN, inf, 0 where a positive is needed)
with one line."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from numbers import Real
from typing import Any

from .errors import InputError


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
        parts = [f"> {self.above:g}" if self.above is not None else "",
                 f">= {self.at_least:g}" if self.at_least is not None else "",
                 f"< {self.below:g}" if self.below is not None else "",
                 f"<= {self.at_most:g}" if self.at_most is not None else ""]
        kind = "an integer" if self.integer else "a finite number"
        bounds = " and ".join(p for p in parts if p)
        return f"{kind} {bounds}".strip() + (" (or leave it out)" if self.optional else "")

    def holds(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
            return False
        if self.integer and value != int(value):
            return False
        return not ((self.above is not None and not value > self.above)
                    or (self.at_least is not None and not value >= self.at_least)
                    or (self.below is not None and not value < self.below)
                    or (self.at_most is not None and not value <= self.at_most))


POSITIVE = Range(above=0)
NON_NEGATIVE = Range(at_least=0)
FINITE = Range()
COUNT = Range(at_least=1, integer=True)
FRACTION = Range(at_least=0, at_most=1)


def check_number(where: str, value: Any, rule: Range = POSITIVE) -> None:
    """Refuse `value` unless it is a finite number within `rule` (None too, when the rule is optional)."""
    if value is None and rule.optional:
        return
    if not rule.holds(value):
        raise InputError(where, f"expected {rule.describe()}; got {value!r}")


def check_fields(settings: Any, rules: Mapping[str, Range], *, name: str | None = None) -> None:
    """Check the named fields of a settings dataclass, each against its range; a tuple or list field is checked
    element by element. Errors name the field as `Class.field` (or `name.field`)."""
    prefix = name or type(settings).__name__
    for field, rule in rules.items():
        value = getattr(settings, field)
        if isinstance(value, (tuple, list)):
            for i, v in enumerate(value):
                check_number(f"{prefix}.{field}[{i}]", v, rule)
        else:
            check_number(f"{prefix}.{field}", value, rule)


def maybe(rule: Range) -> Range:
    """The same range, with None allowed (a setting left automatic)."""
    return Range(rule.above, rule.at_least, rule.below, rule.at_most, rule.integer, optional=True)


__all__ = ["COUNT", "FINITE", "FRACTION", "NON_NEGATIVE", "POSITIVE", "Range", "check_fields", "check_number", "maybe"]
