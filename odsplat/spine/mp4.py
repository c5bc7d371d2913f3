"""Playable mp4 files from frames, one writer for every stage that makes videos to watch (magnified takes,
`odsplat export-video`, the reconstruction's render): 8-bit frames encoded H.264 (libx264, yuv420p, BT.709
limited range) through PyAV, a comment in the file's metadata, written whole or not at all.

H.264 in yuv420p is what every web browser plays in an mp4 (Chromium refuses MPEG-4 Part 2, 'mp4v', which the
writer made through OpenCV before), and what desktop players (VLC, mpv, QuickTime, Windows' player) play too.
PyAV's wheels carry FFmpeg with libx264. yuv420p halves the colour planes, so a frame of odd width or height is
padded by one copy of its last column or row; `Mp4Info` reports the size written. The comment is put in the moov
box after the muxer's trailer (`add_comment`; callers may set `Mp4Writer.comment` until `close()`), so moov stays
the file's last box (no `+faststart`): browsers read it by range requests or from the whole local file.
"""
from __future__ import annotations

import contextlib
import functools
import logging
import struct
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
from av.video.reformatter import VideoReformatter

from odsplat.spine.atomic import atomic_path
from odsplat.spine.errors import InputError, OdsplatError

log = logging.getLogger(__name__)

CODECS = ("libx264",)   # the H.264 encoders the writer uses, preferred first (CRF and presets are x264's)
DISPLAY_PERCENTILES = (0.5, 99.5)
CRF = 18                # x264's constant rate factor: 18 is close to visually lossless, 23 its default
PRESET = "medium"       # x264's speed/size trade-off (its default)
PIX_FMT = "yuv420p"     # the one pixel format every browser's H.264 decoder takes
_BT709 = 1              # AVCOL_PRI/TRC/SPC_BT709: the colour tags written, and the matrix the frames are converted by
_LIMITED = 1            # AVCOL_RANGE_MPEG: 16-235 luma, what players expect of H.264
FPS_RANGE = (1e-3, 1e6)  # playback rates the writer takes, both ends tried (FFmpeg's mp4 muxer refuses 1e-5);
#                          the CLI's and settings' bounds (checks.PLAYBACK_FPS) are narrower


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

@functools.cache
def _encoder() -> str:
    """The first of CODECS this PyAV can encode with (looked up once per process)."""
    for name in CODECS:
        try:
            av.codec.Codec(name, "w")
        except ValueError:   # av.codec.codec.UnknownCodecError
            continue
        log.debug("mp4 encoder: %s (PyAV %s)", name, av.__version__)
        return name
    raise OdsplatError(f"this PyAV ({av.__version__}) has no H.264 encoder ({', '.join(CODECS)}): install the "
                       f"'av' wheel from PyPI, which carries libx264")


def codec() -> str:
    """The codec every mp4 is written in: "h264" (through `_encoder()`; an OdsplatError where PyAV has none)."""
    _encoder()
    return "h264"


def _rate(fps: float) -> Fraction:
    """The playback rate as a fraction (29.97 -> 2997/100, 30000/1001 stays 30000/1001, 2000/64 -> 125/4): the
    stream's frame rate, and its inverse the time base, so that the player's rate is the one asked for."""
    # a denominator of at most 10000, and at most 2^30 / fps: the numerator (the time base's denominator, and the
    # timescale's factor) stays well inside FFmpeg's 32-bit rationals at FPS_RANGE's top
    return Fraction(fps).limit_denominator(max(1, min(10_000, int(2**30 / fps))))


def _mp4_options(rate: Fraction) -> dict[str, str]:
    """The muxer's options: one timescale for the track and the movie, a multiple of the rate's numerator (so
    every frame lasts a whole number of ticks) of at least 10000. The movie's default, 1000 ticks/s,
    rounds the edit list that hides x264's B-frame delay, and at hundreds of frames/s and more it cut the last
    frames (2000 frames/s: 3 written, 2 decoded back; 10000: none)."""
    timescale = rate.numerator
    while timescale < 10_000:
        timescale *= 2
    return {"movie_timescale": str(timescale), "video_track_timescale": str(timescale)}


def count_frames(path: str | Path) -> int:
    """Frames in a video, counted by decoding them (the container's count can be an estimate). 0 where the file
    holds no video stream or cannot be opened; a decoding error ends the count there (logged)."""
    n = 0
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return 0
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for _ in container.decode(stream):
                n += 1
    except (av.FFmpegError, OSError) as exc:
        log.warning("%s: decoding stopped after %d frames: %s", path, n, exc)
    return n


@dataclass(frozen=True)
class Mp4Info:
    """A written video: where, how many frames of what size (as written: even), at what playback rate, with
    which codec."""

    path: Path
    n_frames: int
    width_px: int
    height_px: int
    fps: float
    codec: str
    bytes: int
    comment: str


def _even(frame: np.ndarray) -> np.ndarray:
    """The frame padded to an even width and height (yuv420p's chroma is half size) by one copy of its last
    column and/or row."""
    pad_h, pad_w = frame.shape[0] % 2, frame.shape[1] % 2
    if not (pad_h or pad_w):
        return np.ascontiguousarray(frame)
    return np.pad(frame, ((0, pad_h), (0, pad_w)) + ((0, 0),) * (frame.ndim - 2), mode="edge")


