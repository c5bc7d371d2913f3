"""The viewer's Qt-free core: what a capture has to show (`ViewerData`, which `load.load_viewer` reads), what is
shown (`ViewState`) and the one renderer from the second to the first (`render_view`), which the window, the
exporter, the tests and the bench call. The drawing over the rendered view is `draw.py`'s."""
from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from odsplat.app.viewer.draw import draw_floor, draw_overlays, plasma, project
from odsplat.reconstruction import Camera, quat_from_rotvec, quat_multiply, rasterize_image
from odsplat.spine.geometry import camera_center_m, look_at
from odsplat.spine.store import Capture

log = logging.getLogger(__name__)

WIDTH_PX, HEIGHT_PX = 640, 480
ALPHA_RANGE = (1.0, 1.0e5)   # real structures move micrometres: a mode needs up to 10^4-10^5 to be seen
VISIBLE_SHARE = 0.05      # the default magnification moves the structure's largest motion this share of its size
COLOUR_MODES = ("image", "displacement")


# ---------------------------------------------------------------------------------------------- what a capture has

@dataclass(frozen=True)
class SensorInfo:
    name: str
    position_m: np.ndarray   # (3,)
    direction: np.ndarray    # (3,) unit


@dataclass(frozen=True)
class Mode:
    """One accelerometer mode, and its shapes: at the sensors (accelerometers and, where the video has it, the
    video read at the same points) and on every Gaussian (m/N, None without a video shape)."""

    number: int                      # 1-based, as the analysis numbers them (modes and ODS lines apart)
    freq_hz: float
    damping: float
    mac: float = float("nan")        # video against accelerometers
    sensors_accel: np.ndarray | None = None   # (S,) complex m/N along each sensor's direction
    sensors_video: np.ndarray | None = None   # (S,) complex m/N, the video's shape at the sensors
    kind: str = "mode"               # or "ods": an ODS line, the receptance at freq_hz (m/N) of every point
    surface: np.ndarray | None = None         # (V,) x 3 complex m/N: the video's shape at the surface's vertices
    not_judged: str = ""             # why the video's verdict did not judge it (below the noise floor, ...), or ""
    # its shape on every Gaussian, computed the first time it is asked for (`gaussians`): the window's first frame
    # needs none of them, and each is an interpolation over every Gaussian
    shape_on_gaussians: Callable[[], np.ndarray | None] | None = field(default=None, compare=False, repr=False)

    @functools.cached_property
    def gaussians(self) -> np.ndarray | None:
        """(N, 3) complex m/N on every Gaussian, None without a video shape."""
        return None if self.shape_on_gaussians is None else self.shape_on_gaussians()

    def title(self) -> str:
        return f"mode {self.number}" if self.kind == "mode" else f"ODS line {self.number} ({self.freq_hz:.2f} Hz)"

    def label(self) -> str:
        mac = "" if not math.isfinite(self.mac) else f", MAC {self.mac:.3f}"
        if self.kind == "ods":
            return f"ODS line {self.number}: {self.freq_hz:.2f} Hz (1 N harmonic){mac}"
        text = f"mode {self.number}: {self.freq_hz:.2f} Hz, {100 * self.damping:.2f} %{mac}"
        return f"{text} ({self.not_judged})" if self.not_judged else text

    def shape_names(self) -> tuple[str, str]:
        """Its shapes' names in results.h5: (accelerometers', video's)."""
        if self.kind == "ods":
            return f"accelerometer ODS {self.freq_hz:.2f} Hz", f"video ODS {self.freq_hz:.2f} Hz"
        return f"accelerometer mode {self.number}", f"video mode {self.number}"


@dataclass(frozen=True)
class Scene:
    """The reconstruction as the viewer draws it: world frame, metres; motion in physical metres (the training
    frames' magnification divided out)."""

    means_m: np.ndarray       # (N, 3) float32 at rest
    quats: np.ndarray         # (N, 4) float32 at rest (w, x, y, z)
    scales_m: np.ndarray      # (N, 3) float32
    opacities: np.ndarray     # (N,) float32
    grey: np.ndarray          # (N, C) float32 colours as trained (mono cameras: C = 1)
    background: np.ndarray    # (C,)
    times_s: np.ndarray       # (T,) after the impact onset
    displacement_m: np.ndarray  # (T, N, 3) float32, physical
    rotvec_rad: np.ndarray    # (T, N, 3) float32, rotation from rest, physical
    structure: np.ndarray     # (N,) bool: the analysis's rule (floor, box) with the Gaussians' own motion
    structure_rule: str
    motion_rms_m: np.ndarray  # (N,)

    @property
    def n(self) -> int:
        return len(self.means_m)


