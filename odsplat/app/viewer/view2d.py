"""`odsplat view` on a capture the 2D path analysed (one camera, no force: derived/analysis/video2d.json): its first
frame with a mode's 2D shape drawn on the moving points, magnified so that it is seen, as a screenshot, or one
cycle of it as an mp4/GIF. There is no 3D scene to orbit: the window is for captures with an analysis.json."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from odsplat.analysis import read_video2d
from odsplat.spine.errors import InputError
from odsplat.spine.mp4 import display_range, to_8bit
from odsplat.spine.store import Capture

from .export import check_video_path, write_frames, write_png
from .model import peak_phase

log = logging.getLogger(__name__)

VISIBLE_SHARE = 0.05      # the largest arrow's length as a share of the frame's width (as the 3D view's motion)


@dataclass(frozen=True)
class View2D:
    name: str
    frame: np.ndarray          # (H, W) uint8, the take's first frame for display
    points_px: np.ndarray      # (P, 2) the moving points
    freq_hz: np.ndarray        # (K,)
    labels: tuple[str, ...]    # "mode 1: 23.51 Hz (above the floor)", ...
    shapes: np.ndarray         # (K, P, 2) complex, px (largest component 1)


def load_view2d(capture: Capture) -> View2D:
    doc, arrays = read_video2d(capture)
    with capture.open_take(doc["take"]) as r:
        first = np.asarray(r.read_frames(0, 1)[0], np.float64)
    first = first.mean(axis=-1) if first.ndim == 3 else first
    frame = to_8bit(first[None], display_range(first[None]))[0]
    moving = np.asarray(arrays["moving"], bool)
    labels = tuple(f"{'mode' if m['kind'] == 'mode' else 'FDD peak'} {k + 1}: {m['freq_hz']:.2f} Hz"
                   + ("" if m["above_floor"] else " (below the floor)") for k, m in enumerate(doc["modes"]))
    return View2D(capture.root.name, frame, np.asarray(arrays["points_px"], float)[moving],
                  np.asarray(arrays["freq_hz"], float), labels, np.asarray(arrays["shapes"], complex))


def draw(view: View2D, k: int, theta: float | None = None, alpha: float | None = None) -> np.ndarray:
    """(H, W, 3) uint8: the frame with mode k's shape at phase theta as arrows from each moving point, magnified by
    alpha px per unit of shape (None: the largest arrow VISIBLE_SHARE of the frame's width)."""
    shape = view.shapes[k]
    theta = peak_phase(shape) if theta is None else theta
    h, w = view.frame.shape
    alpha = VISIBLE_SHARE * w / max(float(np.max(np.abs(shape))), 1e-12) if alpha is None else alpha
    img = cv2.cvtColor(view.frame, cv2.COLOR_GRAY2RGB)
    d = alpha * np.real(shape * np.exp(1j * theta))
    amp = np.linalg.norm(np.abs(shape), axis=1) / max(float(np.max(np.abs(shape))), 1e-12)
    for (x, y), (dx, dy), a in zip(view.points_px, d, amp):
        bgr = cv2.applyColorMap(np.uint8([[255 * min(a, 1.0)]]), cv2.COLORMAP_PLASMA)[0, 0]
        colour = tuple(int(c) for c in bgr[::-1])
        cv2.arrowedLine(img, (int(round(x)), int(round(y))), (int(round(x + dx)), int(round(y + dy))), colour, 1,
                        cv2.LINE_AA, tipLength=0.3)
    cv2.putText(img, f"{view.name}: {view.labels[k]}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                cv2.LINE_AA)
    return img


def _mode(view: View2D, mode: int | None) -> int:
    if not len(view.freq_hz):
        raise InputError("video2d.json: modes", "the 2D path found no mode to show")
    if mode is None:
        return 0
    if not 1 <= mode <= len(view.freq_hz):
        raise InputError("ViewSettings.mode", f"expected a mode from 1 to {len(view.freq_hz)}, got {mode}")
    return mode - 1


def screenshot_2d(view: View2D, path: str | Path, mode: int | None = None) -> Path:
    return write_png(path, draw(view, _mode(view, mode)))


def export_2d(view: View2D, path: str | Path, mode: int | None = None, n_frames: int = 48, fps: float = 24.0) -> Path:
    """One cycle of the mode as an .mp4 (H.264) or .gif."""
    k = _mode(view, mode)
    path = check_video_path(path)
    t0 = peak_phase(view.shapes[k])
    frames = [draw(view, k, t0 + 2 * np.pi * i / n_frames) for i in range(n_frames)]
    return write_frames(path, frames, fps, f"odsplat view {view.name}: {view.labels[k]}")


__all__ = ["View2D", "draw", "export_2d", "load_view2d", "screenshot_2d"]
