"""Sync: puts the sequential takes of a capture on one impact-locked timeline.

Public surface: `sync_capture(capture, SyncSettings)` -> `SyncResult` (also `derived/sync.json`), and
`AlignedTake` to read a take's frames on the common grid (`derived/sync/NAME.h5`)."""
from .align import SyncResult, SyncSettings, TakeSync, load_sync, sync_capture, sync_path
from .aligned import AlignedTake

__all__ = ["AlignedTake", "SyncResult", "SyncSettings", "TakeSync", "load_sync", "sync_capture", "sync_path"]
