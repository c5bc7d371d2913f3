"""What a capture has for the viewer to show (`load_viewer` -> ViewerData), read through the stages' documented
readers: the reconstruction's `DynamicScene` and `PoseResult`, the analysis's typed `read_analysis` and
`read_results_h5`, sync's `AlignedTake`, the take files' channels."""
from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from odsplat.analysis import (
    AnalysisDocument,
    AnalyzeSettings,
    read_analysis,
    read_results_h5,
    structure_mask,
    surface_mesh,
)
from odsplat.app.viewer.model import Mode, Scene, SensorInfo, Surface, ViewerData
from odsplat.reconstruction import Camera, DynamicScene, PoseResult
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.impulse import fit_pulse, impact_onsets
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, load_sync

log = logging.getLogger(__name__)

MOVING_FACTOR = 3.0      # a Gaussian moves when its rms motion is this many times the quietest quarter's median
SHAPE_NEIGHBOURS = 8     # surface points a Gaussian's mode shape is interpolated from


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
    scene, surface = None, None
    if scene_data is not None:
        scene = _scene(capture, scene_data, doc)
        # each mode's shape on the Gaussians when first asked for (`Mode.gaussians`)
        modes = tuple(replace(m, shape_on_gaussians=_mode_shape_on(results, m, scene)) for m in modes)
        surface, modes = _surface(results, modes, scene)
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
                      h1, frf_names, times, force, accel, impulse, tuple(notes), surface)


def _sensors(capture: Capture) -> tuple[SensorInfo, ...]:
    out = []
    for c in capture.manifest.channels:
        if c.kind == "acceleration" and c.position_m is not None and c.direction is not None:
            d = np.asarray(c.direction, float)
            out.append(SensorInfo(c.name, np.asarray(c.position_m, float), d / np.linalg.norm(d)))
    return tuple(out)


def _analysis(capture: Capture, need: bool) -> tuple[AnalysisDocument | None, Any]:
    """The capture's analysis.json (typed and checked) and results.h5 (None where it has not been written)."""

    if not capture.paths.analysis_json.exists():
        if need:
            raise InputError(capture.root, "no analysis to view (run `odsplat analyze` or `odsplat run` first)")
        return None, None
    doc = read_analysis(capture)
    path = capture.paths.analysis_dir / "results.h5"
    results = read_results_h5(path, capture.id) if path.exists() else None
    return doc, results


def _reconstruction(capture: Capture, notes: list[str]):

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


def _scene(capture: Capture, sc, doc: AnalysisDocument | None) -> Scene:
    """The DynamicScene's Gaussians in world metres, their physical motion, and which are the structure's."""

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
    # the analysis's own floor margin and box, where it saved them
    settings = AnalyzeSettings(**(doc.structure_settings() if doc is not None else {}))
    keep, rule = structure_mask(capture, means, settings, moving=moving)
    return Scene(means, q0.astype(np.float32), (g.scales.double().numpy() * r).astype(np.float32),
                 g.opacities.double().numpy().astype(np.float32), g.colors.double().numpy().astype(np.float32),
                 np.asarray(sc.background, np.float32), np.asarray(sc.times_s, float), disp, rot.astype(np.float32),
                 keep, rule, rms)


def _signals(capture: Capture, doc: AnalysisDocument | None, sensors: tuple[SensorInfo, ...], notes: list[str]):
    """One hit's force and accelerations on the impact-locked time (0 at the onset), and its impulse."""
    takes = list(doc.takes if doc is not None else ()) or capture.take_names()
    forces = [c.name for c in capture.manifest.channels if c.kind == "force"]
    if not takes or not forces:
        notes.append("no force record: modes drawn for an impulse of 1 N s")
        return 1.0, np.zeros(0), np.zeros(0), np.zeros((len(sensors), 0))
    rate = float(capture.manifest.daq_sample_rate_hz)
    try:
        with capture.open_take(takes[0]) as r:
            force = np.nan_to_num(r.channel(forces[0]))
            accel = np.array([np.nan_to_num(r.channel(s.name)) for s in sensors]).reshape(len(sensors), -1) \
                if sensors else np.zeros((0, len(force)))      # no placed sensor (an imported recording)
    except (OdsplatError, KeyError) as e:
        notes.append(f"no force record ({e}): modes drawn for an impulse of 1 N s")
        return 1.0, np.zeros(0), np.zeros(0), np.zeros((len(sensors), 0))
    pulses = impact_onsets(force, rate) or [fit_pulse(force, rate)]
    onset_s = float(pulses[0].onset_s)
    impulse = float(pulses[0].impulse_n_s) if pulses[0].impulse_n_s > 0 else 1.0
    times = np.arange(len(force)) / rate - onset_s
    keep = (times >= -0.01) & (times <= 0.25)
    return impulse, times[keep], force[keep], accel[:, keep]


