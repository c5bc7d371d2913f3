"""Hit QC, per take, as impact-testing software does it: double hits, overloads, lost data, force band, tags.

Each check gives a reason code (stored in the take's QC flags) and a sentence for the engineer. A take
with any reason is rejected; rejected takes are kept and marked, never deleted.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from odsplat.spine.checks import MAX_FORCE_N, Range, check_fields, maybe
from odsplat.spine.contract import plain
from odsplat.spine.errors import InputError
from odsplat.spine.impulse import ImpactDetector, ImpactSettings
from odsplat.spine.manifest import from_plain
from odsplat.spine.qcfile import QCFile, TakeQC
from odsplat.spine.store import Capture
from odsplat.spine.take_reader import TakeReader
from odsplat.spine.take_writer import QCInfo

from .daq import DAQChannel
from .trigger import TriggeredRecord

REASONS = {
    "double_hit": "more than one impact",
    "force_overload": "the force channel clipped",
    "accel_overload": "an accelerometer clipped",
    "dropped_samples": "DAQ samples were lost",
    "dropped_frames": "camera frames were lost",
    "force_low": "the peak force is below the planned band",
    "force_high": "the peak force is above the planned band",
    "tags_not_visible": "too few AprilTags are visible",
    "camera_timeout": "the camera never delivered its recording (set by the session)",
    "empty": "the take holds neither frames nor samples",
}


@dataclass(frozen=True)
class QCLimits:
    force_band_n: tuple[float, float] = (20.0, 2000.0)  # planned peak force
    impacts: ImpactSettings = field(default_factory=ImpactSettings)  # what an impact is (more than one: double hit)
    overload_fraction: float = 0.999  # a sample this close to full scale counts as clipped
    min_tags: int = 2  # floor tags that must be visible for the pose

    def __post_init__(self) -> None:
        lo, hi = self.force_band_n
        if not 0 <= lo < hi:
            raise InputError("QCLimits.force_band_n", f"expected 0 <= low < high, got {self.force_band_n}")
        if isinstance(self.min_tags, bool) or not isinstance(self.min_tags, int) or self.min_tags < 0:
            raise InputError("QCLimits.min_tags", f"expected a whole number >= 0, got {self.min_tags!r}")


@dataclass(frozen=True)
class HitQC:
    """The verdict on one take, with the figures behind it."""

    reasons: tuple[str, ...]
    details: tuple[str, ...]
    peak_force_n: float
    impact_times_s: tuple[float, ...]  # each impact's onset (odsplat.spine.impulse), relative to the trigger sample
    accel_peak: Mapping[str, float] = field(default_factory=dict)  # m/s^2
    lost_samples: int = 0
    dropped_frames: tuple[int, ...] = ()
    tags_seen: tuple[int, ...] | None = None

    @property
    def accepted(self) -> bool:
        return not self.reasons

    def to_qcinfo(self) -> QCInfo:
        return QCInfo("accepted" if self.accepted else "rejected", self.reasons, "; ".join(self.details))

    def summary(self) -> str:
        """One line for the engineer."""
        acc = ", ".join(f"{k} {v:.3g}" for k, v in self.accel_peak.items())
        verdict = "ACCEPTED" if self.accepted else "REJECTED (" + "; ".join(self.details) + ")"
        tags = "" if self.tags_seen is None else f", tags {list(self.tags_seen)}"
        return (f"peak force {self.peak_force_n:.1f} N, {len(self.impact_times_s)} impact(s), peak acc [m/s^2] {acc}"
                f"{tags}: {verdict}")


def check_hit(record: TriggeredRecord, channels: Sequence[DAQChannel], *, limits: QCLimits | None = None,
              force_channel: str = "force", clipped: set[str] | frozenset[str] = frozenset(),
              dropped_frames: Sequence[int] = (), tags_seen: Sequence[int] | None = None) -> HitQC:
    """Run every check on a triggered record. `clipped`: channels the DAQ flagged as clipped during the take;
    `tags_seen`: floor tag ids found in the take's frame (None: not checked); `limits`: default `QCLimits()`."""
    limits = limits or QCLimits()
    reasons: list[str] = []
    details: list[str] = []

    def fail(code: str, detail: str) -> None:
        if code not in reasons:
            reasons.append(code)
        details.append(detail)

    by_name = {c.name: c for c in channels}
    force = record.channel(force_channel)
    peak = float(np.nanmax(force)) if np.isfinite(force).any() else 0.0
    impacts = ImpactDetector(limits.impacts).detect(force, record.sample_rate_hz, source=force_channel).pulses
    times = tuple((p.onset_sample + record.first_sample - record.trigger_sample) / record.sample_rate_hz
                  for p in impacts)
    if len(impacts) > 1:
        gaps_ms = ", ".join(f"{1e3 * (b - a):.2f}" for a, b in zip(times, times[1:]))
        fail("double_hit", f"double hit: {len(impacts)} impacts, {gaps_ms} ms apart")
    lo, hi = limits.force_band_n
    if peak < lo:
        fail("force_low", f"peak force {peak:.1f} N below the planned {lo:g} N")
    elif peak > hi:
        fail("force_high", f"peak force {peak:.1f} N above the planned {hi:g} N")
    accel_peak: dict[str, float] = {}
    for name in record.channels:
        c = by_name.get(name)
        if c is None:
            continue
        x = record.channel(name)
        over = bool(np.nanmax(np.abs(x), initial=0.0) >= limits.overload_fraction * c.full_scale) or name in clipped
        if c.kind == "acceleration":
            accel_peak[name] = float(np.nanmax(np.abs(x), initial=0.0))
        if over and name == force_channel:
            fail("force_overload", f"force overload: {name!r} reached its +-{c.full_scale:.4g} N full scale")
        elif over and c.kind == "acceleration":
            fail("accel_overload",
                 f"accelerometer overload: {name!r} reached its +-{c.full_scale:.4g} m/s^2 full scale")
    if record.lost_samples:
        fail("dropped_samples", f"{record.lost_samples} DAQ samples lost in {len(record.gaps)} gap(s)")
    if dropped_frames:
        fail("dropped_frames", f"{len(dropped_frames)} camera frame(s) lost (counters {list(dropped_frames)[:8]})")
    if tags_seen is not None and len(tags_seen) < limits.min_tags:
        fail("tags_not_visible", f"{len(tags_seen)} floor AprilTag(s) visible, {limits.min_tags} needed")
    return HitQC(tuple(reasons), tuple(details), peak, times, accel_peak, record.lost_samples,
                 tuple(int(c) for c in dropped_frames), None if tags_seen is None else tuple(int(t) for t in tags_seen))


