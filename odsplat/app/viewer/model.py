"""The viewer's Qt-free core: what a capture has to show (`load_viewer`), what is shown (`ViewState`) and the one
renderer from the second to the first (`render_view`), which the window, the exporter, the tests and the bench call.

Everything is read through the stages' documented readers: the reconstruction's `DynamicScene` and `PoseResult`,
the analysis's `read_analysis` and `read_results_h5`, sync's `AlignedTake`, the take files' channels.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.geometry import camera_center_m, look_at
from odsplat.spine.impulse import fit_pulse, impact_onsets
from odsplat.spine.store import Capture

log = logging.getLogger(__name__)

WIDTH_PX, HEIGHT_PX = 640, 480
ALPHA_RANGE = (1.0, 1000.0)
MOVING_FACTOR = 3.0      # a Gaussian moves when its rms motion is this many times the quietest quarter's median
SHAPE_NEIGHBOURS = 8     # surface points a Gaussian's mode shape is interpolated from
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
    gaussians: np.ndarray | None = None       # (N, 3) complex m/N
    kind: str = "mode"               # or "ods": an ODS line, the receptance at freq_hz (m/N) of every point

    def title(self) -> str:
        return f"mode {self.number}" if self.kind == "mode" else f"ODS line {self.number} ({self.freq_hz:.2f} Hz)"

    def label(self) -> str:
        mac = "" if not math.isfinite(self.mac) else f", MAC {self.mac:.3f}"
        if self.kind == "ods":
            return f"ODS line {self.number}: {self.freq_hz:.2f} Hz (1 N harmonic){mac}"
        return f"mode {self.number}: {self.freq_hz:.2f} Hz, {100 * self.damping:.2f} %{mac}"

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
    width_px: int = WIDTH_PX
    height_px: int = HEIGHT_PX


def default_state(data: ViewerData, **kw) -> ViewState:
    """A view of the whole structure from an oblique angle, the first mode selected where there is no motion."""
    orbit = Orbit(tuple(float(v) for v in data.target_m), distance_m=1.6 * data.extent_m)
    mode = 0 if data.scene is None and data.modes else None
    return ViewState(orbit, mode=mode, time_s=data.time_range_s[0] if mode is None else 0.0, **kw)


def camera_for(data: ViewerData, state: ViewState):
    """The reconstruction.Camera the state looks through, at the state's size."""
    from odsplat.reconstruction import Camera

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


# ---------------------------------------------------------------------------------------------- loading

def load_viewer(capture: Capture | str, *, need_analysis: bool = True) -> ViewerData:
    """What the capture has to show. Refuses (InputError) a capture without an analysis when need_analysis: the
    viewer's modes, FRFs and structure rule come from it."""
    capture = capture if isinstance(capture, Capture) else Capture.open(capture)
    notes: list[str] = []
    sensors = _sensors(capture)
    doc, results = _analysis(capture, need_analysis)
    scene_data, cameras = _reconstruction(capture, notes)
    impulse, times, force, accel = _signals(capture, doc, sensors, notes)
    modes = _modes(doc, results, sensors, notes)
    freq, h1, frf_names = _frfs(results, sensors)
    scene = None
    if scene_data is not None:
        scene = _scene(capture, scene_data, doc)
        # the background moves with no mode: its shapes are noise, and the analysis keeps them out of its own
        modes = tuple(replace(m, gaussians=None if g is None else g * scene.structure[:, None])
                      for m, g in zip(modes, _mode_shapes_on(results, modes, scene)))
    if scene is not None and scene.structure.any():
        pts = scene.means_m[scene.structure]
    elif sensors:      # the sensors and the floor under them (the view without a reconstruction shows both)
        pts = np.array([s.position_m for s in sensors])
        pts = np.concatenate([pts, pts * [1, 1, 0]])
    else:
        pts = np.zeros((1, 3))
    lo, hi = np.percentile(pts, 2, axis=0), np.percentile(pts, 98, axis=0)
    extent = float(max(np.linalg.norm(hi - lo), 0.2))
    return ViewerData(capture.root.name, capture, scene, tuple(cameras), (lo + hi) / 2, extent, sensors, modes, freq,
                      h1, frf_names, times, force, accel, impulse, tuple(notes))


