"""A simulated high-speed camera filming the rig: its own clock, triggers, pretrigger ring buffer,
frame counter, exposure strobe (TTL), dropped frames, sensor noise and exposure-time blur.

Times are rig times (physical, 0 at the DAQ's START) unless named otherwise. The camera's clock may be
offset from and drift against the DAQ's, as real ones do; frames lie on the camera's clock ticks.

`SimCamera` implements the acquisition stage's `CameraDriver` (configure, arm, wait, stop, frames,
describe), so the capture session drives it exactly as it drives a real camera. Its frames carry the
camera's own time (counter / nominal fps); the true exposure times are in `recording` and the truth file.
"""
from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace

import numpy as np

from odsplat.acquisition import CameraTimeout, Frame, RecordingStatus, TriggerSettings
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.manifest import CameraInfo, Intrinsics

from .render import PinholeCamera, RenderResult, expose, render
from .scene import RigScene

TRIGGER_MODES = ("internal", "external")
PRETRIGGER_MODES = ("start", "center", "end")


@dataclass(frozen=True)
class SimCameraConfig:
    fps: float = 2000.0
    exposure_s: float | None = None     # default: half the frame period
    bit_depth: int = 12                 # 8 or 12
    rgb: bool = False
    full_well_e: float = 20_000.0
    read_noise_e: float = 5.0
    shot_noise: bool = True
    blur_samples: int = 1               # renders averaged over the exposure (1: no exposure blur)
    supersample: int = 3
    background: float = 0.5
    ttl_high_v: float = 5.0
    trigger_delay_s: float = 0.0        # from the trigger edge to the camera latching it
    trigger_jitter_s: float = 0.0       # rms scatter of that delay, take to take

    @property
    def exposure(self) -> float:
        return self.exposure_s if self.exposure_s is not None else 0.5 / self.fps

    def validate(self) -> None:
        if self.fps <= 0:
            raise InputError("SimCameraConfig.fps", f"must be positive, got {self.fps}")
        if not 0 < self.exposure <= 1.0 / self.fps:
            raise InputError("SimCameraConfig.exposure_s",
                             f"must lie in (0, 1/fps = {1 / self.fps:.3g} s], got {self.exposure}")
        if self.bit_depth not in (8, 12):
            raise InputError("SimCameraConfig.bit_depth", f"expected 8 or 12, got {self.bit_depth}")
        if self.trigger_delay_s < 0 or self.trigger_jitter_s < 0:
            raise InputError("SimCameraConfig.trigger_delay_s", f"delay and jitter must be >= 0, got "
                             f"{self.trigger_delay_s} and {self.trigger_jitter_s}")
        if not (np.isfinite(self.read_noise_e) and self.read_noise_e >= 0):
            raise InputError("SimCameraConfig.read_noise_e", f"expected electrons >= 0, got {self.read_noise_e}")
        if not (np.isfinite(self.full_well_e) and self.full_well_e >= 100):
            raise InputError("SimCameraConfig.full_well_e", f"expected at least 100 electrons, got {self.full_well_e}")
        if self.blur_samples < 1:
            raise InputError("SimCameraConfig.blur_samples", f"must be at least 1, got {self.blur_samples}")


@dataclass(frozen=True)
class Recording:
    """What one armed-and-triggered acquisition holds: frame counters (0 = trigger frame) and their times."""

    counters: np.ndarray            # camera frame numbers delivered, dropped ones left out
    exposure_start_s: np.ndarray    # DAQ time of each delivered frame's exposure start
    trigger_time_s: float           # DAQ time of the trigger (the edge, or the arm for internal)
    trigger_frame_time_s: float     # DAQ time of frame 0's exposure start
    pretrigger_requested: int
    pretrigger_available: int       # fewer than requested when armed too shortly before the trigger
    dropped: np.ndarray             # counters that were exposed but never delivered
    end_time_s: float               # DAQ time when the last frame's exposure ends: the strobe stops