class Mp4Writer:
    """Writes 8-bit frames (H, W) grey or (H, W, 3) RGB to `path` at `fps` (the playback rate, any float: kept
    as a fraction), H.264 yuv420p (libx264, CRF 18, BT.709), with `comment` in the file's metadata
    (udta/meta/ilst '©cmt', which ffprobe, VLC and exiftool show). The first frame fixes the size; a frame of odd
    width or height is padded by one copy of its last column or row, and `Mp4Info` reports the padded size. The
    file appears at `path` on `close()` only, after its frames were counted back by decoding; an exception
    inside `with` leaves no file. `comment` may be set until `close()` (magnify knows its mapping late)."""

    def __init__(self, path: str | Path, fps: float, comment: str = ""):
        if not (isinstance(fps, (int, float)) and 0 < fps < float("inf")):
            raise InputError("fps", f"expected a playback rate > 0 frames/s, got {fps}")
        if not FPS_RANGE[0] <= fps <= FPS_RANGE[1]:
            raise InputError("fps", f"a playback rate of {fps:g} frames/s is outside what the mp4 writer takes "
                                    f"({FPS_RANGE[0]:g} to {FPS_RANGE[1]:g})")
        self.path, self.fps, self.comment = Path(path), float(fps), comment
        self.codec = codec()
        self._atomic = atomic_path(self.path, suffix=".mp4")
        self._tmp: Path | None = None
        self._container: av.container.OutputContainer | None = None
        self._stream: av.video.stream.VideoStream | None = None
        self._time_base = Fraction(1)
        self._reformatter = VideoReformatter()   # one scaler for every frame (PyAV 18's frame.reformat makes
        #                                          one a frame: 2x the writing time)
        self._shape: tuple[int, int] | None = None    # the frames' (height, width) as given
        self._size: tuple[int, int] | None = None     # (width, height) as written
        self.n_frames = 0

    def _open(self, frame: np.ndarray) -> None:
        """The temporary file and its H.264 stream, sized by the first (even) frame."""
        self._tmp = self._atomic.__enter__()
        try:
            rate = _rate(self.fps)
            self._container = av.open(str(self._tmp), mode="w", format="mp4", options=_mp4_options(rate))
            stream = self._container.add_stream(_encoder(), rate=rate)
            stream.width, stream.height = frame.shape[1], frame.shape[0]
            stream.pix_fmt = PIX_FMT
            stream.time_base = self._time_base = 1 / rate
            cc = stream.codec_context
            cc.options = {"crf": str(CRF), "preset": PRESET}
            cc.color_primaries = cc.color_trc = cc.colorspace = _BT709
            cc.color_range = _LIMITED
            self._stream = stream
        except BaseException:
            self.abort()
            raise
        self._size = (frame.shape[1], frame.shape[0])

    def write(self, frame: np.ndarray) -> None:
        if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
            raise InputError(self.path, f"expected uint8 frames (H, W) or (H, W, 3), got {frame.dtype} {frame.shape}")
        if self._shape is None:
            self._open(_even(frame))
            self._shape = frame.shape[:2]
        elif frame.shape[:2] != self._shape:
            raise InputError(self.path, f"a frame of {frame.shape[1]}x{frame.shape[0]} px in a video of "
                                        f"{self._shape[1]}x{self._shape[0]} px")
        image = av.VideoFrame.from_ndarray(_even(frame), format="gray" if frame.ndim == 2 else "rgb24")
        image = self._reformatter.reformat(image, format=PIX_FMT, dst_colorspace="ITU709")
        image.pts = self.n_frames
        image.time_base = self._time_base
        self._container.mux(self._stream.encode(image))
        self.n_frames += 1

    def close(self) -> Mp4Info:
        """Finish the file: flush the encoder, count its frames back, add the comment, move it into place."""
        if self._container is None:
            raise InputError(self.path, "no frames to write")
        try:
            self._container.mux(self._stream.encode(None))
            self._container.close()
            self._container = None
            decoded = count_frames(self._tmp)
            if decoded != self.n_frames:
                raise OdsplatError(f"{self.path}: wrote {self.n_frames} frames, {decoded} decode back ({self.codec})")
            if self.comment:
                add_comment(self._tmp, self.comment)
        except BaseException:
            self.abort()
            raise
        self._atomic.__exit__(None, None, None)
        self._tmp = None
        w, h = self._size
        return Mp4Info(self.path, self.n_frames, w, h, self.fps, self.codec, self.path.stat().st_size, self.comment)

    def abort(self) -> None:
        """Drop what was written (the temporary file); `path` is left as it was."""
        if self._container is not None:
            with contextlib.suppress(Exception):
                self._container.close()
            self._container = None
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
    """Put `text` in the mp4's moov/udta/meta/ilst '©cmt' (beside the '©too' FFmpeg's muxer writes there). Only
    where moov is the file's last box (as FFmpeg's mp4 muxer writes it without +faststart), so growing it moves no
    sample offset; otherwise logged and left out."""
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
