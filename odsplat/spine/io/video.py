"""Open a filmed test (Photron .cih/.cihx + .mraw, Phantom .cine, an image folder, a .npy array or a video file)
as one streaming `VideoSource` that never loads the frames whole."""
from __future__ import annotations

import glob
import logging
import math
import re
import struct
import xml.etree.ElementTree as ET
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from cine_reader import Cine, unpack_10bit_data

from odsplat.spine.errors import InputError
from odsplat.spine.io.limits import check_frame_rate
from odsplat.spine.io.mraw import unpack_12bit
from odsplat.spine.manifest import check_regular_file

log = logging.getLogger(__name__)

SUPPORTED_KINDS = (
    "a Photron .cih/.cihx header beside its .mraw, a Phantom .cine, a folder of .png/.tif/.tiff images, "
    "a .npy array (T, H, W) or (T, H, W, 3), or a .mp4/.avi/.mov/.mkv video"
)
_IMAGE_SUFFIXES = {".png", ".tif", ".tiff"}
_VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv"}
# OpenCV estimates a Matroska frame count from its duration, so it is counted by decoding instead.
_COUNT_BY_DECODING = {".mkv"}
_FPS_REL_TOL = 1e-3  # a user typing 29.97 for 30000/1001 fps means the same rate
_HEADER_INT = 2**31  # a Photron header's integers are 32-bit: anything beyond is a garbled field


@dataclass
class VideoSource(ABC):
    """A recording opened for streaming; `read` and `iter_chunks` deliver frames as numpy arrays."""

    path: Path
    n_frames: int
    height_px: int
    width_px: int
    n_colors: int  # 1 (mono) or 3 (RGB)
    dtype: np.dtype  # what frames are delivered as: uint8 or uint16
    bit_depth: int  # effective bits per sample: 8, 10, 12 or 16
    fps: float | None  # rate of the frames in this file
    trigger_frame: int | None  # file index of the trigger frame, when the header says
    start_frame: int | None  # camera frame number of the file's first frame (Photron), may be negative
    camera_model: str | None
    header: dict[str, Any]  # raw parsed header, JSON-serialisable
    frame_step: int = field(default=1, kw_only=True)  # camera frames between file frames (Photron save step)
    # False where bit_depth only follows the container (a 16-bit PNG or .npy may hold 12-bit data)
    bit_depth_known: bool = field(default=True, kw_only=True)

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """(H, W) for mono, (H, W, 3) for RGB."""
        hw = (self.height_px, self.width_px)
        return hw if self.n_colors == 1 else (*hw, self.n_colors)

    def read(self, start: int, stop: int) -> np.ndarray:
        """Frames start..stop-1 as a new array of shape (n, *frame_shape)."""
        if not 0 <= start <= stop <= self.n_frames:
            raise IndexError(f"{self.path}: frames {start}:{stop} lie outside 0:{self.n_frames}")
        return self._read(start, stop)

    def iter_chunks(self, chunk_frames: int = 64) -> Iterator[np.ndarray]:
        """All frames in order, `chunk_frames` at a time (the last chunk may be shorter)."""
        if chunk_frames < 1:
            raise ValueError(f"chunk_frames must be at least 1, got {chunk_frames}")
        for start in range(0, self.n_frames, chunk_frames):
            yield self.read(start, min(start + chunk_frames, self.n_frames))

    @abstractmethod
    def _read(self, start: int, stop: int) -> np.ndarray:
        """Frames start..stop-1, the range already checked."""


