"""The capture manifest (`capture.json`): the rig, the viewpoint plan and the list of takes."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import stat
import tomllib
import types
import typing
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine.checks import shown
from odsplat.spine.errors import InputError, SchemaError
from odsplat.spine.units import SI_UNITS

# 1.1: channels carry `source` ("daq" or "can:NODE") and a CAN channel its own `sample_rate_hz`; take files may hold
# /can/NODE groups. A 1.0 file is read as before (every channel from the DAQ).
SCHEMA_VERSION = "1.1"
SCHEMA_MAJOR = 1

CHANNEL_KINDS: dict[str, str] = {
    "force": "N",
    "acceleration": "m/s^2",
    "velocity": "m/s",
    "displacement": "m",
    "ttl": "V",
    "voltage": "V",
    "pressure": "Pa",
}
TAKE_STATUSES = ("complete", "recovered")
QC_STATUSES = ("unchecked", "accepted", "rejected")

NAME_MAX_CHARS = 100  # a take's name is a file name (takes/NAME.h5) on every file system we meet
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]*")


def check_name(value: str, where: str) -> str:
    """A name that becomes a file name inside a capture (a take's `takes/NAME.h5`): letters, digits, `_`, `-` and
    `.`, not starting with `.` or `-`, at most NAME_MAX_CHARS characters; so it names no other folder, no hidden
    file, and nothing outside the capture. Returns it."""
    if not isinstance(value, str) or not value:
        raise InputError(where, f"expected a non-empty name; got {value!r}")
    if len(value) > NAME_MAX_CHARS:
        raise InputError(where, f"{len(value)} characters; a name has at most {NAME_MAX_CHARS}")
    if not _NAME.fullmatch(value):
        raise InputError(where, f"{value!r}: a name holds only letters, digits, '_', '-' and '.' (no separator, "
                                "space or control character) and starts with a letter, digit or '_'")
    return value


def check_regular_file(path: str | os.PathLike, what: str = "file") -> Path:
    """Refuse, before opening it, anything that is not a regular file (a folder, a FIFO that would block the read,
    a device); symbolic links are followed. Returns the path."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror})") from None
    if not stat.S_ISREG(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "not a regular file"
        raise InputError(path, f"is {kind}; expected a {what}")
    return path


def _finite(values: Any, where: str, *, positive: bool = False) -> None:
    """Each of `values` (a number or a list of them) finite, and above 0 where `positive`."""
    for v in values if isinstance(values, (list, tuple)) else [values]:
        if v is None:
            continue
        if not math.isfinite(v) or (positive and not v > 0):
            raise InputError(where, f"expected {'a positive' if positive else 'a finite'} number; got {values!r}")


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def check_schema(version: Any, *, where: str) -> None:
    """Refuse a schema version whose major number this odsplat does not know."""
    try:
        major = int(str(version).split(".")[0])
    except ValueError:
        raise SchemaError(where, f"schema version {version!r} is not of the form MAJOR.MINOR") from None
    if major != SCHEMA_MAJOR:
        raise SchemaError(
            where,
            f"schema version {version} has major {major}; this odsplat reads major {SCHEMA_MAJOR} only "
            f"({'upgrade odsplat' if major > SCHEMA_MAJOR else 'convert the file'})",
        )


@dataclass
class Intrinsics:
    """Pinhole intrinsics in pixels, with OpenCV's distortion vector (k1, k2, p1, p2[, k3...])."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist: list[float] = field(default_factory=list)

    @classmethod
    def from_matrix(cls, K, dist=()) -> Intrinsics:
        """From a 3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), [float(d) for d in dist])

    def validate(self, where: str) -> None:
        for name in ("fx_px", "fy_px", "cx_px", "cy_px", "dist"):
            _finite(getattr(self, name), f"{where}.{name}", positive=name in ("fx_px", "fy_px"))

    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])


@dataclass
class CameraInfo:
    model: str = "unknown"
    width_px: int | None = None
    height_px: int | None = None
    fps: float | None = None
    bit_depth: int | None = None
    n_colors: int = 1
    exposure_s: float | None = None
    intrinsics: Intrinsics | None = None


DAQ_SOURCE = "daq"
CAN_SOURCE_PREFIX = "can:"


def can_source(node: str) -> str:
    """The `source` of a channel recorded by CAN node `node` (its group name in a take file, e.g. "node1")."""
    return CAN_SOURCE_PREFIX + node