@dataclass(frozen=True)
class Surface:
    """The structure's surface as triangles (`analysis.surface_mesh` over the analysis's surface points): the report's
    3D shapes are drawn on the same one."""

    points_m: np.ndarray      # (V, 3) at rest
    faces: np.ndarray         # (F, 3) vertex indices
    nearest: np.ndarray       # (V,) the Gaussian nearest each vertex: the measured motion there


@dataclass(frozen=True)
class ViewerData:
    """Everything the viewer shows of one capture; a part the capture lacks is None (or empty)."""

    name: str
    capture: Capture
    scene: Scene | None
    cameras: tuple = ()                  # reconstruction.Camera of every posed view (take or static photo)
    target_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extent_m: float = 1.0                # the structure's size: the default viewing distance follows it
    sensors: tuple[SensorInfo, ...] = ()
    modes: tuple[Mode, ...] = ()
    frf_freq_hz: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frf_h1: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), complex))   # (S, F) accelerance
    frf_names: tuple[str, ...] = ()
    signal_times_s: np.ndarray = field(default_factory=lambda: np.zeros(0))          # impact-locked
    force_n: np.ndarray = field(default_factory=lambda: np.zeros(0))
    accel_m_s2: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))         # (S, T)
    impulse_n_s: float = 1.0             # the hit's impulse: a mode is drawn at its amplitude after this hit
    notes: tuple[str, ...] = ()
    surface: Surface | None = None       # where the analysis has a video surface

    @property
    def time_range_s(self) -> tuple[float, float]:
        if self.scene is not None:
            return float(self.scene.times_s[0]), float(self.scene.times_s[-1])
        if len(self.signal_times_s):
            return 0.0, float(min(self.signal_times_s[-1], 0.1))
        return 0.0, 0.1

    def mode_nearest(self, freq_hz: float) -> int | None:
        """Index of the mode nearest freq_hz (None without modes; the ODS lines are not modes)."""
        modes = [k for k, m in enumerate(self.modes) if m.kind == "mode"]
        if not modes:
            return None
        return min(modes, key=lambda k: abs(self.modes[k].freq_hz - freq_hz))


# ---------------------------------------------------------------------------------------------- the view

@dataclass(frozen=True)
class Orbit:
    """The virtual camera: looking at target_m from azimuth/elevation (degrees, z up) at distance_m."""

    target_m: tuple[float, float, float]
    azimuth_deg: float = 35.0
    elevation_deg: float = 25.0
    distance_m: float = 2.5
    fov_deg: float = 50.0

    def eye_m(self) -> np.ndarray:
        a, e = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        d = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        return np.asarray(self.target_m, float) + self.distance_m * d

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        return look_at(self.eye_m(), np.asarray(self.target_m, float))

    def rotated(self, d_azimuth_deg: float, d_elevation_deg: float) -> Orbit:
        return replace(self, azimuth_deg=(self.azimuth_deg + d_azimuth_deg) % 360.0,
                       elevation_deg=float(np.clip(self.elevation_deg + d_elevation_deg, -89.0, 89.0)))

    def zoomed(self, factor: float) -> Orbit:
        return replace(self, distance_m=float(np.clip(self.distance_m * factor, 1e-3, 1e4)))

    def panned(self, dx: float, dy: float) -> Orbit:
        """Moves the target by dx, dy of the view's width along the image's right and up."""
        R, _ = self.pose()
        width_m = 2 * self.distance_m * math.tan(math.radians(self.fov_deg) / 2)
        shift = width_m * (dx * R[0] - dy * R[1])      # OpenCV: row 0 right, row 1 down
        return replace(self, target_m=tuple(float(v) for v in np.asarray(self.target_m) + shift))


@dataclass(frozen=True)
class ViewState:
    """What the view shows. time_s is the test's time (after the impact) for the measured motion, and the
    animation clock for a mode (its shape turns at its own frequency: phase 2 pi f time_s)."""

    orbit: Orbit
    snap: int | None = None          # a capture camera's index: its exact pose (until the user orbits)
    time_s: float = 0.0
    mode: int | None = None          # index in ViewerData.modes; None: the measured motion
    alpha: float = 100.0
    structure_only: bool = False
    box_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None   # min, max corners
    colour: str = "image"            # or "displacement"
    show_cameras: bool = True
    show_sensors: bool = True
    surface: bool = False            # the structure drawn as the analysis's surface (triangles), not its Gaussians
    width_px: int = WIDTH_PX
    height_px: int = HEIGHT_PX


