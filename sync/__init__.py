"""Sync: puts the sequential takes of a capture on one impact-locked timeline.

Public surface: `run(capture, SyncSettings)` (alias `sync_capture`) -> `SyncResult` (also `derived/sync.json` and
`sync.png`), and `AlignedTake(capture, path)` to read a take's frames on the common grid, computed from the raw take
as they are read (`derived/sync/NAME.h5` holds how)."""
from .align import SyncResult, SyncSettings, TakeSync, load_sync, sync_capture
from .aligned import AlignedTake

run = sync_capture  # the stage's entry: run(capture, SyncSettings) -> SyncResult, saved to derived/

__all__ = ["AlignedTake", "SyncResult", "SyncSettings", "TakeSync", "load_sync", "run", "sync_capture"]
