"""Sync: puts the sequential takes of a capture on one impact-locked timeline.

Public surface: `run(capture, SyncSettings)` (alias `sync_capture`) -> `SyncResult` (also `derived/sync.json`, `sync.png`), and
`AlignedTake` to read a take's frames on the common grid (`derived/sync/NAME.h5`)."""
from .aligned import AlignedTake
from .align import SyncResult, SyncSettings, TakeSync, load_sync, sync_capture

run = sync_capture  # the stage's entry: run(capture, SyncSettings) -> SyncResult, saved to derived/

__all__ = ["AlignedTake", "SyncResult", "SyncSettings", "TakeSync", "load_sync", "run", "sync_capture"]
