"""The viewer's drawing over a rendered view (OpenCV, in place on an (H, W, 3) uint8 image): the floor grid of the
view without a reconstruction, the capture cameras, the sensors' arrows, the colour bar and the caption. What is
drawn comes from the ViewerData and the ViewState; nothing here reads a file or renders a Gaussian."""
from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from odsplat.spine.geometry import camera_center_m

if TYPE_CHECKING:
    from odsplat.app.viewer.model import ViewerData, ViewState


def draw_overlays(img: np.ndarray, data: ViewerData, state: ViewState, cam, scale: tuple[float, str] | None) -> None:
    """Everything drawn over the view through camera `cam`: the capture cameras and the sensors where the state
    shows them (the sensors always without a reconstruction), the colour bar of `scale` (top, unit) where given,
    and the caption."""
    if state.show_cameras:
        _draw_cameras(img, data, cam)
    if state.show_sensors or data.scene is None:
        _draw_sensors(img, data, state, cam)
    if scale is not None:
        _draw_colour_bar(img, *scale)
    _draw_caption(img, data, state)


def project(cam, pts_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3), metres, in camera `cam`'s pixels (M, 2), and (M,) whether each lies in front of it."""
    pc = np.asarray(pts_m, float) @ np.asarray(cam.R).T + np.asarray(cam.t)
    z = pc[:, 2]
    uv = pc[:, :2] / np.where(z > 1e-6, z, 1e-6)[:, None]
    K = np.asarray(cam.K)
    return np.stack([K[0, 0] * uv[:, 0] + K[0, 2], K[1, 1] * uv[:, 1] + K[1, 2]], axis=1), z > 1e-6


def _line(img: np.ndarray, a, b, colour, thickness: int = 1) -> None:
    p, q = (int(round(a[0] * 16)), int(round(a[1] * 16))), (int(round(b[0] * 16)), int(round(b[1] * 16)))
    if max(abs(v) for v in p + q) < 2 ** 27:
        cv2.line(img, p, q, colour, thickness, cv2.LINE_AA, shift=4)


def draw_floor(img: np.ndarray, data: ViewerData, cam) -> None:
    """A grid on z = 0 under the sensors (the accelerometer-only view has nothing else to stand on)."""
    c = data.target_m
    half = 0.6 * data.extent_m
    for v in np.linspace(-half, half, 9):
        for a, b in (((c[0] + v, c[1] - half, 0), (c[0] + v, c[1] + half, 0)),
                     ((c[0] - half, c[1] + v, 0), (c[0] + half, c[1] + v, 0))):
            uv, ok = project(cam, np.array([a, b]))
            if ok.all():
                _line(img, uv[0], uv[1], (210, 210, 210))


def _camera_pyramids(data: ViewerData) -> np.ndarray:
    """(M, 5, 3): each capture camera's centre and the corners of its image at 8 % of the scene's size."""
    size = 0.08 * data.extent_m
    out = []
    for c in data.cameras:
        R, t = np.asarray(c.R, float), np.asarray(c.t, float)
        centre = camera_center_m(R, t)
        Kinv = np.linalg.inv(np.asarray(c.K, float))
        corners = [centre + size * (R.T @ (Kinv @ np.array([x, y, 1.0])))
                   for x, y in ((0, 0), (c.width_px, 0), (c.width_px, c.height_px), (0, c.height_px))]
        out.append([centre] + corners)
    return np.asarray(out, float).reshape(-1, 5, 3)


def _draw_cameras(img: np.ndarray, data: ViewerData, cam) -> None:
    """Each capture camera as a small pyramid (one projection and one polyline call for all of them)."""
    pyramids = _camera_pyramids(data)
    if not len(pyramids):
        return
    uv, ok = project(cam, pyramids.reshape(-1, 3))
    uv, ok = uv.reshape(-1, 5, 2), ok.reshape(-1, 5).all(axis=1) & (np.abs(uv).reshape(-1, 10).max(axis=1) < 1e5)
    lines = []
    for p in np.round(uv[ok] * 16).astype(np.int32):
        lines += [p[[1, 2, 3, 4, 1]], p[[0, 1]], p[[0, 2]], p[[0, 3]], p[[0, 4]]]
    cv2.polylines(img, lines, False, (40, 120, 255), 1, cv2.LINE_AA, shift=4)


def _draw_sensors(img: np.ndarray, data: ViewerData, state: ViewState, cam) -> None:
    """Each accelerometer as an arrow along its direction; with a mode selected, moved by the accelerometers' shape
    (magnified like the Gaussians) and its arrow scaled by the motion along it."""
    length = 0.1 * data.extent_m
    from odsplat.app.viewer.model import sensor_shifts_m

    moved = state.alpha * sensor_shifts_m(data, state)
    for i, s in enumerate(data.sensors):
        shift = float(moved[i])
        base = s.position_m + shift * s.direction
        uv, ok = project(cam, np.array([s.position_m, base, base + length * s.direction]))
        if not ok.all():
            continue
        p0, p1, p2 = uv
        if data.scene is None:      # nothing else shows their height: a drop line to the floor
            foot, ok_foot = project(cam, (s.position_m * [1, 1, 0])[None])
            if ok_foot.all():
                _line(img, p0, foot[0], (190, 190, 190))
        cv2.circle(img, (int(p0[0]), int(p0[1])), 3, (160, 160, 160), -1, cv2.LINE_AA)
        tip = tuple(int(v) for v in p2)
        if max(abs(v) for v in tip) < 1e6:
            cv2.arrowedLine(img, (int(p1[0]), int(p1[1])), tip, (0, 170, 0), 2, cv2.LINE_AA, tipLength=0.3)
            cv2.putText(img, s.name, (tip[0] + 3, tip[1]), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 110, 0), 1,
                        cv2.LINE_AA)


def _draw_colour_bar(img: np.ndarray, top: float, unit: str) -> None:
    h, w = img.shape[:2]
    x0, y0, y1 = w - 28, 40, h - 40
    ramp = plasma(np.linspace(1, 0, y1 - y0))
    img[y0:y1, x0:x0 + 12] = ramp[:, None, :]
    cv2.rectangle(img, (x0, y0), (x0 + 12, y1), (0, 0, 0), 1)
    for v, y in ((top, y0), (top / 2, (y0 + y1) // 2), (0.0, y1)):
        cv2.putText(img, f"{v:.2g}", (x0 - 44, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, unit, (x0 - 4, y0 - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)


def caption(data: ViewerData, state: ViewState) -> str:
    """One line: what moves, at what magnification."""
    if state.mode is not None:
        what = data.modes[state.mode].label()
    else:
        what = f"measured motion, t = {1e3 * state.time_s:.2f} ms"
    return f"{data.name}: {what}, x{state.alpha:.0f}" + (", structure only" if state.structure_only else "")


def _draw_caption(img: np.ndarray, data: ViewerData, state: ViewState) -> None:
    text = caption(data, state)
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
    cv2.rectangle(img, (4, 4), (12 + tw, 12 + th), (255, 255, 255), -1)
    cv2.putText(img, text, (8, 8 + th), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)


def plasma(x: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB from dark blue (0) through magenta to yellow (1) (the report's animations' map)."""
    stops = np.array([[13, 8, 135], [126, 3, 168], [204, 71, 120], [248, 149, 64], [240, 249, 33]], float)
    t = np.clip(np.nan_to_num(np.asarray(x, float)), 0, 1) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[:, None]
    return np.round(stops[i] * (1 - f) + stops[i + 1] * f).astype(np.uint8)


__all__ = ["caption", "draw_floor", "draw_overlays", "plasma", "project"]
