"""Any UVC camera or a video file as a `CameraDriver`, for dry runs of the capture session without
the high-speed camera.

A background thread reads frames (cv2.VideoCapture) once armed. Before the trigger it keeps only the
last `pretrigger` frames in a ring buffer; from the trigger frame on it keeps the post-trigger frames
until they are downloaded, so memory holds at most `n_frames` frames. UVC cameras have no trigger
input: the capture session calls `software_trigger()` when the DAQ sees the hammer, and the first frame
read after that call is counter 0. A video file plays from its first frame at every arm, paced to its
frame rate when `realtime=True` (as fast as it decodes otherwise); its end ends the recording early.

Frame times are counter / nominal fps. Dropped frames cannot be detected (a UVC camera numbers none of
its frames), so `RecordingStatus.dropped` is always empty, and a webcam's nominal rate is only nominal.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

import cv2
import numpy as np

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.manifest import CameraInfo

from .camera import CameraTimeout, Frame, RecordingStatus, TriggerSettings

log = logging.getLogger(__name__)

_FPS_REL_TOL = 1e-3  # a camera that reports 29.97 when asked for 30000/1001 fps runs at the asked rate
_JOIN_S = 5.0        # how long stop() waits for the reader thread (one frame read, at most)


@dataclass
class _Recording:
    """One armed acquisition, filled by the reader thread; guarded by OpenCVCamera._lock."""

    settings: TriggerSettings
    fps: float                                                # nominal rate: frame times are counter / fps
    ring: deque = field(init=False)                           # pretrigger frames, oldest first
    pre: list[np.ndarray] | None = None                       # frozen ring at the trigger frame
    post: list[np.ndarray] = field(default_factory=list)      # trigger frame and the frames after it
    trigger_requested: bool = False
    frames_read: int = 0
    ended_early: bool = False                                 # the source ran out before the last frame
    error: OdsplatError | None = None
    done: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self.ring = deque(maxlen=self.settings.pretrigger_frames)

    @property
    def post_frames(self) -> int:
        """Frames wanted from the trigger frame on (the trigger frame included)."""
        return self.settings.n_frames - self.settings.pretrigger_frames

    @property
    def triggered(self) -> bool:
        return self.pre is not None


class OpenCVCamera:
    """A UVC camera (`source` an int device index) or a video file (`source` a path) as a camera.

    `fps` overrides the rate the source reports (a file then plays at that rate); `rgb=True` keeps
    colour frames as RGB, else every frame is converted to mono uint8; `realtime=False` reads a file
    as fast as it decodes (tests), `realtime=True` paces it to its frame rate as a live camera would.
    """

    def __init__(self, source: int | str | PathLike, *, fps: float | None = None, name: str | None = None,
                 rgb: bool = False, realtime: bool = True):
        if isinstance(source, bool) or not isinstance(source, (int, str, PathLike)):
            raise InputError("OpenCVCamera.source",
                             f"expected a device index (int) or a video file path, got {source!r}")
        if fps is not None and not fps > 0:
            raise InputError("OpenCVCamera.fps", f"must be positive, got {fps}")
        self._is_file = not isinstance(source, int)
        self._path = Path(source) if self._is_file else None
        self._index = None if self._is_file else int(source)
        self._label = str(self._path) if self._is_file else f"camera device {self._index}"
        self.name = name or (f"opencv:{self._path.name}" if self._is_file else f"opencv:{self._index}")
        self._rgb = bool(rgb)
        self._realtime = bool(realtime)
        if self._is_file and not self._path.is_file():
            raise InputError(self._path, "no such video file")

        capture = self._open()
        try:
            ok, first = capture.read()
            if not ok or first is None:
                raise InputError(self._label, "opened but delivered no frame")
            self._backend = capture.getBackendName()
            reported_fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        except BaseException:
            capture.release()
            raise
        # A file is reopened at every arm (it replays from its first frame); a camera stays open.
        if self._is_file:
            capture.release()
            self._capture = None
        else:
            self._capture = capture
        try:
            self._shape = self._convert(first).shape
            self._fps = self._initial_fps(fps, reported_fps)
        except BaseException:
            capture.release()
            raise
        self._settings: TriggerSettings | None = None
        self._lock = threading.Lock()
        self._recording: _Recording | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        log.info("%s: %s via %s, %s at %g fps", self.name, self._label, self._backend,
                 "x".join(map(str, self._shape)), self._fps)

    # -- data logic: what the camera is ---------------------------------------------------------

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return self._shape

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8)

    @property
    def fps(self) -> float:
        """The nominal frame rate: frame times are counter / fps."""
        return self._fps

    def describe(self) -> CameraInfo:
        return CameraInfo(model=f"opencv:{self._backend}", width_px=self._shape[1], height_px=self._shape[0],
                          fps=self._fps, bit_depth=8, n_colors=self._shape[2] if len(self._shape) == 3 else 1)

    # -- trigger logic -------------------------------------------------------------------------

    def configure(self, settings: TriggerSettings) -> None:
        if self._thread is not None and self._thread.is_alive():
            raise OdsplatError(f"{self.name}: configure() while armed; stop() first")
        if settings.fps is not None:
            self._set_fps(settings.fps)
        if settings.exposure_s is not None:
            # OpenCV's CAP_PROP_EXPOSURE has backend-specific units (and files have none): not settable honestly.
            log.warning("%s: exposure %g s requested, but an OpenCV source's exposure cannot be set; "
                        "it stays as the device or file has it", self.name, settings.exposure_s)
        self._settings = settings

    def software_trigger(self) -> None:
        """The trigger edge, from the host: the next frame read is counter 0."""
        with self._lock:
            rec = self._recording
            if rec is None or self._thread is None:
                raise OdsplatError(f"{self.name}: software_trigger() before arm()")
            if rec.settings.mode != "external":
                raise OdsplatError(f"{self.name}: armed for an internal trigger; it started recording when armed")
            if not rec.triggered and not rec.trigger_requested:
                rec.trigger_requested = True
                log.debug("%s: software trigger after %d frames", self.name, rec.frames_read)

    # -- acquire logic -------------------------------------------------------------------------

    def arm(self) -> None:
        if self._settings is None:
            raise OdsplatError(f"{self.name}: arm() before configure()")
        self.stop()
        capture = self._open() if self._is_file else self._capture
        if capture is None:
            raise OdsplatError(f"{self.name}: arm() after close()")
        rec = _Recording(self._settings, self._fps)
        with self._lock:
            self._recording = rec
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read_loop, args=(capture, rec, self._stop),
                                        name=f"{self.name} reader", daemon=True)
        self._thread.start()

    @property
    def frames_read(self) -> int:
        """Frames read since the last arm (pretrigger frames the ring has since let go included)."""
        with self._lock:
            return 0 if self._recording is None else self._recording.frames_read

    def wait(self, timeout_s: float) -> RecordingStatus:
        rec = self._recording
        if rec is None:
            raise OdsplatError(f"{self.name}: wait() without an armed recording; arm() first")
        if not rec.done.wait(timeout_s):
            with self._lock:
                if not rec.triggered:
                    problem = (f"no trigger within {timeout_s:g} s" if rec.settings.mode == "external"
                               else f"no frame within {timeout_s:g} s of the arm")
                else:
                    problem = (f"recording incomplete after {timeout_s:g} s: {len(rec.post)} of "
                               f"{rec.post_frames} frames from the trigger frame on")
            raise CameraTimeout(self.name, problem)
        if self._thread is not None:
            self._thread.join(_JOIN_S)
        if rec.error is not None:
            raise rec.error
        return self._status(rec)

    def stop(self) -> None:
        """Stop reading; a recording not yet complete is discarded."""
        thread = self._thread
        if thread is not None:
            self._stop.set()
            thread.join(_JOIN_S)
            if thread.is_alive():
                log.warning("%s: the reader thread did not stop within %g s", self.name, _JOIN_S)
            self._thread = None
        with self._lock:
            if self._recording is not None and not self._recording.done.is_set():
                self._recording = None

    def close(self) -> None:
        self.stop()
        if self._capture is not None:
            self._capture.release()
            self._capture = None

    def __enter__(self) -> OpenCVCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- data logic: the recording -------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        rec = self._recording
        if rec is None or not rec.done.is_set() or rec.error is not None:
            raise OdsplatError(f"{self.name}: no complete recording to download; arm() and wait() first")
        pre = rec.pre or []
        return (Frame(counter=counter, time_s=counter / rec.fps, image=image)
                for counter, image in enumerate(pre + rec.post, start=-len(pre)))

    # -- internals -----------------------------------------------------------------------------

    def _open(self) -> cv2.VideoCapture:
        capture = cv2.VideoCapture(str(self._path) if self._is_file else self._index)
        if not capture.isOpened():
            capture.release()
            what = ("cannot be opened as a video by OpenCV (unknown codec or damaged file)" if self._is_file
                    else "cannot be opened by OpenCV (no such device, or it is in use)")
            raise InputError(self._label, what)
        return capture

    def _initial_fps(self, fps: float | None, reported: float) -> float:
        if fps is not None:
            if not self._is_file:
                self._capture.set(cv2.CAP_PROP_FPS, float(fps))
                actual = float(self._capture.get(cv2.CAP_PROP_FPS) or 0.0)
                if actual > 0 and abs(actual - fps) > _FPS_REL_TOL * fps:
                    log.warning("%s: asked for %g fps, the device reports %g fps; frame times use %g fps",
                                self.name, fps, actual, fps)
            return float(fps)
        if reported > 0:
            return reported
        raise InputError(self._label, "reports no frame rate; pass fps= to OpenCVCamera")

    def _set_fps(self, fps: float) -> None:
        if abs(fps - self._fps) <= _FPS_REL_TOL * fps:
            return
        if self._is_file:
            self._fps = float(fps)  # the file plays (and is timed) at the asked rate
            return
        self._capture.set(cv2.CAP_PROP_FPS, float(fps))
        actual = float(self._capture.get(cv2.CAP_PROP_FPS) or 0.0)
        if abs(actual - fps) > _FPS_REL_TOL * fps:
            raise InputError(self._label, f"cannot run at {fps:g} fps; it reports {actual:g} fps after the request")
        self._fps = float(fps)

    def _convert(self, frame: np.ndarray) -> np.ndarray:
        if frame.dtype != np.uint8:
            # Some backends deliver 16-bit frames (e.g. CAP_PROP_CONVERT_RGB off); keep the top 8 bits.
            frame = (frame >> 8).astype(np.uint8) if frame.dtype == np.uint16 else frame.astype(np.uint8)
        if frame.ndim == 2:
            return frame
        if frame.shape[2] == 1:
            return frame[:, :, 0]
        if self._rgb:
            return cv2.cvtColor(frame, cv2.COLOR_BGRA2RGB if frame.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY)

    def _read_loop(self, capture: cv2.VideoCapture, rec: _Recording, stop: threading.Event) -> None:
        pace_s = 1.0 / self._fps if (self._is_file and self._realtime) else None
        start = time.monotonic()
        try:
            while not stop.is_set():
                if pace_s is not None:
                    delay = start + rec.frames_read * pace_s - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                ok, frame = capture.read()
                if not ok or frame is None:
                    self._source_ended(rec)
                    break
                image = self._convert(frame)
                if image.shape != self._shape:
                    raise InputError(self._label,
                                     f"frame {rec.frames_read} is {image.shape}, the first was {self._shape}")
                with self._lock:
                    if self._take(rec, image):
                        break
        except OdsplatError as exc:
            rec.error = exc
            rec.done.set()
        except Exception as exc:  # a decoder or driver failure must reach wait(), not die in the thread
            rec.error = InputError(self._label, f"reading frame {rec.frames_read} failed: {exc}")
            rec.done.set()
        finally:
            if self._is_file:
                capture.release()

    def _take(self, rec: _Recording, image: np.ndarray) -> bool:
        """File one frame; True when the recording is complete. Called with the lock held."""
        rec.frames_read += 1
        if not rec.triggered:
            if rec.settings.mode == "internal" or rec.trigger_requested:
                rec.pre = list(rec.ring)
                rec.ring.clear()
                rec.post.append(image)
                log.debug("%s: trigger frame is frame %d since the arm", self.name, rec.frames_read - 1)
            else:
                rec.ring.append(image)
                return False
        else:
            rec.post.append(image)
        if len(rec.post) >= rec.post_frames:
            rec.done.set()
            return True
        return False

    def _source_ended(self, rec: _Recording) -> None:
        what = "the video file ended" if self._is_file else "the camera stopped delivering frames"
        with self._lock:
            if rec.triggered:
                rec.ended_early = True
                log.warning("%s: %s after %d of %d frames from the trigger frame on; the recording is short",
                            self.name, what, len(rec.post), rec.post_frames)
            else:
                rec.error = InputError(self._label, f"{what} after {rec.frames_read} frames, before any trigger "
                                                    "frame; nothing was recorded")
            rec.done.set()

    def _status(self, rec: _Recording) -> RecordingStatus:
        pre = len(rec.pre or [])
        if pre < rec.settings.pretrigger_frames:
            log.info("%s: %d of %d pretrigger frames available (armed %s before the trigger)", self.name, pre,
                     rec.settings.pretrigger_frames,
                     "at" if rec.settings.mode == "internal" else "too shortly")
        return RecordingStatus(n_frames=pre + len(rec.post), first_counter=-pre, pretrigger_available=pre)
