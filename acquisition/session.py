"""The guided multi-view capture session: for each planned view, place the camera, arm, hit, record, QC, accept or redo.

The session talks to the lab through a `Bench`: the camera (any `CameraDriver`), a way to open the DAQ,
optionally CAN accelerometer nodes (recorded into every take at their own rate, on the DAQ's time base),
and the engineer (where to put the camera, when to hit, accept or redo). `LabBench` asks a person;
`odsplat.hil_sim.bench.SimBench` plays the engineer on the simulated rig. The session's state is the
capture store itself, so it can be stopped and resumed (after a crash too): views with an accepted take
are done; unfinished take files are recovered and kept (marked), never deleted.
"""
from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from tqdm import tqdm

from odsplat.spine.atomic import atomic_open
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import CameraInfo, Manifest, TagLayout, Viewpoint
from odsplat.spine.store import Capture
from odsplat.spine.tags import camera_pose_from_tags, detect_tags
from odsplat.spine.take_writer import QCInfo, TriggerInfo

from .camera import CameraDriver, CameraTimeout, TriggerSettings
from .can_nodes import CANAccelerometers, CANError, CANRecord, CANSetup, record_window
from .daq import DAQChannel, DAQError, SerialDAQ
from .hammer import AutoHammer, FireRecord, HammerError, InterlockError
from .plan import PlanSettings, PoseCheck, check_pose, coverage, describe_view, plan_views, top_view_map
from .qc import HitQC, QCLimits, check_hit
from .trigger import HammerTrigger, TriggeredRecord, wait_for_hit

log = logging.getLogger(__name__)


class Bench(Protocol):
    """The lab as the session sees it."""

    camera: CameraDriver
    channels: Sequence[DAQChannel]  # what open_daq() records
    tags: TagLayout | None
    hammer: AutoHammer | None       # an automatic hammer, fired by the session when its settings say so
    can: CANSetup | None            # CAN accelerometer nodes recorded into every take (optional attribute)

    def open_daq(self) -> SerialDAQ:
        """The DAQ for one take, configured on start (opened per take, closed by the session)."""

    def open_can(self) -> CANAccelerometers:
        """The driver of `can`'s nodes on its bus (only called when `can` is set; once per session, the bench
        closes the bus)."""

    def place_camera(self, view: Viewpoint, instructions: str) -> None:
        """Tell the engineer where to put the camera (and wait until it is there)."""

    def hit(self) -> None:
        """The DAQ is streaming and the camera armed: hit the structure now."""

    def decide(self, qc: HitQC, pose: PoseCheck | None) -> bool:
        """Accept this take (True) or redo it (False)."""

    def take_written(self, take_path: Path, record: TriggeredRecord | None) -> None:
        """Called just before a take is finalised (the simulated rig saves its ground truth here)."""

    def retry_view(self, view: Viewpoint, outcomes: Sequence[TakeOutcome]) -> bool:
        """Every try at this view failed (`outcomes`): try again (True) or move on and leave it missing (False)."""


@dataclass(frozen=True)
class AutoHammerSettings:
    """Fire an automatic hammer (the bench's `hammer`) at a set force for every take."""

    force_n: float = 200.0
    tolerance: float = 0.03        # QC accepts a DAQ peak force within force_n * (1 +- tolerance)
    fire_timeout_s: float = 1.0    # the hammer gives up when it cannot fire within this
    correct_level: bool = True     # scale the commanded level by what the load cell measured on earlier shots
    history: int = 5               # shots the correction uses (their median)

    def __post_init__(self) -> None:
        if not self.force_n > 0:
            raise InputError("AutoHammerSettings.force_n", f"must be positive, got {self.force_n}")
        if not 0 < self.tolerance < 1:
            raise InputError("AutoHammerSettings.tolerance", f"expected a fraction in (0, 1), got {self.tolerance}")

    @property
    def band_n(self) -> tuple[float, float]:
        return self.force_n * (1 - self.tolerance), self.force_n * (1 + self.tolerance)


