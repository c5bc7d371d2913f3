"""The lab configuration for `odsplat capture --config LAB.toml`: which DAQ port and channels, which camera, which
tags, and optionally the automatic hammer and the CAN accelerometer nodes.

```toml
[daq]
url = "/dev/ttyACM0"            # any pyserial URL; simdaq://rig for the simulated DAQ
sample_rate_hz = 25600
channels = [
  { name = "force", input = 0, kind = "force", sensitivity_v_per_unit = 0.00225, range_v = 10.0 },
  { name = "acc1", input = 1, kind = "acceleration", sensitivity_v_per_unit = 0.0102, range_v = 10.0 },
  { name = "cam_ttl", input = 7, kind = "ttl" },
]

[camera]
driver = "opencv"               # a back end of backends.BACKENDS: "opencv" (source = device index or video file),
source = 0                      # "photron" (ip = "...", library) or "sim" (the simulated rig, below)
intrinsics = { fx_px = 1000.0, fy_px = 1000.0, cx_px = 639.5, cy_px = 399.5 }   # optional: enables the pose check

[hammer]                        # optional: an automatic hammer (docs/hammer-protocol.md), fired on every take
url = "/dev/ttyUSB1"            # a pyserial URL (simhammer://rig for the simulated one), or instead:
# can = { interface = "socketcan", channel = "can0", bitrate = 1000000 }
force_n = 200.0                 # the set level; QC accepts the DAQ's peak within force_n * (1 +- tolerance)
tolerance = 0.03
fire_timeout_s = 1.0

[can]                           # optional: CAN accelerometer nodes (docs/can-protocol.md), recorded into every take
interface = "socketcan"         # python-can's interface ("virtual" for the simulated nodes); channel and bitrate
channel = "can0"                # likewise; what the section leaves out comes from python-can's own configuration
bitrate = 1000000               # (CAN_INTERFACE, CAN_CHANNEL, CAN_BITRATE, ~/.canrc)
# options = { ... }             # further can.Bus keywords the adapter needs
sample_rate_hz = 1000           # 250, 500, 1000, 2000 or 4000
range_g = 50                    # 2, 4, 8, 16, 50, 100, 200 or 500 (or range_m_s2 = 490.3325)

[[can.nodes]]
node_id = 1                     # 1..16, distinct
position_m = [0.25, 0.0, 0.60]  # optional: where it sits on the structure (world frame)
direction = ["+X", "+Y", "+Z"]  # optional: where its x, y, z axes point in the world, as axes or unit vectors
t0_daq_s = 0.0                  # where its sample 0 falls on the DAQ's time base (a shared start line, or measured)

[[can.nodes]]
node_id = 2
position_m = [0.0, 0.045, 0.50]
direction = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]
t0_daq_s = -0.0012

[tags]                          # optional: the AprilTag layout, as in capture.json
family = "tag36h11"
size_m = 0.12
tags = [ { id = 0, corners_m = [[...], [...], [...], [...]] } ]
```

With `driver = "sim"` the file runs the simulated rig (hil_sim), which brings its own DAQ, tags, hammer and CAN
nodes: [daq], [tags] and [can] are left out, [hammer] gives only the hammer's settings (force_n, tolerance,
fire_timeout_s), and an optional `[camera.sim]` table sets the rig (`backends.SimRigSettings`: size_px, fps,
bit_depth, seed, structure, texture, floor_tag_m, faults, hammer_link).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.manifest import Intrinsics, TagLayout, from_plain, load_toml
from odsplat.spine.units import STANDARD_GRAVITY_M_S2

from . import canproto as cp
from .backends import SimRigSettings, check_backend, open_camera
from .camera import CameraDriver
from .can_nodes import CANAccelerometers, CANNode, CANSetup
from .daq import DAQChannel
from .hammer import AutoHammer, CANHammerLink
from .session import AutoHammerSettings


@dataclass(frozen=True)
class _DAQ:
    url: str
    sample_rate_hz: float = 25_600.0
    channels: list[dict] = field(default_factory=list)


@dataclass(frozen=True)
class _Camera:
    driver: str
    source: Any = None
    ip: str | None = None
    fps: float | None = None
    library: str | None = None
    intrinsics: Intrinsics | None = None
    sim: SimRigSettings | None = None           # driver = "sim": the simulated rig's settings


@dataclass(frozen=True)
class _Hammer:
    url: str | None = None
    can: dict | None = None
    force_n: float = 200.0
    tolerance: float = 0.03
    fire_timeout_s: float = 1.0


@dataclass(frozen=True)
class _CAN:
    interface: str | None = None
    channel: Any = None  # a name ("can0", "PCAN_USBBUS1") or a number, as the interface wants
    bitrate: int | None = None
    options: dict[str, Any] | None = None
    sample_rate_hz: float = 1000.0
    range_m_s2: float | None = None
    range_g: float | None = None
    nodes: list[dict] = field(default_factory=list)


@dataclass(frozen=True)
class _CANNode:
    node_id: int
    t0_daq_s: float  # required: no default can know the bench's wiring
    position_m: tuple[float, float, float] | None = None
    direction: Any = None  # three axes, each "+X".."-Z" or a unit vector; parsed by _axes


_MAX_T0_S = 1.0  # the session STARTs the nodes just before the DAQ: their offset is milliseconds, never seconds
_AXIS = re.compile(r"^([+-]?)([XYZ])$", re.IGNORECASE)


@dataclass(frozen=True)
class LabConfig:
    daq_url: str | None                         # None with the simulated rig (driver = "sim"): it brings its DAQ
    sample_rate_hz: float
    channels: tuple[DAQChannel, ...]
    camera: _Camera
    tags: TagLayout | None
    hammer: _Hammer | None = None
    can: CANSetup | None = None                 # the [can] nodes, as the session records them
    can_bus: dict[str, Any] | None = None       # can.Bus keywords from [can] (interface, channel, bitrate, options)

    @property
    def simulated(self) -> bool:
        """The simulated rig (driver = "sim"): camera, DAQ, hammer and CAN nodes all hil_sim's."""
        return self.camera.driver == "sim"

    def hammer_settings(self) -> AutoHammerSettings | None:
        h = self.hammer
        return None if h is None else AutoHammerSettings(h.force_n, h.tolerance, h.fire_timeout_s)

    def open_hammer(self) -> AutoHammer | None:
        """The automatic hammer of [hammer], connected (None without the section)."""
        h = self.hammer
        if h is None:
            return None
        if h.url is not None:
            return AutoHammer.open_serial(h.url)
        from .canproto import open_bus

        return AutoHammer(CANHammerLink(open_bus(config=h.can), close_bus=True))

    def open_can(self) -> CANAccelerometers:
        """The driver of [can]'s nodes on the bus it names, opened (the caller shuts the bus down: `.bus.shutdown()`).
        What the section leaves out of the bus comes from python-can's own configuration."""
        if self.can is None:
            raise InputError("lab file", "no [can] section: no CAN nodes to open")
        bus = dict(self.can_bus or {})
        interface, channel = bus.pop("interface", None), bus.pop("channel", None)
        return CANAccelerometers.open([n.node_id for n in self.can.nodes], interface=interface, channel=channel,
                                      config=bus, sample_rate_hz=self.can.sample_rate_hz,
                                      range_m_s2=self.can.range_m_s2)

    def open_camera(self) -> CameraDriver:
        """The camera of [camera], by its back end (backends.BACKENDS), opened with the section's keys."""
        c = self.camera
        options = {k: getattr(c, k) for k in ("source", "ip", "fps", "library") if getattr(c, k) is not None}
        cam = open_camera(c.driver, options)
        if c.intrinsics is not None:
            _describe = cam.describe
            cam.describe = lambda: replace(_describe(), intrinsics=c.intrinsics)  # calibration from the lab file
        return cam


