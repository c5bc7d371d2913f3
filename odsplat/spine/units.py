"""Unit names accepted on input and their conversion to SI; unknown units are refused, never guessed."""
from __future__ import annotations

import numpy as np

from odsplat.spine.errors import InputError

STANDARD_GRAVITY_M_S2 = 9.80665

# SI unit name -> physical quantity, for the units odsplat stores.
SI_UNITS: dict[str, str] = {
    "N": "force",
    "m/s^2": "acceleration",
    "m/s": "velocity",
    "m": "displacement",
    "V": "voltage",
    "Pa": "pressure",
    "s": "time",
    "rad": "angle",
    "1": "dimensionless",
}

# Accepted spelling (compared case-sensitively first, then lower-cased) -> (SI unit, scale to SI).
_ALIASES: dict[str, tuple[str, float]] = {
    "N": ("N", 1.0), "newton": ("N", 1.0), "newtons": ("N", 1.0), "kN": ("N", 1e3), "lbf": ("N", 4.4482216152605),
    "m/s^2": ("m/s^2", 1.0), "m/s2": ("m/s^2", 1.0), "m/s**2": ("m/s^2", 1.0), "m s^-2": ("m/s^2", 1.0),
    "m/s²": ("m/s^2", 1.0), "mm/s^2": ("m/s^2", 1e-3), "g": ("m/s^2", STANDARD_GRAVITY_M_S2),
    "g0": ("m/s^2", STANDARD_GRAVITY_M_S2), "gn": ("m/s^2", STANDARD_GRAVITY_M_S2),
    "m/s": ("m/s", 1.0), "mm/s": ("m/s", 1e-3), "in/s": ("m/s", 0.0254),
    "m": ("m", 1.0), "mm": ("m", 1e-3), "um": ("m", 1e-6), "µm": ("m", 1e-6), "μm": ("m", 1e-6),
    "in": ("m", 0.0254),
    "V": ("V", 1.0), "volt": ("V", 1.0), "volts": ("V", 1.0), "mV": ("V", 1e-3),
    "Pa": ("Pa", 1.0), "kPa": ("Pa", 1e3),
    "s": ("s", 1.0), "sec": ("s", 1.0), "ms": ("s", 1e-3), "us": ("s", 1e-6), "µs": ("s", 1e-6),
    "rad": ("rad", 1.0), "deg": ("rad", np.pi / 180.0),
    "1": ("1", 1.0), "-": ("1", 1.0), "": ("1", 1.0),
}
_LOWER = {k.lower(): v for k, v in _ALIASES.items() if k.lower() not in ("mv",)}
_LOWER["mv"] = ("V", 1e-3)


def parse_unit(text: str, *, where: str) -> tuple[str, float]:
    """Return (SI unit, scale) for a unit spelling; `where` names the file or field for the error."""
    key = text.strip()
    if key in _ALIASES:
        return _ALIASES[key]
    if key.lower() in _LOWER:
        return _LOWER[key.lower()]
    raise InputError(
        where,
        f"unknown unit {text!r}; expected one of {', '.join(sorted(k for k in _ALIASES if k))}",
    )


def to_si(values: np.ndarray, unit: str, *, where: str) -> tuple[np.ndarray, str]:
    """Convert values from `unit` to SI, returning (values, SI unit name)."""
    si, scale = parse_unit(unit, where=where)
    values = np.asarray(values)
    return (values * scale if scale != 1.0 else values), si


def quantity_of(si_unit: str, *, where: str) -> str:
    """The physical quantity of an SI unit name that odsplat stores."""
    if si_unit not in SI_UNITS:
        raise InputError(where,
                         f"unit {si_unit!r} is not an SI unit odsplat stores; expected one of {sorted(SI_UNITS)}")
    return SI_UNITS[si_unit]
