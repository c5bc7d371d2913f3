"""A summary of a capture for `odsplat info`: what was recorded, how big, and what QC said."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from odsplat.spine.errors import OdsplatError
from odsplat.spine.integrity import UNREADABLE_ERRORS, file_problem
from odsplat.spine.store import Capture
from odsplat.spine.take_reader import TakeReader


@dataclass
class TakeSummary:
    name: str
    view: int | None
    status: str
    qc: str
    qc_flags: list[str]
    n_frames: int
    frame_shape: list[int]
    dtype: str
    bit_depth: int | None
    fps: float | None
    duration_s: float | None
    n_samples: int
    size_bytes: int
    problem: str = ""


@dataclass
class CaptureSummary:
    root: str
    name: str
    camera: dict[str, Any]
    daq_sample_rate_hz: float | None
    channels: list[dict[str, Any]]
    takes: list[TakeSummary] = field(default_factory=list)
    unfinished: list[str] = field(default_factory=list)
    unlisted: list[str] = field(default_factory=list)
    total_bytes: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_text(self) -> str:
        cam = self.camera
        lines = [
            f"capture {self.name!r} at {self.root}",
            f"camera  {cam['model']}: {cam['width_px']}x{cam['height_px']} px, {cam['fps']} fps, "
            f"{cam['bit_depth']} bit, {'RGB' if cam['n_colors'] == 3 else 'mono'}",
            f"DAQ     {self.daq_sample_rate_hz} Hz, {len(self.channels)} channels",
        ]
        for ch in self.channels:
            where = f" at {ch['position_m']} dir {ch['direction']}" if ch.get("position_m") else ""
            source = ch.get("source", "daq")
            src = f" from {source} at {ch['sample_rate_hz']:g} Hz" if source != "daq" else ""
            lines.append(f"  {ch['name']:<12} {ch['kind']:<13} [{ch['unit']}]{where}{src}")
        lines.append(f"takes   {len(self.takes)}, {self.total_bytes / 1e6:.1f} MB")
        header = (f"  {'name':<12} {'view':>4} {'frames':>7} {'shape':<12} {'bit':>3} {'dur_s':>8} {'samples':>8} "
                  f"{'MB':>8}  status/QC")
        lines.append(header)
        for t in self.takes:
            shape = "x".join(map(str, t.frame_shape)) or "-"
            dur = f"{t.duration_s:.4f}" if t.duration_s is not None else "-"
            flags = f" {','.join(t.qc_flags)}" if t.qc_flags else ""
            problem = "  PROBLEM (see below)" if t.problem else ""
            lines.append(
                f"  {t.name:<12} {'-' if t.view is None else t.view:>4} {t.n_frames:>7} {shape:<12} "
                f"{t.bit_depth or '-':>3} {dur:>8} {t.n_samples:>8} {t.size_bytes / 1e6:>8.2f}  "
                f"{t.status}/{t.qc}{flags}{problem}"
            )
        for t in self.takes:
            if t.problem:
                lines.append(f"WARNING take {t.name}: {t.problem}; `odsplat verify {self.root}` checks every take")
        for name in self.unfinished:
            lines.append(f"WARNING unfinished take {name}: its writer stopped; run `odsplat recover {self.root}`")
        for name in self.unlisted:
            lines.append(f"WARNING take file {name} is not in the manifest; run `odsplat recover {self.root}`")
        return "\n".join(lines)


def summarize(root: str | Path) -> CaptureSummary:
    cap = Capture.open(root)
    m = cap.manifest
    summary = CaptureSummary(
        root=str(cap.root),
        name=m.name,
        camera=asdict(m.camera),
        daq_sample_rate_hz=m.daq_sample_rate_hz,
        channels=[asdict(c) for c in m.channels],
        unfinished=[p.name for p in cap.partial_takes()],
        unlisted=[p.name for p in cap.unlisted_takes()],
    )
    for record in m.takes:
        path = cap.root / record.file
        found = file_problem(path, record)
        problem = f"{found[0]}: {found[1]}" if found is not None else ""
        try:
            with TakeReader(path) as r:
                qc = r.qc
                fps = r.fps
                t = TakeSummary(
                    name=record.name,
                    view=r.view,
                    status=record.status,
                    qc=qc.status,
                    qc_flags=list(qc.flags),
                    n_frames=r.n_frames,
                    frame_shape=list(r.frame_shape) if r.has_frames else [],
                    dtype=str(r.frames.dtype) if r.has_frames else "",
                    bit_depth=r.bit_depth if r.has_frames else None,
                    fps=fps,
                    duration_s=r.n_frames / fps if fps and r.has_frames else (
                        r.n_samples / r.sample_rate_hz if r.n_samples and r.sample_rate_hz else None),
                    n_samples=r.n_samples,
                    size_bytes=r.size_bytes,
                    problem=problem,
                )
        except (OdsplatError, *UNREADABLE_ERRORS) as exc:   # a damaged header: file_problem says what
            t = TakeSummary(record.name, record.view, record.status, record.qc, [], 0, [], "", None, None, None, 0,
                            path.stat().st_size if path.exists() else 0, problem=problem or str(exc))
        summary.takes.append(t)
        summary.total_bytes += t.size_bytes
    return summary