def _sensors(capture: Capture) -> tuple[SensorInfo, ...]:
    out = []
    for c in capture.manifest.channels:
        if c.kind == "acceleration" and c.position_m is not None and c.direction is not None:
            d = np.asarray(c.direction, float)
            out.append(SensorInfo(c.name, np.asarray(c.position_m, float), d / np.linalg.norm(d)))
    return tuple(out)


def _analysis(capture: Capture, need: bool):
    from odsplat.analysis import read_analysis, read_results_h5

    if not capture.paths.analysis_json.exists():
        if need:
            raise InputError(capture.root, "no analysis to view (run `odsplat analyze` or `odsplat run` first)")
        return None, None
    doc = read_analysis(capture)
    path = capture.paths.analysis_dir / "results.h5"
    results = read_results_h5(path, capture.id) if path.exists() else None
    return doc, results


def _reconstruction(capture: Capture, notes: list[str]):
    from odsplat.reconstruction import Camera, DynamicScene, PoseResult

    cameras = []
    if capture.paths.poses_json.exists():
        try:
            poses = PoseResult.read(capture)
            cameras = [Camera(np.asarray(v.K, float), np.asarray(v.R, float), np.asarray(v.t, float), v.width_px,
                              v.height_px, v.name) for v in poses.views]
        except OdsplatError as e:
            notes.append(f"no capture cameras: {e}")
    if not capture.paths.trajectories_npz.exists():
        notes.append("no reconstruction: the sensors' shapes on their positions, and the plots")
        return None, cameras
    try:
        return DynamicScene.load(capture), cameras
    except OdsplatError as e:
        notes.append(f"the reconstruction could not be read ({e}): the sensors and the plots only")
        return None, cameras


