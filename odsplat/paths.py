"""Where every derived file of a capture lives: the one registry of `derived/...` paths (`Capture.paths`).

No other module spells a derived path. The registry only names paths; it creates nothing (a stage that writes
calls `ensure` on the folder it writes into). Its root is the capture's `derived/` unless the capture was
opened with another folder (a notebook that must not write into the capture, say).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class DerivedPaths:
    """The derived files of one capture, by the stage that writes them (formats in docs/architecture.md)."""

    root: Path

    # -- pipeline ----------------------------------------------------------------------------------------------
    @property
    def pipeline_dir(self) -> Path:
        """The pipeline's stage stamps: `pipeline/STAGE.json`, written after a stage's outputs."""
        return self.root / "pipeline"

    def stamp(self, stage: str) -> Path:
        return self.pipeline_dir / f"{stage}.json"

    # -- qc ------------------------------------------------------------------------------------------------------
    @property
    def qc_json(self) -> Path:
        return self.root / "qc.json"

    # -- sync ----------------------------------------------------------------------------------------------------
    @property
    def sync_json(self) -> Path:
        return self.root / "sync.json"

    @property
    def sync_png(self) -> Path:
        return self.root / "sync.png"

    @property
    def aligned_dir(self) -> Path:
        return self.root / "sync"

    def aligned(self, take: str) -> Path:
        return self.aligned_dir / f"{take}.h5"

    # -- processing ----------------------------------------------------------------------------------------------
    @property
    def magnified_root(self) -> Path:
        return self.root / "magnified"

    def magnified_dir(self, method: str) -> Path:
        return self.magnified_root / method

    def magnified(self, method: str, take: str) -> Path:
        return self.magnified_dir(method) / f"{take}.h5"

    def magnified_video(self, method: str, take: str) -> Path:
        """The magnified take as an 8-bit mp4 to watch, beside its frames (slow motion: magnify.json says at what
        rate it plays and was recorded)."""
        return self.magnified_dir(method) / f"{take}.mp4"

    def magnify_json(self, method: str) -> Path:
        return self.magnified_dir(method) / "magnify.json"

    def frames(self, source: str, take: str) -> Path:
        """A take's derived frames by source name: 'sync' (aligned) or 'magnified/METHOD'."""
        if source == "sync":
            return self.aligned(take)
        return self.root / source / f"{take}.h5"

    def frames_dir(self, source: str) -> Path:
        return self.aligned_dir if source == "sync" else self.root / source

    def exported_video(self, source: str, take: str) -> Path:
        """`odsplat export-video`'s default output: a take's frames by source ('raw', 'sync', 'magnified/METHOD')
        as an mp4 (no stage's output: written on request, replaced by the next request)."""
        return self.root / "videos" / source / f"{take}.mp4"

    # -- poses ---------------------------------------------------------------------------------------------------
    @property
    def poses_json(self) -> Path:
        return self.root / "poses.json"

    @property
    def points_npz(self) -> Path:
        return self.root / "points.npz"

    @property
    def poses_work_dir(self) -> Path:
        """COLMAP's work files (images, database, models), replaced on each run."""
        return self.root / "poses"

    # -- reconstruction ------------------------------------------------------------------------------------------
    @property
    def reconstruction_dir(self) -> Path:
        return self.root / "reconstruction"

    @property
    def reconstruction_json(self) -> Path:
        return self.reconstruction_dir / "reconstruction.json"

    @property
    def gaussians_ply(self) -> Path:
        return self.reconstruction_dir / "gaussians_t0.ply"

    @property
    def trajectories_npz(self) -> Path:
        return self.reconstruction_dir / "trajectories.npz"

    @property
    def measured_motion_npz(self) -> Path:
        return self.reconstruction_dir / "measured_motion.npz"

    @property
    def render_dir(self) -> Path:
        return self.reconstruction_dir / "render"

    # -- analysis ------------------------------------------------------------------------------------------------
    @property
    def analysis_dir(self) -> Path:
        return self.root / "analysis"

    @property
    def analysis_json(self) -> Path:
        return self.analysis_dir / "analysis.json"

    @property
    def report_html(self) -> Path:
        return self.analysis_dir / "report.html"

    @staticmethod
    def ensure(folder: Path) -> Path:
        """Create `folder` (and its parents) for writing; returns it."""
        folder.mkdir(parents=True, exist_ok=True)
        return folder
