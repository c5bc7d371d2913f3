"""Any take's frames as an mp4 to watch (`odsplat export-video`): the raw take, sync's aligned frames or a
magnified take, through the one mp4 writer (`odsplat.spine.mp4`) with the magnify stage's 8-bit mapping."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.mp4 import Mp4Info, Mp4Writer, display_range, to_8bit
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, load_sync

from .magnify import METHODS, MagnifiedVideo, MagnifyResult, video_comment

log = logging.getLogger(__name__)

SOURCES = ("raw", "sync", *(f"magnified/{m}" for m in METHODS))
RANGE_FRAMES = 16   # the first frames whose percentiles set a take's 8-bit mapping (as the magnify stage's chunk)


@dataclass(frozen=True)
class ExportedVideo:
    take: str
    source: str
    recorded_fps: float
    dn_range: tuple[float, float]
    seconds: float
    mp4: Mp4Info


def _open(capture: Capture, take: str, source: str):
    """(reader with iter_frames, n_frames and frame times, its frame rate, the 8-bit mapping the magnify stage
    recorded or None) for one take of one source; an InputError naming what is missing."""
    if source == "raw":
        if take not in capture.take_names():
            raise InputError("--take", f"no take {take!r} in {capture.root} (it has {', '.join(capture.take_names())})")
        reader = capture.open_take(take)
        if not reader.n_frames:
            reader.close()
            raise InputError("--take", f"take {take!r} has no frames")
        return reader, reader.fps, None
    if source == "sync":

        sync = load_sync(capture)
        files = {t.name: t.aligned_file for t in sync.ok if t.aligned_file}
        if take not in files:
            raise InputError("--take", f"sync has no aligned frames of {take!r} (it has {', '.join(files) or 'none'})")
        reader = AlignedTake(capture, capture.paths.listed(files[take]), sync.generation)
        return reader, _rate(reader.times_s), None
    method = source.partition("/")[2]
    result = MagnifyResult.read(capture, method)
    found = next((t for t in result.takes if t.name == take), None)
    if found is None:
        raise InputError("--take", f"no magnified {take!r} in {source} (it has "
                                   f"{', '.join(t.name for t in result.takes)})")
    reader = MagnifiedVideo(capture.paths.listed(found.file), result.generation, capture.id)
    dn_range = tuple(found.video["dn_range"]) if found.video else None
    return reader, _rate(reader.times_s), dn_range


def _rate(times_s: np.ndarray) -> float | None:
    return float(1.0 / np.median(np.diff(times_s))) if len(times_s) > 1 else None


def source_takes(capture: Capture, source: str) -> list[str]:
    """The takes a source holds: every take with frames (raw), sync's aligned ones, or those magnified."""
    if source == "raw":
        return [t.name for t in capture.manifest.takes if t.n_frames > 0]
    if source == "sync":

        return [t.name for t in load_sync(capture).ok if t.aligned_file]
    return [t.name for t in MagnifyResult.read(capture, source.partition("/")[2]).takes]


def check_export(capture: Capture, take: str, source: str, out: Path | None, fps: float) -> Path:
    """Refuse bad input before anything is written; returns the output path."""
    if not (isinstance(fps, (int, float)) and 0 < fps < math.inf):
        raise InputError("--fps", f"expected a playback rate > 0 frames/s, got {fps}")
    if source not in SOURCES:
        raise InputError("--source", f"expected one of {', '.join(SOURCES)}; got {source!r}")
    if out is not None:
        if out.suffix.lower() != ".mp4":
            raise InputError("-o", f"expected a file name ending in .mp4, got {out}")
        if out.exists():
            raise InputError("-o", f"{out} exists already (remove it or choose another name)")
        return out
    return capture.paths.exported_video(source, take)


def export_video(capture: Capture, take: str, source: str = "raw", out: Path | None = None, fps: float = 30.0
                 ) -> ExportedVideo:
    """Write one take's frames from `source` ('raw', 'sync' or 'magnified/METHOD') to an 8-bit mp4 playing at
    `fps` (default: `paths.exported_video`); its comment holds the recorded rate and the DN mapping, the magnify
    stage's for a magnified take, else the first frames' 0.5-99.5 percentiles."""
    import time

    t0 = time.perf_counter()
    path = check_export(capture, take, source, out, fps)
    reader, recorded_fps, dn_range = _open(capture, take, source)
    try:
        if dn_range is None:
            dn_range = display_range(next(reader.iter_frames(RANGE_FRAMES)))
        what = {"raw": "raw frames", "sync": "frames on sync's common grid"}.get(source, f"{source} frames")
        comment = video_comment(take, what, recorded_fps or fps, fps, dn_range)
        capture.paths.ensure(path.parent)
        writer = Mp4Writer(path, fps, comment)
        try:
            for block in reader.iter_frames(RANGE_FRAMES):
                for frame in to_8bit(block, dn_range):
                    writer.write(frame)
        except BaseException:
            writer.abort()
            raise
        info = writer.close()
    finally:
        reader.close()
    log.info("%s (%s) -> %s: %d frames, %d bytes", take, source, info.path, info.n_frames, info.bytes)
    return ExportedVideo(take, source, recorded_fps or fps, dn_range, time.perf_counter() - t0, info)


__all__ = ["SOURCES", "ExportedVideo", "check_export", "export_video", "source_takes"]