def _scene(capture: Capture, sc, doc: dict | None) -> Scene:
    """The DynamicScene's Gaussians in world metres, their physical motion, and which are the structure's."""
    from odsplat.analysis import AnalyzeSettings, structure_mask

    r = sc.scene.radius
    g = sc.rest
    means = sc.means_rest_m.astype(np.float32)
    q0 = np.asarray(sc.quats[0], np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    disp = (sc.displacement_m / sc.source_alpha).astype(np.float32)
    rot = sc.turns_rad() / sc.source_alpha
    rms = np.sqrt(np.mean(np.sum(disp.astype(np.float64) ** 2, axis=2), axis=0))
    quiet = np.median(np.sort(rms)[: max(1, len(rms) // 4)])
    moving = rms > MOVING_FACTOR * max(quiet, 1e-12)
    settings = AnalyzeSettings()
    if doc is not None:      # the analysis's own floor margin and box, where it saved them
        st = doc.get("settings", {}) or {}
        kw = {}
        if "floor_margin_m" in st:
            kw["floor_margin_m"] = st["floor_margin_m"]
        if st.get("structure_box_m") is not None:
            kw["structure_box_m"] = tuple(tuple(c) for c in st["structure_box_m"])
        if kw:
            settings = AnalyzeSettings(**kw)
    keep, rule = structure_mask(capture, means, settings, moving=moving)
    return Scene(means, q0.astype(np.float32), (g.scales.double().numpy() * r).astype(np.float32),
                 g.opacities.double().numpy().astype(np.float32), g.colors.double().numpy().astype(np.float32),
                 np.asarray(sc.background, np.float32), np.asarray(sc.times_s, float), disp, rot.astype(np.float32),
                 keep, rule, rms)


def _quat_from_rotvec(r: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    k = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-30), 0.5)
    return np.concatenate([np.cos(half), r * k], axis=-1)


def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - np.sum(av * bv, axis=-1, keepdims=True),
                           aw * bv + bw * av + np.cross(av, bv)], axis=-1)


def _signals(capture: Capture, doc: dict | None, sensors: tuple[SensorInfo, ...], notes: list[str]):
    """One hit's force and accelerations on the impact-locked time (0 at the onset), and its impulse."""
    takes = list((doc or {}).get("takes", [])) or capture.take_names()
    forces = [c.name for c in capture.manifest.channels if c.kind == "force"]
    if not takes or not forces:
        notes.append("no force record: modes drawn for an impulse of 1 N s")
        return 1.0, np.zeros(0), np.zeros(0), np.zeros((len(sensors), 0))
    rate = float(capture.manifest.daq_sample_rate_hz)
    try:
        with capture.open_take(takes[0]) as r:
            force = np.nan_to_num(r.channel(forces[0]))
            accel = np.array([np.nan_to_num(r.channel(s.name)) for s in sensors]).reshape(len(sensors), -1)
    except (OdsplatError, KeyError) as e:
        notes.append(f"no force record ({e}): modes drawn for an impulse of 1 N s")
        return 1.0, np.zeros(0), np.zeros(0), np.zeros((len(sensors), 0))
    pulses = impact_onsets(force, rate) or [fit_pulse(force, rate)]
    onset_s = float(pulses[0].onset_s)
    impulse = float(pulses[0].impulse_n_s) if pulses[0].impulse_n_s > 0 else 1.0
    times = np.arange(len(force)) / rate - onset_s
    keep = (times >= -0.01) & (times <= 0.25)
    return impulse, times[keep], force[keep], accel[:, keep]


def _modes(doc: dict | None, results, sensors: tuple[SensorInfo, ...], notes: list[str]) -> tuple[Mode, ...]:
    if doc is None:
        return ()
    macs = {}
    for p in ((doc.get("correlation") or {}).get("pairs") or []):
        try:
            macs[int(p["a"])] = float(p["mac"])
        except (KeyError, TypeError, ValueError):
            continue
    shapes = {} if results is None else {s.name: s for s in results.shapes}
    node = {} if results is None or results.geometry is None else \
        {int(i): k for k, i in enumerate(results.geometry.node_ids)}
    def at_sensors(mode: Mode) -> Mode:
        acc_name, vid_name = mode.shape_names()
        acc, vid = shapes.get(acc_name), shapes.get(vid_name)
        at = None
        if acc is not None and len(sensors) and len(acc.node_ids) == len(sensors):
            at = np.array([np.dot(acc.values[i], s.direction) for i, s in enumerate(sensors)])
        at_video = None
        if vid is not None and node and len(sensors):
            pts = results.geometry.coords_m[[node[int(i)] for i in vid.node_ids]]
            at_video = np.array([np.dot(v, s.direction) for v, s in
                                 zip(_interpolate(pts, vid.values, np.array([s.position_m for s in sensors]), 16),
                                     sensors)])
        return replace(mode, sensors_accel=at, sensors_video=at_video)

    out = [at_sensors(Mode(k + 1, float(m["freq_hz"]), float(m["damping"]), macs.get(k, float("nan"))))
           for k, m in enumerate(doc.get("modes", []))]
    # the ODS lines (the modal frequencies by default, or those asked for with `odsplat analyze --ods F`)
    for k, line in enumerate(doc.get("ods") or []):
        out.append(at_sensors(Mode(k + 1, float(line["freq_hz"]), 0.0, float(line.get("mac", float("nan"))),
                                   kind="ods")))
    if out and results is None:
        notes.append("no results.h5: mode shapes unavailable")
    return tuple(out)


def _interpolate(points_m: np.ndarray, values: np.ndarray, at_m: np.ndarray, k: int,
                 reach_m: float | None = None) -> np.ndarray:
    """values (P, 3) at points_m, inverse-distance mean of the k nearest at at_m (M, 3); zero beyond reach_m of
    every point."""
    k = min(k, len(points_m))
    tree = cKDTree(points_m)
    d, i = tree.query(at_m, k=k)
    d, i = d.reshape(len(at_m), k), i.reshape(len(at_m), k)
    w = 1.0 / np.maximum(d, 1e-6)
    out = np.einsum("mk,mkc->mc", w, values[i]) / w.sum(axis=1, keepdims=True)
    if reach_m is not None:
        out[d[:, 0] > reach_m] = 0
    return out


def _mode_shapes_on(results, modes: tuple[Mode, ...], scene: Scene) -> list[np.ndarray | None]:
    """Each mode's video shape (m/N) on every Gaussian: the analysis's surface residues, inverse-distance
    interpolated from the 8 nearest surface points; zero further than 3 point spacings from any (the background
    the analysis left out of its shapes)."""
    if results is None or results.geometry is None:
        return [None] * len(modes)
    shapes = {s.name: s for s in results.shapes}
    node = {int(i): k for k, i in enumerate(results.geometry.node_ids)}
    out: list[np.ndarray | None] = []
    for m in modes:
        vid = shapes.get(m.shape_names()[1])
        if vid is None:
            out.append(None)
            continue
        pts = results.geometry.coords_m[[node[int(i)] for i in vid.node_ids]]
        spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])) if len(pts) > 1 else 1.0
        out.append(_interpolate(pts, vid.values, scene.means_m.astype(float), SHAPE_NEIGHBOURS,
                                3 * spacing).astype(np.complex64))
    return out


