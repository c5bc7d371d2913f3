"""Sync a capture: every take's impact onset and frame times in DAQ time, one common impact-locked grid,
and each take's frames resampled onto it.

Per take: the hammer pulse gives the impact onset to a fraction of a DAQ sample; the exposure strobe
(when recorded) or the trigger frame refined by the images gives counter 0's exposure start. The
take's `offset_s` is then the time from the impact onset to the middle of counter 0's exposure. Takes
with no hit, two hits or unusable timing are excluded with the reason, not guessed. The AprilTags seen in the
rest image are recorded (`tags_seen`); none seen is a flag, not an exclusion: timing does not need them.
Results go to `derived/sync.json` (format in docs/sync.md), the aligned frames to `derived/sync/`.
"""
from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from odsplat.spine.atomic import atomic_write_text
from odsplat.spine.checks import WORKERS, Range, check_choice, check_fields, maybe
from odsplat.spine.contract import check, describe
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.framefile import begin_outputs, discard_outputs, prune_outputs
from odsplat.spine.impulse import ImpactDetector, ImpactSettings
from odsplat.spine.manifest import CameraInfo, TagLayout, load_json, utc_now
from odsplat.spine.pool import process_pool
from odsplat.spine.store import TAKE_SELECTIONS, Capture
from odsplat.spine.tags import detect_tags
from odsplat.spine.take_reader import TakeReader

from .aligned import write_aligned
from .image import DisplacementBasis, fit_frame_times, motion_gram, noise_sd
from .resample import fill_dropped, fractional_shift
from .strobe import fit_strobe

log = logging.getLogger(__name__)

KIND = "odsplat.sync"
SCHEMA = 3   # 3: generation, the run id its aligned files carry
METHODS = ("auto", "ttl", "image")
RESPONSE_S = 0.05  # how much of each take's response the cross-check compares


@dataclass(frozen=True)
class SyncSettings:
    method: str = "auto"                  # auto: the strobe when a take has a ttl channel, else the images
    takes: str = "accepted"               # which takes: those QC accepted, or all
    normalize_impulse: bool = False       # scale each take's motion to the median impulse (the structure is linear)
    write_frames: bool = True             # the aligned takes, derived/sync/NAME.h5 (computed from the raw take)
    check_with_image: bool = True         # strobe-timed takes: date them from the images too, as a check
    camera_trigger_delay_s: float = 0.0   # from the DAQ's trigger to the camera latching it
    search_frames: float = 1.5            # image method: how far around the trigger frame to look
    # What an impact is (every stage's rule, odsplat.spine.impulse); a peak under 5 N is noise, not a hit.
    impacts: ImpactSettings = field(default_factory=lambda: ImpactSettings(min_peak_n=5.0))
    max_memory_mb: float = 256.0          # working memory per take (pixels kept, rows per band)
    plot: bool = True                     # derived/sync.png
    workers: int | None = None            # processes aligning the takes' frames; None: one per core, at most one
    #                                       per take (the results are the same with any number)

    def __post_init__(self) -> None:
        check_choice("SyncSettings.method", self.method, METHODS)
        check_choice("SyncSettings.takes", self.takes, TAKE_SELECTIONS)
        # search_frames: the image method tries a shift every 0.02 frame across it, and a camera's trigger is never
        # 100 frames late; max_memory_mb: a budget (what is read is bounded by the take), up to a terabyte.
        check_fields(self, {"camera_trigger_delay_s": Range(above=-1, below=1),
                            "search_frames": Range(above=0, at_most=100),
                            "max_memory_mb": Range(above=0, at_most=1e6), "workers": maybe(WORKERS)})