# ---------------------------------------------------------------------------------------------- the qc stage



@dataclass(frozen=True)
class QCSettings:
    """The pipeline's qc stage: every take's hit checked again from its file."""

    force_band_n: tuple[float, float] | None = None  # the planned peak force (N); None: any
    impacts: ImpactSettings = field(default_factory=ImpactSettings)  # what an impact is (more than one: double hit)

    def __post_init__(self) -> None:
        check_fields(self, {"force_band_n": maybe(Range(at_least=0, at_most=MAX_FORCE_N))})
        if self.force_band_n is not None and not self.force_band_n[0] < self.force_band_n[1]:
            raise InputError("QCSettings.force_band_n", f"expected LOW < HIGH in N, got {list(self.force_band_n)}")

    def limits(self) -> QCLimits:
        band = self.force_band_n if self.force_band_n is not None else (0.0, float("inf"))
        return QCLimits(force_band_n=band, impacts=self.impacts)


@dataclass(frozen=True)
class QCReport:
    takes: tuple[TakeQC, ...]
    settings: QCSettings

    def summary(self) -> str:
        acc = sum(t.status == "accepted" for t in self.takes)
        lines = [f"{acc}/{len(self.takes)} takes accepted"]
        for t in self.takes:
            if t.checked != t.recorded and t.recorded != "unchecked":
                lines.append(f"  {t.name}: recorded {t.recorded}, the file now checks {t.checked}"
                             + (f" ({'; '.join(t.details)})" if t.details else ""))
            elif t.recorded == "unchecked":
                lines.append(f"  {t.name}: unchecked until now, {t.checked}"
                             + (f" ({'; '.join(t.details)})" if t.details else ""))
        return "\n".join(lines)

    def write(self, capture: Capture) -> None:
        """derived/qc.json (its format: odsplat.spine.qcfile)."""
        QCFile(self.takes, plain(self.settings)).write(capture.paths.qc_json, capture.id)

    @classmethod
    def read(cls, capture: Capture) -> QCReport:
        path = capture.paths.qc_json
        doc = QCFile.read(path, capture.id)
        return cls(doc.takes, from_plain(QCSettings, dict(doc.settings), f"{path}: settings"))


def take_content(reader: TakeReader) -> str:
    """What a take holds: "frames", "response" (DAQ or CAN channels other than force) and "force", joined by "+"
    in that order ("frames", "frames+response", "frames+force+response", "force+response", ...)."""
    parts = []
    if reader.has_frames and reader.n_frames:
        parts.append("frames")
    names = reader.channel_names if reader.n_samples else []
    force = reader.channels_of_kind("force") if names else []
    if force:
        parts.append("force")
    others = [c for c in names if c not in force]
    if others or reader.can_channel_names:
        parts.append("response")
    return "+".join(parts) or "empty"