def _frfs(results, sensors):
    if results is None or not results.frfs:
        return np.zeros(0), np.zeros((0, 0), complex), ()
    frfs = [f for f in results.frfs if f.name.startswith("H1 ")] or list(results.frfs)
    freq = np.asarray(frfs[0].freq_hz, float)
    h1 = np.array([np.asarray(f.values) for f in frfs if len(f.values) == len(freq)])
    return freq, h1, tuple(f.name for f in frfs if len(f.values) == len(freq))


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
        phase = np.exp(2j * np.pi * m.freq_hz * state.time_s)
        # a mode: its free decay right after this test's hit, at its start: 2 |A| J along its shape (A in m/N as
        # the analysis gives it, J the hit's impulse); an ODS line: the steady response to a harmonic force of 1 N
        # at its frequency (its receptance, m/N). The rotation is not known and left at rest.
        gain = 2 * data.impulse_n_s if m.kind == "mode" else 1.0
        return (gain * np.real(m.gaussians * phase)).astype(np.float32), np.zeros_like(sc.means_m)
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
    from odsplat.reconstruction import rasterize_image

    cam = camera_for(data, state)
    w, h = state.width_px, state.height_px
    sc = data.scene
    if sc is None:
        img = np.full((h, w, 3), 255, np.uint8)
        _draw_floor(img, data, cam)
    else:
        disp, rot = motion_at(data, state)
        keep = visible(data, state)
        every = bool(keep.all())
        pick = (lambda a: a) if every else (lambda a: a[keep])  # noqa: E731  (no copies when all are drawn)
        means = pick(sc.means_m) + np.float32(state.alpha) * pick(disp)
        quats = pick(sc.quats)
        if state.mode is None and np.any(rot):
            quats = _quat_multiply(_quat_from_rotvec(np.float32(state.alpha) * pick(rot)), quats)
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
        image, _ = rasterize_image(means.astype(np.float32, copy=False), quats, pick(sc.scales_m),
                                   pick(sc.opacities), colours, view, cam.K, w, h, background=background)
        img = cv2.convertScaleAbs(image, alpha=255.0)       # rounded, saturated to 0..255
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB) if img.ndim == 2 or img.shape[2] == 1 else img
    if overlays:
        if state.show_cameras:
            _draw_cameras(img, data, cam)
        if state.show_sensors or sc is None:
            _draw_sensors(img, data, state, cam)
        if state.colour == "displacement" and sc is not None:
            _draw_colour_bar(img, *colour_scale(data, state))
        _draw_caption(img, data, state)
    return img


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