@dataclass
class TakeSync:
    """One take on the common timeline. Times are DAQ times (s) unless named `offset`."""

    name: str
    view: int | None
    status: str = "ok"                       # "ok" or "excluded"
    error: str | None = None                 # why it was excluded
    method: str | None = None                # "ttl" or "image"
    offset_s: float | None = None            # middle of counter 0's exposure, after the impact onset
    hit_daq_time_s: float | None = None
    frame0_daq_time_s: float | None = None   # counter 0's exposure start
    period_s: float | None = None
    exposure_s: float | None = None
    residual_frames: float | None = None     # ttl: rms of the edge fit; image: one sigma of the shift
    flags: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    peak_force_n: float | None = None
    impulse_n_s: float | None = None
    pulse_duration_s: float | None = None
    pulse_residual: float | None = None      # half-sine misfit, relative to the peak
    pulse_method: str | None = None
    fps_error_ppm: float | None = None       # ttl: the camera's true rate against its nominal, on the DAQ clock
    dropped_counters: list[int] = field(default_factory=list)
    image_motion_z: float | None = None      # how clearly the images see motion: its energy over noise's, in sd
    image_check_frames: float | None = None  # ttl takes: image timing minus strobe timing
    xcorr_lag_s: float | None = None         # the accelerometers' response against the reference take's, after locking
    xcorr_coeff: float | None = None
    tags_seen: list[int] = field(default_factory=list)
    counters: list[int] = field(default_factory=list, repr=False)  # stored frames' counters (not in the JSON)
    impulse_scale: float | None = None       # applied to the motion when normalising
    grid_shift_frames: float | None = None   # the take's input frame index at grid frame 0
    drift_frames: float | None = None        # largest timing error of a single shift over the grid (rate error)
    aligned_file: str | None = None          # relative to the derived root: sync/NAME.h5

    def exclude(self, error: str) -> TakeSync:
        self.status, self.error = "excluded", error
        return self


@dataclass
class SyncResult:
    capture: str
    fps: float | None
    n_frames: int
    t0_s: float | None                       # grid frame 0's mid-exposure time after the impact onset
    frame_shape: list[int]
    reference_impulse_n_s: float | None
    normalized: bool
    takes: list[TakeSync]
    settings: dict[str, Any]
    created_utc: str = field(default_factory=utc_now)
    generation: str = ""                     # the run's id; every aligned file it wrote carries it

    @property
    def ok(self) -> list[TakeSync]:
        return [t for t in self.takes if t.status == "ok"]

    @property
    def times_s(self) -> np.ndarray:
        return (self.t0_s or 0.0) + np.arange(self.n_frames) / (self.fps or 1.0)

    def to_json(self, capture_id: str) -> str:
        d = asdict(self)
        for t in d["takes"]:
            t.pop("counters")
        header = describe(capture_id, KIND, SCHEMA, self.settings).header()
        return json.dumps({**header, **d}, indent=1, allow_nan=False, default=float)

    def write(self, capture: Capture) -> Path:
        """derived/sync.json, atomically (the aligned frames are written before it)."""
        path = capture.paths.sync_json
        capture.paths.ensure(path.parent)
        atomic_write_text(path, self.to_json(capture.id))
        return path

    @classmethod
    def read(cls, capture: Capture) -> SyncResult:
        """The capture's sync result; a file of another kind, schema or capture is refused with one line."""
        path = capture.paths.sync_json
        d = load_json(path, missing="no sync result (run `odsplat sync` first)")
        check(d, path, kind=KIND, schema_version=SCHEMA, capture_id=capture.id)
        names = {f.name for f in fields(TakeSync)}
        mine = {f.name for f in fields(cls)}
        try:
            d["takes"] = [TakeSync(**{k: v for k, v in t.items() if k in names}) for t in d["takes"]]
            return cls(**{k: v for k, v in d.items() if k in mine})
        except (TypeError, KeyError, AttributeError) as exc:
            raise InputError(path, f"not a readable sync result: {exc}") from None

    def summary(self) -> str:
        head = f"{len(self.ok)}/{len(self.takes)} takes synced"
        own = self.ok and all(t.method == "frames" for t in self.ok)
        if self.ok:
            head += (f"; grid {self.n_frames} frames at {self.fps:g} fps from {1e3 * self.t0_s:+.3f} ms "
                     + ("after counter 0's exposure start (no force: the takes keep their own frame times)" if own
                        else "after the impact"))
        lines = [head]
        for t in self.takes:
            if t.status == "ok" and t.method == "frames":
                lines.append(f"  {t.name:<10} on its own frame times (no force channel)"
                             f"{'  [' + ', '.join(t.flags) + ']' if t.flags else ''}")
            elif t.status == "ok":
                extra = f"  image check {t.image_check_frames:+.3f} fr" if t.image_check_frames is not None else ""
                lines.append(f"  {t.name:<10} {t.method:<5} offset {1e3 * t.offset_s:+.4f} ms "
                             f"({t.offset_s * self.fps:+.3f} fr), residual {t.residual_frames:.3f} fr{extra}"
                             f"{'  [' + ', '.join(t.flags) + ']' if t.flags else ''}")
            else:
                lines.append(f"  {t.name:<10} EXCLUDED: {t.error}")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- per take

