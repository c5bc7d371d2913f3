"""The one table of the pipeline's stages: each stage's settings class, entry, inputs, outputs and summary, and what
its command says it does. The configuration (`config.STAGES`, `settings_types`), the pipeline (`GRAPH`, `stage`)
and the stage commands of the command line are all read from it.

Lazy loading, the rule (written here and nowhere else): processing, reconstruction and analysis load torch when
they are imported, so this table names each stage's settings class and entry by import path, "package:name", and
resolves them with importlib on first use, as python-can's table of interfaces does. `odsplat --help` and the light
commands (`info`, `verify`, `qc`) import no stage that loads torch. The same imports stand below under
`if TYPE_CHECKING:`, so that grimp and import-linter see the dependency; a test holds the two together.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from odsplat.spine._deps import resolve
from odsplat.spine.errors import InputError

if TYPE_CHECKING:   # the table's import paths, for the tools (the rule above); resolved on use at run time
    from odsplat.acquisition import QCSettings, run_qc  # noqa: F401
    from odsplat.analysis import AnalyzeSettings  # noqa: F401
    from odsplat.analysis import run as analysis_run  # noqa: F401
    from odsplat.app.config import Config
    from odsplat.app.report import ReportSettings, write_report  # noqa: F401
    from odsplat.processing import MagnifySettings  # noqa: F401
    from odsplat.processing import run as processing_run  # noqa: F401
    from odsplat.reconstruction import PoseSettings, ReconstructSettings, run_poses  # noqa: F401
    from odsplat.reconstruction import run as reconstruction_run  # noqa: F401
    from odsplat.spine.store import Capture
    from odsplat.sync import SyncSettings  # noqa: F401
    from odsplat.sync import run as sync_run  # noqa: F401


@dataclass(frozen=True)
class Stage:
    """One stage: its settings and entry (by import path), what it reads and writes, and its command's help."""

    name: str
    settings_path: str | None                          # its settings class, "package:Class"; None: it has none
    entry_path: str                                    # run(capture, settings) -> result; saves its own outputs
    upstream: Callable[[Config], tuple[str, ...]]      # the stages whose outputs it reads, under this configuration
    outputs: Callable[[Capture, Any], list[Path]]      # the files and folders it writes
    summary: Callable[[Any], str]                      # its result in a few lines
    doc: str                                           # what it does: its command's help
    volatile: tuple[str, ...] = ()                     # settings that do not change the result (threads, memory)
    raw: bool = False                                  # reads the raw takes themselves
    needs_views: int = 0                               # takes with frames from this many views, or it does not apply
    geometry: bool = False                             # reads the sensors' placement (odsplat geometry changes it)
    per_view: bool = False                             # its entry takes `executor=` for its per-view tasks

    @property
    def settings_class(self) -> type | None:
        """The settings class, imported now (some stages load torch)."""
        return None if self.settings_path is None else resolve(self.settings_path)

    def entry(self, capture: Capture, settings: Any, **kwargs: Any) -> Any:
        """Run the stage's entry, imported now (with no settings where it has none); the per-view stages'
        `executor=`."""
        run = resolve(self.entry_path)
        return run(capture, **kwargs) if settings is None else run(capture, settings, **kwargs)


def walk(path: Path) -> list[Path]:
    """The files under a folder (not the hidden ones), or the file itself."""
    if path.is_dir():
        return sorted(p for p in path.rglob("*") if p.is_file() and not p.name.startswith("."))
    return [path]


def _magnify_upstream(c: Config) -> tuple[str, ...]:
    return ("qc",) if c.magnify.source == "raw" else ("qc", "sync")


def _reconstruct_upstream(c: Config) -> tuple[str, ...]:
    return ("poses", "sync") if c.reconstruct.source == "sync" else ("poses", "magnify")


def _analyze_upstream(c: Config) -> tuple[str, ...]:
    return ("qc", "sync", "reconstruct") if c.analyze.video else ("qc",)


def _lines(text: Any) -> str:
    return "\n".join(text) if isinstance(text, (list, tuple)) else str(text)