def peak_time_s(scene: Scene) -> float:
    """The time after the impact when the structure moves most (its points' rms displacement): where the recorded
    motion is best seen; the first timestep when none is after it."""
    t = np.asarray(scene.times_s, float)
    after = t >= 0
    if not after.any():
        return float(t[0])
    d = scene.displacement_m[:, scene.structure] if scene.structure.any() else scene.displacement_m
    rms = np.sqrt(np.mean(np.sum(np.asarray(d, np.float64) ** 2, axis=2), axis=1))
    return float(t[after][int(np.argmax(rms[after]))])


def peak_phase(shape: np.ndarray) -> float:
    """The phase theta in [0, pi) at which a complex shape stands furthest from rest: Re(g e^(i theta)) is largest
    in the sum of squares at theta = -arg(sum g^2) / 2 (a complex shape drawn at phase 0 could stand near rest)."""
    return float((-0.5 * np.angle(np.sum(np.asarray(shape, complex) ** 2))) % np.pi)


def mode_peak_time_s(mode: Mode) -> float:
    """The time in a mode's first cycle when its shape stands furthest from rest (`peak_phase`)."""
    g = mode.gaussians if mode.gaussians is not None else mode.sensors_accel
    if g is None or not mode.freq_hz > 0:
        return 0.0
    return peak_phase(g) / (2 * np.pi * mode.freq_hz)


def start_time_s(data: ViewerData, mode: int | None) -> float:
    """Where a view of mode `mode` (None: the measured motion) starts: the mode furthest from rest, the motion at its
    largest after the impact (a screenshot before the impact showed nothing)."""
    if mode is not None:
        return mode_peak_time_s(data.modes[mode])
    return peak_time_s(data.scene) if data.scene is not None else data.time_range_s[0]


def mode_gain(data: ViewerData, m: Mode) -> float:
    """What a shape (m/N) is multiplied by to show metres: a mode's free decay right after this test's hit, at its
    start, 2 |A| J along its shape (A in m/N as the analysis gives it, J the hit's impulse); an ODS line's steady
    response to a harmonic force of 1 N at its frequency (its receptance, m/N)."""
    return 2 * data.impulse_n_s if m.kind == "mode" else 1.0


def mode_motion(data: ViewerData, m: Mode, shape: np.ndarray, time_s: float) -> np.ndarray:
    """A mode's physical displacement (metres) at `time_s` of its animation, from its complex shape (m/N) at some
    points: on the Gaussians (`motion_at`) or on the surface's vertices (`surface_motion`)."""
    return mode_gain(data, m) * np.real(shape * np.exp(2j * np.pi * m.freq_hz * time_s))


def sensor_shifts_m(data: ViewerData, state: ViewState) -> np.ndarray:
    """Each accelerometer's physical displacement along its direction (metres, before magnification) in the state:
    the selected mode's at its animation time, with that mode's gain (a mode's free decay, an ODS line per newton);
    zeros without a mode or without the accelerometers' shape."""
    m = data.modes[state.mode] if state.mode is not None else None
    if m is None or m.sensors_accel is None:
        return np.zeros(len(data.sensors))
    return mode_motion(data, m, np.asarray(m.sensors_accel), state.time_s)


def largest_motion_m(data: ViewerData, state: ViewState) -> float:
    """The largest physical displacement the state shows (metres, before magnification): a mode's at the start of
    its free decay after this test's hit (2 |A| J; an ODS line per newton), over the structure's Gaussians or, without
    them, at the sensors; the measured motion's over its whole time (99th percentiles: a stray point aside)."""
    sc = data.scene
    if state.mode is not None:
        m = data.modes[state.mode]
        gain = mode_gain(data, m)
        if m.gaussians is not None and sc is not None and sc.structure.any():
            return gain * float(np.percentile(np.linalg.norm(np.abs(m.gaussians[sc.structure]), axis=1), 99))
        return gain * float(np.max(np.abs(m.sensors_accel), initial=0.0)) if m.sensors_accel is not None else 0.0
    if sc is None:
        return 0.0
    d = sc.displacement_m[:, sc.structure] if sc.structure.any() else sc.displacement_m
    return float(np.percentile(np.linalg.norm(d, axis=2), 99)) if d.size else 0.0