def force_channel(reader: TakeReader) -> str:
    """The take's one force channel (the hammer's load cell)."""
    names = reader.channels_of_kind("force")
    if len(names) != 1:
        raise InputError(reader.path, f"expected exactly one DAQ channel of kind 'force', found {names}")
    return names[0]


class _TakeAnalysis:
    """Everything sync learns about one take, computed from its file alone."""

    def __init__(self, reader: TakeReader, layout: TagLayout | None, camera: CameraInfo, settings: SyncSettings):
        self.r = reader
        self.s = settings
        self.layout = layout
        self.cam_exposure_s = camera.exposure_s
        self.fps = camera.fps
        self.out = TakeSync(reader.name, reader.view)
        # The accelerometers locked to the onset (and the DAQ rate), for the cross-check between takes.
        self.response: tuple[np.ndarray, float] | None = None

    def run(self) -> TakeSync:
        try:
            self._run()
        except InputError as e:  # the take's own file is named by the take; anything narrower is kept
            self.out.exclude(e.problem if e.source == str(self.r.path) else f"{e.source}: {e.problem}")
        if self.out.status != "ok":
            log.warning("take %s excluded from sync: %s", self.out.name, self.out.error)
        return self.out

    def _run(self) -> None:
        r, s, out = self.r, self.s, self.out
        if not r.has_frames or r.n_frames < 4:
            raise InputError(r.path, f"the take holds {r.n_frames} frames; sync needs at least 4")
        if not r.fps:
            raise InputError(r.path, "the take has no frame rate (fps attribute)")
        if self.fps is not None and abs(r.fps - self.fps) > 1e-6 * self.fps:
            raise InputError(r.path, f"filmed at {r.fps:g} fps; the capture's camera runs at {self.fps:g} fps")
        if not (r.n_samples and r.channels_of_kind("force")):
            self._own_time()
            return
        fs = r.sample_rate_hz
        force_name = force_channel(r)
        force = r.channel(force_name).astype(float)
        hits = ImpactDetector(s.impacts).detect(force, fs, source=force_name)
        if not hits.n:
            raise InputError(force_name, f"no hit found: the force peaks at {hits.peak_n:.3g} N, below "
                                         f"{hits.floor_n:.3g} N")
        if hits.double_hit:
            onsets = [p.onset_s for p in hits.pulses]
            gaps = ", ".join(f"{1e3 * (b - a):.2f}" for a, b in zip(onsets, onsets[1:]))
            raise InputError(force_name,
                             f"{hits.n} hits found ({gaps} ms apart): a double hit cannot be locked to one impact")
        pulse = hits.pulses[0]
        resp = _response(r, pulse.onset_sample, pulse.impulse_n_s, int(RESPONSE_S * fs))
        self.response = None if resp is None else (resp, fs)
        out.hit_daq_time_s = r.daq_t0_s + pulse.onset_s
        out.peak_force_n, out.impulse_n_s, out.pulse_duration_s = pulse.peak_n, pulse.impulse_n_s, pulse.duration_s
        out.pulse_residual, out.pulse_method = pulse.residual, pulse.method
        if pulse.residual > 0.1:
            out.flags.append("pulse_not_half_sine")

        counters = self._counters()
        period = 1.0 / r.fps
        trigger_time = r.trigger.trigger_time_s
        ttl = r.channels_of_kind("ttl")
        method = s.method if s.method != "auto" else ("ttl" if ttl else "image")
        if method == "ttl" and not ttl:
            raise InputError(r.path, "method 'ttl' asked for, but the take records no channel of kind 'ttl'")
        out.method = method
        if trigger_time is None:
            out.flags.append("no_trigger_time")
            trigger_time = out.hit_daq_time_s  # the camera's trigger came from this force: its rise is as good

        if method == "ttl":
            st = fit_strobe(r.channel(ttl[0]), fs, r.daq_t0_s, counters, nominal_fps=r.fps, trigger_time_s=trigger_time,
                            trigger_delay_s=s.camera_trigger_delay_s, source=f"{r.path}: {ttl[0]}")
            out.frame0_daq_time_s, out.period_s = st.frame0_start_s, st.period_s
            out.exposure_s = st.exposure_s if np.isfinite(st.exposure_s) else self._exposure(period)
            out.residual_frames = st.residual_frames
            out.fps_error_ppm = (1.0 / (st.period_s * r.fps) - 1.0) * 1e6
            out.flags += list(st.flags)
            out.notes += list(st.notes)
        # Counter 0 starts within a frame after the trigger.
        prior = trigger_time + s.camera_trigger_delay_s + 0.5 * period - 0.5 / fs
        start_guess = out.frame0_daq_time_s if method == "ttl" else prior
        rest_image, rest_std, rest = self._rest(counters, start_guess, period, method == "ttl")
        self._check_tags(rest_image)
        if method == "image" or s.check_with_image:
            timing = self._image_timing(counters, rest, rest_image, rest_std, period, start_guess)
            if method == "image":
                if timing is None:
                    raise InputError(r.path,
                                     "image timing needs accelerometer channels (kind 'acceleration') in the take")
                if not _dates_frames(timing):
                    raise InputError(r.path,
                                     f"the images do not date the frames (sigma {timing.sigma_frames:.3g} frame, "
                                     f"motion {timing.motion_z:.1f} sd above noise; {'; '.join(timing.notes)})")
                out.frame0_daq_time_s, out.period_s = timing.frame0_start_s, period
                out.exposure_s = self._exposure(period)
                out.residual_frames = timing.sigma_frames
            elif timing is not None:
                out.image_check_frames = (timing.frame0_start_s - out.frame0_daq_time_s) / period
                if not _dates_frames(timing):
                    # Images that barely see the motion (small, low-contrast, coarse texture) cannot check the strobe.
                    out.flags.append("image_check_inconclusive")
                    out.notes.append(f"the images do not date the frames well enough to check the strobe (sigma "
                                     f"{timing.sigma_frames:.3g} frame, motion {timing.motion_z:.1f} sd above noise)")
                elif abs(out.image_check_frames) > 0.25:
                    out.flags.append("image_disagrees")
                    out.notes.append(f"the images date the frames {out.image_check_frames:+.2f} frame from the strobe")
            if timing is not None:
                out.image_motion_z = timing.motion_z
                out.flags += [f for f in timing.flags if f not in out.flags]
                out.notes += list(timing.notes)
        out.offset_s = out.frame0_daq_time_s + 0.5 * out.exposure_s - out.hit_daq_time_s

    def _counters(self) -> np.ndarray:
        """The stored frames' counters, recorded with the ones dropped (filled on the grid, flagged)."""
        out = self.out
        counters = self.r.frame_counter.astype(int)
        out.counters = counters.tolist()
        full, _ = fill_dropped(counters)
        out.dropped_counters = sorted(set(full.tolist()) - set(out.counters))
        if out.dropped_counters:
            out.flags.append("dropped_frames_filled")
        return counters

    def _own_time(self) -> None:
        """A take without a force channel (a video on its own, an operating machine nobody hits): there is no impact to
        lock it to, so it keeps its own frame times, counter 0's exposure starting at time 0."""
        r, out = self.r, self.out
        counters = self._counters()
        out.method, out.period_s, out.frame0_daq_time_s = "frames", 1.0 / r.fps, 0.0
        out.exposure_s = self._exposure(out.period_s)
        out.offset_s = 0.5 * out.exposure_s
        out.flags.append("no_force")
        out.notes.append("no force channel: the take keeps its own frame times (time 0 is counter 0's exposure "
                         "start), not an impact's")
        times = r.frame_times_s
        zero = np.flatnonzero(counters == 0)
        if r.n_samples and len(zero) and len(times) == len(counters) and np.isfinite(times[zero[0]]):
            # the take says when counter 0 was exposed on the DAQ's clock: its samples stand on the frames' time
            out.frame0_daq_time_s = float(times[zero[0]])
            out.flags.append("daq_clock")
            out.notes.append(f"its DAQ samples are on the same clock: counter 0's exposure starts at "
                             f"{out.frame0_daq_time_s:.6f} s of the DAQ's time")
        self._check_tags(r.read_frames(0, min(8, r.n_frames)).astype(np.float64).mean(axis=0))   # tags need no rest

    def _exposure(self, period: float) -> float:
        if self.cam_exposure_s:
            return float(self.cam_exposure_s)
        self.out.flags.append("exposure_unknown")
        return period

    def _rest(self, counters: np.ndarray, start_guess: float, period: float, known: bool):
        """Frames surely before the hit (their exposure ends before it, however the timing comes out), and their
        per-pixel mean and scatter."""
        margin = 0.0 if known else self.s.search_frames
        ends = start_guess + (counters + margin) * period + (self.cam_exposure_s or period)
        rest = ends < self.out.hit_daq_time_s
        if rest.sum() < 3:
            raise InputError(self.r.path,
                             f"{int(rest.sum())} frame(s) before the hit; sync needs 3 to see the structure at "
                             "rest (record with more pretrigger frames)")
        idx = np.flatnonzero(rest)
        acc = acc2 = None
        for k in idx:  # pretrigger frames come first and are few
            f = self.r.frames[int(k)].astype(np.float64)
            acc = f if acc is None else acc + f
            acc2 = f * f if acc2 is None else acc2 + f * f
        mean = acc / idx.size
        var = np.maximum(acc2 / idx.size - mean ** 2, 0.0) * idx.size / (idx.size - 1)
        return mean, noise_sd(mean, var, idx.size), rest

    def _check_tags(self, rest_image: np.ndarray) -> None:
        if self.layout is None:
            self.out.flags.append("no_tag_layout")
            return
        img = rest_image if rest_image.ndim == 2 else rest_image.mean(axis=2)
        scale = 255.0 / max(float(np.percentile(img, 99.9)), 1e-9)
        dets = detect_tags(np.clip(img * scale, 0, 255).astype(np.uint8))
        known = {t.id for t in self.layout.tags}
        self.out.tags_seen = sorted(d.id for d in dets if d.id in known)
        if not self.out.tags_seen:
            # Timing needs no tags: the take is synced, and the pose stage, which does need them, says so.
            self.out.flags.append("no_tags_visible")
            self.out.notes.append("no AprilTag of the capture's layout is visible in the rest image; timing does not "
                                  "need them, locating the view does (the pose stage decides)")

    def _image_timing(self, counters, rest, rest_image, rest_std, period, start_guess):
        r = self.r
        basis = DisplacementBasis.from_take(r, self.out.hit_daq_time_s, self.cam_exposure_s or period)
        if basis is None:
            return None
        motion = motion_gram(r.iter_frames(32), r.n_frames, rest_image, rest_std,
                             max_memory_bytes=self.s.max_memory_mb * 1e6)
        return fit_frame_times(motion, counters, period, basis, start_guess,
                               search_frames=self.s.search_frames, rest=rest, hit_time_s=self.out.hit_daq_time_s)