TABLE: tuple[Stage, ...] = (
    Stage("qc", "odsplat.acquisition:QCSettings", "odsplat.acquisition:run_qc", upstream=lambda c: (),
          outputs=lambda cap, s: [cap.paths.qc_json], summary=lambda r: r.summary(), raw=True,
          doc="Check every take's hit from its file (impacts, force band, lost samples, dropped frames): "
              "derived/qc.json."),
    Stage("sync", "odsplat.sync:SyncSettings", "odsplat.sync:run", upstream=lambda c: ("qc",),
          outputs=lambda cap, s: [cap.paths.sync_json] + ([cap.paths.sync_png] if s.plot else [])
          + ([cap.paths.aligned_dir] if s.write_frames else []),
          summary=lambda r: r.summary(), volatile=("max_memory_mb", "workers"), raw=True, needs_views=1,
          per_view=True,
          doc="Put the takes of CAPTURE_DIR on one impact-locked timeline: derived/sync.json and the aligned frames."),
    Stage("magnify", "odsplat.processing:MagnifySettings", "odsplat.processing:run", upstream=_magnify_upstream,
          outputs=lambda cap, s: [cap.paths.magnified_dir(s.method)],
          summary=lambda r: r.summary(), volatile=("workers",), raw=True, needs_views=1, per_view=True,
          doc="Magnify the motion in the first view of CAPTURE_DIR (or the views named; every view where the "
              "reconstruction reads magnified frames) into derived/magnified/METHOD/ (frames, and an mp4 to watch); "
              "warns where alpha x the measured motion passes the method's bound."),
    Stage("poses", "odsplat.reconstruction:PoseSettings", "odsplat.reconstruction:run_poses",
          upstream=lambda c: ("qc",), outputs=lambda cap, s: [cap.paths.poses_json, cap.paths.points_npz],
          summary=lambda r: _lines(r.report_lines()), volatile=("threads",), raw=True, needs_views=2,
          doc="Camera poses of every view of CAPTURE_DIR in metres, floor z = 0: derived/poses.json, "
              "derived/points.npz."),
    Stage("reconstruct", "odsplat.reconstruction:ReconstructSettings", "odsplat.reconstruction:run",
          upstream=_reconstruct_upstream,
          outputs=lambda cap, s: [cap.paths.reconstruction_json, cap.paths.gaussians_ply, cap.paths.trajectories_npz,
                                  cap.paths.measured_motion_npz],
          summary=lambda r: r.summary(), volatile=("threads", "linear.workers", "linear.progress"), needs_views=2,
          doc="Train dynamic 3D Gaussians on CAPTURE_DIR's posed views into derived/reconstruction/ "
              "(docs/reconstruction.md)."),
    Stage("analyze", "odsplat.analysis:AnalyzeSettings", "odsplat.analysis:run", upstream=_analyze_upstream,
          outputs=lambda cap, s: [p for p in walk(cap.paths.analysis_dir) if p != cap.paths.report_html],
          summary=lambda r: r.text(), geometry=True,
          doc="FRFs, modes, the video's 3D shapes and their correlation for CAPTURE_DIR, into derived/analysis/ "
              "(docs/analysis.md)."),
    Stage("report", "odsplat.app.report:ReportSettings", "odsplat.app.report:write_report",
          upstream=lambda c: ("analyze",), outputs=lambda cap, s: [cap.paths.report_html, cap.paths.mode_clips_dir],
          summary=str,
          doc="Write derived/analysis/report.html from the last `odsplat analyze` of CAPTURE_DIR, and each mode's "
              "amplified clip rendered from the Gaussians (derived/mode_clips/)."),
)
STAGES: tuple[str, ...] = tuple(s.name for s in TABLE)
BY_NAME: dict[str, Stage] = {s.name: s for s in TABLE}


def stage(name: str) -> Stage:
    """The stage of that name; an unknown name is refused with one line listing them."""
    try:
        return BY_NAME[name]
    except (KeyError, TypeError):
        raise InputError("stage", f"expected one of {', '.join(STAGES)}; got {name!r}") from None


__all__ = ["BY_NAME", "STAGES", "TABLE", "Stage", "resolve", "stage", "walk"]
