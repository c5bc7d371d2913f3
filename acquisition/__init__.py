"""Acquisition: camera, hammer and DAQ drivers, triggering, hit QC and the guided capture session.

The public surface; drivers for particular hardware (`opencv_camera`, `photron`) and the session's
internals are imported from their modules."""
from .camera import CameraDriver, CameraTimeout, Frame, RecordingStatus, TriggerSettings
from .daq import DAQChannel, DAQError, SerialDAQ
from .plan import PlanSettings, PoseCheck, check_pose, coverage, describe_view, plan_views, top_view_map, view_pose
from .qc import HitQC, QCLimits, check_hit
from .trigger import HammerTrigger, NoTrigger, TriggeredRecord, wait_for_hit

__all__ = [
    "CameraDriver", "CameraTimeout", "Frame", "RecordingStatus", "TriggerSettings",
    "DAQChannel", "DAQError", "SerialDAQ",
    "PlanSettings", "PoseCheck", "check_pose", "coverage", "describe_view", "plan_views", "top_view_map", "view_pose",
    "HitQC", "QCLimits", "check_hit",
    "HammerTrigger", "NoTrigger", "TriggeredRecord", "wait_for_hit",
]