def load_lab_config(path: str | Path) -> LabConfig:
    path = Path(path)
    data = load_toml(path, missing="lab configuration not found")
    if "camera" not in data:
        raise InputError(str(path), "missing section [camera]")
    camera = from_plain(_Camera, _driver(data["camera"], f"{path}: camera"), f"{path}: camera")
    check_backend(camera.driver, f"{path}: camera.driver")
    hammer = from_plain(_Hammer, data["hammer"], f"{path}: hammer") if "hammer" in data else None
    if camera.driver == "sim":
        return _simulated_lab(data, camera, hammer, path)
    if camera.sim is not None:
        raise InputError(f"{path}: camera.sim", f"the simulated rig's settings, for driver = \"sim\" only; the driver "
                                                f"is {camera.driver!r}")
    if "daq" not in data:
        raise InputError(str(path), "missing section [daq]")
    daq = from_plain(_DAQ, data["daq"], f"{path}: daq")
    if not daq.channels:
        raise InputError(f"{path}: daq.channels", "at least one channel is needed (the hammer's force)")
    channels = tuple(from_plain(DAQChannel, c, f"{path}: daq.channels[{i}]") for i, c in enumerate(daq.channels))
    tags = from_plain(TagLayout, data["tags"], f"{path}: tags") if "tags" in data else None
    if hammer is not None and (hammer.url is None) == (hammer.can is None):
        raise InputError(f"{path}: hammer", "give exactly one of url (serial) or can = { interface, channel, ... }")
    can, can_bus = _load_can(data["can"], f"{path}: can") if "can" in data else (None, None)
    return LabConfig(daq.url, daq.sample_rate_hz, channels, camera, tags, hammer, can, can_bus)


