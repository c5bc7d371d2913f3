"""`odsplat import`: build a capture from recordings of other equipment plus a small rig file.

The rig file format is documented in docs/import.md. The capture is assembled in a temporary
directory beside the target and renamed into place only when every take has been written,
so a bad input leaves nothing behind.
"""
from __future__ import annotations

import glob
import logging
import math
import os
import shutil
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from odsplat.spine.atomic import fsync_path
from odsplat.spine.errors import InputError
from odsplat.spine.io.signals import SignalSet, read_signals
from odsplat.spine.io.video import VideoSource, open_video
from odsplat.spine.manifest import (
    CHANNEL_KINDS,
    CameraInfo,
    ChannelInfo,
    Intrinsics,
    Manifest,
    TagLayout,
    Viewpoint,
    check_name,
    check_regular_file,
    from_plain,
    load_toml,
)
from odsplat.spine.store import Capture
from odsplat.spine.take_writer import QCInfo, TriggerInfo

log = logging.getLogger(__name__)

RATE_TOLERANCE = 1e-6  # signal files whose rates differ by less (relative) share one clock
_TEMPORARY = ".importing-"  # a capture is built in OUT's folder as .NAME.importing-HOST-PID, then renamed to OUT
BIT_DEPTHS = (8, 10, 12, 14, 16)  # what [camera] bit_depth accepts, and what detection chooses from


@dataclass
class RigChannel:
    """A channel of the rig file: the manifest's ChannelInfo plus where to find it in the files."""

    name: str
    kind: str
    column: str | None = None
    unit: str | None = None
    sensitivity_v_per_unit: float | None = None
    position_m: list[float] | None = None
    direction: list[float] | None = None
    node: int | None = None
    device: str = ""

    def info(self) -> ChannelInfo:
        return ChannelInfo(
            name=self.name,
            kind=self.kind,
            unit=CHANNEL_KINDS.get(self.kind, "?"),
            sensitivity_v_per_unit=self.sensitivity_v_per_unit,
            position_m=self.position_m,
            direction=self.direction,
            node=self.node,
            device=self.device,
        )


@dataclass
class RigTake:
    name: str | None = None
    view: int | None = None
    video: str | None = None
    signals: str | None = None
    fps: float | None = None
    pretrigger_samples: int | None = None
    camera_trigger_time_s: float | None = None
    trigger_frame: int | None = None   # file index of the camera's trigger frame (image sequences, .npy, video files)
    recorded_fps: float | None = None  # the rate a slow-motion file was filmed at (its own says its playback)
    time_column: str | None = None     # the signal file's time column, when not the first with a time name
    sample_rate_hz: float | None = None  # the DAQ's rate: used as the rate; needed by a CSV without a time column
    notes: str = ""

    def validate(self, where: str) -> None:
        """The take's own fields; those that need its files (trigger_frame, pretrigger_samples' upper bound, the
        rates) are checked when they are read."""
        if self.name is not None:
            check_name(self.name, f"{where}.name")
        for field_name in ("video", "signals"):
            value = getattr(self, field_name)
            if value is not None and not value.strip():
                raise InputError(f"{where}.{field_name}", "is empty; name a file, or leave the field out")
        if self.video is None and self.signals is None:
            raise InputError(where, "a take needs a video, a signals file, or both")
        for field_name in ("view", "pretrigger_samples"):
            value = getattr(self, field_name)
            if value is not None and value < 0:
                raise InputError(f"{where}.{field_name}", f"expected 0 or more; got {value}")


@dataclass
class RigCamera:
    model: str | None = None
    intrinsics: Intrinsics | None = None
    exposure_s: float | None = None
    bit_depth: int | None = None  # bits of data per sample (12 in 16-bit words); default: the header's, else the data's

    def validate(self, where: str) -> None:
        if self.exposure_s is not None and not self.exposure_s > 0:
            raise InputError(f"{where}.exposure_s", f"expected a positive time in s; got {self.exposure_s}")
        if self.intrinsics is not None:
            self.intrinsics.validate(f"{where}.intrinsics")


