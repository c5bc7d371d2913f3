"""Where every derived file of a capture lives: the one registry of `derived/...` paths (`Capture.paths`).

No other module spells a derived path. The registry only names paths; it creates nothing (a stage that writes
calls `ensure` on the folder it writes into). Its root is the capture's `derived/` unless the capture was
opened with another folder (a notebook that must not write into the capture, say). Every path it names is
checked as it is named (`guard.check_inside`): inside the root, through no symbolic link, so a link planted in
`derived/` is refused with one line before anything is written or deleted through it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from odsplat.spine.guard import check_inside


@dataclass(frozen=True)
class DerivedPaths:
    """The derived files of one capture, by the stage that writes them (formats in docs/architecture.md)."""

    root: Path

    def _at(self, *parts: str) -> Path:
        """`root / parts...`, refused (one line) if it leaves the root or passes through a symbolic link."""
        return check_inside(self.root, self.root.joinpath(*parts))

    def listed(self, relative: str) -> Path:
        """A file an index names relative to the root (sync.json's `aligned_file`, magnify.json's `file`), refused
        like any other derived path if it leads out of the root or through a link."""
        return self._at(str(relative))

    @property
    def lock(self) -> Path:
        """The capture's lock (`odsplat.spine.lock`): held by the command writing here, naming it."""
        return self._at(".odsplat.lock")

    # -- pipeline ----------------------------------------------------------------------------------------------
    @property
    def pipeline_dir(self) -> Path:
        """The pipeline's stage stamps: `pipeline/STAGE.json`, written after a stage's outputs."""
        return self._at("pipeline")

    def stamp(self, stage: str) -> Path:
        return self._at("pipeline", f"{stage}.json")

    # -- qc ------------------------------------------------------------------------------------------------------
    @property
    def qc_json(self) -> Path:
        return self._at("qc.json")

    # -- sync ----------------------------------------------------------------------------------------------------
    @property
    def sync_json(self) -> Path:
        return self._at("sync.json")

    @property
    def sync_png(self) -> Path:
        return self._at("sync.png")

    @property
    def aligned_dir(self) -> Path:
        return self._at("sync")

    def aligned(self, take: str) -> Path:
        return self._at("sync", f"{take}.h5")

    # -- processing ----------------------------------------------------------------------------------------------
    @property
    def magnified_root(self) -> Path:
        return self._at("magnified")

    def magnified_dir(self, method: str) -> Path:
        return self._at("magnified", method)

    def magnified(self, method: str, take: str) -> Path:
        return self._at("magnified", method, f"{take}.h5")

    def magnified_video(self, method: str, take: str) -> Path:
        """The magnified take as an 8-bit mp4 to watch, beside its frames (slow motion: magnify.json says at what
        rate it plays and was recorded)."""
        return self._at("magnified", method, f"{take}.mp4")

    def magnify_json(self, method: str) -> Path:
        return self._at("magnified", method, "magnify.json")

    def frames(self, source: str, take: str) -> Path:
        """A take's derived frames by source name: 'sync' (aligned) or 'magnified/METHOD'."""
        if source == "sync":
            return self.aligned(take)
        return self._at(source, f"{take}.h5")

    def frames_dir(self, source: str) -> Path:
        return self.aligned_dir if source == "sync" else self._at(source)

    def exported_video(self, source: str, take: str) -> Path:
        """`odsplat export-video`'s default output: a take's frames by source ('raw', 'sync', 'magnified/METHOD')
        as an mp4 (no stage's output: written on request, replaced by the next request)."""
        return self._at("videos", source, f"{take}.mp4")

    # -- poses ---------------------------------------------------------------------------------------------------
    @property
    def poses_json(self) -> Path:
        return self._at("poses.json")

    @property
    def points_npz(self) -> Path:
        return self._at("points.npz")

    @property
    def poses_work_dir(self) -> Path:
        """COLMAP's work files (images, database, models), replaced on each run."""
        return self._at("poses")

    # -- reconstruction ------------------------------------------------------------------------------------------
    @property
    def reconstruction_dir(self) -> Path:
        return self._at("reconstruction")

    @property
    def reconstruction_json(self) -> Path:
        return self._at("reconstruction", "reconstruction.json")

    @property
    def gaussians_ply(self) -> Path:
        return self._at("reconstruction", "gaussians_t0.ply")

    @property
    def trajectories_npz(self) -> Path:
        return self._at("reconstruction", "trajectories.npz")

    @property
    def measured_motion_npz(self) -> Path:
        return self._at("reconstruction", "measured_motion.npz")

    @property
    def render_dir(self) -> Path:
        return self._at("reconstruction", "render")

    # -- analysis ------------------------------------------------------------------------------------------------
    @property
    def analysis_dir(self) -> Path:
        return self._at("analysis")

    @property
    def analysis_json(self) -> Path:
        return self._at("analysis", "analysis.json")

    @property
    def video2d_json(self) -> Path:
        return self._at("analysis", "video2d.json")

    @property
    def video2d_npz(self) -> Path:
        return self._at("analysis", "video2d.npz")

    @property
    def report_html(self) -> Path:
        return self._at("analysis", "report.html")

    # -- report ------------------------------------------------------------------------------------------------
    @property
    def mode_clips_dir(self) -> Path:
        """Each mode's amplified clip on the 3D path, written by the report stage (`odsplat.app.report`)."""
        return self._at("mode_clips")

    def mode_clip(self, number: int) -> Path:
        return self._at("mode_clips", f"mode_{int(number):02d}.mp4")

    @staticmethod
    def ensure(folder: Path) -> Path:
        """Create `folder` (and its parents) for writing; returns it."""
        folder.mkdir(parents=True, exist_ok=True)
        return folder