def choose_hammer(mode: str | None, *, simulated_engineer: bool, lab_settings: AutoHammerSettings | None,
                  has_lab: bool, force_n: float | None = None, tolerance: float | None = None,
                  where: str = "lab file") -> AutoHammerSettings | None:
    """The automatic hammer a session fires, or None for hits by hand. `mode` None picks: automatic with the
    simulated engineer or a lab file with a [hammer] section, else by hand. `force_n` and `tolerance` replace the
    lab file's (or the defaults)."""
    if mode not in (None, "auto", "manual"):
        raise InputError("--hammer", f"expected auto or manual, got {mode!r}")
    if mode is None:
        mode = "auto" if simulated_engineer or lab_settings is not None else "manual"
    if mode == "manual":
        return None
    if has_lab and lab_settings is None:
        raise InputError(where, "--hammer auto needs a [hammer] section (url or can) in the lab file")
    base = lab_settings or AutoHammerSettings()
    given = {k: v for k, v in (("force_n", force_n), ("tolerance", tolerance)) if v is not None}
    return replace(base, **given)


@dataclass(frozen=True)
class SessionSettings:
    name: str = "capture"
    plan: PlanSettings = field(default_factory=PlanSettings)
    n_frames: int = 100
    pretrigger_frames: int = 10
    fps: float | None = None
    trigger: HammerTrigger = field(default_factory=HammerTrigger)
    limits: QCLimits = field(default_factory=QCLimits)
    max_attempts: int = 5  # per view, before the session moves on and reports the view as missing
    hit_timeout_s: float = 60.0
    camera_timeout_s: float = 10.0
    static_photos: bool = False  # one still photo per view into static/, for the reconstruction's poses
    hammer: AutoHammerSettings | None = None  # None: the engineer hits (manual hammer)

    def __post_init__(self) -> None:
        if not 0 <= self.pretrigger_frames < self.n_frames:
            raise InputError("SessionSettings.pretrigger_frames",
                             f"must lie in 0..{self.n_frames - 1}, got {self.pretrigger_frames}")
        if self.max_attempts < 1:
            raise InputError("SessionSettings.max_attempts", f"must be at least 1, got {self.max_attempts}")
        if not self.hit_timeout_s > 0:
            raise InputError("SessionSettings.hit_timeout_s", f"must be > 0 s, got {self.hit_timeout_s}")


@dataclass(frozen=True)
class TakeOutcome:
    name: str
    view: int
    accepted: bool
    qc: HitQC | None
    pose: PoseCheck | None
    error: str | None = None
    fire: FireRecord | None = None  # the automatic hammer's shot


@dataclass
class SessionReport:
    root: Path
    n_views: int
    done_views: list[int]
    missing_views: list[int]
    outcomes: list[TakeOutcome]
    recovered: list[str]
    coverage: float

    @property
    def complete(self) -> bool:
        return not self.missing_views

    def summary(self) -> str:
        rejected = [o for o in self.outcomes if not o.accepted]
        reasons: dict[str, int] = {}
        for o in rejected:
            fallback = (f"hammer_{o.fire.outcome}",) if o.fire and not o.fire.fired else ("daq_error",)
            for r in (o.qc.reasons if o.qc else ()) or fallback:
                reasons[r] = reasons.get(r, 0) + 1
        why = ", ".join(f"{k} x{v}" for k, v in sorted(reasons.items())) or "none"
        return (f"{self.root}: {len(self.done_views)}/{self.n_views} views accepted, coverage {self.coverage:.0%}; "
                f"{len(self.outcomes)} takes this run, {len(rejected)} rejected ({why}); "
                f"{len(self.recovered)} unfinished take(s) recovered" +
                (f"; missing views {self.missing_views}" if self.missing_views else ""))


class Feedback(Protocol):
    def show_view(self, view: Viewpoint, n_views: int, instructions: str) -> None: ...

    def show_take(self, outcome: TakeOutcome, record: TriggeredRecord | None, coverage: float,
                  plan_map: str) -> None: ...