def _dates_frames(timing) -> bool:
    """Whether the images date the frames: a sigma under 0.3 frame, motion 10 sd above noise, not at the window's
    edge."""
    return (bool(np.isfinite(timing.sigma_frames)) and timing.sigma_frames <= 0.3 and timing.motion_z >= 10
            and "image_fit_at_window_edge" not in timing.flags)


# ---------------------------------------------------------------------------------------------- across takes

def _response(reader: TakeReader, onset_sample: float, impulse: float, n: int) -> np.ndarray | None:
    """The accelerometers' response from 1 ms before the onset, locked to it to a fraction of a sample, per unit
    impulse."""
    accels = reader.channels_of_kind("acceleration")
    if not accels:
        return None
    fs = reader.sample_rate_hz
    pre = int(round(1e-3 * fs))
    i0 = int(math.floor(onset_sample)) - pre
    if i0 < 0 or i0 + n + 1 > reader.n_samples:
        return None
    x = np.stack([np.nan_to_num(reader.channel(a)[i0:i0 + n + 1].astype(float)) for a in accels], axis=1)
    return fractional_shift(x, onset_sample - math.floor(onset_sample), axis=0)[:n] / impulse


def _lag(ref: np.ndarray, x: np.ndarray, max_lag: int = 8) -> tuple[float, float]:
    """Lag (samples) of x against ref, both (n, channels), by the peak of their cross-correlation summed over the
    channels, and its correlation coefficient."""
    n = len(ref)
    lags = np.arange(-max_lag, max_lag + 1)
    c = np.array([float((ref[max(0, -k):n - max(0, k)] * x[max(0, k):n - max(0, -k)]).sum()) for k in lags])
    i = int(np.argmax(c))
    frac = 0.0
    if 0 < i < len(c) - 1:
        a, b, d = c[i - 1], c[i], c[i + 1]
        frac = 0.5 * (a - d) / (a - 2 * b + d) if a - 2 * b + d < 0 else 0.0
    coeff = c[i] / np.sqrt(float((ref ** 2).sum()) * float((x ** 2).sum()) + 1e-300)
    return float(lags[i] + frac), float(coeff)


