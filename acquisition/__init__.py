"""Acquisition: camera, hammer and DAQ drivers, triggering, hit QC and the guided capture session.

The public surface; drivers for particular hardware (`opencv_camera`, `photron`) and the session's
internals are imported from their modules."""
from .camera import CameraDriver, CameraTimeout, Frame, RecordingStatus, TriggerSettings
from .daq import DAQChannel, DAQError, SerialDAQ
from .plan import PlanSettings, PoseCheck, check_pose, coverage, describe_view, plan_views, top_view_map, view_pose
from .qc import HitQC, QCLimits, QCReport, QCSettings, TakeQC, check_hit, run_qc
from .trigger import HammerTrigger, NoTrigger, TriggeredRecord, wait_for_hit
from .session import AutoHammerSettings, CaptureSession, LabBench, SessionReport, SessionSettings, choose_hammer
from .lab import LabConfig, load_lab_config
from .live import PlotFeedback, TextFeedback, display_available

__all__ = [
    "CameraDriver", "CameraTimeout", "Frame", "RecordingStatus", "TriggerSettings",
    "DAQChannel", "DAQError", "SerialDAQ",
    "PlanSettings", "PoseCheck", "check_pose", "coverage", "describe_view", "plan_views", "top_view_map", "view_pose",
    "HitQC", "QCLimits", "QCReport", "QCSettings", "TakeQC", "check_hit", "run_qc",
    "HammerTrigger", "NoTrigger", "TriggeredRecord", "wait_for_hit",
    "AutoHammerSettings", "CaptureSession", "LabBench", "SessionReport", "SessionSettings", "choose_hammer",
    "LabConfig", "load_lab_config", "PlotFeedback", "TextFeedback", "display_available",
]