def _modes(doc: AnalysisDocument | None, results, sensors: tuple[SensorInfo, ...],
           notes: list[str]) -> tuple[Mode, ...]:
    """The analysis's modes, then its ODS lines, each with its MAC and its shapes at the sensors."""
    if doc is None:
        return ()
    macs = {k: p.mac for k, p in doc.pair_by_mode().items()}
    shapes = {} if results is None else {s.name: s for s in results.shapes}

    def at_sensors(mode: Mode) -> Mode:
        acc_name, vid_name = mode.shape_names()
        acc, vid = shapes.get(acc_name), shapes.get(vid_name)
        at = None
        if acc is not None and len(sensors) and len(acc.node_ids) == len(sensors):
            at = np.array([np.dot(acc.values[i], s.direction) for i, s in enumerate(sensors)])
        at_video = None
        if vid is not None and results.geometry is not None and len(sensors):
            pts = _node_points(results, vid)
            at_video = np.array([np.dot(v, s.direction) for v, s in
                                 zip(_interpolate(pts, vid.values, np.array([s.position_m for s in sensors]), 16),
                                     sensors)])
        return replace(mode, sensors_accel=at, sensors_video=at_video)

    grey = doc.not_judged()
    out = [at_sensors(Mode(k + 1, m.freq_hz, m.damping, macs.get(k, float("nan")), not_judged=grey.get(k, "")))
           for k, m in enumerate(doc.modes)]
    # the ODS lines (the modal frequencies by default, or those asked for with `odsplat analyze --ods F`)
    out += [at_sensors(Mode(k + 1, line.freq_hz, 0.0, line.mac, kind="ods")) for k, line in enumerate(doc.ods)]
    if out and results is None:
        notes.append("no results.h5: mode shapes unavailable")
    return tuple(out)


def _node_points(results, shape) -> np.ndarray:
    """(P, 3) metres: where a shape of results.h5 is given, its nodes' coordinates in the geometry."""
    node = {int(i): k for k, i in enumerate(results.geometry.node_ids)}
    return results.geometry.coords_m[[node[int(i)] for i in shape.node_ids]]


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


def _mode_shape_on(results, mode: Mode, scene: Scene):
    """What computes the mode's video shape (m/N) on every Gaussian, or None without one: the analysis's surface
    residues, inverse-distance interpolated from the 8 nearest surface points; zero further than 3 point spacings
    from any, and on the background (it moves with no mode: its shapes are noise, and the analysis keeps them out of
    its own)."""
    if results is None or results.geometry is None:
        return None
    vid = next((s for s in results.shapes if s.name == mode.shape_names()[1]), None)
    if vid is None:
        return None

    def shape() -> np.ndarray:
        pts = _node_points(results, vid)
        spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])) if len(pts) > 1 else 1.0
        g = _interpolate(pts, vid.values, scene.means_m.astype(float), SHAPE_NEIGHBOURS, 3 * spacing)
        return (g * scene.structure[:, None]).astype(np.complex64)

    return shape


def _surface(results, modes: tuple[Mode, ...], scene: Scene) -> tuple[Surface | None, tuple[Mode, ...]]:
    """The structure's surface (`analysis.surface_mesh` over the points the video's shapes are given at) and each
    mode's shape at its vertices; (None, the modes) where the analysis has no video shape or the points span no
    surface."""
    if results is None or results.geometry is None:
        return None, modes
    shapes = {s.name: s for s in results.shapes if s.name.startswith("video ")}
    if not shapes:
        return None, modes
    first = next(iter(shapes.values()))
    ids, pts = np.asarray(first.node_ids, int), _node_points(results, first)
    pick, faces = surface_mesh(pts)
    if not len(faces):
        return None, modes
    nearest = cKDTree(scene.means_m).query(pts[pick])[1]
    surface = Surface(pts[pick], faces, np.asarray(nearest, int))
    at = {int(i): k for k, i in enumerate(ids[pick])}

    def on_surface(m: Mode) -> np.ndarray | None:
        vid = shapes.get(m.shape_names()[1])
        if vid is None:
            return None
        out = np.zeros((len(pick), 3), complex)
        for i, v in zip(vid.node_ids, np.asarray(vid.values)):
            if int(i) in at:
                out[at[int(i)]] = v
        return out

    return surface, tuple(replace(m, surface=on_surface(m)) for m in modes)


def _frfs(results, sensors):
    if results is None or not results.frfs:
        return np.zeros(0), np.zeros((0, 0), complex), ()
    frfs = [f for f in results.frfs if f.name.startswith("H1 ")] or list(results.frfs)
    freq = np.asarray(frfs[0].freq_hz, float)
    h1 = np.array([np.asarray(f.values) for f in frfs if len(f.values) == len(freq)])
    return freq, h1, tuple(f.name for f in frfs if len(f.values) == len(freq))


def aligned_frame(data: ViewerData, take: str, time_s: float) -> np.ndarray | None:
    """(H, W) uint8: a capture camera's real frame on sync's common grid nearest time_s (impact-locked), or None
    where the capture has no aligned frames for that take."""

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
        with AlignedTake(capture, path, generation) as f:
            k = int(np.argmin(np.abs(f.times_s - time_s)))
            frame = np.asarray(f.read_frames(k, k + 1)[0], float)
    except OdsplatError as e:
        log.warning("%s", e)
        return None
    frame = frame[..., 0] if frame.ndim == 3 else frame
    lo, hi = np.percentile(frame, (0.5, 99.5))
    return np.round(np.clip((frame - lo) / max(hi - lo, 1e-9), 0, 1) * 255).astype(np.uint8)


__all__ = ["aligned_frame", "load_viewer"]