def open_video(path: str | PathLike, fps: float | None = None, *, recorded_fps: float | None = None) -> VideoSource:
    """Open a recording by its kind; `fps` supplies the rate where the file has none and must agree where it has.
    `recorded_fps` is the rate the frames were filmed at, replacing what the file says: a slow-motion clip filmed
    at 600 fps and stored for playback at 29.97 fps, as phones and many high-speed tools save them."""
    path = Path(path)
    for name, value in (("fps", fps), ("recorded_fps", recorded_fps)):
        if value is not None:
            check_frame_rate(value, name)
    if fps is not None and recorded_fps is not None:
        raise InputError("recorded_fps", "give fps (the file has no rate) or recorded_fps (the file's rate is "
                                         "its playback rate), not both")
    if not path.exists():
        raise InputError(path, "does not exist")
    suffix = path.suffix.lower()
    if not path.is_dir():
        check_regular_file(path, "recording")
    if path.is_dir():
        source = _open_image_sequence(path)
    elif suffix in (".cih", ".cihx", ".mraw"):
        source = _open_photron(path)
    elif suffix == ".cine":
        source = _open_cine(path)
    elif suffix == ".npy":
        source = _open_npy(path)
    elif suffix in _VIDEO_SUFFIXES:
        source = _open_video_file(path)
    else:
        raise InputError(path, f"is not a supported recording; expected {SUPPORTED_KINDS}")
    if min(source.n_frames, source.height_px, source.width_px) < 1:
        raise InputError(path, f"holds {source.n_frames} frames of {source.width_px}x{source.height_px} pixels; "
                               "nothing to import")
    if fps is not None:
        if source.fps is None:
            source.fps = float(fps)
        elif not math.isclose(fps, source.fps, rel_tol=_FPS_REL_TOL):
            raise InputError(path, f"the file says {source.fps:g} fps, but fps={fps:g} was given (a slow-motion "
                                   f"file filmed at {fps:g} fps: give recorded_fps = {fps:g} instead)")
    if recorded_fps is not None:
        if source.fps is not None and not math.isclose(recorded_fps, source.fps, rel_tol=_FPS_REL_TOL):
            log.info("%s: filmed at %g fps, stored for playback at %g fps (recorded_fps)", path, recorded_fps,
                     source.fps)
            source.header = {**source.header, "playback_fps": source.fps}
        source.fps = float(recorded_fps)
    log.debug("opened %s: %d frames of %s at %s fps", path, source.n_frames,
              _describe(source.frame_shape, source.dtype), source.fps)
    return source


# ---------------------------------------------------------------- Photron

@dataclass
class _PhotronSource(VideoSource):
    mraw_path: Path
    stored_bits: int  # bits per sample in the .mraw: 8, 12 (packed) or 16
    shift: int  # right shift that brings Higher-side data down to 0..2**bit_depth-1
    raw: np.memmap = field(repr=False, compare=False)

    def _read(self, start: int, stop: int) -> np.ndarray:
        raw = self.raw[start:stop]
        if self.stored_bits == 12:
            frames = unpack_12bit(raw).reshape((stop - start, *self.frame_shape))
        else:
            # A native-endian copy, so callers never hold (or write through) the file's map.
            frames = np.array(raw, dtype=self.dtype)
        if self.shift:
            frames >>= self.shift
        return frames



# The fields we use: (.cih key, .cihx element path). PFV 4 calls the save step "skipFrame".
_PHOTRON_FIELDS = {
    "fps": ("Record Rate(fps)", "recordInfo/recordRate"),
    "n_frames": ("Total Frame", "frameInfo/totalFrame"),
    "width": ("Image Width", "imageDataInfo/resolution/width"),
    "height": ("Image Height", "imageDataInfo/resolution/height"),
    "color_bit": ("Color Bit", "imageDataInfo/colorInfo/bit"),
    "color_type": ("Color Type", "imageDataInfo/colorInfo/type"),
    "effective_depth": ("EffectiveBit Depth", "imageDataInfo/effectiveBit/depth"),
    "effective_side": ("EffectiveBit Side", "imageDataInfo/effectiveBit/side"),
    "start_frame": ("Start Frame", "frameInfo/startFrame"),
    "correct_trigger_frame": ("Correct Trigger Frame", "frameInfo/correctTriggerFrame"),
    "save_step": ("Save Step", "frameInfo/skipFrame"),
    "recorded_frames": ("Original Total Frame", "frameInfo/recordedFrame"),
    "camera": ("Camera Type", "deviceInfo/deviceName"),
    "file_format": ("File Format", "imageFileInfo/fileFormat"),
}
# "Raw" is unprocessed sensor data (e.g. a Nova S16 -M, a mono camera): one channel, like Mono.
_PHOTRON_COLORS = {"mono": 1, "raw": 1, "color": 3}