def visible_alpha(data: ViewerData, state: ViewState) -> float:
    """The magnification that moves the structure's largest motion VISIBLE_SHARE of its size (ALPHA_RANGE at most;
    100 where nothing moves): a mode at x100 was barely visible on the demo."""
    top = largest_motion_m(data, state)
    if not top > 0:
        return 100.0
    return float(np.clip(VISIBLE_SHARE * data.extent_m / top, *ALPHA_RANGE))


def default_state(data: ViewerData, **kw) -> ViewState:
    """A view of the whole structure from an oblique angle; the recorded motion at its largest after the impact, or
    the first mode where there is no motion (a screenshot before the impact showed nothing)."""
    orbit = Orbit(tuple(float(v) for v in data.target_m), distance_m=1.6 * data.extent_m)
    mode = 0 if data.scene is None and data.modes else None
    alpha = kw.pop("alpha", None)
    state = ViewState(orbit, mode=mode, time_s=start_time_s(data, mode), **kw)
    return replace(state, alpha=visible_alpha(data, state) if alpha is None else alpha)


def camera_for(data: ViewerData, state: ViewState):
    """The reconstruction.Camera the state looks through, at the state's size."""

    w, h = state.width_px, state.height_px
    if state.snap is not None and 0 <= state.snap < len(data.cameras):
        cam = data.cameras[state.snap]
        # the capture camera's field of view, fitted into the view's size (its aspect kept, letterboxed by K)
        s = min(w / cam.width_px, h / cam.height_px)
        K = np.array(cam.K, float)
        K[0, 0] *= s
        K[1, 1] *= s
        K[0, 2] = (cam.K[0, 2] + 0.5) * s - 0.5 + 0.5 * (w - s * cam.width_px)
        K[1, 2] = (cam.K[1, 2] + 0.5) * s - 0.5 + 0.5 * (h - s * cam.height_px)
        return Camera(K, np.asarray(cam.R, float), np.asarray(cam.t, float), w, h, cam.name)
    R, t = state.orbit.pose()
    f = 0.5 * w / math.tan(math.radians(state.orbit.fov_deg) / 2)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    return Camera(K, R, t, w, h, "view")


def snap_orbit(data: ViewerData, index: int, orbit: Orbit) -> Orbit:
    """The orbit nearest capture camera `index`: the same eye, looking along its axis at the target's depth, and
    its horizontal field of view."""
    cam = data.cameras[index]
    eye = camera_center_m(cam.R, cam.t)
    forward = np.asarray(cam.R, float)[2]
    depth = max(float(np.dot(np.asarray(orbit.target_m) - eye, forward)), 1e-3)
    target = eye + depth * forward
    d = eye - target
    az = math.degrees(math.atan2(d[1], d[0]))
    el = math.degrees(math.asin(float(np.clip(d[2] / np.linalg.norm(d), -1, 1))))
    fov = math.degrees(2 * math.atan(0.5 * cam.width_px / cam.K[0][0]))
    return Orbit(tuple(float(v) for v in target), az, el, float(np.linalg.norm(d)), fov)


# ---------------------------------------------------------------------------------------------- rendering

