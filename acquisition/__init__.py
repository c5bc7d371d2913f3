"""Acquisition: camera, hammer and DAQ drivers, triggering, hit QC and the guided capture session.

The public surface, which the other stages (hil_sim's simulated bench and devices) and the command line import:
the wire protocols (`daqproto`, `canproto`, `hammerproto`, each spoken by a driver here and a device in hil_sim),
the drivers, the capture session, and the qc stage's entry `run_qc(capture, QCSettings) -> QCReport` (derived/qc.json).
Drivers for particular hardware (`opencv_camera`, `photron`) are chosen by name through `BACKENDS` (`open_bench`
assembles a capture's set-up from a lab file or the simulated rig's settings); the session's internals are imported
from their modules."""
from . import canproto, daqproto, hammerproto  # the wire protocols, shared with hil_sim's devices
from .backends import BACKENDS, SimRigSettings, open_bench
from .camera import CameraDriver, CameraTimeout, Frame, RecordingStatus, TriggerSettings
from .can_nodes import CANAccelerometers, CANError, CANNode, CANRecord, CANSetup, record_window
from .daq import DAQChannel, DAQError, SerialDAQ
from .hammer import AutoHammer, CANHammerLink, SerialHammerLink
from .lab import LabConfig, load_lab_config
from .live import PlotFeedback, TextFeedback, display_available
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
from .qc import HitQC, QCLimits, QCReport, QCSettings, TakeQC, check_hit, run_qc
from .session import (
    AutoHammerSettings,
    CaptureSession,
    Feedback,
    LabBench,
    SessionReport,
    SessionSettings,
    choose_hammer,
)
from .trigger import HammerTrigger, NoTrigger, TriggeredRecord, wait_for_hit

__all__ = [
    "canproto", "daqproto", "hammerproto",
    "BACKENDS", "SimRigSettings", "open_bench",
    "CameraDriver", "CameraTimeout", "Frame", "RecordingStatus", "TriggerSettings",
    "CANAccelerometers", "CANError", "CANNode", "CANRecord", "CANSetup", "record_window",
    "DAQChannel", "DAQError", "SerialDAQ",
    "AutoHammer", "CANHammerLink", "SerialHammerLink",
    "LabConfig", "load_lab_config", "PlotFeedback", "TextFeedback", "display_available",
    "PlanSettings", "PoseCheck", "check_pose", "coverage", "describe_view", "plan_views", "top_view_map",
    "view_eye_m", "view_pose",
    "HitQC", "QCLimits", "QCReport", "QCSettings", "TakeQC", "check_hit", "run_qc",
    "AutoHammerSettings", "CaptureSession", "Feedback", "LabBench", "SessionReport", "SessionSettings", "choose_hammer",
    "HammerTrigger", "NoTrigger", "TriggeredRecord", "wait_for_hit",
]
