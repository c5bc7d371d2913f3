"""The lab configuration for `odsplat capture --config LAB.toml`: which DAQ port and channels, which camera, which tags.

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
driver = "opencv"               # "opencv" (source = device index or video file) or "photron" (ip = "...")
source = 0
intrinsics = { fx_px = 1000.0, fy_px = 1000.0, cx_px = 639.5, cy_px = 399.5 }   # optional: enables the pose check

[hammer]                        # optional: an automatic hammer (docs/hammer-protocol.md), fired on every take
url = "/dev/ttyUSB1"            # a pyserial URL (simhammer://rig for the simulated one), or instead:
# can = { interface = "socketcan", channel = "can0", bitrate = 1000000 }
force_n = 200.0                 # the set level; QC accepts the DAQ's peak within force_n * (1 +- tolerance)
tolerance = 0.03
fire_timeout_s = 1.0

[tags]                          # optional: the AprilTag layout, as in capture.json
family = "tag36h11"
size_m = 0.12
tags = [ { id = 0, corners_m = [[...], [...], [...], [...]] } ]
```
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from odsplat.errors import InputError
from odsplat.manifest import Intrinsics, TagLayout, from_plain, load_toml

from .camera import CameraDriver
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


@dataclass(frozen=True)
class _Hammer:
    url: str | None = None
    can: dict | None = None
    force_n: float = 200.0
    tolerance: float = 0.03
    fire_timeout_s: float = 1.0


@dataclass(frozen=True)
class LabConfig:
    daq_url: str
    sample_rate_hz: float
    channels: tuple[DAQChannel, ...]
    camera: _Camera
    tags: TagLayout | None
    hammer: _Hammer | None = None

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

    def open_camera(self) -> CameraDriver:
        c = self.camera
        if c.driver == "opencv":
            from .opencv_camera import OpenCVCamera

            cam = OpenCVCamera(c.source if c.source is not None else 0, fps=c.fps)
        elif c.driver == "photron":
            from .photron import PhotronCamera

            if not c.ip:
                raise InputError("camera.ip", "the photron driver needs the camera's IP address")
            cam = PhotronCamera(c.ip, library=c.library)
        else:
            raise InputError("camera.driver", f"expected 'opencv' or 'photron', got {c.driver!r}")
        if c.intrinsics is not None:
            _describe = cam.describe
            cam.describe = lambda: replace(_describe(), intrinsics=c.intrinsics)  # calibration from the lab file
        return cam


def load_lab_config(path: str | Path) -> LabConfig:
    path = Path(path)
    data = load_toml(path, missing="lab configuration not found")
    for section in ("daq", "camera"):
        if section not in data:
            raise InputError(str(path), f"missing section [{section}]")
    daq = from_plain(_DAQ, data["daq"], f"{path}: daq")
    if not daq.channels:
        raise InputError(f"{path}: daq.channels", "at least one channel is needed (the hammer's force)")
    channels = tuple(from_plain(DAQChannel, c, f"{path}: daq.channels[{i}]") for i, c in enumerate(daq.channels))
    camera = from_plain(_Camera, data["camera"], f"{path}: camera")
    tags = from_plain(TagLayout, data["tags"], f"{path}: tags") if "tags" in data else None
    hammer = from_plain(_Hammer, data["hammer"], f"{path}: hammer") if "hammer" in data else None
    if hammer is not None and (hammer.url is None) == (hammer.can is None):
        raise InputError(f"{path}: hammer", "give exactly one of url (serial) or can = { interface, channel, ... }")
    return LabConfig(daq.url, daq.sample_rate_hz, channels, camera, tags, hammer)