class SimCamera:
    """The camera device model. `motion(t_s)` gives the structure's modal coordinates (n_modes, T) at rig times;
    `clock()` gives the rig time now (used by the driver-style `arm()`)."""

    model = "odsplat hil_sim camera"

    def __init__(self, scene: RigScene, camera: PinholeCamera, motion: Callable[[np.ndarray], np.ndarray],
                 config: SimCameraConfig | None = None, *, clock_offset_s: float = 0.0, clock_drift_ppm: float = 0.0,
                 drop_counters: Sequence[int] = (), seed: int | None = 0, clock: Callable[[], float] | None = None,
                 lock: threading.RLock | None = None, name: str = "simcam"):
        self.name = name
        self.clock = clock or (lambda: 0.0)
        # Shared with the rig: arming at "now" must not interleave with the DAQ producing samples.
        self._lock = lock or threading.RLock()
        self.settings: TriggerSettings | None = None
        self._done = threading.Event()
        self.scene = scene
        self.camera = camera
        self.motion = motion
        self.config = config or SimCameraConfig()
        self.config.validate()
        self.clock_offset_s = float(clock_offset_s)
        self.clock_drift_ppm = float(clock_drift_ppm)
        self.drop_counters = frozenset(int(c) for c in drop_counters)
        self._rng = np.random.default_rng(seed)
        self._armed_at_s: float | None = None
        self._plan: tuple[int, int, str] | None = None
        self.recording: Recording | None = None

    # -- clock --------------------------------------------------------------------------------

    @property
    def period_s(self) -> float:
        """The true frame period in DAQ time: the nominal one, stretched by the clock drift."""
        return 1.0 / (self.config.fps * (1.0 + 1e-6 * self.clock_drift_ppm))

    def tick_time_s(self, tick: np.ndarray | int) -> np.ndarray:
        """DAQ time of the exposure start of the camera's clock tick `tick`."""
        return self.clock_offset_s + np.asarray(tick, float) * self.period_s

    def _first_tick_at_or_after(self, t_s: float) -> int:
        return int(np.ceil((t_s - self.clock_offset_s) / self.period_s - 1e-9))

    # -- trigger and acquire -------------------------------------------------------------------

    def configure(self, settings: TriggerSettings) -> None:
        """Driver interface, trigger logic: frames, pretrigger, trigger mode, and fps/exposure if given."""
        changes = {k: v for k, v in (("fps", settings.fps), ("exposure_s", settings.exposure_s)) if v is not None}
        if changes:
            config = replace(self.config, **changes)
            config.validate()
            self.config = config
        self.settings = settings

    def arm(self, *, n_frames: int | None = None, pretrigger: str | int | None = None, trigger: str | None = None,
            at_s: float | None = None) -> None:
        """Start filling the ring buffer at rig time `at_s` (default: now, from the clock); the take will hold
        `n_frames` frames. Arguments left out come from `configure()` (driver interface, acquire logic)."""
        s = self.settings
        if n_frames is None:
            if s is None:
                raise OdsplatError(f"{self.name}: arm() without arguments needs configure() first")
            n_frames = s.n_frames
            pretrigger, trigger = s.pretrigger if pretrigger is None else pretrigger, trigger or s.mode
        pretrigger = "start" if pretrigger is None else pretrigger
        trigger = trigger or "external"
        with self._lock:
            self._arm(n_frames, pretrigger, trigger, self.clock() if at_s is None else at_s)

    def _arm(self, n_frames: int, pretrigger: str | int, trigger: str, at_s: float) -> None:
        if trigger not in TRIGGER_MODES:
            raise InputError("SimCamera.trigger", f"expected one of {TRIGGER_MODES}, got {trigger!r}")
        if n_frames < 1:
            raise InputError("SimCamera.n_frames", f"must be at least 1, got {n_frames}")
        if isinstance(pretrigger, str):
            if pretrigger not in PRETRIGGER_MODES:
                raise InputError("SimCamera.pretrigger",
                                 f"expected one of {PRETRIGGER_MODES} or a frame count, got {pretrigger!r}")
            pre = {"start": 0, "center": n_frames // 2, "end": n_frames - 1}[pretrigger]
        else:
            pre = int(pretrigger)
            if not 0 <= pre < n_frames:
                raise InputError("SimCamera.pretrigger", f"must lie in 0..{n_frames - 1} frames, got {pre}")
        self._armed_at_s = float(at_s)
        self._plan = (n_frames, pre, trigger)
        self.recording = None
        self._done.clear()
        if trigger == "internal":
            self._record(float(at_s))

    @property
    def waiting_for_trigger(self) -> bool:
        """Armed for an external trigger that has not come yet."""
        return self._plan is not None and self._plan[2] == "external" and self.recording is None

    def trigger_at(self, t_s: float) -> Recording:
        """An external trigger edge at DAQ time t_s: frame 0 is the first exposure starting at or after the camera
        latches it (`trigger_delay_s` later, give or take `trigger_jitter_s`)."""
        if self._plan is None or self._armed_at_s is None:
            raise OdsplatError(f"{self.name}: trigger before arm")
        if self._plan[2] != "external":
            raise OdsplatError("SimCamera: armed for an internal trigger; it started recording when armed")
        if t_s < self._armed_at_s:
            raise OdsplatError(f"SimCamera: trigger at {t_s} s precedes the arm at {self._armed_at_s} s")
        return self._record(float(t_s))

    def _record(self, t_trigger_s: float) -> Recording:
        n_frames, pre, _ = self._plan
        cfg = self.config
        jitter = cfg.trigger_jitter_s * self._rng.standard_normal() if cfg.trigger_jitter_s else 0.0
        latched = t_trigger_s + max(0.0, cfg.trigger_delay_s + jitter)
        trigger_tick = self._first_tick_at_or_after(latched)
        # The ring buffer holds only what was exposed since the arm.
        first_buffered = self._first_tick_at_or_after(self._armed_at_s)
        available = min(pre, trigger_tick - first_buffered)
        ticks = np.arange(trigger_tick - available, trigger_tick - pre + n_frames)
        counters = ticks - trigger_tick
        keep = ~np.isin(counters, list(self.drop_counters))
        self.recording = Recording(
            counters=counters[keep],
            exposure_start_s=self.tick_time_s(ticks[keep]),
            trigger_time_s=t_trigger_s,
            trigger_frame_time_s=float(self.tick_time_s(trigger_tick)),
            pretrigger_requested=pre,
            pretrigger_available=int(available),
            dropped=counters[~keep],
            end_time_s=float(self.tick_time_s(ticks[-1])) + self.config.exposure,
        )
        self._done.set()
        return self.recording

    def wait(self, timeout_s: float) -> RecordingStatus:
        """Driver interface, acquire logic: block until the recording is complete."""
        if self._plan is None:
            raise OdsplatError(f"{self.name}: wait() before arm()")
        if not self._done.wait(timeout_s):
            raise CameraTimeout(self.name, f"no trigger within {timeout_s:g} s")
        rec = self.recording
        return RecordingStatus(n_frames=len(rec.counters),
                               first_counter=int(rec.counters[0]) if len(rec.counters) else 0,
                               pretrigger_available=rec.pretrigger_available,
                               dropped=tuple(int(c) for c in rec.dropped))

    def stop(self) -> None:
        """Disarm; the recording (if any) is forgotten."""
        self._plan = None
        self._armed_at_s = None
        self.recording = None
        self._done.clear()

    def close(self) -> None:
        self.stop()

    def reseed(self, seed: int | None) -> None:
        """A fresh noise sequence (each take's sensor noise is independent)."""
        self._rng = np.random.default_rng(seed)

    def describe(self) -> CameraInfo:
        cfg = self.config
        return CameraInfo(model=self.model, width_px=self.camera.width_px, height_px=self.camera.height_px, fps=cfg.fps,
                          bit_depth=cfg.bit_depth, n_colors=3 if cfg.rgb else 1, exposure_s=cfg.exposure,
                          intrinsics=Intrinsics.from_matrix(self.camera.K))

    # -- data ---------------------------------------------------------------------------------

    def _require_recording(self) -> Recording:
        if self.recording is None:
            raise OdsplatError("SimCamera: nothing recorded yet (arm, then trigger)")
        return self.recording

    def radiance(self, t_start_s: float, *, alpha: float = 1.0) -> np.ndarray:
        """Noise-free radiance integrated over one exposure starting at DAQ time t_start_s."""
        cfg = self.config
        times = t_start_s + (np.arange(cfg.blur_samples) + 0.5) / cfg.blur_samples * cfg.exposure
        q = np.asarray(self.motion(times), float).reshape(self.scene.structure.n_modes, len(times))
        acc = None
        for k in range(len(times)):
            image = render(self.scene.mesh(q[:, k], alpha), self.camera, self.scene.atlas,
                           supersample=cfg.supersample, background=cfg.background).image
            acc = image if acc is None else acc + image
        return acc / len(times)

    def truth(self, t_start_s: float, *, alpha: float = 1.0) -> RenderResult:
        """Ground truth at the middle of an exposure: image (motion times alpha), depth, object id, coverage."""
        q = np.asarray(self.motion(np.array([t_start_s + 0.5 * self.config.exposure])), float).reshape(-1)
        return render(self.scene.mesh(q, alpha), self.camera, self.scene.atlas,
                      supersample=self.config.supersample, background=self.config.background)

    def expose(self, radiance: np.ndarray) -> np.ndarray:
        cfg = self.config
        return expose(radiance, bit_depth=cfg.bit_depth, full_well_e=cfg.full_well_e, read_noise_e=cfg.read_noise_e,
                      shot_noise=cfg.shot_noise, rng=self._rng, rgb=cfg.rgb)

    def frames(self) -> Iterator[Frame]:
        """Driver interface, data logic: the recorded frames in order, stamped with the camera's own clock
        (counter / nominal fps). The true exposure starts (rig time) are `recording.exposure_start_s`."""
        rec = self._require_recording()
        for counter, t in zip(rec.counters, rec.exposure_start_s):
            yield Frame(int(counter), int(counter) / self.config.fps, self.expose(self.radiance(float(t))))

    @property
    def frame_shape(self) -> tuple[int, ...]:
        hw = (self.camera.height_px, self.camera.width_px)
        return (*hw, 3) if self.config.rgb else hw

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.config.bit_depth == 8 else np.uint16)

    def ttl(self, t_s: np.ndarray) -> np.ndarray:
        """The exposure strobe in volts at DAQ times t_s: high while any frame since the arm is exposed.

        Dropped frames were still exposed, so they strobe too: that is how sync finds them.
        """
        t = np.asarray(t_s, float)
        if self._armed_at_s is None:
            return np.zeros_like(t)
        rec = self.recording
        first = self._first_tick_at_or_after(self._armed_at_s)
        phase = (t - self.clock_offset_s) / self.period_s
        tick = np.floor(phase)
        exposed = (phase - tick) * self.period_s < self.config.exposure
        live = tick >= first
        if rec is not None:
            live &= t < rec.end_time_s
        return np.where(exposed & live, self.config.ttl_high_v, 0.0)