def _driver(section: Any, where: str) -> Any:
    """[camera] with `backend`, the back end's other name, read as `driver`."""
    if not isinstance(section, dict) or "backend" not in section:
        return section
    if "driver" in section:
        raise InputError(f"{where}.backend", "give driver or backend (the same key), not both")
    return {("driver" if k == "backend" else k): v for k, v in section.items()}


def _simulated_lab(data: dict[str, Any], camera: _Camera, hammer: _Hammer | None, path: Path) -> LabConfig:
    """A lab file for the simulated rig: it brings its DAQ, tags and CAN nodes; [hammer] sets its hammer's level."""
    given = [s for s in ("daq", "tags", "can") if s in data]
    if given:
        raise InputError(f"{path}: [{given[0]}]", "the simulated rig (driver = \"sim\") brings its own DAQ, tags and "
                                                 "CAN nodes: leave the section out")
    if hammer is not None and (hammer.url is not None or hammer.can is not None):
        raise InputError(f"{path}: hammer", "the simulated rig's hammer is reached over camera.sim.hammer_link: "
                                            "leave url and can out")
    stray = [k for k in ("source", "ip", "fps", "library") if getattr(camera, k) is not None]
    if stray:
        raise InputError(f"{path}: camera.{stray[0]}", "the simulated rig's camera is set in [camera.sim] (size_px, "
                                                     "fps, bit_depth, ...)")
    return LabConfig(None, 0.0, (), replace(camera, sim=camera.sim or SimRigSettings()), None, hammer)