@dataclass
class Rig:
    name: str
    takes: list[RigTake]
    camera: RigCamera = field(default_factory=RigCamera)
    channels: list[RigChannel] = field(default_factory=list)
    tags: TagLayout | None = None
    views: list[Viewpoint] = field(default_factory=list)
    static: list[str] = field(default_factory=list)
    structure: dict[str, Any] = field(default_factory=dict)
    notes: str = ""

    @classmethod
    def load(cls, path: str | Path) -> Rig:
        """The rig file, every field checked on its own (the files it names are checked when opened)."""
        path = Path(path)
        plain = load_toml(path, missing="no such rig file")
        _check_plain(plain, str(path))
        rig = from_plain(cls, plain, str(path))
        if not rig.takes:
            raise InputError(f"{path}: takes", "the rig lists no takes; add at least one [[takes]] table")
        names: set[str] = set()
        for i, take in enumerate(rig.takes):
            take.validate(f"{path}: takes[{i}]")
            if take.name in names:
                raise InputError(f"{path}: takes[{i}].name", f"{take.name!r} names an earlier take too")
            names.add(take.name)
        for i, ch in enumerate(rig.channels):
            ch.info().validate(f"{path}: channels[{i}]")
        rig.camera.validate(f"{path}: camera")
        if rig.tags is not None:
            rig.tags.validate(f"{path}: tags")
        for i, view in enumerate(rig.views):
            view.validate(f"{path}: views[{i}]")
        return rig