@dataclass
class ChannelInfo:
    """One measured channel; `position_m` and `direction` place the sensor on the structure (world frame).

    `source` says where its samples come from: "daq" (the DAQ, at the capture's `daq_sample_rate_hz`) or
    "can:NODE" (a CAN accelerometer node, at its own `sample_rate_hz`, stored in the take's /can/NODE group)."""

    name: str
    kind: str
    unit: str
    sensitivity_v_per_unit: float | None = None
    position_m: list[float] | None = None
    direction: list[float] | None = None
    node: int | None = None
    device: str = ""
    source: str = DAQ_SOURCE
    sample_rate_hz: float | None = None  # a CAN channel's own rate; None for a DAQ channel (the DAQ's rate)

    @property
    def can_node(self) -> str | None:
        """The CAN node group this channel is stored in, or None for a DAQ channel."""
        return self.source[len(CAN_SOURCE_PREFIX):] if self.source.startswith(CAN_SOURCE_PREFIX) else None

    def validate(self, where: str) -> None:
        if not self.name or "/" in self.name or "\0" in self.name or self.name in (".", ".."):
            raise InputError(where, f"channel name {self.name!r} must be non-empty, contain no '/' or NUL and not be "
                                    "'.' or '..' (it names the channel's data in the take file)")
        node = self.can_node
        if self.source != DAQ_SOURCE and (not node or "/" in node):
            raise InputError(f"{where}.source", f"expected 'daq' or 'can:NODE' (NODE without '/'); got {self.source!r}")
        if node is None and self.sample_rate_hz is not None:
            raise InputError(f"{where}.sample_rate_hz",
                             "a DAQ channel is sampled at the capture's daq_sample_rate_hz; leave it out")
        if node is not None and not (self.sample_rate_hz is not None and np.isfinite(self.sample_rate_hz)
                                     and self.sample_rate_hz > 0):
            raise InputError(f"{where}.sample_rate_hz",
                             f"a CAN channel needs its node's sample rate (> 0 Hz); got {self.sample_rate_hz!r}")
        if self.kind not in CHANNEL_KINDS:
            raise InputError(f"{where}.kind", f"expected one of {', '.join(CHANNEL_KINDS)}; got {self.kind!r}")
        if self.unit not in SI_UNITS:
            raise InputError(f"{where}.unit", f"expected an SI unit ({', '.join(SI_UNITS)}); got {self.unit!r}")
        if self.unit != CHANNEL_KINDS[self.kind]:
            raise InputError(f"{where}.unit",
                             f"a {self.kind} channel is stored in {CHANNEL_KINDS[self.kind]}, got {self.unit!r}")
        for name in ("position_m", "direction"):
            value = getattr(self, name)
            if value is not None and len(value) != 3:
                raise InputError(f"{where}.{name}", f"expected 3 numbers (x, y, z); got {value!r}")
            _finite(value, f"{where}.{name}")
        if self.direction is not None and not any(self.direction):
            raise InputError(f"{where}.direction", "expected a non-zero direction; got [0, 0, 0]")
        _finite(self.sensitivity_v_per_unit, f"{where}.sensitivity_v_per_unit", positive=True)


@dataclass
class TagPlacement:
    """A tag's four corners in world coordinates, in the normalised corner order (see sync docs)."""

    id: int
    corners_m: list[list[float]]
    on_structure: bool = False
    size_m: float | None = None  # side of the black square; TagLayout.size_m when None


@dataclass
class TagLayout:
    family: str = "tag36h11"
    size_m: float | None = None
    tags: list[TagPlacement] = field(default_factory=list)

    def validate(self, where: str) -> None:
        _finite(self.size_m, f"{where}.size_m", positive=True)
        for i, tag in enumerate(self.tags):
            at = f"{where}.tags[{i}]"
            if tag.id < 0:
                raise InputError(f"{at}.id", f"expected a tag id of 0 or more; got {tag.id}")
            if len(tag.corners_m) != 4 or any(len(c) != 3 for c in tag.corners_m):
                raise InputError(f"{at}.corners_m", f"expected 4 corners of 3 numbers (x, y, z); got {tag.corners_m!r}")
            _finite([v for c in tag.corners_m for v in c], f"{at}.corners_m")
            _finite(tag.size_m, f"{at}.size_m", positive=True)