def _grid(takes: list[TakeSync], fps: float) -> tuple[float, int]:
    period = 1.0 / fps
    lo = max(t.offset_s + min(t.counters) * t.period_s for t in takes)
    hi = min(t.offset_s + max(t.counters) * t.period_s for t in takes)
    t0 = math.ceil(lo / period - 1e-9) * period
    n = int(math.floor((hi - t0) / period + 1e-9)) + 1
    if n < 2:
        raise OdsplatError("the synced takes share fewer than 2 frames of time: nothing to align")
    return t0, n


def _write_aligned(capture: Capture, t: TakeSync, reader: TakeReader, rest_counters: np.ndarray, t0: float, fps: float,
                   n_grid: int, settings: SyncSettings, out_dir: Path, generation: str) -> None:
    counters = np.asarray(t.counters)
    full, pos = fill_dropped(counters)
    grid = t0 + np.arange(n_grid) / fps
    u = (grid - t.offset_s) / t.period_s - full[0]  # each grid frame's place among the take's (filled) frames
    mean_shift = float(np.mean(u - np.arange(n_grid)))
    t.grid_shift_frames = mean_shift
    t.drift_frames = float(np.max(np.abs(u - np.arange(n_grid) - mean_shift)))
    if t.drift_frames > 0.02:
        t.flags.append("rate_drift")
        t.notes.append(f"one shift per take leaves {t.drift_frames:.3f} frame of timing error at the grid's ends")
    source_frame = np.full(full.size, -1, np.int64)
    source_frame[pos] = np.arange(len(pos))
    rest_dn = None
    if t.impulse_scale not in (None, 1.0):
        rest_dn = _mean_frames(reader, np.flatnonzero(np.isin(counters, rest_counters)), settings.max_memory_mb)
    path = out_dir / f"{t.name}.h5"
    write_aligned(path, take=t.name, times_s=grid, source_frame=source_frame, grid_shift_frames=mean_shift,
                  bit_depth=reader.bit_depth, rest_dn=rest_dn,
                  attrs=dict(view=t.view, offset_s=t.offset_s, method=t.method, impulse_scale=t.impulse_scale or 1.0,
                             generation=generation), capture_id=capture.id)
    t.aligned_file = os.path.relpath(path, capture.paths.root)  # relative to the derived root


