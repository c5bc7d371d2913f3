"""hil_sim: the simulated impact-test rig that stands in for every device.

Importing it registers the `simdaq://` pyserial URL handler, so drivers open the simulated DAQ
like any port. Kept light: pyserial imports this package on every `simdaq://` open.
"""
import serial as _serial

if "odsplat.hil_sim" not in _serial.protocol_handler_packages:
    _serial.protocol_handler_packages.append("odsplat.hil_sim")

# The public surface, imported on first use (the package itself stays light for pyserial).
_EXPORTS = {
    "SimBench": "bench", "SimBenchSettings": "bench", "parse_faults": "bench", "simulate_capture": "bench",
    "RigConfig": "rig", "SimRig": "rig", "make_rig": "rig", "rig_config": "rig",
    "SceneSettings": "scene", "SimCameraConfig": "camera",
    "STRUCTURES": "structure", "make_structure": "structure",   # the rigs by name: arm, plate, frame, mast
    "VideoSimSettings": "video", "VideoTruth": "video", "simulate_video": "video",  # one camera, no DAQ
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
