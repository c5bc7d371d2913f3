"""Acquisition: camera, hammer and DAQ drivers, triggering, hit QC and the guided capture session.

The public surface, which the other stages (hil_sim's simulated bench) import; drivers for particular hardware
(`opencv_camera`, `photron`) and the session's internals are imported from their modules."""
from .camera import CameraDriver, CameraTimeout, Frame, RecordingStatus, TriggerSettings
from .daq import DAQChannel, DAQError, SerialDAQ
from .hammer import AutoHammer, CANHammerLink, SerialHammerLink
from .plan import (
    PlanSettings,
    PoseCheck,
    check_pose,
    coverage,
    describe_view,
    plan_views,
    top_view_map,
    view_eye_m,
    view_pose,
)
from .qc import HitQC, QCLimits, check_hit
from .session import AutoHammerSettings, CaptureSession, SessionReport, SessionSettings
from .trigger import HammerTrigger, NoTrigger, TriggeredRecord, wait_for_hit

__all__ = [
    "CameraDriver", "CameraTimeout", "Frame", "RecordingStatus", "TriggerSettings",
    "DAQChannel", "DAQError", "SerialDAQ",
    "AutoHammer", "CANHammerLink", "SerialHammerLink",
    "PlanSettings", "PoseCheck", "check_pose", "coverage", "describe_view", "plan_views", "top_view_map",
    "view_eye_m", "view_pose",
    "HitQC", "QCLimits", "check_hit",
    "AutoHammerSettings", "CaptureSession", "SessionReport", "SessionSettings",
    "HammerTrigger", "NoTrigger", "TriggeredRecord", "wait_for_hit",
]