def _mean_frames(reader: TakeReader, index: np.ndarray, max_memory_mb: float) -> np.ndarray | None:
    """The mean of the raw frames at `index`, read within the memory budget; None for none."""
    if not len(index):
        return None
    step = max(1, int(max_memory_mb * 1e6 // (np.prod(reader.frame_shape) * 4)))
    total = np.zeros(reader.frame_shape, np.float64)
    for a in range(int(index[0]), int(index[-1]) + 1, step):
        block = reader.read_frames(a, min(a + step, int(index[-1]) + 1))
        total += np.asarray(block[np.isin(np.arange(a, a + len(block)), index)], np.float64).sum(axis=0)
    return (total / len(index)).astype(np.float32)


class _Serial:
    """Executor-like `map` in this process."""

    def map(self, fn: Callable[..., Any], *iterables: Iterable[Any]) -> Iterator[Any]:
        return map(fn, *iterables)


def align_take(capture_root: str, derived_root: str, t: TakeSync, t0: float, fps: float, n_grid: int,
               settings: SyncSettings, out_dir: str, generation: str, shape: list[int]) -> TakeSync:
    """One take's frames onto the common grid, `out_dir/NAME.h5` (its own file); returns the take's record with
    the alignment's numbers, or excluded when its frames are of another shape. Runs in any process."""
    capture = Capture.open(capture_root, derived=derived_root)
    with capture.open_take(t.name) as r:
        if list(r.frame_shape) != shape:
            return t.exclude(f"frame shape {list(r.frame_shape)} differs from the capture's {shape}")
        if t.hit_daq_time_s is None:  # on its own frame times: no rest before a hit
            rest = np.empty(0, int)
        else:
            hit_counter = (t.hit_daq_time_s - t.frame0_daq_time_s) / t.period_s
            rest = np.asarray(t.counters)[np.asarray(t.counters) + 1 < hit_counter]
        _write_aligned(capture, t, r, rest, t0, fps, n_grid, settings, Path(out_dir), generation)
    return t


def sync_capture(capture: Capture, settings: SyncSettings | None = None, *, progress: bool = True,
                 executor: Executor | None = None) -> SyncResult:
    """Sync every selected take of the capture; writes derived/sync.json and, if asked, the aligned frames.

    `executor`: writes each take's aligned frames as its own task (`executor.map`, e.g. a Dask client's
    executor); by default in a pool of `settings.workers` processes (one after another in this process where
    that is 1). The results are the same either way."""
    s = settings or SyncSettings()
    records = capture.select_takes(s.takes)
    if not records:
        raise OdsplatError(f"{capture.root}: no {'' if s.takes == 'all' else 'accepted '}takes to sync"
                           + ("" if s.takes == "all" else capture.unchecked_hint()))
    out_dir = capture.paths.aligned_dir
    generation = begin_outputs(capture.paths.sync_json, out_dir)
    try:
        return _sync(capture, s, records, generation, out_dir, progress, executor)
    except BaseException:
        discard_outputs(out_dir)
        raise


def _sync(capture: Capture, s: SyncSettings, records, generation: str, out_dir: Path, progress: bool,
          executor: Executor | None) -> SyncResult:
    m = capture.manifest
    results: list[TakeSync] = []
    responses: dict[str, tuple[np.ndarray, float]] = {}
    for rec in tqdm(records, desc="sync: timing", unit="take", disable=not progress):
        with capture.open_take(rec.name) as r:
            a = _TakeAnalysis(r, m.tags, m.camera, s)
            results.append(a.run())
            if a.response is not None:
                responses[rec.name] = a.response
    _one_timeline(results)
    ok = [t for t in results if t.status == "ok"]
    fps = m.camera.fps
    if ok and fps is None:
        nominal = {round(1.0 / t.period_s) for t in ok if t.method == "image"}
        if len(nominal) > 1:
            raise OdsplatError(f"{capture.root}: the takes were filmed at different frame rates {sorted(nominal)} fps")
        fps = 1.0 / float(np.median([t.period_s for t in ok]))
    impulses = [t.impulse_n_s for t in ok if t.impulse_n_s is not None]
    ref_impulse = float(np.median(impulses)) if impulses else None
    _cross_check(ok, responses)
    for t in ok:
        t.impulse_scale = ref_impulse / t.impulse_n_s if s.normalize_impulse and t.impulse_n_s else 1.0
    t0, n_grid, shape = None, 0, []
    if ok:
        t0, n_grid = _grid(ok, fps)
        with capture.open_take(ok[0].name) as r:
            shape = list(r.frame_shape)
        if s.write_frames:
            capture.paths.ensure(out_dir)
            args = [(str(capture.root), str(capture.paths.root), t, t0, fps, n_grid, s, str(out_dir), generation, shape)
                    for t in ok]
            # one take per task: a pool of `workers` processes by default (on the demo, 27 takes of 256 frames at
            # 400x300 px, the whole stage took 79 s on 2 cores against 130 s one after another)
            workers = max(1, min(s.workers or os.cpu_count() or 1, len(ok)))
            pool = nullcontext(executor) if executor is not None else \
                process_pool(workers) if workers > 1 else nullcontext(_Serial())
            with pool as run:
                done = run.map(align_take, *zip(*args))
                aligned = {t.name: t for t in tqdm(done, total=len(ok), desc="sync: aligning frames", unit="take",
                                                   disable=not progress)}
            results = [aligned.get(t.name, t) for t in results]
    result = SyncResult(capture=m.name, fps=fps, n_frames=n_grid, t0_s=t0, frame_shape=shape,
                        reference_impulse_n_s=ref_impulse, normalized=s.normalize_impulse, takes=results,
                        settings=asdict(s), generation=generation)
    path = result.write(capture)
    prune_outputs(out_dir, [capture.paths.listed(t.aligned_file) for t in result.ok if t.aligned_file])
    log.info("sync: %d/%d takes on the common grid (%d frames); %s", len(result.ok), len(results), n_grid, path)
    if s.plot and result.ok:
        from .plot import plot_sync

        plot_sync(capture, result)
    return result


def _one_timeline(takes: list[TakeSync]) -> None:
    """Takes locked to an impact and takes on their own frame times do not share a timeline: where both are
    synced, those without force are excluded, saying why."""
    ok = [t for t in takes if t.status == "ok"]
    if any(t.method == "frames" for t in ok) and any(t.method != "frames" for t in ok):
        for t in ok:
            if t.method == "frames":
                t.exclude("no force channel, beside takes locked to their impact: it has no place on their timeline")
                log.warning("take %s excluded from sync: %s", t.name, t.error)


def _cross_check(ok: list[TakeSync], responses: dict[str, tuple[np.ndarray, float]]) -> None:
    """Cross-correlate every take's response (accelerometers locked to its onset, per unit impulse) with the
    first take's.

    A linear structure hit at the same place gives the same response per unit impulse: a lag means an onset
    is off, a low coefficient that the hit (place, direction) differed."""
    if len(ok) < 2:
        return
    ref = None
    for t in ok:
        if t.name not in responses:
            continue
        resp, fs = responses[t.name]
        if ref is None:
            ref = resp
        if resp.shape != ref.shape:
            continue
        lag, coeff = _lag(ref, resp)
        t.xcorr_lag_s, t.xcorr_coeff = lag / fs, coeff
        if abs(lag) > 0.25:
            t.flags.append("onset_inconsistent")
            t.notes.append(f"its response lags the reference take's by {lag:+.2f} DAQ samples after locking")
        if coeff < 0.9:
            t.flags.append("response_differs")
            t.notes.append(f"its response per unit impulse correlates {coeff:.2f} with the reference take's "
                           "(hit elsewhere or in another direction?)")


def load_sync(capture: Capture) -> SyncResult:
    return SyncResult.read(capture)


__all__ = ["SyncResult", "SyncSettings", "TakeSync", "load_sync", "sync_capture"]