def _project(cam, pts_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pc = np.asarray(pts_m, float) @ np.asarray(cam.R).T + np.asarray(cam.t)
    z = pc[:, 2]
    uv = pc[:, :2] / np.where(z > 1e-6, z, 1e-6)[:, None]
    K = np.asarray(cam.K)
    return np.stack([K[0, 0] * uv[:, 0] + K[0, 2], K[1, 1] * uv[:, 1] + K[1, 2]], axis=1), z > 1e-6


def _line(img: np.ndarray, a, b, colour, thickness: int = 1) -> None:
    p, q = (int(round(a[0] * 16)), int(round(a[1] * 16))), (int(round(b[0] * 16)), int(round(b[1] * 16)))
    if max(abs(v) for v in p + q) < 2 ** 27:
        cv2.line(img, p, q, colour, thickness, cv2.LINE_AA, shift=4)


def _draw_floor(img: np.ndarray, data: ViewerData, cam) -> None:
    """A grid on z = 0 under the sensors (the accelerometer-only view has nothing else to stand on)."""
    c = data.target_m
    half = 0.6 * data.extent_m
    for v in np.linspace(-half, half, 9):
        for a, b in (((c[0] + v, c[1] - half, 0), (c[0] + v, c[1] + half, 0)),
                     ((c[0] - half, c[1] + v, 0), (c[0] + half, c[1] + v, 0))):
            uv, ok = _project(cam, np.array([a, b]))
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
    uv, ok = _project(cam, pyramids.reshape(-1, 3))
    uv, ok = uv.reshape(-1, 5, 2), ok.reshape(-1, 5).all(axis=1) & (np.abs(uv).reshape(-1, 10).max(axis=1) < 1e5)
    lines = []
    for p in np.round(uv[ok] * 16).astype(np.int32):
        lines += [p[[1, 2, 3, 4, 1]], p[[0, 1]], p[[0, 2]], p[[0, 3]], p[[0, 4]]]
    cv2.polylines(img, lines, False, (40, 120, 255), 1, cv2.LINE_AA, shift=4)


def _draw_sensors(img: np.ndarray, data: ViewerData, state: ViewState, cam) -> None:
    """Each accelerometer as an arrow along its direction; with a mode selected, moved by the accelerometers' shape
    (magnified like the Gaussians) and its arrow scaled by the motion along it."""
    length = 0.1 * data.extent_m
    mode = data.modes[state.mode] if state.mode is not None else None
    phase = np.exp(2j * np.pi * mode.freq_hz * state.time_s) if mode is not None else 1.0
    for i, s in enumerate(data.sensors):
        shift = 0.0
        if mode is not None and mode.sensors_accel is not None:
            shift = float(state.alpha * 2 * data.impulse_n_s * np.real(mode.sensors_accel[i] * phase))
        base = s.position_m + shift * s.direction
        uv, ok = _project(cam, np.array([s.position_m, base, base + length * s.direction]))
        if not ok.all():
            continue
        p0, p1, p2 = uv
        if data.scene is None:      # nothing else shows their height: a drop line to the floor
            foot, ok_foot = _project(cam, (s.position_m * [1, 1, 0])[None])
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


def aligned_frame(data: ViewerData, take: str, time_s: float) -> np.ndarray | None:
    """(H, W) uint8: a capture camera's real frame on sync's common grid nearest time_s (impact-locked), or None
    where the capture has no aligned frames for that take."""
    from odsplat.sync import AlignedTake, load_sync

    capture = data.capture
    path = capture.paths.frames("sync", take)
    if not path.exists():
        return None
    try:
        generation = load_sync(capture).generation
    except OdsplatError as e:
        log.warning("sync's index could not be read (%s); the aligned frames are shown unchecked", e)
        generation = None
    try:
        with AlignedTake(path, generation, capture.id) as f:
            k = int(np.argmin(np.abs(f.times_s - time_s)))
            frame = np.asarray(f.read_frames(k, k + 1)[0], float)
    except OdsplatError as e:
        log.warning("%s", e)
        return None
    frame = frame[..., 0] if frame.ndim == 3 else frame
    lo, hi = np.percentile(frame, (0.5, 99.5))
    return np.round(np.clip((frame - lo) / max(hi - lo, 1e-9), 0, 1) * 255).astype(np.uint8)


__all__ = ["COLOUR_MODES", "Mode", "Orbit", "Scene", "SensorInfo", "ViewState", "ViewerData", "aligned_frame",
           "best_threads", "camera_for", "caption", "colour_scale", "default_state", "load_viewer", "motion_at",
           "plasma", "render_view", "snap_orbit", "visible"]