def _losses(reader: TakeReader, lost_samples: int, reasons: list[str], details: list[str]) -> tuple[int, ...]:
    """The reasons for lost samples and dropped frames (gaps in the camera's counter), added to `reasons` and
    `details`; the dropped counters."""
    if lost_samples:
        reasons.append("dropped_samples")
        details.append(f"{lost_samples} DAQ samples lost")
    dropped: tuple[int, ...] = ()
    if reader.has_frames and reader.n_frames > 1:
        counter = np.asarray(reader.frame_counter, np.int64)
        dropped = tuple(int(c) for c in np.setdiff1d(np.arange(counter[0], counter[-1] + 1), counter))
    if dropped:
        reasons.append("dropped_frames")
        details.append(f"{len(dropped)} camera frame(s) lost (counters {list(dropped)[:8]})")
    return dropped


def check_unforced(reader: TakeReader) -> HitQC:
    """The checks for a take without a force channel (a video on its own, or video and response channels, from an
    operating machine nobody hits): lost samples in its channels and dropped frames. There is no hit to judge."""
    reasons, details = [], []
    lost = 0
    if reader.n_samples:
        lost = sum(int(np.count_nonzero(~np.isfinite(reader.channel(c)))) for c in reader.channel_names)
    dropped = _losses(reader, lost, reasons, details)
    return HitQC(tuple(reasons), tuple(details), 0.0, (), {}, lost, dropped)


def check_take(reader: TakeReader, limits: QCLimits) -> HitQC:
    """The checks a take's file allows afterwards: impacts, force band, lost samples (NaN) and dropped frames
    (gaps in the camera's counter). Overloads need the DAQ's range, which only the live session knows."""
    names = reader.channels_of_kind("force")
    if len(names) != 1:
        raise InputError(reader.path, f"expected exactly one DAQ channel of kind 'force', found {names}")
    force = reader.channel(names[0]).astype(float)
    reasons, details = [], []
    peak = float(np.nanmax(force)) if np.isfinite(force).any() else 0.0
    fs = reader.sample_rate_hz
    impacts = ImpactDetector(limits.impacts).detect(force, fs, source=f"{reader.path}: {names[0]}").pulses
    times = tuple(p.onset_s for p in impacts)
    if len(impacts) == 0:
        reasons.append("force_low")
        details.append("no impact in the force record")
    elif len(impacts) > 1:
        reasons.append("double_hit")
        details.append(f"double hit: {len(impacts)} impacts, "
                       + ", ".join(f"{1e3 * (b - a):.2f}" for a, b in zip(times, times[1:])) + " ms apart")
    lo, hi = limits.force_band_n
    if len(impacts) and peak < lo:
        reasons.append("force_low")
        details.append(f"peak force {peak:.1f} N below the planned {lo:g} N")
    elif peak > hi:
        reasons.append("force_high")
        details.append(f"peak force {peak:.1f} N above the planned {hi:g} N")
    lost = int(np.count_nonzero(~np.isfinite(force)))
    dropped = _losses(reader, lost, reasons, details)
    return HitQC(tuple(reasons), tuple(details), peak, times, {}, lost, dropped)


def run_qc(capture: Capture, settings: QCSettings | None = None) -> QCReport:
    """The qc stage: every complete take's hit checked from its file, beside the verdict recorded with it;
    writes derived/qc.json. A take recorded as unchecked (imported, say) gets the check's verdict there."""
    s = settings or QCSettings()
    limits = s.limits()
    out = []
    for rec in capture.manifest.takes:
        if rec.status not in ("complete", "recovered"):
            continue
        with capture.open_take(rec.name) as reader:
            content = take_content(reader)
            if "force" in content:
                hit = check_take(reader, limits)
            elif "frames" in content or "response" in content:
                hit = check_unforced(reader)
            else:
                out.append(TakeQC(rec.name, rec.qc, "rejected", ("empty",), ("neither frames nor samples",), None, 0,
                                  content))
                continue
        out.append(TakeQC(rec.name, rec.qc, "accepted" if hit.accepted else "rejected", hit.reasons, hit.details,
                          hit.peak_force_n if "force" in content else None, len(hit.impact_times_s), content))
    if not out:
        raise InputError(capture.root / "capture.json", "no complete take to check")
    report = QCReport(tuple(out), s)
    report.write(capture)
    return report