def motion_at(data: ViewerData, state: ViewState) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 3) physical displacement (metres) and (N, 3) rotation vectors of every Gaussian in the state, before
    magnification; None without a reconstruction."""
    sc = data.scene
    if sc is None:
        return None
    if state.mode is not None:
        m = data.modes[state.mode]
        if m.gaussians is None:
            return np.zeros_like(sc.means_m), np.zeros_like(sc.means_m)
        # the rotation is not known and left at rest
        return mode_motion(data, m, m.gaussians, state.time_s).astype(np.float32), np.zeros_like(sc.means_m)
    ts = sc.times_s
    t = float(np.clip(state.time_s, ts[0], ts[-1]))
    k = int(np.clip(np.searchsorted(ts, t, side="right") - 1, 0, max(len(ts) - 2, 0)))
    k1 = min(k + 1, len(ts) - 1)
    w = 0.0 if k1 == k else float((t - ts[k]) / (ts[k1] - ts[k]))
    disp = (1 - w) * sc.displacement_m[k] + w * sc.displacement_m[k1]
    rot = (1 - w) * sc.rotvec_rad[k] + w * sc.rotvec_rad[k1]
    return disp, rot


def visible(data: ViewerData, state: ViewState) -> np.ndarray:
    """(N,) bool: the Gaussians drawn (structure only: the structure's; inside the box where one is given)."""
    sc = data.scene
    keep = sc.structure.copy() if state.structure_only else np.ones(sc.n, bool)
    if state.box_m is not None:
        lo, hi = np.asarray(state.box_m[0], float), np.asarray(state.box_m[1], float)
        keep &= np.all((sc.means_m >= lo) & (sc.means_m <= hi), axis=1)
    return keep


def colour_scale(data: ViewerData, state: ViewState) -> tuple[float, str]:
    """The colour bar's top (amplitude) and unit: metres for the measured motion, m/N for a mode."""
    sc = data.scene
    if state.mode is not None:
        g = data.modes[state.mode].gaussians
        amp = np.linalg.norm(np.abs(g), axis=1)[sc.structure] if g is not None else np.zeros(1)
        return float(np.percentile(amp, 99)) if amp.size else 1.0, "m/N"
    peak = np.linalg.norm(sc.displacement_m[:, sc.structure], axis=2) if sc.structure.any() else np.zeros(1)
    return float(np.percentile(peak, 99.5)) if peak.size else 1.0, "m"


def render_view(data: ViewerData, state: ViewState, *, overlays: bool = True) -> np.ndarray:
    """(H, W, 3) uint8: the reconstruction's Gaussians in the state (magnified in 3D at render time), or without a
    reconstruction the sensors' shapes on their positions; the capture cameras, the sensors' arrows and the colour
    bar drawn over it (overlays)."""

    cam = camera_for(data, state)
    w, h = state.width_px, state.height_px
    sc = data.scene
    if sc is None:
        img = np.full((h, w, 3), 255, np.uint8)
        draw_floor(img, data, cam)
    else:
        disp, rot = motion_at(data, state)
        keep = visible(data, state)
        mesh = state.surface and data.surface is not None
        if mesh:            # the structure is drawn as the surface below, over what else is shown
            keep &= ~sc.structure
        every = bool(keep.all())
        pick = (lambda a: a) if every else (lambda a: a[keep])  # noqa: E731  (no copies when all are drawn)
        means = pick(sc.means_m) + np.float32(state.alpha) * pick(disp)
        quats = pick(sc.quats)
        if state.mode is None and np.any(rot):
            quats = _turned(quats, np.float32(state.alpha) * pick(rot))
        if state.colour == "displacement":
            top, _ = colour_scale(data, state)
            amp = np.linalg.norm(np.abs(pick(data.modes[state.mode].gaussians)), axis=1) if (
                state.mode is not None and data.modes[state.mode].gaussians is not None) else \
                np.linalg.norm(pick(disp), axis=1)
            colours = plasma(amp / max(top, 1e-30)).astype(np.float32) / 255
            background = np.ones(3, np.float32)
        else:      # mono: one channel rendered, made grey RGB after
            colours = pick(sc.grey[:, :1])
            background = sc.background[:1]
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = cam.R, cam.t
        if len(means):
            image, _ = rasterize_image(means.astype(np.float32, copy=False), quats, pick(sc.scales_m),
                                       pick(sc.opacities), colours, view, cam.K, w, h, background=background)
        else:
            image = np.broadcast_to(background, (h, w, len(background))).copy()
        img = cv2.convertScaleAbs(image, alpha=255.0)       # rounded, saturated to 0..255
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB) if img.ndim == 2 or img.shape[2] == 1 else img
        if mesh:
            _draw_surface(img, data, state, cam, disp)
    if overlays:
        draw_overlays(img, data, state, cam,
                      colour_scale(data, state) if state.colour == "displacement" and sc is not None else None)
    return img


def surface_motion(data: ViewerData, state: ViewState, disp: np.ndarray) -> np.ndarray:
    """(V, 3) physical displacement of the surface's vertices in the state: a mode's shape there (as `motion_at`'s
    on the Gaussians), the measured motion of the Gaussian nearest each."""
    surf = data.surface
    if state.mode is not None:
        m = data.modes[state.mode]
        return np.zeros_like(surf.points_m) if m.surface is None else mode_motion(data, m, m.surface, state.time_s)
    return np.asarray(disp, float)[surf.nearest]