class CaptureSession:
    """Runs the plan into the capture at `root` (created, or resumed when it exists)."""

    def __init__(self, root: str | Path, settings: SessionSettings, bench: Bench, *, feedback: Feedback | None = None):
        self.root = Path(root)
        self.settings = settings
        self.bench = bench
        self.feedback = feedback
        self.views = plan_views(settings.plan)
        self.outcomes: list[TakeOutcome] = []
        self.hammer: AutoHammer | None = None
        if settings.hammer is not None:
            self.hammer = getattr(bench, "hammer", None)
            if self.hammer is None:
                raise InputError("odsplat capture",
                             "the session is set to fire an automatic hammer, but the bench has none")
            self.settings = replace(settings, limits=replace(settings.limits, force_band_n=settings.hammer.band_n))
        self._gains: list[float] = []      # DAQ peak / commanded level, of recent clean shots
        self.can: CANSetup | None = getattr(bench, "can", None)
        self._can: CANAccelerometers | None = None  # opened on the first take
        self._hammer_reset_due = False     # the session itself faulted or e-stopped the hammer: reset before firing

    # ------------------------------------------------------------------------------ the store

    def _open_capture(self) -> tuple[Capture, list[str]]:
        if (self.root / "capture.json").exists():
            cap = Capture.open(self.root)
            planned = [(v.azimuth_deg, v.elevation_deg) for v in self.views]
            stored = [(v.azimuth_deg, v.elevation_deg) for v in cap.manifest.views]
            if stored and (len(stored) != len(planned) or not np.allclose(stored, planned, atol=1e-6)):
                raise InputError(str(self.root / "capture.json"), "its views differ from this session's plan; "
                                 "resume with the same plan settings, or capture into a new folder")
            reports = cap.recover()
            recovered = [r.name for r in reports]
            for r in reports:
                log.warning("resume: %s", r.message)
            log.info("resuming %s: %d takes, %d views accepted", self.root, len(cap.manifest.takes),
                     len(self._done(cap)))
            return cap, recovered
        cam = self.bench.camera.describe()
        if self.settings.fps is not None:       # every take is filmed at the session's rate, not the camera's own
            cam = replace(cam, fps=float(self.settings.fps))
        channels = [c.info() for c in self.bench.channels] + (self.can.channels() if self.can else [])
        manifest = Manifest(name=self.settings.name, camera=cam, channels=channels, tags=self.bench.tags,
                            views=list(self.views), notes="recorded by odsplat capture")
        return Capture.create(self.root, manifest), []

    @staticmethod
    def _done(cap: Capture) -> set[int]:
        return {t.view for t in cap.manifest.takes if t.qc == "accepted" and t.view is not None}

    # ------------------------------------------------------------------------------ the loop

    def run(self) -> SessionReport:
        cap, recovered = self._open_capture()
        if self.hammer is not None:
            if self.hammer.fire_log is None:
                self.hammer.fire_log = cap.root / "hammer_fires.jsonl"
            self.hammer.hello()
        try:
            return self._run(cap, recovered)
        finally:
            if self._can is not None:
                self._can.stop()
            if self.hammer is not None and self.hammer.armed:
                try:
                    self.hammer.disarm()
                except HammerError as e:
                    log.error("could not disarm the hammer: %s", e)

    def _run(self, cap: Capture, recovered: list[str]) -> SessionReport:
        n = len(self.views)
        todo = [v for v in self.views if v.index not in self._done(cap)]
        for view in tqdm(todo, desc="views", unit="view", disable=None):
            instructions = describe_view(view, n) + "\n" + top_view_map(
                self.views, self.settings.plan, done=sorted(self._done(cap)), current=view.index)
            if self.feedback is not None:
                self.feedback.show_view(view, n, instructions)
            self.bench.place_camera(view, instructions)
            if self.settings.static_photos:
                self._static_photo(cap, view)
            tries: list[TakeOutcome] = []
            attempt = 0
            while True:
                if attempt == self.settings.max_attempts:
                    log.error("view %d: no accepted take after %d attempts", view.index, attempt)
                    if not self.bench.retry_view(view, tries):
                        log.error("view %d: moving on; it stays missing", view.index)
                        break
                    attempt = 0
                attempt += 1
                outcome, record = self._take(cap, view)
                tries.append(outcome)
                accepted = outcome.accepted and self.bench.decide(outcome.qc, outcome.pose)
                if outcome.accepted and not accepted:  # the engineer redoes a take QC passed: mark it so
                    outcome = TakeOutcome(outcome.name, view.index, False, outcome.qc, outcome.pose,
                                          "redone by the engineer")
                    self._remark(cap, outcome.name, "rejected", ("redone_by_engineer",))
                self.outcomes.append(outcome)
                if self.feedback is not None:
                    done = sorted(self._done(cap))
                    self.feedback.show_take(
                        outcome, record, coverage([self.views[i] for i in done], self.settings.plan),
                        top_view_map(self.views, self.settings.plan, done=done, current=view.index))
                if accepted:
                    break
                log.warning("view %d: take %s rejected (%s); redo %d/%d", view.index, outcome.name or "(none)",
                            outcome.error or "; ".join(outcome.qc.details), attempt, self.settings.max_attempts)
        done = self._done(cap)
        return SessionReport(self.root, n, sorted(done), [v.index for v in self.views if v.index not in done],
                             self.outcomes, recovered,
                             coverage([self.views[i] for i in sorted(done)], self.settings.plan))

    def _static_photo(self, cap: Capture, view: Viewpoint) -> Path:
        """A still of the structure at rest from this view (internal trigger, one frame), as a PNG in static/."""
        path = cap.static_dir / f"view_{view.index:02d}.png"
        if path.exists():
            return path
        camera = self.bench.camera
        camera.configure(TriggerSettings(n_frames=1, mode="internal", fps=self.settings.fps))
        camera.arm()
        camera.wait(self.settings.camera_timeout_s)
        image = next(camera.frames()).image
        camera.stop()
        bit_depth = camera.describe().bit_depth or image.dtype.itemsize * 8
        if image.dtype == np.uint16 and bit_depth < 16:
            image = image << (16 - bit_depth)  # PNG viewers expect 16-bit full scale
        if image.ndim == 3:
            image = image[..., ::-1]  # OpenCV writes BGR
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise InputError(str(path), "could not encode the static photo as PNG")
        cap.static_dir.mkdir(exist_ok=True)
        with atomic_open(path, "wb") as fh:
            fh.write(png.tobytes())
        log.info("view %d: static photo %s", view.index, path.name)
        return path

    def _remark(self, cap: Capture, name: str, status: str, flags: tuple[str, ...]) -> None:
        """Only the manifest's verdict changes (raw take files are never rewritten); the flags go in its notes."""
        for t in cap.manifest.takes:
            if t.name == name:
                t.qc = status
        cap.manifest.notes += f"\n{name}: {status} ({', '.join(flags)})"
        cap.save_manifest()

    def _take(self, cap: Capture, view: Viewpoint) -> tuple[TakeOutcome, TriggeredRecord | None]:
        s = self.settings
        camera = self.bench.camera
        name = cap.next_take_name(view.index)
        camera.configure(TriggerSettings(n_frames=s.n_frames, mode="external", pretrigger=s.pretrigger_frames,
                                         fps=s.fps))
        daq = self.bench.open_daq()
        record: TriggeredRecord | None = None
        fire: FireRecord | None = None
        error: str | None = None
        lost_waiting = 0  # samples lost on the link while no trigger came
        clipped: set[str] = set()
        can_records: list[CANRecord] = []
        can_error = self._start_can()
        try:
            daq.start()
            if cap.manifest.daq_sample_rate_hz != daq.sample_rate_hz:
                cap.manifest.daq_sample_rate_hz = daq.sample_rate_hz
                cap.save_manifest()
            camera.arm()
            if self.hammer is None:
                self.bench.hit()
            else:
                # The pretrigger must be in the buffers before the hammer strikes.
                fps = camera.describe().fps
                pre_s = max(s.trigger.pretrigger_s, s.pretrigger_frames / fps if fps else 0.0)
                daq.wait_for(int(1.2 * pre_s * daq.sample_rate_hz) + 1, timeout_s=max(2.0, 5 * pre_s))
                fire = self._fire(daq)
                if fire is None or not fire.fired:  # nothing struck: no take, the redo loop tries again
                    daq.stop()
                    camera.stop()
                    return self._no_hit(name, view, fire), None
            soft = getattr(camera, "software_trigger", None)
            record = wait_for_hit(daq, s.trigger, s.hit_timeout_s, on_trigger=(lambda _: soft()) if soft else None)
            if self._can is not None and can_error is None:  # before the DAQ stops: the nodes keep its pace
                can_records = record_window(self._can, self.can, record.t0_s, record.stop_sample / daq.sample_rate_hz)
            daq.stop()
            clipped = set(daq.clipped)
        except DAQError as e:
            error = str(e)
            lost_waiting = getattr(e, "lost_samples", 0)
            log.error("view %d: %s", view.index, error)
            record = self._salvage(daq)
            if record is not None and self._can is not None and can_error is None:
                can_records = record_window(self._can, self.can, record.t0_s,
                                            record.stop_sample / record.sample_rate_hz, wait=False)
        finally:
            daq.close()
            if self._can is not None:
                self._can.stop()
        camera_error: str | None = None
        try:
            status = camera.wait(s.camera_timeout_s)
        except CameraTimeout as e:  # the DAQ's record may still be good: it is kept and checked as usual
            status = None
            camera_error = str(e)
            log.error("view %d: %s", view.index, camera_error)
            camera.stop()
        outcome = self._write(cap, name, view, record, status, clipped, error, daq.channels, camera_error, fire,
                              can_records, can_error, lost_waiting)
        if self.hammer is not None and fire is not None and outcome.qc is not None:
            self._learn_gain(fire, outcome.qc)
        return outcome, record

    def _start_can(self) -> str | None:
        """START the CAN nodes for this take (sample 0 again); what went wrong, or None."""
        if self.can is None:
            return None
        if self._can is None:
            self._can = self.bench.open_can()
        try:
            self._can.start()
        except (InputError, CANError) as e:  # a silent node: this take has no CAN samples, QC says so
            log.error("CAN: %s", e)
            return str(e)
        return None

    # ------------------------------------------------------------------------------ the automatic hammer

    def commanded_force_n(self) -> float:
        """The level to command: the set force divided by the hammer's gain on this structure, as measured by
        the DAQ's load cell on recent clean shots (a hammer calibrated on another structure is off)."""
        h = self.settings.hammer
        if not h.correct_level or not self._gains:
            return h.force_n
        return h.force_n / float(np.median(self._gains[-h.history:]))

    def _learn_gain(self, fire: FireRecord, qc: HitQC) -> None:
        if set(qc.reasons) & {"double_hit", "force_overload", "dropped_samples"} or not qc.peak_force_n > 0:
            return
        self._gains.append(qc.peak_force_n / fire.level)

    def _fire(self, daq: SerialDAQ) -> FireRecord | None:
        """Arm and fire the hammer for this take; None or a record that did not fire when nothing struck."""
        hammer, h = self.hammer, self.settings.hammer
        hammer.recording_armed = lambda: daq.error is None and daq.next_sample > 0  # the camera was armed before this
        try:
            if self._hammer_reset_due:
                hammer.reset()
                self._hammer_reset_due = False
            hammer.arm()
            return hammer.fire(force_n=self.commanded_force_n(), timeout_s=h.fire_timeout_s)
        except InterlockError:
            raise  # the e-stop is latched, or the recording is not armed: never work around an interlock
        except HammerError as e:
            log.error("hammer: %s", e)
            if e.record is not None and e.record.outcome in ("fault", "no_response"):
                self._hammer_reset_due = True
            return e.record
        finally:
            hammer.recording_armed = lambda: False

    def _no_hit(self, name: str, view: Viewpoint, fire: FireRecord | None) -> TakeOutcome:
        """The hammer did not strike: nothing was recorded worth keeping; the fire log has the attempt."""
        if fire is None:  # refused before any FIRE was sent (arm or reset failed)
            why = "hammer: no shot"
        else:
            why = f"hammer: {fire.outcome}" + (f" ({fire.detail})" if fire.detail else "")
        log.warning("view %d: no take (%s)", view.index, why)
        return TakeOutcome("", view.index, False, None, None, why, fire)

    def _salvage(self, daq: SerialDAQ) -> TriggeredRecord | None:
        """What the DAQ delivered before it failed: kept, never thrown away."""
        stop = daq.next_sample
        if stop == 0 or daq.sample_rate_hz is None:
            return None
        first = max(0, stop - self.settings.trigger.samples(daq.sample_rate_hz)[1],
                    stop - int(daq.buffer_s * daq.sample_rate_hz) + 1)
        return TriggeredRecord(first, first, stop, daq.sample_rate_hz, tuple(c.name for c in daq.channels),
                               daq.read(first, stop), daq.gaps_in(first, stop))

    def _write(self, cap: Capture, name: str, view: Viewpoint, record: TriggeredRecord | None, status,
               clipped: set[str], error: str | None, channels: Sequence[DAQChannel], camera_error: str | None = None,
               fire: FireRecord | None = None, can_records: Sequence[CANRecord] = (),
               can_error: str | None = None, lost_waiting: int = 0) -> TakeOutcome:
        camera = self.bench.camera
        info = camera.describe()
        frames = camera.frames() if status is not None else iter(())
        first = next(frames, None)
        pose, tags_seen = self._pose(first.image if first is not None else None, info, view)
        attrs = {"session": self.settings.name, "camera_model": info.model}
        if pose is not None:
            attrs.update(pose_angular_error_deg=pose.angular_error_deg, pose_distance_error_m=pose.distance_error_m)
        if fire is not None:
            attrs.update(hammer_set_force_n=self.settings.hammer.force_n, hammer_command_n=fire.level,
                         hammer_peak_force_n=fire.peak_force_n, hammer_delay_s=fire.delay_s,
                         hammer_shot_count=fire.shot_count, hammer_rebound=fire.rebound, hammer_fire_time_s=fire.time_s)
        writer = cap.new_take(name, view=view.index, frame_shape=camera.frame_shape if first is not None else None,
                              dtype=camera.dtype, bit_depth=info.bit_depth, fps=info.fps, attrs=attrs,
                              daq_t0_s=record.t0_s if record is not None else 0.0,
                              channels=cap.manifest.channels if record is not None else [])
        with writer:
            if record is not None:
                writer.append_samples({c: record.data[k] for k, c in enumerate(record.channels)})
            can_problems = [can_error] if can_error and writer.can_channels else []
            for rec in can_records:
                if rec.node.name not in writer.can_channels:
                    log.warning("take %s: CAN node %s is not in the capture's channels; not stored", name,
                                rec.node.name)
                    continue
                writer.append_can_samples(rec.node.name, rec.times_s, rec.block())
                if rec.problem or rec.lost_samples:
                    can_problems.append(rec.problem or f"CAN {rec.node.name}: {rec.lost_samples} sample(s) lost")
            trigger_index = None
            # One frame at a time, straight from the camera into the take file (flushed per frame).
            for k, frame in enumerate(itertools.chain([first] if first is not None else [], frames)):
                if frame.counter == 0:
                    trigger_index = k
                writer.append_frames(frame.image[None], np.array([frame.time_s]), np.array([frame.counter]))
            if error is None and record is not None:
                writer.set_trigger(TriggerInfo(record.pretrigger_samples, record.pretrigger_samples, trigger_index,
                                               record.trigger_sample / record.sample_rate_hz))
                qc = check_hit(record, channels, limits=self.settings.limits,
                               force_channel=self.settings.trigger.channel, clipped=clipped,
                               dropped_frames=status.dropped if status else (), tags_seen=tags_seen)
                if camera_error:
                    qc = replace(qc, reasons=qc.reasons + ("camera_timeout",),
                                 details=qc.details + (f"no frames: {camera_error}",))
                if can_problems:
                    qc = replace(qc, reasons=qc.reasons + ("can_samples_lost",),
                                 details=qc.details + tuple(can_problems))
                writer.set_qc(qc.to_qcinfo())
            else:
                qc = None
                flags = (("daq_error",) + (("dropped_samples",) if lost_waiting else ())
                         + (("camera_timeout",) if camera_error else ()))
                writer.set_trigger(TriggerInfo(camera_trigger_frame=trigger_index))
                detail = "; ".join(filter(None, (error or "no DAQ data", camera_error)))
                writer.set_qc(QCInfo("rejected", flags, detail))
            self.bench.take_written(writer.final_path, record)
            writer.finalize()
        accepted = qc is not None and qc.accepted
        log.info("take %s (view %d): %s", name, view.index, qc.summary() if qc else f"REJECTED ({error})")
        return TakeOutcome(name, view.index, accepted, qc, pose, error, fire)

    def _pose(self, image: np.ndarray | None, info: CameraInfo,
              view: Viewpoint) -> tuple[PoseCheck | None, tuple[int, ...] | None]:
        """Floor tags seen in the first frame, and the pose they give checked against the plan."""
        layout = self.bench.tags
        if image is None or layout is None:
            return None, None
        detections = detect_tags(image)
        floor = {t.id for t in layout.tags if not t.on_structure}
        seen = tuple(d.id for d in detections if d.id in floor)
        if info.intrinsics is None or not seen:
            return None, seen
        k = info.intrinsics
        pose = camera_pose_from_tags(detections, layout, k.matrix(), np.asarray(k.dist) if k.dist else None,
                                     min_tags=max(1, self.settings.limits.min_tags))
        if pose is None:
            return None, seen
        check = check_pose(view, pose.R, pose.t)
        log.info("view %d: camera %.1f deg and %+.3f m off the plan (from %d tags, %.2f px rms)", view.index,
                 check.angular_error_deg, check.distance_error_m, len(pose.tag_ids), pose.rms_px)
        return check, seen


