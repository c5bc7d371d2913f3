"""The camera driver interface, split as ophyd-async splits a detector: trigger, acquire and data logic.

- **Trigger logic** (`configure(TriggerSettings)`): internal or external-edge trigger, the number of
  frames, and where the trigger frame lies in them (pretrigger: start, center, end or a count).
- **Acquire logic**: `arm()` starts filling the camera's ring buffer, `wait(timeout_s)` blocks until the
  recording is complete (trigger seen and the post-trigger frames taken), `stop()` aborts.
- **Data logic**: `describe()` gives the metadata, `frames()` downloads the recording as `Frame`s, whose
  `counter` is the camera's frame number (0 = trigger frame) and `time_s` the camera's own clock
  (counter / nominal fps). Host receive time is never a timestamp.

Every camera (simulated, OpenCV, Photron) implements `CameraDriver`; the capture session only uses this.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.manifest import CameraInfo

TRIGGER_MODES = ("internal", "external")
PRETRIGGER_MODES = ("start", "center", "end")


@dataclass(frozen=True)
class TriggerSettings:
    """What to record: `n_frames` frames, `pretrigger` of them before the trigger frame."""

    n_frames: int
    mode: str = "external"
    pretrigger: str | int = "start"
    fps: float | None = None          # None: keep the camera's current rate
    exposure_s: float | None = None   # None: keep the camera's current exposure

    def __post_init__(self) -> None:
        if self.mode not in TRIGGER_MODES:
            raise InputError("TriggerSettings.mode", f"expected one of {TRIGGER_MODES}, got {self.mode!r}")
        if self.n_frames < 1:
            raise InputError("TriggerSettings.n_frames", f"must be at least 1, got {self.n_frames}")
        if isinstance(self.pretrigger, str):
            if self.pretrigger not in PRETRIGGER_MODES:
                raise InputError("TriggerSettings.pretrigger",
                                 f"expected one of {PRETRIGGER_MODES} or a frame count, got {self.pretrigger!r}")
        elif not 0 <= int(self.pretrigger) < self.n_frames:
            raise InputError("TriggerSettings.pretrigger",
                             f"must lie in 0..{self.n_frames - 1} frames, got {self.pretrigger}")
        if self.fps is not None and self.fps <= 0:
            raise InputError("TriggerSettings.fps", f"must be positive, got {self.fps}")
        if self.exposure_s is not None and self.exposure_s <= 0:
            raise InputError("TriggerSettings.exposure_s", f"must be positive, got {self.exposure_s}")

    @property
    def pretrigger_frames(self) -> int:
        """Frames recorded before the trigger frame."""
        if isinstance(self.pretrigger, str):
            return {"start": 0, "center": self.n_frames // 2, "end": self.n_frames - 1}[self.pretrigger]
        return int(self.pretrigger)


@dataclass(frozen=True)
class Frame:
    counter: int          # camera frame number, 0 = the trigger frame
    time_s: float         # camera clock: counter / nominal fps
    image: np.ndarray     # (H, W) or (H, W, 3), the camera's dtype


@dataclass(frozen=True)
class RecordingStatus:
    """What `wait()` reports: the frames the camera holds for this recording."""

    n_frames: int                     # frames available for download
    first_counter: int                # counter of the first of them
    pretrigger_available: int         # fewer than requested when armed too shortly before the trigger
    dropped: tuple[int, ...] = ()     # counters the camera knows it lost


class CameraTimeout(InputError):
    """No trigger (or no complete recording) within the wait."""


@runtime_checkable
class CameraDriver(Protocol):
    """The interface every camera implements (see the module docstring)."""

    name: str

    def describe(self) -> CameraInfo: ...

    @property
    def frame_shape(self) -> tuple[int, ...]: ...

    @property
    def dtype(self) -> np.dtype: ...

    def configure(self, settings: TriggerSettings) -> None: ...

    def arm(self) -> None: ...

    def wait(self, timeout_s: float) -> RecordingStatus: ...

    def stop(self) -> None: ...

    def frames(self) -> Iterator[Frame]: ...

    def close(self) -> None: ...
