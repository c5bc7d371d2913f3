"""The guided multi-view capture session: for each planned view, place the camera, arm, hit, record, QC, accept or redo.

The session talks to the lab through a `Bench`: the camera (any `CameraDriver`), a way to open the DAQ,
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

from odsplat.errors import InputError
from odsplat.manifest import CameraInfo, Manifest, TagLayout, Viewpoint
from odsplat.store import Capture, QCInfo, TriggerInfo, atomic_open
from odsplat.tags import camera_pose_from_tags, detect_tags

from .camera import CameraDriver, CameraTimeout, TriggerSettings
from .daq import DAQChannel, DAQError, SerialDAQ
from .plan import PlanSettings, PoseCheck, check_pose, coverage, describe_view, plan_views, top_view_map
from .qc import HitQC, QCLimits, check_hit
from .trigger import HammerTrigger, TriggeredRecord, wait_for_hit

log = logging.getLogger(__name__)


class Bench(Protocol):
    """The lab as the session sees it."""

    camera: CameraDriver
    channels: Sequence[DAQChannel]  # what open_daq() records
    tags: TagLayout | None

    def open_daq(self) -> SerialDAQ:
        """The DAQ for one take, configured on start (opened per take, closed by the session)."""

    def place_camera(self, view: Viewpoint, instructions: str) -> None:
        """Tell the engineer where to put the camera (and wait until it is there)."""

    def hit(self) -> None:
        """The DAQ is streaming and the camera armed: hit the structure now."""

    def decide(self, qc: HitQC, pose: PoseCheck | None) -> bool:
        """Accept this take (True) or redo it (False)."""

    def take_written(self, take_path: Path, record: TriggeredRecord | None) -> None:
        """Called just before a take is finalised (the simulated rig saves its ground truth here)."""


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

    def __post_init__(self) -> None:
        if not 0 <= self.pretrigger_frames < self.n_frames:
            raise InputError("SessionSettings.pretrigger_frames", f"must lie in 0..{self.n_frames - 1}, got {self.pretrigger_frames}")
        if self.max_attempts < 1:
            raise InputError("SessionSettings.max_attempts", f"must be at least 1, got {self.max_attempts}")


@dataclass(frozen=True)
class TakeOutcome:
    name: str
    view: int
    accepted: bool
    qc: HitQC | None
    pose: PoseCheck | None
    error: str | None = None


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
            for r in (o.qc.reasons if o.qc else ()) or ("daq_error",):
                reasons[r] = reasons.get(r, 0) + 1
        why = ", ".join(f"{k} x{v}" for k, v in sorted(reasons.items())) or "none"
        return (f"{self.root}: {len(self.done_views)}/{self.n_views} views accepted, coverage {self.coverage:.0%}; "
                f"{len(self.outcomes)} takes this run, {len(rejected)} rejected ({why}); "
                f"{len(self.recovered)} unfinished take(s) recovered" +
                (f"; missing views {self.missing_views}" if self.missing_views else ""))


class Feedback(Protocol):
    def show_view(self, view: Viewpoint, n_views: int, instructions: str) -> None: ...

    def show_take(self, outcome: TakeOutcome, record: TriggeredRecord | None, coverage: float, plan_map: str) -> None: ...


class CaptureSession:
    """Runs the plan into the capture at `root` (created, or resumed when it exists)."""

    def __init__(self, root: str | Path, settings: SessionSettings, bench: Bench, *, feedback: Feedback | None = None):
        self.root = Path(root)
        self.settings = settings
        self.bench = bench
        self.feedback = feedback
        self.views = plan_views(settings.plan)
        self.outcomes: list[TakeOutcome] = []

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
            log.info("resuming %s: %d takes, %d views accepted", self.root, len(cap.manifest.takes), len(self._done(cap)))
            return cap, recovered
        cam = self.bench.camera.describe()
        channels = [c.info() for c in self.bench.channels]
        manifest = Manifest(name=self.settings.name, camera=cam, channels=channels, tags=self.bench.tags,
                            views=list(self.views), notes="recorded by odsplat capture")
        return Capture.create(self.root, manifest), []

    @staticmethod
    def _done(cap: Capture) -> set[int]:
        return {t.view for t in cap.manifest.takes if t.qc == "accepted" and t.view is not None}

    # ------------------------------------------------------------------------------ the loop

    def run(self) -> SessionReport:
        cap, recovered = self._open_capture()
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
            for attempt in range(self.settings.max_attempts):
                outcome, record = self._take(cap, view)
                accepted = outcome.accepted and self.bench.decide(outcome.qc, outcome.pose)
                if outcome.accepted and not accepted:  # the engineer redoes a take QC passed: mark it so
                    outcome = TakeOutcome(outcome.name, view.index, False, outcome.qc, outcome.pose, "redone by the engineer")
                    self._remark(cap, outcome.name, "rejected", ("redone_by_engineer",))
                self.outcomes.append(outcome)
                if self.feedback is not None:
                    done = sorted(self._done(cap))
                    self.feedback.show_take(outcome, record, coverage([self.views[i] for i in done], self.settings.plan),
                                            top_view_map(self.views, self.settings.plan, done=done, current=view.index))
                if accepted:
                    break
                log.warning("view %d: take %s rejected (%s); redo %d/%d", view.index, outcome.name,
                            outcome.error or "; ".join(outcome.qc.details), attempt + 1, self.settings.max_attempts)
            else:
                log.error("view %d: no accepted take after %d attempts; moving on", view.index, self.settings.max_attempts)
        done = self._done(cap)
        return SessionReport(self.root, n, sorted(done), [v.index for v in self.views if v.index not in done],
                             self.outcomes, recovered, coverage([self.views[i] for i in sorted(done)], self.settings.plan))

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
        camera.configure(TriggerSettings(n_frames=s.n_frames, mode="external", pretrigger=s.pretrigger_frames, fps=s.fps))
        daq = self.bench.open_daq()
        record: TriggeredRecord | None = None
        error: str | None = None
        clipped: set[str] = set()
        try:
            daq.start()
            if cap.manifest.daq_sample_rate_hz != daq.sample_rate_hz:
                cap.manifest.daq_sample_rate_hz = daq.sample_rate_hz
                cap.save_manifest()
            camera.arm()
            self.bench.hit()
            soft = getattr(camera, "software_trigger", None)
            record = wait_for_hit(daq, s.trigger, s.hit_timeout_s, on_trigger=(lambda _: soft()) if soft else None)
            daq.stop()
            clipped = set(daq.clipped)
        except DAQError as e:
            error = str(e)
            log.error("view %d: %s", view.index, error)
            record = self._salvage(daq)
        finally:
            daq.close()
        camera_error: str | None = None
        try:
            status = camera.wait(s.camera_timeout_s)
        except CameraTimeout as e:  # the DAQ's record may still be good: it is kept and checked as usual
            status = None
            camera_error = str(e)
            log.error("view %d: %s", view.index, camera_error)
            camera.stop()
        outcome = self._write(cap, name, view, record, status, clipped, error, daq.channels, camera_error)
        return outcome, record

    def _salvage(self, daq: SerialDAQ) -> TriggeredRecord | None:
        """What the DAQ delivered before it failed: kept, never thrown away."""
        stop = daq.next_sample
        if stop == 0 or daq.sample_rate_hz is None:
            return None
        first = max(0, stop - self.settings.trigger.samples(daq.sample_rate_hz)[1], stop - int(daq.buffer_s * daq.sample_rate_hz) + 1)
        return TriggeredRecord(first, first, stop, daq.sample_rate_hz, tuple(c.name for c in daq.channels),
                               daq.read(first, stop), daq.gaps_in(first, stop))

    def _write(self, cap: Capture, name: str, view: Viewpoint, record: TriggeredRecord | None, status, clipped: set[str],
               error: str | None, channels: Sequence[DAQChannel], camera_error: str | None = None) -> TakeOutcome:
        camera = self.bench.camera
        info = camera.describe()
        frames = camera.frames() if status is not None else iter(())
        first = next(frames, None)
        pose, tags_seen = self._pose(first.image if first is not None else None, info, view)
        attrs = {"session": self.settings.name, "camera_model": info.model}
        if pose is not None:
            attrs.update(pose_angular_error_deg=pose.angular_error_deg, pose_distance_error_m=pose.distance_error_m)
        writer = cap.new_take(name, view=view.index, frame_shape=camera.frame_shape if first is not None else None,
                              dtype=camera.dtype, bit_depth=info.bit_depth, fps=info.fps, attrs=attrs,
                              daq_t0_s=record.t0_s if record is not None else 0.0,
                              channels=cap.manifest.channels if record is not None else [])
        with writer:
            if record is not None:
                writer.append_samples({c: record.data[k] for k, c in enumerate(record.channels)})
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
                writer.set_qc(qc.to_qcinfo())
            else:
                qc = None
                flags = ("daq_error",) + (("camera_timeout",) if camera_error else ())
                writer.set_trigger(TriggerInfo(camera_trigger_frame=trigger_index))
                writer.set_qc(QCInfo("rejected", flags, "; ".join(filter(None, (error or "no DAQ data", camera_error)))))
            self.bench.take_written(writer.final_path, record)
            writer.finalize()
        accepted = qc is not None and qc.accepted
        log.info("take %s (view %d): %s", name, view.index, qc.summary() if qc else f"REJECTED ({error})")
        return TakeOutcome(name, view.index, accepted, qc, pose, error)

    def _pose(self, image: np.ndarray | None, info: CameraInfo, view: Viewpoint) -> tuple[PoseCheck | None, tuple[int, ...] | None]:
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
                                     min_tags=self.settings.limits.min_tags)
        if pose is None:
            return None, seen
        check = check_pose(view, pose.R, pose.t)
        log.info("view %d: camera %.1f deg and %+.3f m off the plan (from %d tags, %.2f px rms)", view.index,
                 check.angular_error_deg, check.distance_error_m, len(pose.tag_ids), pose.rms_px)
        return check, seen


# ---------------------------------------------------------------------------------- the lab


class LabBench:
    """A person at the rig: prompts on the terminal. The camera and the DAQ are real devices."""

    def __init__(self, camera: CameraDriver, daq_url: str, channels: Sequence[DAQChannel], sample_rate_hz: float,
                 tags: TagLayout | None, *, ask: Callable[[str], str] = input, tell: Callable[[str], None] = print):
        self.camera = camera
        self.tags = tags
        self.channels = tuple(channels)
        self.daq_url = daq_url
        self.sample_rate_hz = sample_rate_hz
        self._ask = ask
        self._tell = tell

    def open_daq(self) -> SerialDAQ:
        return SerialDAQ.from_url(self.daq_url, self.channels, self.sample_rate_hz)

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