SHADE_AMBIENT = 0.35     # the surface's shade: this, plus the rest times |cos| of the angle to the view


def _draw_surface(img: np.ndarray, data: ViewerData, state: ViewState, cam, disp: np.ndarray) -> None:
    """The structure's surface, moved by the state's motion magnified alpha times, in place: its triangles far to
    near (the painter's order), each shaded by its angle to the view and coloured by the amplitude (colour
    "displacement") or by the nearest Gaussian's trained grey."""
    surf = data.surface
    motion = surface_motion(data, state, disp)
    moved = surf.points_m + state.alpha * motion
    uv, front = project(cam, moved)
    tri = moved[surf.faces]                                              # (F, 3, 3)
    ok = front[surf.faces].all(axis=1)
    depth = (tri @ np.asarray(cam.R)[2] + np.asarray(cam.t)[2]).mean(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    to_eye = camera_center_m(cam.R, cam.t) - tri.mean(axis=1)
    cos = np.abs(np.sum(normal * to_eye, axis=1)) / np.maximum(
        np.linalg.norm(normal, axis=1) * np.linalg.norm(to_eye, axis=1), 1e-30)
    shade = SHADE_AMBIENT + (1 - SHADE_AMBIENT) * cos
    if state.colour == "displacement":
        top, _ = colour_scale(data, state)
        shape = data.modes[state.mode].surface if state.mode is not None else None
        amp = np.linalg.norm(np.abs(shape) if shape is not None else motion, axis=1)   # a mode: its amplitude
        base = plasma(amp / max(top, 1e-30)).astype(float)[surf.faces].mean(axis=1)          # (F, 3) 0..255
    else:
        grey = data.scene.grey[surf.nearest, 0].astype(float)[surf.faces].mean(axis=1)
        base = np.repeat(255 * np.clip(grey, 0, 1)[:, None], 3, axis=1)
    colours = np.clip(base * shade[:, None], 0, 255).astype(np.uint8)
    corners = np.round(uv[surf.faces] * 16).astype(np.int64)              # 4 bits of sub-pixel
    inside = ok & (np.abs(corners).max(axis=(1, 2)) < 2 ** 27)
    for f in np.flatnonzero(inside)[np.argsort(-depth[inside])]:
        cv2.fillConvexPoly(img, corners[f].astype(np.int32), tuple(int(c) for c in colours[f]), cv2.LINE_AA, shift=4)


def _turned(quats: np.ndarray, rotvec_rad: np.ndarray) -> np.ndarray:
    """(N, 4) float32 orientations (w, x, y, z) turned by (N, 3) rotation vectors: reconstruction's quaternions."""
    import torch


    turn = quat_from_rotvec(torch.from_numpy(np.ascontiguousarray(rotvec_rad, np.float32)))
    return quat_multiply(turn, torch.from_numpy(np.ascontiguousarray(quats, np.float32))).numpy()


def best_threads(data: ViewerData, state: ViewState, repeats: int = 3) -> int:
    """The thread count (all of torch's, or one) that renders this view faster here, measured by rendering it
    `repeats` times with each, alternately; torch's count is left at the answer. On two cores shared with other
    work, two threads of the rasterizer wait on each other and one is faster (bench/viewer.py: 25 against 16
    frames/s on the loaded 2-core machine); on idle cores two are."""
    import time

    import torch

    most = torch.get_num_threads()
    if most <= 1:
        return most
    spent = {most: [], 1: []}
    try:
        for _ in range(repeats):
            for n in (most, 1):
                torch.set_num_threads(n)
                t0 = time.perf_counter()
                render_view(data, state, overlays=False)
                spent[n].append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(most)
    best = min(spent, key=lambda n: float(np.median(spent[n])))
    torch.set_num_threads(best)
    log.info("rendering on %d thread(s): %.0f ms a frame (%d threads: %.0f ms)", best, 1e3 * np.median(spent[best]),
             most if best == 1 else 1, 1e3 * np.median(spent[most if best == 1 else 1]))
    return best


__all__ = ["ALPHA_RANGE", "COLOUR_MODES", "Mode", "Orbit", "Scene", "SensorInfo", "ViewState", "ViewerData",
           "best_threads", "camera_for", "colour_scale", "default_state", "largest_motion_m", "mode_peak_time_s",
           "motion_at", "peak_phase", "peak_time_s", "render_view", "snap_orbit", "start_time_s", "visible",
           "visible_alpha"]
