"""The viewer's exports: the current view as an mp4 (odsplat.spine.mp4, its one writer) or a GIF (Pillow), a
turntable or a fixed camera, the measured motion or one mode through a cycle; and a screenshot (PNG)."""
from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from odsplat.app.viewer.model import ViewerData, ViewState, render_view
from odsplat.spine.errors import InputError
from odsplat.spine.mp4 import write_mp4

log = logging.getLogger(__name__)

FORMATS = (".mp4", ".gif")


def frame_states(data: ViewerData, state: ViewState, n_frames: int, *, turntable: bool = False) -> list[ViewState]:
    """The states of an export's frames: a mode through one cycle of its frequency from the state's time (the
    view's default: the shape furthest from rest, so the first frame shows it; the last frame one step before the
    first, so the video loops), the measured motion over the reconstruction's time span; a turntable turns the
    camera once around the target meanwhile."""
    if n_frames < 1:
        raise InputError("--frames", f"expected at least 1 frame, got {n_frames}")
    if state.mode is not None:
        period = 1.0 / data.modes[state.mode].freq_hz
        times = state.time_s + np.arange(n_frames) * period / n_frames
    else:
        t0, t1 = data.time_range_s
        times = np.linspace(t0, t1, n_frames)
    out = []
    for k, t in enumerate(times):
        s = replace(state, time_s=float(t))
        if turntable:
            s = replace(s, snap=None, orbit=state.orbit.rotated(360.0 * k / n_frames, 0.0))
        out.append(s)
    return out


def export_video(data: ViewerData, state: ViewState, path: str | Path, *, n_frames: int = 48, fps: float = 24.0,
                 turntable: bool = False, progress: bool = True) -> Path:
    """Writes the view as mp4 or GIF (by the suffix) of n_frames at fps; returns the path."""
    path = check_video_path(path)
    states = frame_states(data, state, n_frames, turntable=turntable)
    frames = (render_view(data, s) for s in tqdm(states, desc="export", unit="frame", disable=not progress))
    what = data.modes[state.mode].label() if state.mode is not None else "measured motion"
    return write_frames(path, frames, fps, f"odsplat view {data.name}: {what}, alpha {state.alpha:g}, "
                                          f"{n_frames} frames")


def check_video_path(path: str | Path) -> Path:
    """An export's file name: .mp4 or .gif, in a folder that exists (one line naming it where not)."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise InputError(path, f"expected an .mp4 or .gif file name, got {path.suffix or 'no suffix'}")
    return _in_folder(path)


def write_frames(path: Path, frames, fps: float, comment: str) -> Path:
    """(H, W, 3) uint8 frames as an mp4 (H.264, odsplat.spine.mp4) or a GIF by `path`'s suffix (check_video_path),
    written whole or not at all; returns the path."""
    if path.suffix.lower() == ".mp4":
        info = write_mp4(path, frames, fps, comment=comment)
        log.info("%s: %d frames", info.path, info.n_frames)
        return info.path
    images = [Image.fromarray(f) for f in frames]
    tmp = path.with_name(path.name + ".partial")
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0,
                   optimize=False, comment=comment.encode())
    tmp.replace(path)
    log.info("%s: %d frames", path, len(images))
    return path


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """An (H, W, 3) uint8 image as a PNG in a folder that exists."""
    path = _in_folder(Path(path))
    Image.fromarray(image).save(path, format="PNG")
    return path


def _in_folder(path: Path) -> Path:
    if not path.parent.exists():
        raise InputError(path.parent, "no such folder")
    return path


def save_screenshot(data: ViewerData, state: ViewState, path: str | Path) -> Path:
    """The current view as a PNG (its folder checked before the render, which is the slow part)."""
    return write_png(_in_folder(Path(path)), render_view(data, state))


__all__ = ["FORMATS", "check_video_path", "export_video", "frame_states", "save_screenshot", "write_frames",
           "write_png"]
