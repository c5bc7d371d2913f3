"""Playable mp4 files from frames, one writer for every stage that makes videos to watch (magnified takes,
`odsplat export-video`, the reconstruction's render): 8-bit frames through OpenCV, a comment in the file's
metadata, written whole or not at all.

OpenCV's pip builds carry FFmpeg without an H.264 encoder (libx264) on most machines; the writer tries H.264
('avc1') first and falls back to MPEG-4 Part 2 ('mp4v'), which this build writes and reads back, and which
desktop players (VLC, mpv, QuickTime, Windows' player) play. Web browsers play only H.264 in mp4.
"""
from __future__ import annotations

import contextlib
import functools
import logging
import os
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from odsplat.spine.atomic import atomic_path
from odsplat.spine.errors import InputError, OdsplatError

log = logging.getLogger(__name__)

CODECS = ("avc1", "mp4v")   # preferred first
DISPLAY_PERCENTILES = (0.5, 99.5)


# ------------------------------------------------------------------------------------------ 8-bit for viewing

def display_range(frames: np.ndarray, percentiles: tuple[float, float] = DISPLAY_PERCENTILES) -> tuple[float, float]:
    """The values (DN) that map to black and white: the frames' 0.5 and 99.5 percentiles (all channels), kept apart
    by at least one DN so that a flat frame does not divide by zero. Computed once per take (from its first
    frames) so that every frame of a video, and a take's raw and magnified videos, share one mapping."""
    lo, hi = (float(v) for v in np.percentile(np.asarray(frames, np.float32), percentiles))
    return lo, max(hi, lo + 1.0)


def to_8bit(frames: np.ndarray, dn_range: tuple[float, float]) -> np.ndarray:
    """DN to uint8 by the fixed mapping `dn_range` (black, white), clipped."""
    lo, hi = dn_range
    scaled = (np.asarray(frames, np.float32) - lo) * (255.0 / (hi - lo))
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------ the writer

