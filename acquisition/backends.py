"""The camera back ends by name, and the one place a capture's set-up is assembled.

`BACKENDS` maps the name a lab file's `[camera] driver` gives to a "module:Class" string, imported when that back end
is chosen (python-can's table of interfaces): a lab without a Photron never loads its driver. `sim` is hil_sim's
simulated rig, which brings its own camera, DAQ, automatic hammer and CAN nodes; hil_sim sits above acquisition in
the layers, so it is named here by a string and never imported by name.

`open_bench` assembles the set-up a capture session runs on (camera + DAQ + hammer + CAN nodes) from a lab file or
the simulated rig's settings: `odsplat capture --config LAB.toml`, `odsplat capture --sim` and `odsplat demo` all go
through it.
"""
from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from odsplat.spine._deps import resolve
from odsplat.spine.checks import shown
from odsplat.spine.errors import InputError

from .session import Bench, LabBench

if TYPE_CHECKING:
    from .camera import CameraDriver
    from .lab import LabConfig

BACKENDS: dict[str, str] = {
    "opencv": "odsplat.acquisition.opencv_camera:OpenCVCamera",   # a UVC camera or a video file: source, fps
    "photron": "odsplat.acquisition.photron:PhotronCamera",       # a Photron FASTCAM through PDCLIB: ip, library
    "sim": "odsplat.hil_sim:SimBench",                            # the simulated rig, a whole bench (SimRigSettings)
}
_DEFAULTS: dict[str, dict[str, Any]] = {"opencv": {"source": 0}}   # what a lab file may leave out


def check_backend(name: Any, where: str = "camera.driver") -> str:
    """`name` if it is a back end's; else one line listing them."""
    if not (isinstance(name, str) and name in BACKENDS):
        raise InputError(where, f"expected one of {', '.join(BACKENDS)}; got {shown(name)}")
    return name


def backend(name: str, where: str = "camera.driver") -> Any:
    """The class `BACKENDS` names for `name`, imported now."""
    return resolve(BACKENDS[check_backend(name, where)])


def open_camera(name: str, options: dict[str, Any], where: str = "camera") -> CameraDriver:
    """A camera of back end `name`, made with the lab file's [camera] keys as its keywords (`source` and `fps` for
    opencv, `ip` and `library` for photron); a key it does not take, or one it needs and lacks, is one line."""
    if name == "sim":
        raise InputError(f"{where}.driver", "the simulated camera comes with its rig: open the set-up with open_bench")
    cls = backend(name, f"{where}.driver")
    kwargs = {**_DEFAULTS.get(name, {}), **options}
    params = inspect.signature(cls).parameters
    for key in kwargs:
        if key not in params:
            takes = ", ".join(p for p in params if p != "self")
            raise InputError(f"{where}.{key}", f"the {name} back end takes no {key} (it takes {takes})")
    for key, p in params.items():
        if p.default is inspect.Parameter.empty and p.kind is not p.VAR_KEYWORD and key not in kwargs:
            raise InputError(f"{where}.{key}", f"the {name} back end needs it")
    return cls(**kwargs)


@dataclass(frozen=True)
class SimRigSettings:
    """The simulated rig's set-up: `odsplat capture --sim`'s options, or a lab file's [camera.sim] table."""

    size_px: tuple[int, int] = (400, 300)   # the camera's image, width and height
    fps: float = 2000.0                     # the camera's frame rate
    bit_depth: int = 12                     # 12 (in 16-bit words, as Photron writes them) or 8
    seed: int = 0                           # the rig's noise and the engineer's scatter
    structure: str = "arm"                  # the rig: "arm", "plate", "frame" or "mast"
    texture: str = "speckle"                # the structure's: "speckle", "value_noise" or "checker"
    floor_tag_m: float = 0.12               # the floor tags' size: 0.12 is ~20 px at 256x256
    faults: str = ""                        # faults on takes of this run, e.g. "2:double_hit,5:disconnect"
    hammer_link: str = "serial"             # the automatic hammer's link: "serial" (a PTY) or "can" (a virtual bus)


def _simulated_rig(s: SimRigSettings, hammer: bool) -> Bench:
    """hil_sim's bench for these settings: its package named by BACKENDS["sim"], imported now."""
    sim = importlib.import_module(BACKENDS["sim"].partition(":")[0])
    scene = sim.SceneSettings(floor_tag_size_m=s.floor_tag_m, texture=s.texture)
    width, height = s.size_px
    settings = sim.SimBenchSettings(width_px=width, height_px=height, seed=s.seed, structure=s.structure,
                                    scene=scene, camera=sim.SimCameraConfig(fps=s.fps, bit_depth=s.bit_depth))
    return backend("sim")(sim.make_rig(s.structure, scene, seed=s.seed), settings, faults=sim.parse_faults(s.faults),
                          hammer=s.hammer_link if hammer else None)


def open_bench(lab: LabConfig | None = None, sim: SimRigSettings | None = None, *, hammer: bool = False,
               ask: Callable[[str], str] = input, tell: Callable[[str], None] = print) -> Bench:
    """The set-up a capture session runs on, opened: the camera the lab file's [camera] names, its DAQ, the
    automatic hammer (`hammer`: the session fires one) and the CAN nodes; or the simulated rig, which brings them
    all, for a lab file with driver = "sim" or for `sim`'s settings without a lab file. Close it when done."""
    if lab is not None and sim is not None:
        raise InputError("open_bench", "give a lab file or the simulated rig's settings, not both")
    if lab is None or lab.simulated:
        return _simulated_rig(sim or (lab.camera.sim if lab is not None else None) or SimRigSettings(), hammer)
    return LabBench(lab.open_camera(), lab.daq_url, lab.channels, lab.sample_rate_hz, lab.tags, ask=ask, tell=tell,
                    hammer=lab.open_hammer() if hammer else None, can=lab.can,
                    open_can=lab.open_can if lab.can is not None else None)


__all__ = ["BACKENDS", "SimRigSettings", "backend", "check_backend", "open_bench", "open_camera"]