def _check_plain(value: Any, where: str) -> None:
    """What no field of a rig may hold: a NaN or infinite number (TOML spells them nan and inf), an integer beyond
    64 bits, or a string with a NUL (a name, a path or a note: each ends up in a file name or an HDF5 attribute)."""
    if isinstance(value, dict):
        for key, item in value.items():
            _check_plain(item, f"{where}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_plain(item, f"{where}[{i}]")
    elif isinstance(value, float) and not math.isfinite(value):
        raise InputError(where, f"expected a finite number; got {value}")
    elif isinstance(value, int) and not -2**63 <= value < 2**63:   # HDF5 attributes and JSON readers hold 64 bits
        raise InputError(where, f"expected an integer of at most 64 bits; got {value}")
    elif isinstance(value, str) and "\0" in value:
        raise InputError(where, f"holds a NUL character: {value!r}")


def import_capture(rig_path: str | Path, out: str | Path, *, data_dir: str | Path | None = None,
                   chunk_frames: int = 64) -> Capture:
    """Build the capture `out` from the rig file; relative paths resolve against `data_dir` (default: the rig's
    folder)."""
    rig_path = Path(rig_path)
    rig = Rig.load(rig_path)
    base = Path(data_dir) if data_dir is not None else rig_path.parent
    if not base.is_dir():
        raise InputError(base, "is not a folder; --data names the folder the rig's file names are relative to")
    out = Path(out)
    if out.exists() or out.is_symlink():
        raise InputError(out, "exists already; choose a new capture directory")
    if not out.parent.is_dir():
        problem = "is not a folder" if out.parent.exists() else "does not exist"
        raise InputError(out, f"its folder {out.parent} {problem}; the capture is created in an existing folder")
    _remove_stale_temporaries(out.parent)
    tmp = out.with_name(f".{out.name}{_TEMPORARY}{socket.gethostname()}-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        capture = _build(rig, rig_path, base.resolve(), tmp, chunk_frames)
        os.replace(tmp, out)
        fsync_path(out.parent)
    except OSError as exc:   # the disk, not the input: full, read-only, a name too long for the file system
        shutil.rmtree(tmp, ignore_errors=True)
        raise InputError(exc.filename or out, exc.strerror or str(exc)) from exc
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("imported %d takes into %s", len(capture.manifest.takes), out)
    return Capture.open(out)   # opened anew: the one built has its root and derived paths in the temporary folder


def _remove_stale_temporaries(folder: Path) -> None:
    """Remove what killed imports left in `folder`: temporaries of this host whose process is gone."""
    if os.name != "posix":   # no cheap, safe test of a process's life: leave them
        return
    host = socket.gethostname()
    for path in folder.glob(f".*{_TEMPORARY}*"):
        owner, _, pid = path.name.rpartition(_TEMPORARY)[2].rpartition("-")
        if not pid.isdigit() or owner not in ("", host) or not path.is_dir() or path.is_symlink():
            continue
        try:
            os.kill(int(pid), 0)
            continue   # still running (an import beside this one)
        except ProcessLookupError:
            pass
        except (PermissionError, OverflowError):
            continue   # another user's live process, or no PID at all
        log.info("removing %s, left by an import that was killed (process %s is gone)", path, pid)
        shutil.rmtree(path, ignore_errors=True)


def _build(rig: Rig, rig_path: Path, base: Path, root: Path, chunk_frames: int) -> Capture:
    # Open and check every input before writing anything, so errors surface early.
    videos: list[VideoSource | None] = []
    signals: list[SignalSet | None] = []
    for i, take in enumerate(rig.takes):
        where = f"{rig_path}: takes[{i}]"
        try:
            videos.append(open_video(_resolve(base, take.video, f"{where}.video"), fps=take.fps,
                                     recorded_fps=take.recorded_fps) if take.video is not None else None)
        except InputError as exc:
            if exc.source in ("fps", "recorded_fps"):   # a rig value: name where it stands
                raise InputError(f"{where}.{exc.source}", exc.problem) from None
            raise
        if videos[-1] is not None and videos[-1].fps is None:
            raise InputError(f"{where}.fps", f"{videos[-1].path.name} holds no frame rate; give the take's fps")
        signals.append(_read_take_signals(rig, base, take, where) if take.signals is not None else None)
        _check_trigger_frame(f"{where}.trigger_frame", take, videos[-1])
        _check_pretrigger(f"{where}.pretrigger_samples", take, signals[-1])
    _resolve_bit_depth(rig, rig_path, videos, chunk_frames)
    camera = _camera_info(rig, rig_path, videos)
    rates = sorted({s.sample_rate_hz for s in signals if s is not None})
    # Time stamps printed to 7 significant digits put the same clock at rates 1e-7 apart: one rate to 1e-6.
    if rates and rates[-1] - rates[0] > RATE_TOLERANCE * rates[0]:
        raise InputError(f"{rig_path}: takes", f"signal files disagree on the sample rate: {rates} Hz (more than "
                                               f"{RATE_TOLERANCE:g} apart)")
    rates = {float(np.median(rates))} if rates else set()
    manifest = Manifest(
        name=rig.name,
        camera=camera,
        daq_sample_rate_hz=rates.pop() if rates else None,
        channels=[c.info() for c in rig.channels],
        tags=rig.tags,
        views=rig.views,
        structure=rig.structure,
        notes=rig.notes,
    )
    static = _static_files(rig, rig_path, base)
    capture = Capture.create(root, manifest)
    capture.copy_static(static)
    declared = f"{rig_path}: camera.bit_depth" if rig.camera.bit_depth is not None else None
    for take, video, sigs in zip(rig.takes, videos, signals):
        _write_take(capture, take, video, sigs, chunk_frames, declared)
    return capture


def _check_pretrigger(where: str, take: RigTake, sigs: SignalSet | None) -> None:
    if take.pretrigger_samples is None:
        return
    if sigs is None:
        raise InputError(where, "pretrigger samples need the take's signals file")
    if take.pretrigger_samples >= sigs.n_samples:
        raise InputError(where, f"{take.pretrigger_samples}, but {sigs.path.name} holds {sigs.n_samples} samples")


def _resolve(base: Path, name: str, where: str) -> Path:
    """A file the rig names, relative to `base` (resolved already): resolved, links followed, it must lie in it."""
    if not name.strip():
        raise InputError(where, "is empty; name a file, or leave the field out")
    path = (base / name).resolve()
    if not path.is_relative_to(base):
        raise InputError(where, f"{name!r} leads outside {base} (to {path}); the rig's files must lie in the data "
                                "folder (--data, default: the rig file's folder)")
    return path


def _static_files(rig: Rig, rig_path: Path, base: Path) -> list[Path]:
    """The files the rig's `static` patterns match: regular files in the data folder, one name each."""
    files: dict[str, Path] = {}
    for i, pattern in enumerate(rig.static):
        where = f"{rig_path}: static[{i}]"
        _resolve(base, pattern, where)   # the pattern itself, before anything is matched
        matches = sorted(glob.glob(str(base / pattern)))
        if not matches:
            raise InputError(where, f"{pattern!r} matches no file in {base}")
        for match in matches:
            path = check_regular_file(_resolve(base, match, where), "file (static photos are files)")
            if path.name in files and files[path.name] != path:
                raise InputError(where, f"{path} and {files[path.name]} would both be static/{path.name}")
            files[path.name] = path
    return list(files.values())


def _read_take_signals(rig: Rig, base: Path, take: RigTake, where: str) -> SignalSet:
    path = _resolve(base, take.signals, f"{where}.signals")
    columns = [c.column or c.name for c in rig.channels]
    if not columns:
        raise InputError(path, "the rig declares no [[channels]], so there is nothing to read from the signal file")
    units = {c.column or c.name: c.unit for c in rig.channels if c.unit}
    sigs = read_signals(path, units=units, columns=columns, time_column=take.time_column,
                        sample_rate_hz=take.sample_rate_hz)
    for ch, col in zip(rig.channels, columns):
        si = sigs.channel(col).unit
        if si != CHANNEL_KINDS[ch.kind]:
            raise InputError(path, f"column {col!r} is in {si}, but channel {ch.name!r} is a {ch.kind} channel "
                                   f"({CHANNEL_KINDS[ch.kind]}); fix the rig's kind or unit")
    return sigs


def _resolve_bit_depth(rig: Rig, rig_path: Path, videos: list[VideoSource | None], chunk_frames: int) -> None:
    """Each video's bit depth: the rig's [camera] bit_depth where given (checked against the container here and
    against the data as it is written), else the header's, else the smallest of BIT_DEPTHS that holds the data."""
    declared, where = rig.camera.bit_depth, f"{rig_path}: camera.bit_depth"
    if declared is not None and declared not in BIT_DEPTHS:
        raise InputError(where, f"expected one of {', '.join(map(str, BIT_DEPTHS))}; got {declared}")
    for video in videos:
        if video is None:
            continue
        container = video.dtype.itemsize * 8
        if declared is not None:
            if declared > container:
                raise InputError(where, f"{declared}, but {video.path.name} holds {container}-bit samples "
                                        f"({video.dtype})")
            if video.bit_depth_known and video.bit_depth != declared:
                log.info("%s: its header says %d bit; the rig's camera.bit_depth says %d", video.path.name,
                         video.bit_depth, declared)
            video.bit_depth = declared
        elif not video.bit_depth_known:
            peak = max(int(chunk.max()) for chunk in video.iter_chunks(chunk_frames))
            video.bit_depth = next(bits for bits in BIT_DEPTHS if peak < 2**bits)
            log.info("%s: %d-bit data detected in %d-bit samples (the largest value is %d); give [camera] bit_depth "
                     "in the rig to say otherwise", video.path.name, video.bit_depth, container, peak)


def _camera_info(rig: Rig, rig_path: Path, videos: list[VideoSource | None]) -> CameraInfo:
    present = [v for v in videos if v is not None]
    if not present:
        return CameraInfo(model=rig.camera.model or "none", intrinsics=rig.camera.intrinsics)
    first = present[0]
    for v in present[1:]:
        if (v.frame_shape, v.fps, v.bit_depth) != (first.frame_shape, first.fps, first.bit_depth):
            raise InputError(v.path, f"{v.frame_shape} at {v.fps} fps, {v.bit_depth} bit differs from the first "
                                     f"take's {first.frame_shape} at {first.fps} fps, {first.bit_depth} bit "
                                     f"({first.path.name})")
    return CameraInfo(
        model=rig.camera.model or first.camera_model or "unknown",
        width_px=first.width_px,
        height_px=first.height_px,
        fps=first.fps,
        bit_depth=first.bit_depth,
        n_colors=first.n_colors,
        exposure_s=rig.camera.exposure_s,
        intrinsics=rig.camera.intrinsics,
    )


def _write_take(capture: Capture, take: RigTake, video: VideoSource | None, sigs: SignalSet | None,
                chunk_frames: int, declared_bit_depth: str | None) -> None:
    """Write one take; a frame holding more bits than the video's bit depth is refused, naming the rig's bit_depth
    field (`declared_bit_depth`) when the rig gives one, else the file whose header says it."""
    manifest = capture.manifest
    attrs: dict[str, Any] = {"source": "import", "notes": take.notes}
    if video is not None:
        attrs["source_video"] = str(video.path)
        attrs["video_header"] = video.header
    if sigs is not None:
        attrs["source_signals"] = str(sigs.path)
    writer = capture.new_take(
        take.name,
        view=take.view,
        frame_shape=video.frame_shape if video else None,
        dtype=video.dtype if video else np.uint16,
        bit_depth=video.bit_depth if video else None,
        channels=manifest.channels if sigs else [],
        fps=video.fps if video else None,
        attrs=attrs,
        daq_t0_s=sigs.t0_s if sigs else 0.0,
    )
    with writer:
        trigger_sample = take.pretrigger_samples
        trigger_time_s = None
        if sigs is not None:
            # The signals were read with the rig's columns in the manifest's channel order.
            writer.append_samples({ch.name: sc.values for ch, sc in zip(manifest.channels, sigs.channels, strict=True)})
            if trigger_sample is not None:
                trigger_time_s = sigs.t0_s + trigger_sample / sigs.sample_rate_hz
        camera_trigger = _trigger_frame(take, video) if video else None
        if video is not None:
            counter = _camera_frame_numbers(video, camera_trigger)
            times = _frame_times(video, counter, take)
            progress = tqdm(total=video.n_frames, desc=f"import {writer.name}", unit="frame", leave=False,
                            disable=None)
            k = 0
            for block in video.iter_chunks(chunk_frames):
                n = len(block)
                _check_bit_depth(declared_bit_depth, video, block, k)
                writer.append_frames(block, times[k:k + n], counter[k:k + n])
                k += n
                progress.update(n)
            progress.close()
            if k != video.n_frames:
                raise InputError(video.path, f"delivered {k} frames, but its header declares {video.n_frames}")
        writer.set_trigger(TriggerInfo(
            trigger_sample=trigger_sample,
            pretrigger_samples=take.pretrigger_samples,
            camera_trigger_frame=camera_trigger,
            trigger_time_s=trigger_time_s,
        ))
        writer.set_qc(QCInfo(status="unchecked", notes="imported; hit QC not yet run"))
        writer.finalize()


def _check_bit_depth(declared: str | None, video: VideoSource, block: np.ndarray, first: int) -> None:
    peak = int(block.max()) if block.size else 0
    if peak >> video.bit_depth:
        frame = first + int(np.argmax(block.reshape(len(block), -1).max(axis=1)))
        if declared is not None:
            raise InputError(declared, f"{video.bit_depth}, but frame {frame} of {video.path.name} holds {peak}, "
                                       f"more than {2**video.bit_depth - 1}; give the data's bit depth or leave it "
                                       "out to detect it")
        raise InputError(video.path, f"its header says {video.bit_depth}-bit data, but frame {frame} holds {peak}, "
                                     f"more than {2**video.bit_depth - 1}; give [camera] bit_depth in the rig if the "
                                     "header is wrong")


def _check_trigger_frame(where: str, take: RigTake, video: VideoSource | None) -> None:
    if take.trigger_frame is None:
        return
    if video is None:
        raise InputError(where, "a trigger frame needs the take's video")
    if not 0 <= take.trigger_frame < video.n_frames:
        raise InputError(where, f"expected a frame index from 0 to {video.n_frames - 1}; got {take.trigger_frame}")
    if video.trigger_frame is not None and video.trigger_frame != take.trigger_frame:
        raise InputError(where, f"{take.trigger_frame}, but the header of {video.path.name} says "
                                f"{video.trigger_frame}")


def _trigger_frame(take: RigTake, video: VideoSource) -> int | None:
    """The file index of the camera's trigger frame: the rig's, else the file header's (None: unknown)."""
    return take.trigger_frame if take.trigger_frame is not None else video.trigger_frame


def _camera_frame_numbers(video: VideoSource, trigger: int | None) -> np.ndarray:
    """The camera's frame number of each file frame, the trigger frame being 0 (as sync reads them): Photron's
    own numbering, else the file index less the trigger frame's (the first frame when unknown)."""
    index = np.arange(video.n_frames)
    if video.start_frame is None:
        return index - (trigger or 0)
    return video.start_frame + index * video.frame_step


def _frame_times(video: VideoSource, counter: np.ndarray, take: RigTake) -> np.ndarray:
    """Frame times in the DAQ time base when the rig says when the camera's trigger frame was exposed."""
    if take.camera_trigger_time_s is None or not video.fps:
        return np.full(video.n_frames, np.nan)
    record_rate = video.fps * video.frame_step
    return take.camera_trigger_time_s + counter / record_rate       # counter 0 is the trigger frame