def _load_can(data: Any, where: str) -> tuple[CANSetup, dict[str, Any]]:
    """[can]: the nodes as the session records them, and the can.Bus keywords; errors name the field."""
    sec = from_plain(_CAN, data, where)
    bus: dict[str, Any] = dict(sec.options or {})
    for key in ("interface", "channel", "bitrate"):
        if getattr(sec, key) is not None:
            if key in bus:
                raise InputError(f"{where}.options.{key}", f"given twice: set {key} in [can] itself")
            bus[key] = getattr(sec, key)
    if sec.channel is not None and (isinstance(sec.channel, bool) or not isinstance(sec.channel, (str, int))):
        raise InputError(f"{where}.channel", f"expected a name or a number; got {sec.channel!r}")
    if sec.bitrate is not None and sec.bitrate <= 0:
        raise InputError(f"{where}.bitrate", f"expected bit/s > 0; got {sec.bitrate}")
    try:
        rate = cp.SAMPLE_RATES_HZ[cp.rate_code(sec.sample_rate_hz)]
    except InputError as e:
        raise InputError(f"{where}.sample_rate_hz", e.problem) from None
    if sec.range_m_s2 is not None and sec.range_g is not None:
        raise InputError(f"{where}.range_g", "give range_g or range_m_s2, not both")
    if sec.range_g is not None:
        try:
            range_m_s2 = cp.RANGES_M_S2[cp.range_code(sec.range_g * STANDARD_GRAVITY_M_S2)]
        except InputError:
            table = sorted(round(v / STANDARD_GRAVITY_M_S2) for v in cp.RANGES_M_S2.values())
            raise InputError(f"{where}.range_g", f"{sec.range_g:g} is not one of {table}") from None
    elif sec.range_m_s2 is not None:
        try:
            range_m_s2 = cp.RANGES_M_S2[cp.range_code(sec.range_m_s2)]
        except InputError as e:
            raise InputError(f"{where}.range_m_s2", e.problem) from None
    else:
        range_m_s2 = CANSetup.range_m_s2
    if not sec.nodes:
        raise InputError(f"{where}.nodes", "no node: add one [[can.nodes]] table per node")
    nodes: list[CANNode] = []
    for i, raw in enumerate(sec.nodes):
        at = f"{where}.nodes[{i}]"
        n = from_plain(_CANNode, raw, at)
        if n.node_id not in cp.NODE_IDS:
            raise InputError(f"{at}.node_id", f"{n.node_id} is outside {cp.NODE_IDS.start}..{cp.NODE_IDS.stop - 1} "
                             f"(the node ids of {cp.DBC_RESOURCE})")
        same = [j for j, m in enumerate(nodes) if m.node_id == n.node_id]
        if same:
            raise InputError(f"{at}.node_id", f"{n.node_id} is also can.nodes[{same[0]}]'s; node ids must be distinct")
        if not (math.isfinite(n.t0_daq_s) and abs(n.t0_daq_s) < _MAX_T0_S):
            raise InputError(f"{at}.t0_daq_s", f"expected the node's start relative to the DAQ's in s, within "
                             f"+-{_MAX_T0_S:g} s (milliseconds are typical); got {n.t0_daq_s!r}")
        if n.position_m is not None and not all(math.isfinite(v) for v in n.position_m):
            raise InputError(f"{at}.position_m", f"expected 3 finite numbers in m; got {list(n.position_m)}")
        axes = None if n.direction is None else _axes(n.direction, f"{at}.direction")
        nodes.append(CANNode(n.node_id, n.position_m, axes, n.t0_daq_s))
    load = cp.bus_load(len(nodes), rate, sec.bitrate) if sec.bitrate is not None else 0.0
    if load > 0.7:  # docs/can-protocol.md: beyond it frames queue in the nodes and are dropped
        raise InputError(f"{where}.sample_rate_hz", f"{len(nodes)} node(s) at {rate:g} Hz take {load:.0%} of a "
                         f"{sec.bitrate} bit/s bus (worst case); keep it under 70 %: fewer nodes, a lower rate or a "
                         "second bus")
    return CANSetup(tuple(nodes), rate, range_m_s2), bus


def _axes(value: Any, where: str) -> tuple[tuple[float, float, float], ...]:
    """A node's x, y, z axes in world coordinates from three "+X".."-Z" strings or unit vectors (mixed is fine):
    orthonormal and right-handed, as a triaxial sensor's axes are."""
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(where, f"expected the node's x, y and z axes, three of \"+X\"..\"-Z\" or [x, y, z]; "
                         f"got {value!r}")
    rows = []
    for k, axis in enumerate(value):
        if isinstance(axis, str):
            m = _AXIS.match(axis.strip())
            if m is None:
                raise InputError(f"{where}[{k}]", f"expected one of +X, -X, +Y, -Y, +Z, -Z; got {axis!r}")
            row = [0.0, 0.0, 0.0]
            row["XYZ".index(m.group(2).upper())] = -1.0 if m.group(1) == "-" else 1.0
        elif (isinstance(axis, list) and len(axis) == 3
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in axis)):
            row = [float(v) for v in axis]
            if not abs(np.linalg.norm(row) - 1.0) < 1e-6:
                raise InputError(f"{where}[{k}]", f"expected a unit vector; got {axis} (length "
                                 f"{np.linalg.norm(row):.6g})")
        else:
            raise InputError(f"{where}[{k}]", f"expected \"+X\"..\"-Z\" or [x, y, z]; got {axis!r}")
        rows.append(row)
    a = np.array(rows)
    if not np.allclose(a @ a.T, np.eye(3), atol=1e-6):
        raise InputError(where, f"the node's axes must be perpendicular to each other; got {value!r}")
    if np.linalg.det(a) < 0:
        raise InputError(where, f"a left-handed set {value!r}: a sensor's x, y, z are right-handed (x cross y = z); "
                         "one axis has the wrong sign")
    return tuple((float(r[0]), float(r[1]), float(r[2])) for r in rows)