def _open_photron(path: Path) -> _PhotronSource:
    cih_path, mraw_path = _photron_pair(path)
    header = _parse_cihx(cih_path) if cih_path.suffix.lower() == ".cihx" else _parse_cih(cih_path)
    xml = cih_path.suffix.lower() == ".cihx"

    def get(name: str, kind: type = str, default: Any = None) -> Any:
        key = _PHOTRON_FIELDS[name][xml]
        value = _lookup(header, key) if xml else header.get(key)
        if value in (None, ""):
            if default is None and kind is not str:
                raise InputError(cih_path, f"has no '{key}' field")
            return default
        try:
            if not isinstance(value, str):  # a .cihx element with children where a value belongs
                raise ValueError
            converted = kind(value)
        except ValueError:
            raise InputError(cih_path, f"field '{key}' = {value!r} is not a {kind.__name__}") from None
        if kind is int and not -_HEADER_INT <= converted < _HEADER_INT:
            raise InputError(cih_path, f"field '{key}' = {value!r} lies beyond the header's 32-bit integers")
        return converted

    file_format = get("file_format", default="MRaw")
    if file_format.lower() != "mraw":
        raise InputError(cih_path, f"its frames are stored as {file_format}, not MRaw; open their folder instead")
    width, height, n_frames = get("width", int), get("height", int), get("n_frames", int)
    color_type = get("color_type", default="Mono")
    n_colors = _PHOTRON_COLORS.get(color_type.lower())
    if n_colors is None:
        raise InputError(cih_path, f"Color Type {color_type!r} is not one of Mono, Raw or Color")
    stored_bits = get("color_bit", int)
    if stored_bits not in (8, 12, 16):
        raise InputError(cih_path, f"Color Bit {stored_bits} is not supported; expected 8, 12 (packed) or 16")
    if stored_bits == 12 and (width * height * n_colors) % 2:
        raise InputError(cih_path, f"packed 12-bit frames of {width}x{height} do not fill whole bytes")
    effective = get("effective_depth", int, stored_bits)
    if not 8 <= effective <= 16:
        raise InputError(cih_path, f"field '{_PHOTRON_FIELDS['effective_depth'][xml]}' = {effective}; expected 8 to "
                                   "16 bits")
    effective = min(effective, stored_bits)
    higher = get("effective_side", default="Lower").lower() == "higher"
    shift = 16 - effective if stored_bits == 16 and higher else 0
    if n_frames < 1 or width < 1 or height < 1:
        raise InputError(cih_path, f"declares {n_frames} frames of {width}x{height}; nothing to read")
    record_rate = check_frame_rate(get("fps", float), f"{cih_path}: {_PHOTRON_FIELDS['fps'][xml]}")
    step = get("save_step", int, 1)
    if step < 1:
        raise InputError(cih_path, f"declares a save step of {step}; expected 1 or more")

    _check_mraw_size(mraw_path, cih_path, n_frames, width, height, n_colors, stored_bits)
    frame_shape = (height, width) if n_colors == 1 else (height, width, n_colors)
    if stored_bits == 12:
        raw = np.memmap(mraw_path, dtype=np.uint8, mode="r", shape=(n_frames, width * height * n_colors * 3 // 2))
    else:
        raw = np.memmap(mraw_path, dtype="<u2" if stored_bits == 16 else np.uint8, mode="r",
                        shape=(n_frames, *frame_shape))

    # A file saved with a save step keeps every step-th camera frame, so its frames lie step / record
    # rate apart: fps is the rate of the frames in this file (data_showcase: every 100th at 15 kHz).
    # beam.cihx declares a step of 2500 for 4 frames out of 400 recorded, which cannot be: a header
    # that contradicts itself so is read as consecutive frames, with a warning.
    recorded = get("recorded_frames", int, 0)
    if step > 1 and recorded and step * (n_frames - 1) + 1 > recorded:
        log.warning("%s: a save step of %d cannot take %d frames out of %d recorded; reading the frames as "
                    "consecutive at the record rate", cih_path.name, step, n_frames, recorded)
        step = 1
    if step > 1:
        log.info("%s keeps every %d-th frame of a %g fps recording: %g fps in this file",
                 cih_path.name, step, record_rate, record_rate / step)
    # Photron numbers camera frames from the trigger, which is frame 0 ("Zero Frame : Exist"); "Start
    # Frame" is the number of the file's first frame: 0 for a start trigger, negative for an end or
    # centre trigger, beyond 0 when the saved range begins after it (ball_12bit: 52..66, no trigger).
    # So the trigger's file index is -start / step when that lands on a saved frame.
    start = get("start_frame", int, 0)
    trigger = -start // step if start <= 0 and -start % step == 0 and -start // step < n_frames else None
    if get("correct_trigger_frame", int, 0):
        log.warning("%s has a nonzero Correct Trigger Frame; the trigger index assumes the trigger is frame 0",
                    cih_path.name)
    return _PhotronSource(
        path=cih_path, n_frames=n_frames, height_px=height, width_px=width, n_colors=n_colors,
        dtype=np.dtype(np.uint8 if stored_bits == 8 else np.uint16), bit_depth=effective,
        fps=record_rate / step, frame_step=step, trigger_frame=trigger, start_frame=start, camera_model=get("camera"),
        header=header, mraw_path=mraw_path, stored_bits=stored_bits, shift=shift, raw=raw,
    )


def _photron_pair(path: Path) -> tuple[Path, Path]:
    """The header and data files of a Photron recording, from either one's path."""
    siblings = {p.suffix.lower(): p for p in path.parent.glob(f"{glob.escape(path.stem)}.*")}
    if path.suffix.lower() == ".mraw":
        cih = siblings.get(".cihx") or siblings.get(".cih")
        if cih is None:
            raise InputError(path, f"has no {path.stem}.cih or {path.stem}.cihx header beside it")
        return check_regular_file(cih, "Photron header"), check_regular_file(path, "Photron .mraw")
    mraw = siblings.get(".mraw")
    if mraw is None:
        raise InputError(path.with_suffix(".mraw"), f"is missing; {path.name} needs its frames beside it")
    return check_regular_file(path, "Photron header"), check_regular_file(mraw, "Photron .mraw")


def _check_mraw_size(mraw: Path, cih: Path, n_frames: int, width: int, height: int, n_colors: int,
                     bits: int) -> None:
    frame_bytes = width * height * n_colors * bits // 8
    expected = n_frames * frame_bytes
    size = mraw.stat().st_size
    if size == expected:
        return
    declared = (f"{cih.name} declares {n_frames} frames of {width}x{height}{' RGB' if n_colors == 3 else ''}"
                f" at {bits} bit = {expected} bytes")
    held = f"holds {size} bytes ({size / frame_bytes:.4g} frames)"
    if size < expected:
        raise InputError(mraw, f"truncated: {held}, {declared}")
    raise InputError(mraw, f"{held}, but {declared}; the header and {mraw.name} disagree on the frame count or size")


def _parse_cih(path: Path) -> dict[str, str]:
    """The camera section of a text .cih (`key : value` lines up to the first blank line); first value wins."""
    header: dict[str, str] = {}
    for line in path.read_bytes().decode("utf-8", errors="replace").splitlines():
        line = line.strip()
        if not line:
            if header:
                break
            continue
        if line.startswith("#") or ":" not in line:
            continue
        key, _, value = line.partition(":")
        header.setdefault(key.strip(), value.strip())
    if not header:
        raise InputError(path, "holds no 'key : value' lines; not a Photron .cih header")
    return header


def _parse_cihx(path: Path) -> dict[str, Any]:
    """The XML of a .cihx, which follows a binary preamble, as nested dicts of strings."""
    data = path.read_bytes()
    begin, end = data.find(b"<cih>"), data.rfind(b"</cih>")
    if begin < 0 or end < begin:
        raise InputError(path, "holds no <cih> ... </cih> block; not a Photron .cihx header")
    try:
        root = ET.fromstring(data[begin:end + len(b"</cih>")].decode("utf-8", errors="replace"))
    except ET.ParseError as exc:
        raise InputError(path, f"its XML is malformed ({exc})") from None
    return _xml_to_dict(root)


def _xml_to_dict(element: ET.Element) -> Any:
    if len(element) == 0:
        return (element.text or "").strip()
    out: dict[str, Any] = {}
    for child in element:
        value = _xml_to_dict(child)
        if child.tag in out:  # repeated elements (e.g. externalOutInfo) become a list
            previous = out[child.tag]
            out[child.tag] = [*previous, value] if isinstance(previous, list) else [previous, value]
        else:
            out[child.tag] = value
    return out


def _lookup(tree: dict[str, Any], key: str) -> Any:
    node: Any = tree
    for part in key.split("/"):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


# ---------------------------------------------------------------- Phantom .cine

# CINEFILEHEADER (44 bytes, little-endian): Type "CI", Headersize, Compression, Version, FirstMovieImage,
# TotalImageCount, FirstImageNo, ImageCount, OffImageHeader, OffSetup, OffImageOffsets, TriggerTime.
_CINE_HEADER = struct.Struct("<2sHHHiIiIIIIQ")
_CINE_PACKED_10BIT = 256  # BITMAPINFOHEADER.biCompression of Phantom's packed 10-bit frames
_CINE_GRAY = 0  # CINEFILEHEADER.Compression of grey frames (1: JPEG, 2: raw colour, not read)


@dataclass
class _CineSource(VideoSource):
    offsets: np.ndarray = field(repr=False)  # file position of each frame's annotation block
    image_bytes: int  # bytes of one frame's pixels
    packed: bool  # Phantom packed 10-bit, linearised to 12 bit on reading
    bottom_up: bool  # rows stored bottom first (a BMP's positive biHeight)

    def _read(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, *self.frame_shape), dtype=self.dtype)
        with self.path.open("rb") as f:
            for i in range(start, stop):
                f.seek(int(self.offsets[i]))
                annotation = int.from_bytes(f.read(4), "little")  # its size, these 4 bytes included
                f.seek(int(self.offsets[i]) + annotation)
                data = f.read(self.image_bytes)
                if len(data) != self.image_bytes or annotation < 8:
                    raise InputError(self.path, f"truncated: frame {i} ends past the end of the file")
                if self.packed:
                    # Phantom's 10-bit codes are not linear: cine-handler unpacks them and maps each through
                    # Vision Research's LinLUT to its linear 12-bit value.
                    frame = unpack_10bit_data(data)[: self.height_px * self.width_px]
                else:
                    frame = np.frombuffer(data, dtype=self.dtype)
                frame = frame.reshape(self.frame_shape)
                out[i - start] = frame[::-1] if self.bottom_up else frame
        return out


def _open_cine(path: Path) -> _CineSource:
    """A Phantom .cine of grey frames (8 or 16 bit, or packed 10 bit). The headers are read with cine-handler
    (`cine_reader`, what pyidi uses); the frames are located and decoded here, so that each is checked against
    the file's size and a header field the file does not hold (a field past an older SETUP's end) is never used."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(_CINE_HEADER.size)
    if len(head) < _CINE_HEADER.size:
        raise InputError(path, f"truncated: holds {size} bytes, less than the {_CINE_HEADER.size}-byte file header")
    (kind, _, compression, version, _, total, first_no, count, _, off_setup, off_offsets,
     _) = _CINE_HEADER.unpack(head)
    if kind != b"CI":
        raise InputError(path, f"Type is {kind!r}, not b'CI': not a Phantom .cine file")
    if version not in (0, 1):
        raise InputError(path, f"Version is {version}; a .cine header says 0 or 1")
    if compression != _CINE_GRAY:
        raise InputError(path, f"Compression is {compression} (1: JPEG, 2: raw colour); only grey frames (0) "
                               "are read: save the cine uncompressed from PCC")
    if count < 1:
        raise InputError(path, "ImageCount is 0: the file holds no frames")
    offset_bytes = 8 if version == 1 else 4
    table_end = off_offsets + count * offset_bytes
    if off_setup >= off_offsets or table_end > size:
        raise InputError(path, f"truncated or garbled: OffImageOffsets {off_offsets} + ImageCount {count} x "
                               f"{offset_bytes} bytes = {table_end}, but the file holds {size} bytes")
    try:
        cine = Cine(path, keep_annotations=False)
        cine.close_file()
    except (ValueError, EOFError, IndexError, struct.error) as exc:
        raise InputError(path, f"its headers cannot be read as a Phantom .cine ({exc})") from None
    bitmap, setup = cine.image_header, cine.camera_setup
    width, height, bits = int(bitmap.biWidth), abs(int(bitmap.biHeight)), int(bitmap.biBitCount)
    if width < 1 or height < 1:
        raise InputError(path, f"biWidth {width} x biHeight {bitmap.biHeight}: no frame to read")
    if bits not in (8, 16) or int(getattr(setup, "CFA", 0)) or bool(setup.bEnableColor):
        raise InputError(path, f"holds colour frames (biBitCount {bits}, CFA {getattr(setup, 'CFA', 0)}); only "
                               "grey cines are read")
    packed = int(bitmap.biCompression) == _CINE_PACKED_10BIT
    if int(bitmap.biCompression) not in (0, _CINE_PACKED_10BIT):
        raise InputError(path, f"biCompression is {bitmap.biCompression}; expected 0 or 256 (packed 10-bit)")
    image_bytes = width * height * (10 if packed else bits) // 8
    if int(bitmap.biSizeImage) not in (0, image_bytes):
        raise InputError(path, f"biSizeImage is {bitmap.biSizeImage} bytes, but {width}x{height} at "
                               f"{10 if packed else bits} bit is {image_bytes}")
    offsets = np.asarray(cine.image_locations.pImage[:count], dtype=np.int64)
    beyond = np.flatnonzero(offsets + 8 + image_bytes > size)
    if beyond.size:
        raise InputError(path, f"truncated: holds {size} bytes, {beyond[0]} whole frames of the {count} its "
                               f"header (ImageCount) declares")
    # The integer FrameRate is always there; the exact dFrameRate only in newer SETUPs (the sample's, of
    # software 717, ends before it, and what lies there is not a rate): it is trusted where it rounds to it.
    rate = float(setup.FrameRate)
    exact = float(setup.dFrameRate)
    if math.isfinite(exact) and exact > 0 and abs(exact - rate) <= 1.0:
        rate = exact
    rate = check_frame_rate(rate, f"{path}: FrameRate")
    real_bpp = int(setup.RealBPP)
    if packed:
        bit_depth = 12  # linearised
    elif bits == 8:
        bit_depth = 8
    else:
        bit_depth = real_bpp if 8 < real_bpp <= 16 else 16
    # Phantom numbers images from the trigger (image 0); FirstImageNo is the number of the file's first.
    trigger = -first_no if 0 <= -first_no < count else None
    serial = getattr(setup, "Serial", None)
    model = f"Phantom, serial {serial}" if serial else "Phantom"
    header = {"FirstImageNo": first_no, "ImageCount": count, "TotalImageCount": total, "FrameRate": rate,
              "ShutterNs": int(setup.ShutterNs), "RealBPP": real_bpp, "biBitCount": bits,
              "biCompression": int(bitmap.biCompression), "biWidth": width, "biHeight": int(bitmap.biHeight),
              "Version": version}
    return _CineSource(
        path=path, n_frames=count, height_px=height, width_px=width, n_colors=1,
        dtype=np.dtype(np.uint8 if bits == 8 else np.uint16), bit_depth=bit_depth, fps=rate,
        trigger_frame=trigger, start_frame=first_no, camera_model=model, header=header,
        offsets=offsets, image_bytes=image_bytes, packed=packed, bottom_up=not packed and int(bitmap.biHeight) > 0,
    )


# ---------------------------------------------------------------- image sequences

@dataclass
class _ImageSequenceSource(VideoSource):
    files: list[Path] = field(repr=False)

    def _read(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, *self.frame_shape), dtype=self.dtype)
        for i, file in enumerate(self.files[start:stop]):
            image = _read_image(file)
            if image.shape != self.frame_shape or image.dtype != self.dtype:
                raise InputError(file, f"is {_describe(image.shape, image.dtype)}, but the sequence's first "
                                       f"image {self.files[0].name} is {_describe(self.frame_shape, self.dtype)}")
            out[i] = image
        return out


def _open_image_sequence(folder: Path) -> _ImageSequenceSource:
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES),
                   key=_natural_key)
    if not files:
        raise InputError(folder, f"holds no .png, .tif or .tiff images; expected {SUPPORTED_KINDS}")
    first = _read_image(files[0])
    if first.dtype not in (np.uint8, np.uint16):
        raise InputError(files[0], f"has pixels of {first.dtype}; image sequences must be uint8 or uint16")
    # bit_depth follows the container (8 or 16): the importer finds a 16-bit file's from its data or the rig.
    return _ImageSequenceSource(
        path=folder, n_frames=len(files), height_px=first.shape[0], width_px=first.shape[1],
        n_colors=1 if first.ndim == 2 else 3, dtype=first.dtype, bit_depth=first.dtype.itemsize * 8,
        fps=None, trigger_frame=None, start_frame=None, camera_model=None,
        header={"n_files": len(files), "first_file": files[0].name, "last_file": files[-1].name},
        files=files, bit_depth_known=first.dtype == np.uint8,
    )


def _natural_key(path: Path) -> list[int | str]:
    """frame_2 before frame_10: digit runs compare as numbers."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def _read_image(path: Path) -> np.ndarray:
    """One image as (H, W) or RGB (H, W, 3); alpha is dropped."""
    # imdecode of the bytes, because cv2.imread cannot open non-ASCII paths on Windows.
    data = np.fromfile(check_regular_file(path, "image"), dtype=np.uint8)
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except cv2.error:
        image = None
    if image is None or image.size == 0:
        raise InputError(path, f"cannot be decoded as an image ({data.size} bytes)")
    if image.ndim == 3:  # BGR(A) to RGB; grey + alpha to grey
        image = image[..., 0] if image.shape[2] <= 2 else np.ascontiguousarray(image[..., 2::-1])
    return image


def _describe(shape: tuple[int, ...], dtype: np.dtype) -> str:
    return f"{shape[1]}x{shape[0]}{' RGB' if len(shape) == 3 else ''} {np.dtype(dtype)}"


# ---------------------------------------------------------------- .npy

@dataclass
class _NpySource(VideoSource):
    array: np.ndarray = field(repr=False, compare=False)

    def _read(self, start: int, stop: int) -> np.ndarray:
        return np.array(self.array[start:stop])


def _open_npy(path: Path) -> _NpySource:
    # open_memmap, not np.load: np.load opens a zip (an .npz renamed) as an NpzFile, and the header is parsed
    # here, so whatever a garbled one raises is caught; the mapping checks the file holds what the header says.
    try:
        array = np.lib.format.open_memmap(path, mode="r")
    except Exception as exc:  # numpy's header parser raises what the text makes it (TokenError, SyntaxError, ...)
        raise InputError(path, f"cannot be read as a plain .npy array ({type(exc).__name__}: "
                               f"{str(exc).splitlines()[0] if str(exc) else 'empty'})") from None
    # A header that says fewer frames or pixels than the file holds would map part of it and drop the rest.
    held = path.stat().st_size - array.offset
    if held != array.nbytes:
        raise InputError(path, f"its header says {array.shape} of {array.dtype} ({array.nbytes} bytes), but the file "
                               f"holds {held} bytes after the header")
    if array.dtype not in (np.uint8, np.uint16) or not array.dtype.isnative:
        raise InputError(path, f"has dtype {array.dtype}; accepted: uint8 or uint16 (native byte order)")
    if not (array.ndim == 3 or (array.ndim == 4 and array.shape[3] == 3)):
        raise InputError(path, f"has shape {array.shape}; accepted: (T, H, W) or (T, H, W, 3)")
    return _NpySource(
        path=path, n_frames=array.shape[0], height_px=array.shape[1], width_px=array.shape[2],
        n_colors=1 if array.ndim == 3 else 3, dtype=array.dtype, bit_depth=array.dtype.itemsize * 8,
        fps=None, trigger_frame=None, start_frame=None, camera_model=None,
        header={"shape": list(array.shape), "dtype": str(array.dtype)}, array=array,
        bit_depth_known=array.dtype == np.uint8,
    )


# ---------------------------------------------------------------- video files

@dataclass
class _VideoFileSource(VideoSource):
    _capture: cv2.VideoCapture | None = field(default=None, init=False, repr=False, compare=False)
    _next: int = field(default=0, init=False, repr=False, compare=False)  # index the capture decodes next

    def _read(self, start: int, stop: int) -> np.ndarray:
        # Decoding forward from a fresh capture is exact; CAP_PROP_POS_FRAMES seeks can land off by a
        # few frames on streams with B-frames. Reading in order (iter_chunks) never rewinds.
        if self._capture is None or start < self._next:
            self._capture, self._next = _open_capture(self.path), 0
        while self._next < start:
            self._advance(self._capture.grab())
        out = np.empty((stop - start, *self.frame_shape), dtype=np.uint8)
        for i in range(stop - start):
            ok, frame = self._capture.read()
            self._advance(ok)
            cv2.cvtColor(frame, cv2.COLOR_BGR2RGB, dst=out[i])
        return out

    def _advance(self, ok: bool) -> None:
        if not ok:
            raise InputError(self.path, f"ended after {self._next} frames, though {self.n_frames} were expected")
        self._next += 1


def _open_capture(path: Path) -> cv2.VideoCapture:
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise InputError(path, "cannot be opened as a video by OpenCV (unknown codec or damaged file)")
    return capture


def _open_video_file(path: Path) -> _VideoFileSource:
    capture = _open_capture(path)
    try:
        fps_property = capture.get(cv2.CAP_PROP_FPS)
        count_property = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fourcc = int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode("latin-1").strip("\0 ")
        # The decoded size, not the container's: rotation metadata can swap width and height.
        ok, first = capture.read()
        if not ok:
            raise InputError(path, "holds no decodable frame")
        n_frames = count_property
        if count_property <= 0 or path.suffix.lower() in _COUNT_BY_DECODING:
            n_frames = 1
            while capture.grab():
                n_frames += 1
            log.info("%s: counted %d frames by decoding (the container said %d)", path.name, n_frames,
                     count_property)
    finally:
        capture.release()
    # Three channels even when R = G = B: a grey-looking first frame does not prove a mono camera.
    return _VideoFileSource(
        path=path, n_frames=n_frames, height_px=first.shape[0], width_px=first.shape[1], n_colors=3,
        dtype=np.dtype(np.uint8), bit_depth=8, fps=_container_rate(path, fps_property),
        trigger_frame=None, start_frame=None, camera_model=None,
        header={"fourcc": fourcc, "frame_count_property": count_property, "fps_property": fps_property},
    )


def _container_rate(path: Path, fps_property: float) -> float | None:
    """The container's frame rate, None where OpenCV reports none or one no camera films at (give fps then)."""
    try:
        return check_frame_rate(fps_property, str(path)) if fps_property else None
    except InputError as exc:
        log.warning("%s: ignoring the container's frame rate (%s); give the take's fps", path.name, exc.problem)
        return None
