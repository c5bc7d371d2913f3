"""Importers: video and signal files from other equipment, read into odsplat's in-memory types."""
from odsplat.spine.io.signals import SignalChannel, SignalSet, read_signals
from odsplat.spine.io.video import SUPPORTED_KINDS, VideoSource, open_video

__all__ = ["SUPPORTED_KINDS", "SignalChannel", "SignalSet", "VideoSource", "open_video", "read_signals"]
