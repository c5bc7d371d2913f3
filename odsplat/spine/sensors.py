"""Where the sensors sit, given or corrected after the recording: `odsplat geometry CAPTURE FILE`.

An imported recording often comes without sensor positions; frequencies and damping need none, shapes need
them. A geometry file is TOML, one table per sensor, positions in metres in the capture's world frame (z up,
floor z = 0) and directions as an axis ("+X" .. "-Z") or a vector:

    [[sensors]]
    name = "acc"
    position_m = [0.25, 0.0, 0.01]
    direction = "+Z"

Only the capture's manifest changes (written atomically); the raw takes are never touched. The analysis
records the geometry it used, so `odsplat run` redoes the analysis after a change.
"""
from __future__ import annotations

import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from odsplat.spine.contract import digest
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture

AXES = {"+X": (1.0, 0.0, 0.0), "-X": (-1.0, 0.0, 0.0), "+Y": (0.0, 1.0, 0.0), "-Y": (0.0, -1.0, 0.0),
        "+Z": (0.0, 0.0, 1.0), "-Z": (0.0, 0.0, -1.0)}
PLACEABLE_KINDS = ("acceleration", "velocity", "displacement", "force")


@dataclass(frozen=True)
class Placement:
    """One sensor's position (m) and unit direction in the capture's world frame."""

    name: str
    position_m: tuple[float, float, float]
    direction: tuple[float, float, float]


def _triple(value: Any, where: str) -> tuple[float, float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise InputError(where, f"expected 3 numbers (x, y, z); got {value!r}")
    out = tuple(float(v) for v in value)
    if not all(math.isfinite(v) for v in out):
        raise InputError(where, f"expected finite numbers; got {value!r}")
    return out  # type: ignore[return-value]


def parse_direction(value: Any, where: str) -> tuple[float, float, float]:
    """An axis name ("+X" .. "-Z", sign optional) or a non-zero 3-vector, as a unit vector."""
    if isinstance(value, str):
        key = value.strip().upper()
        key = key if key[:1] in "+-" else "+" + key
        if key not in AXES:
            raise InputError(where, f"expected an axis ({', '.join(AXES)}) or 3 numbers; got {value!r}")
        return AXES[key]
    x, y, z = _triple(value, where)
    norm = math.sqrt(x * x + y * y + z * z)
    if not norm > 0:
        raise InputError(where, "expected a non-zero direction; got [0, 0, 0]")
    return x / norm, y / norm, z / norm


def read_geometry(path: str | Path) -> list[Placement]:
    """The placements in a geometry file, checked; one clear line names the file and field at fault."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "no such geometry file") from None
    except IsADirectoryError:
        raise InputError(path, "expected a geometry file (TOML), got a directory") from None
    except UnicodeDecodeError:
        raise InputError(path, "not a text file (expected TOML in UTF-8)") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(path, f"not valid TOML: {e}") from None
    unknown = set(doc) - {"sensors"}
    if unknown:
        raise InputError(path, f"unknown key(s) {sorted(unknown)}; expected [[sensors]] tables")
    tables = doc.get("sensors")
    if not isinstance(tables, list) or not tables:
        raise InputError(path, "expected one or more [[sensors]] tables (name, position_m, direction)")
    out, seen = [], set()
    for i, t in enumerate(tables):
        where = f"{path}: sensors[{i}]"
        if not isinstance(t, dict):
            raise InputError(where, "expected a table")
        extra = set(t) - {"name", "position_m", "direction"}
        if extra:
            raise InputError(where, f"unknown key(s) {sorted(extra)}; expected name, position_m, direction")
        name = t.get("name")
        if not isinstance(name, str) or not name:
            raise InputError(f"{where}.name", "expected the channel's name")
        if name in seen:
            raise InputError(f"{where}.name", f"{name!r} is placed twice")
        seen.add(name)
        for key in ("position_m", "direction"):
            if key not in t:
                raise InputError(f"{where}.{key}", "missing")
        out.append(Placement(name, _triple(t["position_m"], f"{where}.position_m"),
                             parse_direction(t["direction"], f"{where}.direction")))
    return out


def apply_geometry(capture: Capture, placements: Sequence[Placement], source: str | Path = "geometry") -> list[str]:
    """Set the placements in the capture's manifest (atomically); returns a line per channel that changed."""
    chans = {c.name: c for c in capture.manifest.channels}
    for p in placements:
        c = chans.get(p.name)
        if c is None:
            raise InputError(f"{source}: {p.name}", f"no such channel; the capture has {sorted(chans)}")
        if c.kind not in PLACEABLE_KINDS:
            raise InputError(f"{source}: {p.name}", f"a {c.kind} channel is not on the structure")
    changes = []
    for p in placements:
        c = chans[p.name]
        new_pos, new_dir = [float(v) for v in p.position_m], [float(v) for v in p.direction]
        if c.position_m == new_pos and c.direction == new_dir:
            continue
        was = "unplaced" if c.position_m is None else f"{_fmt(c.position_m)} m, {_fmt(c.direction or [])}"
        changes.append(f"{p.name}: {was} -> {_fmt(new_pos)} m, {_fmt(new_dir)}")
        c.position_m, c.direction = new_pos, new_dir
    if changes:
        capture.save_manifest()
    return changes


def geometry_identity(capture: Capture) -> str:
    """A hash of every channel's placement: what an analysis's shapes depend on."""
    return digest([[c.name, c.position_m, c.direction] for c in capture.manifest.channels])


def geometry_toml(capture: Capture) -> str:
    """The capture's sensor geometry as a geometry file, unplaced sensors commented out, to edit and apply."""
    lines = [f"# Sensor geometry of {capture.root.name}: positions in metres, world frame (z up, floor z = 0).",
             "# Edit, then apply with `odsplat geometry CAPTURE THIS_FILE`.", ""]
    for c in capture.manifest.channels:
        if c.kind not in PLACEABLE_KINDS:
            continue
        placed = c.position_m is not None and c.direction is not None
        pre = "" if placed else "# "
        lines += [f"{pre}[[sensors]]", f'{pre}name = "{c.name}"',
                  f"{pre}position_m = {_fmt(c.position_m or [0.0, 0.0, 0.0])}",
                  f"{pre}direction = {_fmt(c.direction or [0.0, 0.0, 1.0])}"
                  + ("" if placed else f"    # {c.kind}: not placed yet"), ""]
    return "\n".join(lines)


def _fmt(v: Sequence[float]) -> str:
    return "[" + ", ".join(f"{float(x):.6g}" for x in v) + "]"


__all__ = ["Placement", "apply_geometry", "geometry_identity", "geometry_toml", "parse_direction", "read_geometry"]