@contextlib.contextmanager
def _quiet_stderr():
    """FFmpeg reports a missing encoder on the process's stderr (fd 2), past Python: silenced while probing."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@functools.cache
def codec() -> str:
    """The first of CODECS that this OpenCV writes to mp4 and reads back (probed once per process)."""
    with tempfile.TemporaryDirectory() as tmp:
        for fourcc in CODECS:
            path = os.path.join(tmp, f"probe_{fourcc}.mp4")
            with _quiet_stderr():
                writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*fourcc), 30.0, (32, 32))
                opened = writer.isOpened()
                if opened:
                    for _ in range(2):
                        writer.write(np.zeros((32, 32, 3), np.uint8))
                writer.release()
            if opened and count_frames(path) == 2:
                log.debug("mp4 codec: %s", fourcc)
                return fourcc
    raise OdsplatError(f"this OpenCV ({cv2.__version__}) writes no mp4 codec of {CODECS}")


def count_frames(path: str | Path) -> int:
    """Frames in a video, counted by decoding them (the container's count can be an estimate)."""
    cap = cv2.VideoCapture(str(path))
    try:
        n = 0
        while cap.isOpened() and cap.grab():
            n += 1
        return n
    finally:
        cap.release()


@dataclass(frozen=True)
class Mp4Info:
    """A written video: where, how many frames of what size, at what playback rate, with which codec."""

    path: Path
    n_frames: int
    width_px: int
    height_px: int
    fps: float
    codec: str
    bytes: int
    comment: str


class Mp4Writer:
    """Writes 8-bit frames (H, W) grey or (H, W, 3) RGB to `path` at `fps` (the playback rate), with `comment`
    in the file's metadata (udta/meta/ilst '©cmt', which ffprobe, VLC and exiftool show). The file appears at
    `path` on `close()` only, after its frames were counted back by decoding; an exception inside `with` leaves no
    file. The first frame fixes the size."""

    def __init__(self, path: str | Path, fps: float, comment: str = ""):
        if not (isinstance(fps, (int, float)) and 0 < fps < float("inf")):
            raise InputError("fps", f"expected a playback rate > 0 frames/s, got {fps}")
        self.path, self.fps, self.comment = Path(path), float(fps), comment
        self.codec = codec()
        self._atomic = atomic_path(self.path, suffix=".mp4")
        self._tmp: Path | None = None
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self.n_frames = 0

    def write(self, frame: np.ndarray) -> None:
        if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
            raise InputError(self.path, f"expected uint8 frames (H, W) or (H, W, 3), got {frame.dtype} {frame.shape}")
        size = (frame.shape[1], frame.shape[0])
        if self._writer is None:
            self._tmp = self._atomic.__enter__()
            self._writer = cv2.VideoWriter(str(self._tmp), cv2.VideoWriter_fourcc(*self.codec), self.fps, size)
            if not self._writer.isOpened():
                self.abort()
                raise OdsplatError(f"{self.path}: OpenCV cannot open an mp4 ({self.codec}) here")
            self._size = size
        elif size != self._size:
            raise InputError(self.path, f"a frame of {size[0]}x{size[1]} px in a video of {self._size[0]}x"
                                        f"{self._size[1]} px")
        self._writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR if frame.ndim == 2 else cv2.COLOR_RGB2BGR))
        self.n_frames += 1

    def close(self) -> Mp4Info:
        """Finish the file: count its frames back, add the comment, move it into place."""
        if self._writer is None:
            raise InputError(self.path, "no frames to write")
        self._writer.release()
        self._writer = None
        try:
            decoded = count_frames(self._tmp)
            if decoded != self.n_frames:
                raise OdsplatError(f"{self.path}: wrote {self.n_frames} frames, {decoded} decode back ({self.codec})")
            if self.comment:
                add_comment(self._tmp, self.comment)
        except BaseException as exc:
            self._atomic.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._atomic.__exit__(None, None, None)
        w, h = self._size
        return Mp4Info(self.path, self.n_frames, w, h, self.fps, self.codec, self.path.stat().st_size, self.comment)

    def abort(self) -> None:
        """Drop what was written (the temporary file); `path` is left as it was."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._tmp is not None:
            with contextlib.suppress(OdsplatError):
                self._atomic.__exit__(OdsplatError, OdsplatError("aborted"), None)
            self._tmp = None

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_mp4(path: str | Path, frames, fps: float, comment: str = "") -> Mp4Info:
    """Every 8-bit frame of an iterable into one mp4 (`Mp4Writer`)."""
    writer = Mp4Writer(path, fps, comment)
    try:
        for frame in frames:
            writer.write(frame)
    except BaseException:
        writer.abort()
        raise
    return writer.close()


# ------------------------------------------------------------------------------------------ the comment

def _boxes(data: bytes, start: int, end: int):
    """(type, offset, size, header size) of the ISO-BMFF boxes in data[start:end]."""
    off = start
    while off + 8 <= end:
        size, kind = struct.unpack(">I4s", data[off:off + 8])
        head = 8
        if size == 1:
            size, head = struct.unpack(">Q", data[off + 8:off + 16])[0], 16
        elif size == 0:
            size = end - off
        if size < head or off + size > end:
            raise OdsplatError(f"a malformed mp4 box {kind!r} at byte {off}")
        yield kind, off, size, head
        off += size


def _box(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I4s", 8 + len(body), kind) + body


_CONTAINERS = {b"moov": 0, b"udta": 0, b"meta": 4, b"ilst": 0}   # the boxes on the way, and their extra header
_COMMENT = b"\xa9cmt"


def _with_child(box: bytes, path: list[bytes], child: bytes) -> bytes:
    """`box` (whole, 32-bit size) with `child` added at the end of the container reached by `path` below it,
    the containers missing on the way created."""
    kind = box[4:8]
    head = 8 + _CONTAINERS[kind]
    body = box[head:]
    if path:
        for k, off, size, _ in _boxes(body, 0, len(body)):
            if k == path[0]:
                body = body[:off] + _with_child(body[off:off + size], path[1:], child) + body[off + size:]
                break
        else:
            body = body + _new(path, child)
    else:
        body = body + child
    return struct.pack(">I", 8 + _CONTAINERS[kind] + len(body)) + box[4:head] + body


def _new(path: list[bytes], child: bytes) -> bytes:
    kind, rest = path[0], path[1:]
    inner = _new(rest, child) if rest else child
    if kind == b"meta":   # version/flags, then the handler that makes ilst's keys iTunes-style
        hdlr = _box(b"hdlr", bytes(8) + b"mdir" + b"appl" + bytes(9))
        return _box(b"meta", bytes(4) + hdlr + inner)
    return _box(kind, inner)


def add_comment(path: str | Path, text: str) -> None:
    """Put `text` in the mp4's moov/udta/meta/ilst '©cmt'. Only where moov is the file's last box (as OpenCV's
    FFmpeg writes it), so growing it moves no sample offset; otherwise logged and left out."""
    path = Path(path)
    data = path.read_bytes()
    boxes = list(_boxes(data, 0, len(data)))
    moov = [b for b in boxes if b[0] == b"moov"]
    if not moov or moov[0] != boxes[-1] or moov[0][3] != 8:
        log.warning("%s: moov is not the last box; the comment is left out", path)
        return
    _, off, size, _ = moov[0]
    entry = _box(_COMMENT, _box(b"data", struct.pack(">II", 1, 0) + text.encode("utf-8")))
    new_moov = _with_child(data[off:off + size], [b"udta", b"meta", b"ilst"], entry)
    with open(path, "r+b") as fh:
        fh.seek(off)
        fh.write(new_moov)
        fh.truncate()


def read_comment(path: str | Path) -> str | None:
    """The '©cmt' text `add_comment` wrote, or None."""
    data = Path(path).read_bytes()

    def find(start: int, end: int, path: list[bytes]) -> str | None:
        for kind, off, size, head in _boxes(data, start, end):
            if kind != path[0]:
                continue
            if len(path) == 1:
                for k, o, s, h in _boxes(data, off + head, off + size):
                    if k == b"data":
                        return data[o + h + 8:o + s].decode("utf-8")
                return None
            return find(off + head + _CONTAINERS.get(kind, 0), off + size, path[1:])
        return None

    return find(0, len(data), [b"moov", b"udta", b"meta", b"ilst", _COMMENT])


__all__ = ["CODECS", "DISPLAY_PERCENTILES", "Mp4Info", "Mp4Writer", "add_comment", "codec", "count_frames",
           "display_range", "read_comment", "to_8bit", "write_mp4"]