@dataclass
class Viewpoint:
    index: int
    azimuth_deg: float
    elevation_deg: float
    distance_m: float
    target_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])

    def validate(self, where: str) -> None:
        if self.index < 0:
            raise InputError(f"{where}.index", f"expected a viewpoint index of 0 or more; got {self.index}")
        for name in ("azimuth_deg", "elevation_deg", "distance_m"):
            _finite(getattr(self, name), f"{where}.{name}", positive=name == "distance_m")
        if len(self.target_m) != 3:
            raise InputError(f"{where}.target_m", f"expected 3 numbers (x, y, z); got {self.target_m!r}")
        _finite(self.target_m, f"{where}.target_m")


@dataclass
class TakeRecord:
    """A finalised take file under `takes/`, as listed in the manifest."""

    name: str
    file: str
    view: int | None = None
    status: str = "complete"
    qc: str = "unchecked"
    n_frames: int = 0
    n_samples: int = 0
    created_utc: str = ""


@dataclass
class Manifest:
    name: str
    camera: CameraInfo = field(default_factory=CameraInfo)
    daq_sample_rate_hz: float | None = None
    channels: list[ChannelInfo] = field(default_factory=list)
    tags: TagLayout | None = None
    views: list[Viewpoint] = field(default_factory=list)
    takes: list[TakeRecord] = field(default_factory=list)
    structure: dict[str, Any] = field(default_factory=dict)
    notes: str = ""
    created_utc: str = field(default_factory=utc_now)
    schema_version: str = SCHEMA_VERSION
    capture_id: str = ""  # set when the capture is created; recorded in every derived file

    @property
    def has_force(self) -> bool:
        """Whether the capture records a force channel: the hammer's input-output path; without one, a video is
        analysed from its motion alone (the analysis's 2D path)."""
        return any(c.kind == "force" for c in self.channels)

    def validate(self, where: str = "capture.json") -> None:
        names = [c.name for c in self.channels]
        for i, ch in enumerate(self.channels):
            ch.validate(f"{where}: channels[{i}]")
        if self.camera.intrinsics is not None:
            self.camera.intrinsics.validate(f"{where}: camera.intrinsics")
        if self.tags is not None:
            self.tags.validate(f"{where}: tags")
        for i, view in enumerate(self.views):
            view.validate(f"{where}: views[{i}]")
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise InputError(f"{where}: channels", f"duplicate channel names {sorted(dup)}")
        for i, take in enumerate(self.takes):
            check_name(take.name, f"{where}: takes[{i}].name")   # names become file names: checked on every load
            if take.file != f"takes/{take.name}.h5":
                raise InputError(f"{where}: takes[{i}].file", f"expected 'takes/{take.name}.h5' (a take's file is "
                                                              f"named after it, inside takes/); got {take.file!r}")
            if take.status not in TAKE_STATUSES:
                raise InputError(f"{where}: takes[{i}].status", f"expected one of {TAKE_STATUSES}; got {take.status!r}")
            if take.qc not in QC_STATUSES:
                raise InputError(f"{where}: takes[{i}].qc", f"expected one of {QC_STATUSES}; got {take.qc!r}")

    def channel(self, name: str) -> ChannelInfo:
        for ch in self.channels:
            if ch.name == name:
                return ch
        raise KeyError(f"no channel {name!r}; the manifest has {[c.name for c in self.channels]}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=False) + "\n"

    @classmethod
    def from_dict(cls, data: Any, *, where: str = "capture.json") -> Manifest:
        if not isinstance(data, dict):
            raise InputError(where, "expected a JSON object at the top level")
        check_schema(data.get("schema_version", "missing"), where=f"{where}: schema_version")
        manifest = from_plain(cls, data, where)
        manifest.validate(where)
        return manifest

    @classmethod
    def load(cls, path: str | Path) -> Manifest:
        data = load_json(path, missing="no capture manifest here; is this a capture directory?")
        return cls.from_dict(data, where=str(path))


def load_json(path: str | Path, *, missing: str) -> Any:
    """Read a JSON file; errors name the file (`missing` says what was expected there)."""
    return _load_text(path, json.loads, json.JSONDecodeError, "JSON", missing)


# A TOML file odsplat reads is written by hand or by a short script: a configuration, a rig, a lab, a thousand views'
# cameras fit in well under a megabyte. Larger is refused before it is read (tomllib takes seconds a megabyte).
MAX_TOML_BYTES = 4 * 2**20
# Tables and lists nested deeper than this are refused: odsplat's deepest TOML is four levels.
MAX_TOML_DEPTH = 16


def load_toml(path: str | Path, *, missing: str) -> dict[str, Any]:
    """Read a TOML configuration file; errors name the file (`missing` says what was expected there)."""
    data = _load_text(path, tomllib.loads, tomllib.TOMLDecodeError, "TOML", missing, max_bytes=MAX_TOML_BYTES)
    check_depth(data, str(path))
    return data


def parse_toml_value(text: str, where: str) -> Any:
    """One TOML value (`--set`'s VALUE); InputError naming `where` when it is nested too deep or an integer too long
    to read; TOMLDecodeError when it is not TOML."""
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except RecursionError:
        raise InputError(where, f"nested too deep to read; settings nest at most {MAX_TOML_DEPTH} levels") from None
    except tomllib.TOMLDecodeError:
        raise
    except ValueError as exc:  # an integer of more than 4300 digits (Python's limit on reading one)
        raise InputError(where, f"not a value odsplat can read: {str(exc).partition(':')[0]}") from None
    check_depth(value, where)
    return value


def check_depth(data: Any, where: str, limit: int = MAX_TOML_DEPTH) -> None:
    """Refuse tables and lists nested more than `limit` deep, walked without recursion (a hostile file may nest
    a hundred thousand levels)."""
    stack = [(data, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict):
            children = value.values()
        elif isinstance(value, list | tuple):
            children = value
        else:
            continue
        if depth > limit:
            raise InputError(where, f"nested too deep: more than {limit} levels of tables and lists")
        stack.extend((child, depth + 1) for child in children)


def _load_text(path: str | Path, parse, error: type[Exception], fmt: str, missing: str,
               max_bytes: int | None = None) -> Any:
    path = Path(path)
    if not path.exists():
        raise InputError(path, missing)
    check_regular_file(path, f"{fmt} file")
    try:
        if max_bytes is not None and path.stat().st_size > max_bytes:
            raise InputError(path, f"{path.stat().st_size / 2**20:.1f} MiB: too large for a {fmt} file odsplat "
                                   f"reads (at most {max_bytes / 2**20:g} MiB)")
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot be read: {exc.strerror or exc}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not {fmt}: not UTF-8 text (byte {exc.start} is {data[exc.start:exc.start + 1]!r}); "
                               f"save it as UTF-8 {fmt}") from None
    try:
        return parse(text)
    except error as exc:
        raise InputError(path, f"not valid {fmt}: {exc}") from None
    except RecursionError:
        raise InputError(path, f"not {fmt} odsplat can read: nested too deep") from None
    except MemoryError:
        raise InputError(path, f"not {fmt} odsplat can read: too large to hold in memory") from None
    except ValueError as exc:  # an integer of more than 4300 digits (Python's limit on reading one)
        raise InputError(path, f"not {fmt} odsplat can read: {str(exc).partition(':')[0]}") from None


def from_plain(cls: type, data: Any, where: str) -> Any:
    """Build dataclass `cls` from JSON-like data, naming the field path in any error."""
    if not isinstance(data, dict):
        raise InputError(where, f"expected an object for {cls.__name__}; got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise InputError(where, f"unknown field(s) {shown(sorted(unknown))}; expected some of {sorted(known)}")
    kwargs = {}
    for name, f in known.items():
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], f"{where}.{name}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise InputError(f"{where}.{name}", "required field is missing")
    return cls(**kwargs)


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _convert(inner, value, where)
    if dataclasses.is_dataclass(tp):
        return from_plain(tp, value, where)
    if origin is list:
        if not isinstance(value, list):
            raise InputError(where, f"expected a list; got {type(value).__name__}")
        (inner,) = typing.get_args(tp)
        return [_convert(inner, v, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(where, f"expected a list; got {type(value).__name__}")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise InputError(where, f"expected {len(args)} values; got {len(value)}")
        return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin is dict:
        if not isinstance(value, dict):
            raise InputError(where, f"expected an object; got {type(value).__name__}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(where, f"expected a number; got {shown(value)}")
        try:
            return float(value)
        except OverflowError:  # an int past a float's range
            raise InputError(where, f"expected a finite number; got {shown(value)}") from None
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(where, f"expected an integer; got {shown(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise InputError(where, f"expected true or false; got {shown(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise InputError(where, f"expected a string; got {shown(value)}")
        return value
    if tp is Path:
        if not isinstance(value, (str, os.PathLike)):
            raise InputError(where, f"expected a path (a string); got {shown(value)}")
        return value
    return value
