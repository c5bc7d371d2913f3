"""The report stage: each mode's amplified clip on the 3D path, then the report page (`analysis.write_report`).

A clip is the reconstruction's Gaussians deformed by one mode's video shape through one cycle, rendered by the
viewer's one renderer (`viewer.export_video`: the structure only, coloured by amplitude, the sensors' arrows and
the colour bar drawn over it) at the viewer's default magnification (the structure's largest motion 5 % of its
size), as a browser-playable H.264 mp4 in derived/mode_clips/mode_NN.mp4. The report stage writes them because
they are the page's: the analysis gives the shapes and the reconstruction the Gaussians, and only the application
may read both into one view. The report inlines each beside the mode's interactive 3D shape.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from odsplat.spine.checks import PLAYBACK_FPS, Range, check_fields
from odsplat.spine.errors import OdsplatError
from odsplat.spine.framefile import prune_outputs
from odsplat.spine.store import Capture

log = logging.getLogger(__name__)

MAX_CLIP_FRAMES = 600


@dataclass(frozen=True)
class ReportSettings:
    """What the report stage writes besides the page."""

    mode_clips: bool = True               # each mode's amplified clip, rendered from the Gaussians (3D path only)
    clip_frames: int = 24                 # frames of one cycle
    clip_fps: float = 20.0                # playback rate (one cycle in 1.2 s)
    clip_size_px: tuple[int, int] = (480, 360)   # width and height

    def __post_init__(self) -> None:
        check_fields(self, {"clip_frames": Range(at_least=2, at_most=MAX_CLIP_FRAMES, integer=True),
                            "clip_fps": PLAYBACK_FPS, "clip_size_px": Range(at_least=16, at_most=4096, integer=True)})


def write_mode_clips(capture: Capture, settings: ReportSettings) -> list[Path]:
    """Each mode's clip (module docstring) for a capture with a reconstruction and the analysis's video shapes;
    returns the files written. Clips of an earlier run that this one does not write are removed, so the page never
    shows a stale one. A reconstruction the viewer cannot read leaves the page without clips, with a warning."""
    folder = capture.paths.mode_clips_dir
    written: list[Path] = []
    data = _viewer_data(capture) if settings.mode_clips and capture.paths.gaussians_ply.is_file() else None
    if data is not None and data.scene is None:
        log.warning("report: no mode clips: %s", "; ".join(data.notes) or "the reconstruction could not be read")
    elif data is not None:
        from odsplat.app.display import ViewSettings, view_state
        from odsplat.app.viewer import export_video

        modes = [m for m in data.modes if m.kind == "mode" and m.freq_hz > 0 and m.gaussians is not None]
        for m in tqdm(modes, desc="report: mode clips", unit="mode"):
            view = ViewSettings(mode=m.number, structure_only=True, colour="displacement",
                                size_px=settings.clip_size_px)
            capture.paths.ensure(folder)
            written.append(export_video(data, view_state(data, view), capture.paths.mode_clip(m.number),
                                        n_frames=settings.clip_frames, fps=settings.clip_fps, progress=False))
    if folder.is_dir():
        prune_outputs(folder, written)
    return written


def _viewer_data(capture: Capture):
    """The viewer's data of the capture, or None (a warning) where it cannot be read."""
    from odsplat.app.viewer import load_viewer

    try:
        return load_viewer(capture)
    except OdsplatError as e:
        log.warning("report: no mode clips: %s", e)
        return None


def write_report(capture: Capture, settings: ReportSettings | None = None) -> Path:
    """The report stage: the mode clips (`write_mode_clips`), then derived/analysis/report.html."""
    from odsplat.analysis import write_report as write_page

    settings = settings or ReportSettings()
    clips = write_mode_clips(capture, settings)
    if clips:
        log.info("report: %d mode clips in %s", len(clips), capture.paths.mode_clips_dir)
    return write_page(capture)


__all__ = ["ReportSettings", "write_mode_clips", "write_report"]
