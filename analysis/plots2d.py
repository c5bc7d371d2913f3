"""The 2D path's figures and clips (derived/analysis/plots/, clips/): the displacement spectrum with the modes
marked, the stabilisation chart, each mode's shape drawn on the first frame, and each mode's amplified clip."""
from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np

from odsplat.spine.atomic import atomic_path

from .clips import PLAYBACK_FPS, ClipSpec, band_hz, clip_alpha, clip_box, write_clip
from .plots import plot_stabilisation
from .video2d import Video2DResult

log = logging.getLogger(__name__)

ARROW_SHARE = 0.08     # the largest arrow of a shape: this share of the frame's larger side


def _save(fig, path: Path) -> None:
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=110)


def plot_spectrum(result: Video2DResult):
    """The FDD's first singular values over the moving points' displacement, the noise along them, the modes."""
    from matplotlib.figure import Figure

    fdd, oma = result.oma.fdd, result.oma
    fig = Figure(figsize=(10, 4.5), dpi=110)
    ax = fig.add_subplot()
    for k in range(min(3, fdd.singular_values.shape[1])):
        ax.semilogy(fdd.freqs_hz, np.maximum(fdd.singular_values[:, k], 1e-30), lw=1.0 if k == 0 else 0.7,
                    color=("0.1", "0.5", "0.75")[k], label=f"singular value {k + 1}")
    ax.axhline(float(oma.noise_psd.sum()), color="C3", lw=0.8, ls="--", label="noise, all channels")
    for i, m in enumerate(result.modes, 1):
        colour = "C0" if m.above_floor else "0.6"
        ax.axvline(m.freq_hz, color=colour, lw=0.8, ls=":")
        ax.annotate(f"{i}: {m.freq_hz:.2f} Hz" + ("" if m.above_floor else " (below floor)"), (m.freq_hz, 1.0),
                    xycoords=("data", "axes fraction"), rotation=90, va="top", ha="right", fontsize=8, color=colour)
    lo, hi = oma.band_hz
    ax.set_xlim(lo, hi)
    ax.set(xlabel="frequency (Hz)", ylabel="px²/Hz", title=f"Displacement spectrum (FDD) of {int(result.moving.sum())} "
                                                           f"moving points, x and y")
    ax.legend(loc="upper right", fontsize="small")
    ax.grid(True, alpha=0.3)
    return fig


def plot_shape(result: Video2DResult, frame: np.ndarray, k: int):
    """Mode k's shape on the first frame: each moving point's arrow (the shape's real part), coloured by its
    amplitude; the points left out (still or lost) as small grey dots."""
    from matplotlib.figure import Figure

    m = result.modes[k]
    pts = result.points_px[result.moving]
    shape = np.real(m.shape)
    amp = np.abs(m.shape).sum(axis=1) / max(float(np.abs(m.shape).sum(axis=1).max()), 1e-30)
    h, w = frame.shape
    scale = ARROW_SHARE * max(h, w) / max(float(np.abs(m.shape).max()), 1e-30)
    fig = Figure(figsize=(8, 8 * h / w + 0.8), dpi=110)
    ax = fig.add_subplot()
    ax.imshow(frame, cmap="gray", interpolation="nearest")
    still = result.points_px[~result.moving]
    ax.plot(still[:, 0], still[:, 1], ".", ms=2, color="0.6")
    ax.quiver(pts[:, 0], pts[:, 1], shape[:, 0] * scale, shape[:, 1] * scale, amp, cmap="plasma", angles="xy",
              scale_units="xy", scale=1.0, width=0.004)
    state = "" if m.above_floor else "  BELOW THE FLOOR: shape not judged"
    what = f"damping {100 * m.damping:.2f} %" if m.kind == "mode" else "FDD peak (ODS at its line)"
    ax.set_title(f"{m.label} {k + 1}: {m.freq_hz:.2f} Hz, {what}, MPC {m.mpc:.2f}{state}",
                 fontsize=10, color="k" if m.above_floor else "0.4")
    ax.set_axis_off()
    fig.tight_layout()
    return fig


def write_figures(dest: Path, result: Video2DResult, frame: np.ndarray) -> dict[str, str]:
    """The figures into dest/plots/; their paths relative to dest, by name."""
    plots = dest / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}
    if result.oma is None:
        return files
    _save(plot_spectrum(result), plots / "video2d_spectrum.png")
    files["spectrum"] = "plots/video2d_spectrum.png"
    _save(plot_stabilisation(result.oma.chart, band_hz=result.oma.band_hz,
                             selected_hz=[m.freq_hz for m in result.modes]), plots / "video2d_stabilisation.png")
    files["stabilisation"] = "plots/video2d_stabilisation.png"
    for k in range(len(result.modes)):
        name = f"video2d_shape_{k + 1:02d}.png"
        _save(plot_shape(result, frame, k), plots / name)
        files[f"shape_{k + 1:02d}"] = f"plots/{name}"
    return files


def write_clips(dest: Path, result: Video2DResult, frames, frame_shape: tuple[int, int],
                max_frames: int) -> dict[int, tuple[str, float]]:
    """An amplified clip of each mode above the floor, dest/clips/mode_KK.mp4; {mode index: (its path relative to
    dest, its magnification)}.
    `frames()` gives a fresh iterator over the take's mono frames."""
    todo = [k for k, m in enumerate(result.modes) if m.above_floor]
    if not todo or result.oma is None:
        return {}
    clips = dest / "clips"
    clips.mkdir(parents=True, exist_ok=True)
    box = clip_box(result.points_px[result.moving], frame_shape)
    spectrum = (result.oma.fdd.freqs_hz, result.oma.fdd.singular_values[:, 0])
    out = {}
    for k in todo:
        m = result.modes[k]
        alpha = clip_alpha(m.amplitude_px)
        title = f"{m.label} {k + 1}: {m.freq_hz:.2f} Hz x{alpha:.0f}  left: recorded, right: magnified"
        spec = ClipSpec(m.freq_hz, alpha, box, title)
        lo, hi = band_hz(m.freq_hz, result.fps)
        comment = (f"odsplat: take {result.take}, {m.label} {k + 1} at {m.freq_hz:.3f} Hz magnified x{alpha:.3g} "
                   f"(phase, warp, band {lo:.3g}-{hi:.3g} Hz); recorded at {result.fps:g} fps, played at "
                   f"{PLAYBACK_FPS:g} fps")
        info = write_clip(clips / f"mode_{k + 1:02d}.mp4", itertools.islice(frames(), max_frames), result.fps, spec,
                          spectrum, comment)
        out[k] = (f"clips/{info.path.name}", alpha)
        log.info("clip of mode %d (%.2f Hz, x%.0f): %s", k + 1, m.freq_hz, alpha, info.path)
    return out


__all__ = ["plot_shape", "plot_spectrum", "write_clips", "write_figures"]
