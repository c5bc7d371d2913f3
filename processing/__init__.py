"""Processing: video motion magnification of every view, streamed in bounded memory.

Public surface: `run(capture, MagnifySettings)` (alias `magnify_capture`) -> `MagnifyResult`, saved to
`derived/magnified/METHOD/` (frames and mp4s); `MagnifiedVideo` reads a magnified take; `export_video` writes any
take's raw, aligned or magnified frames to an mp4; `check_limit` is a method's motion bound. Magnifiers and
filters for use on their own are in their modules."""
from .base import LUMA, luma
from .learned import TrainConfig, train
from .limits import MotionLimit, check_limit
from .magnify import (
    METHODS,
    MagnifiedTake,
    MagnifiedVideo,
    MagnifyResult,
    MagnifySettings,
    magnify_capture,
    make_magnifier,
    parse_options,
)
from .video import SOURCES as VIDEO_SOURCES
from .video import ExportedVideo, check_export, export_video, source_takes

run = magnify_capture  # the stage's entry

__all__ = ["LUMA", "METHODS", "VIDEO_SOURCES", "ExportedVideo", "MagnifiedTake", "MagnifiedVideo", "MagnifyResult",
           "MagnifySettings", "MotionLimit", "check_export", "check_limit", "export_video", "magnify_capture",
           "luma", "make_magnifier", "parse_options", "run", "source_takes", "TrainConfig", "train"]