# ---------------------------------------------------------------------------------- the lab


class LabBench:
    """A person at the rig: prompts on the terminal. The camera and the DAQ are real devices, and so are the CAN
    accelerometer nodes when `can` is given (`open_can` opens their bus: `LabConfig.open_can`)."""

    def __init__(self, camera: CameraDriver, daq_url: str, channels: Sequence[DAQChannel], sample_rate_hz: float,
                 tags: TagLayout | None, *, ask: Callable[[str], str] = input, tell: Callable[[str], None] = print,
                 hammer: AutoHammer | None = None, can: CANSetup | None = None,
                 open_can: Callable[[], CANAccelerometers] | None = None):
        if (can is None) != (open_can is None):
            raise InputError("LabBench", "give both the CAN nodes (can) and the way to open their bus (open_can)")
        self.camera = camera
        self.hammer = hammer
        self.tags = tags
        self.channels = tuple(channels)
        self.daq_url = daq_url
        self.sample_rate_hz = sample_rate_hz
        self._ask = ask
        self._tell = tell
        self.can = can
        # Opened now, so that a bus that is down or misnamed stops the session before the first view.
        self._can: CANAccelerometers | None = open_can() if open_can is not None else None

    def open_daq(self) -> SerialDAQ:
        return SerialDAQ.from_url(self.daq_url, self.channels, self.sample_rate_hz)

    def open_can(self) -> CANAccelerometers:
        if self._can is None:
            raise InputError("LabBench.open_can", "this bench has no CAN nodes (the lab file has no [can] section)")
        return self._can

    def close(self) -> None:
        """Close the automatic hammer's driver and shut the CAN nodes' bus down, if any (idempotent). The session
        has already STOPped the nodes."""
        if self._can is not None:
            self._can.bus.shutdown()
            self._can = None
        if self.hammer is not None:
            self.hammer.close()
            self.hammer = None

    def __enter__(self) -> LabBench:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def place_camera(self, view: Viewpoint, instructions: str) -> None:
        self._tell(instructions)
        self._ask("Place the camera as shown, then press Enter. ")

    def hit(self) -> None:
        self._tell("Armed: hit the structure now.")

    def decide(self, qc: HitQC, pose: PoseCheck | None) -> bool:
        where = "" if pose is None else f" (camera {pose.angular_error_deg:.1f} deg off the plan)"
        answer = self._ask(f"{qc.summary()}{where}. Accept? [Y/n] ").strip().lower()
        return answer in ("", "y", "yes")

    def take_written(self, take_path: Path, record: TriggeredRecord | None) -> None:
        pass

    def retry_view(self, view: Viewpoint, outcomes: Sequence[TakeOutcome]) -> bool:
        why = "; ".join(o.error or "; ".join(o.qc.details if o.qc else ()) for o in outcomes[-3:])
        answer = self._ask(f"View {view.index}: {len(outcomes)} tries failed (last: {why}). Try again? [y/N] ")
        return answer.strip().lower() in ("y", "yes")
