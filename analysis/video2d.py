"""One camera, no force: the structure's modes from the video alone, in the image plane.

Points are picked where the first frame is textured (Shi-Tomasi, `tracking.good_points`) and tracked through every
frame (`tracking.track_points`); the points that move above their own noise carry the output-only identification
(`oma.identify`: FDD and SSI-cov, the stabilisation chart). Each mode's 2D shape is known as well as its peak stands
above the channels' noise along it: the MAC that noise allows is snr / (1 + snr) (OMAMode.snr); under 0.95 the mode
is below the floor, reported and not judged. Each mode above the floor gets its shape drawn on the frame and an
amplified clip (`clips.py`). Results go to derived/analysis/video2d.json and video2d.npz (this module is their one
reader and writer), figures to derived/analysis/plots/, clips to derived/analysis/clips/.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.processing import luma
from odsplat.spine.atomic import atomic_open, atomic_write_text
from odsplat.spine.checks import Range, check_fields, maybe
from odsplat.spine.contract import check, describe, plain
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.manifest import load_json, utc_now
from odsplat.spine.store import Capture

from .clips import band_hz
from .oma import OMAResult, identify
from .tracking import METHODS, edge_points, good_points, grid_points, track_points

log = logging.getLogger(__name__)

KIND = "odsplat.video2d"
SCHEMA = 1
FLOOR_MAC = 0.95          # a shape the noise allows less than this MAC to is below the floor
MOVING_SNR = 10.0         # a point moves when its motion's variance in the band is this many times its noise's
VIDEO_BAND = 0.45         # modes are sought below this fraction of the frame rate
MAX_PEAKS = 3             # FDD peaks that no mode explains, reported as ODS lines
POINT_LAYOUTS = ("texture", "grid", "edges")
NOISE_FRAMES = 32         # the camera's noise is fitted on the take's first frames


@dataclass(frozen=True)
class Video2DSettings:
    tracker: str = "gradient"                 # tracking.METHODS
    window_px: int = 11                       # the tracking window's side (odd): small, so that a window stays on
    #                                           one part of the structure (15 px read 0.89-0.96 against 0.96-0.99
    #                                           on hil_sim's arm at 192x144 px)
    max_points: int = 300                     # points tracked, strongest texture first
    min_distance_px: float | None = None      # between points; None: half the window's side (a grid: its side)
    points_px: tuple[tuple[float, float], ...] | None = None  # track these (x, y) instead of picking points
    layout: str = "texture"                   # where points are picked (POINT_LAYOUTS): "texture" (Shi-Tomasi, the
    #                                           strongest first), "grid" (every min_distance_px where the texture
    #                                           can be tracked) or "edges" (on the outlines, Canny)
    fmin_hz: float | None = None              # the identification's band; None: 3 lines of the FDD
    fmax_hz: float | None = None              # None: 0.45 x the frame rate
    n_modes: int | None = None                # keep the strongest this many
    approx_freq_hz: tuple[float, ...] | None = None  # pick these modes instead of automatic selection
    scale_m_per_px: float | None = None       # the image scale at the structure (metres per pixel); None: from the
    #                                           capture's tags seen in the first frame (tag_scale), where there are
    clips: bool = True                        # an amplified clip of each mode above the floor (clips.py)
    clip_frames: int = 600                    # at most this many frames per clip

    def __post_init__(self) -> None:
        if self.layout not in POINT_LAYOUTS:
            raise InputError("analyze.video2d.layout", f"expected one of {', '.join(POINT_LAYOUTS)}; got "
                                                        f"{self.layout!r}")
        if self.tracker not in METHODS:
            raise InputError("analyze.video2d.tracker", f"expected one of {', '.join(METHODS)}; got {self.tracker!r}")
        check_fields(self, {"window_px": Range(at_least=5, at_most=255, integer=True),
                            "points_px": maybe(Range(at_least=-1e5, at_most=1e5)),
                            "max_points": Range(at_least=1, at_most=5000, integer=True),
                            "min_distance_px": maybe(Range(above=0, at_most=1e4)),
                            "fmin_hz": maybe(Range(at_least=0, at_most=1e7)),
                            "fmax_hz": maybe(Range(above=0, at_most=1e7)),
                            "n_modes": maybe(Range(at_least=1, at_most=100, integer=True)),
                            "approx_freq_hz": maybe(Range(above=0, at_most=1e7)),
                            "scale_m_per_px": maybe(Range(above=0, at_most=10)),
                            "clip_frames": Range(at_least=16, at_most=100_000, integer=True)})
        if self.window_px % 2 == 0:
            raise InputError("analyze.video2d.window_px", f"expected an odd number of pixels; got {self.window_px}")


@dataclass(frozen=True)
class Mode2D:
    """One mode found in the video: its frequency, damping and 2D shape over the moving points ((P, 2) complex, x
    and y, largest component 1), how well the noise lets the shape be known, and whether that is above the floor."""

    freq_hz: float
    damping: float
    mpc: float
    snr: float
    floor_mac: float           # the MAC the noise allows the shape: snr / (1 + snr)
    above_floor: bool
    amplitude_px: float        # the mode's rms motion at its largest point, in its band (px)
    shape: np.ndarray          # (P, 2) complex over the moving points
    clip: str | None = None    # relative to derived/analysis/
    clip_alpha: float | None = None  # its magnification
    kind: str = "mode"         # "mode": a pole SSI found stable; "peak": an FDD peak no pole explains (a short or
    #                            steady record's dominant oscillation), its shape the ODS at that line, no damping

    @property
    def label(self) -> str:
        """What it is called in figures, clips and the summary."""
        return "mode" if self.kind == "mode" else "FDD peak"


@dataclass(frozen=True)
class Video2DResult:
    """The 2D path's result for one take (the first view's)."""

    take: str
    view: int | None
    fps: float
    n_frames: int
    tracker: str
    window_px: int
    points_px: np.ndarray      # (P, 2) every point tracked
    moving: np.ndarray         # (P,) bool: those that move above their noise (the shapes' points)
    noise_px: np.ndarray       # (P, 2) each point's rms noise, x and y, over the band
    crlb_px: np.ndarray        # (P, 2) each point's Cramér-Rao bound, x and y (one frame against the first)
    camera_noise: str          # the camera's noise model the bound rests on
    displacement_px: np.ndarray  # (T, P, 2) float32, against frame 0
    modes: tuple[Mode2D, ...]
    oma: OMAResult | None
    scale_m_per_px: float | None
    notes: tuple[str, ...] = ()
    files: dict[str, str] = field(default_factory=dict)
    sensor_view: Any = None    # sensorview.SensorView: the accelerometers the view sees, at these modes

    def text(self) -> str:
        """A few lines for the engineer."""
        unit = f", {1e3 * self.scale_m_per_px:.4g} mm/px" if self.scale_m_per_px else ""
        lines = [f"video only ({self.take}, {self.n_frames} frames at {self.fps:g} fps): {int(self.moving.sum())} of "
                 f"{len(self.moving)} points move above their noise ({self.tracker} tracker{unit})"]
        for k, m in enumerate(self.modes, 1):
            state = "above the floor" if m.above_floor else "BELOW THE FLOOR (not judged)"
            damping = f"damping {100 * m.damping:5.2f} %" if m.kind == "mode" else "no pole"
            lines.append(f"  {m.label} {k}: {m.freq_hz:8.3f} Hz  {damping}  MPC {m.mpc:.2f}  "
                         f"{m.amplitude_px:.3g} px rms  shape known to MAC {m.floor_mac:.3f}: {state}")
        if not self.modes:
            lines.append("  no mode found: " + ("; ".join(self.notes) or "nothing stands above the noise"))
        lines += [f"  note: {n}" for n in self.notes]
        if self.sensor_view is not None:
            lines.append(self.sensor_view.text())
        return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ frames

def _take(capture: Capture, takes: str) -> tuple[str, int | None]:
    """The first view's first selected take with frames."""
    records = [r for r in capture.select_takes(takes) if r.n_frames]
    if not records:
        raise OdsplatError(f"{capture.root}: no {'' if takes == 'all' else 'accepted '}take with frames to analyse"
                           + ("" if takes == "all" else capture.unchecked_hint()))
    views = sorted({r.view for r in records if r.view is not None})
    first = [r for r in records if r.view == views[0]] if views else records
    return first[0].name, first[0].view


def mono(block: np.ndarray) -> np.ndarray:
    """Frames (n, H, W) or (n, H, W, 3) as float32 luma (n, H, W) (`processing.luma`, what magnification reads)."""
    return luma(np.asarray(block, np.float32))


def frames(capture: Capture, take: str, stop: int | None = None):
    """The take's frames as mono float32 (H, W), one by one."""
    with capture.open_take(take) as r:
        for block in r.iter_frames(64, 0, stop):
            yield from mono(block)


def first_frame(capture: Capture, take: str) -> np.ndarray:
    with capture.open_take(take) as r:
        return mono(r.read_frames(0, 1))[0]


# ------------------------------------------------------------------------------------------------ points

def pick_points(frame: np.ndarray, s: Video2DSettings) -> np.ndarray:
    """The points to track: those given, or as `layout` places them: the most textured ones (at least 0.5 % of the
    strongest's texture, spaced half a window apart), a grid (a window apart where there is texture to track) or the
    edges (half a window apart)."""
    if s.points_px is not None:
        p = np.asarray(s.points_px, float)
        if p.ndim != 2 or p.shape[1] != 2 or len(p) == 0:
            raise InputError("analyze.video2d.points_px", f"expected a list of [x, y] pixels; got shape {p.shape}")
        return p
    spacing = s.min_distance_px or 0.5 * s.window_px
    if s.layout == "grid":
        return grid_points(frame, spacing_px=s.min_distance_px or s.window_px, window_px=s.window_px,
                           max_points=s.max_points)
    if s.layout == "edges":
        return edge_points(frame, spacing_px=spacing, window_px=s.window_px, max_points=s.max_points)
    return good_points(frame, max_points=s.max_points, min_distance_px=spacing, window_px=s.window_px,
                       quality_level=0.005)


def _band_noise(noise_psd: np.ndarray, band_hz: tuple[float, float]) -> np.ndarray:
    """Each channel's rms noise over the band (white at its PSD)."""
    return np.sqrt(noise_psd * max(band_hz[1] - band_hz[0], 0.0))


def moving_points(d: np.ndarray, fps: float, band_hz: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(P,) bool: the tracked points whose motion's variance in the band is MOVING_SNR times their noise's, and
    each point's rms noise (P, 2), from the noise level (`oma.noise_psd`) of their own displacement."""
    from .oma import noise_psd

    T, P, _ = d.shape
    x = (d - d.mean(axis=0)).reshape(T, 2 * P).astype(np.float64)
    level = noise_psd(x, fps, fmin_hz=band_hz[0], fmax_hz=band_hz[1])
    noise = _band_noise(level, band_hz).reshape(P, 2)
    var = x.var(axis=0).reshape(P, 2)
    snr = var.sum(axis=1) / np.maximum((noise ** 2).sum(axis=1), 1e-30)
    return snr >= MOVING_SNR, noise


# ------------------------------------------------------------------------------------------------ the analysis

def _tag_m_per_px(corners_px: np.ndarray, size_m: float) -> float:
    """Metres per pixel at a tag's centre, along the direction its plane is not foreshortened: the tag square's
    homography onto its corners, its Jacobian at the centre, over the larger singular value (px per metre). A tag
    seen obliquely is foreshortened across its tilt only; along the tilt's axis it keeps the scale at its depth."""
    import cv2

    h = 0.5 * size_m
    square = np.array([[-h, -h], [h, -h], [h, h], [-h, h]], np.float32)
    H = cv2.getPerspectiveTransform(square, np.asarray(corners_px, np.float32))
    # d(H x) / dx at x = 0: (H[:2, :2] w - H[:2, 2] H[2, :2]) / w^2, w = H[2, 2]
    w = H[2, 2]
    J = (H[:2, :2] * w - np.outer(H[:2, 2], H[2, :2])) / w ** 2
    return float(1.0 / np.linalg.svd(J, compute_uv=False)[0])


def tag_scale(capture: Capture, frame: np.ndarray) -> tuple[float | None, str]:
    """Metres per pixel from the capture's AprilTags seen in the frame: each tag's (`_tag_m_per_px`, from its
    layout's size_m); the tags on the structure where any is seen, else every tag of known size; the median
    over them. A scale at the tags' depth: points nearer or further see the same motion larger or smaller."""
    layout = capture.manifest.tags
    if layout is None:
        return None, "no tag layout in the capture: motion in pixels (give analyze.video2d.scale_m_per_px)"
    from odsplat.spine.tags import detect_tags

    known = {t.id: t for t in layout.tags}
    found = []
    for d in detect_tags(frame, family=layout.family):
        place = known.get(d.id)
        size = (place.size_m if place is not None and place.size_m else None) or layout.size_m
        if size:
            found.append((place is not None and place.on_structure, d.id, _tag_m_per_px(d.corners_px, size)))
    if not found:
        return None, "no tag of known size seen in the first frame: motion in pixels"
    on = [f for f in found if f[0]] or found
    scale = float(np.median([f[2] for f in on]))
    where = "on the structure" if on[0][0] else "in the view"
    return scale, (f"scale {1e3 * scale:.4g} mm/px from tag(s) {sorted(f[1] for f in on)} {where}: true at their "
                   "depth, not at every point")


def point_bounds(capture: Capture, take: str, first: np.ndarray, points: np.ndarray, window_px: int
                 ) -> tuple[np.ndarray, str]:
    """Each point's Cramér-Rao bound (P, 2) (x, y) in px: the Fisher information of its window in the first frame
    (`crlb.fisher_2d`) under the camera's noise fitted on the first NOISE_FRAMES frames (`crlb.fit_noise_model`:
    pixels that move are left out of that fit, so a take need not start at rest); and the noise model in words."""
    from .crlb import fisher_2d, fit_noise_model, sigma_2d_px

    with capture.open_take(take) as r:
        raw = r.read_frames(0, min(NOISE_FRAMES, r.n_frames))
        bit_depth = r.bit_depth
    model = fit_noise_model(raw, bit_depth)
    return sigma_2d_px(fisher_2d(first, model, points, window_px)), model.describe()


def _band(s: Video2DSettings, fps: float) -> tuple[float | None, float]:
    hi = min(s.fmax_hz or VIDEO_BAND * fps, 0.5 * fps)
    if s.fmin_hz is not None and s.fmin_hz >= hi:
        raise InputError("analyze.video2d.fmin_hz", f"expected below the band's top, {hi:g} Hz; got {s.fmin_hz:g}")
    return s.fmin_hz, hi


def _amplitude(x: np.ndarray, fps: float, f_hz: float, shape: np.ndarray) -> float:
    """The mode's rms motion at its largest point: x (T, C) band-passed over its band (`clips.band_hz`: what its
    clip magnifies), at the channel pair where the shape is largest."""
    from scipy.signal import butter, sosfiltfilt

    lo, hi = band_hz(f_hz, fps)
    if not 0 < lo < hi:
        return float("nan")
    sos = butter(2, [lo, hi], btype="bandpass", fs=fps, output="sos")
    P = x.shape[1] // 2
    p = int(np.argmax(np.abs(shape.reshape(P, 2)).sum(axis=1)))
    y = sosfiltfilt(sos, x[:, 2 * p:2 * p + 2], axis=0)
    return float(np.sqrt((y ** 2).sum(axis=1).mean()))


def floor_mac(snr: float) -> float:
    """The MAC noise allows a shape whose peak stands snr above the noise along it: snr / (1 + snr); 1 without
    noise."""
    return 1.0 if math.isinf(snr) else snr / (1.0 + snr)


def _peaks(x: np.ndarray, fps: float, oma: OMAResult, modes_hz: list[float]) -> list[Mode2D]:
    """The FDD's peaks that no mode explains (more than 3 lines from every mode's frequency), at most MAX_PEAKS, the
    strongest: each an operational deflection shape at its line (`oma.ods_at`), known as well as its peak stands
    above the noise along it."""
    from .oma import mpc, normalise_shape, ods_at, shape_snr

    spectrum = oma.fdd
    out = []
    for f in spectrum.peaks_hz(*oma.band_hz):
        if any(abs(f - g) <= 3 * spectrum.df_hz for g in modes_hz) or f <= 0:
            continue
        shape = normalise_shape(ods_at(x, fps, f, nperseg=spectrum.nperseg))
        snr = shape_snr(float(spectrum.singular_values[spectrum.line(f), 0]), shape, oma.noise_psd)
        floor = floor_mac(snr)
        out.append(Mode2D(float(f), float("nan"), float(mpc(shape)[0]), snr, floor, floor >= FLOOR_MAC,
                          _amplitude(x, fps, float(f), shape), shape.reshape(-1, 2), kind="peak"))
    return sorted(out, key=lambda m: -m.snr)[:MAX_PEAKS]


def analyze_video(capture: Capture, s: Video2DSettings, *, takes: str = "accepted") -> Video2DResult:
    """The 2D output-only analysis of the capture's first view (see the module's doc)."""
    take, view = _take(capture, takes)
    with capture.open_take(take) as r:
        fps, n_frames = r.fps, r.n_frames
    if not fps:
        raise InputError(take, "the take has no frame rate: frequencies cannot be measured")
    first = first_frame(capture, take)
    notes: list[str] = []
    scale = s.scale_m_per_px
    if scale is None:
        scale, why = tag_scale(capture, first)
        notes.append(why)
    points = pick_points(first, s)
    if not len(points):
        raise OdsplatError(f"{take}: no textured point to track in the first frame")
    tracks = track_points(frames(capture, take), points, method=s.tracker, window_px=s.window_px, progress=True)
    crlb, camera = point_bounds(capture, take, first, points, s.window_px)
    d = tracks.displacement_px
    tracked = np.isfinite(d).all(axis=(0, 2))
    if not tracked.all():
        notes.append(f"{int((~tracked).sum())} of {len(tracked)} points were lost and are left out")
    lo, hi = _band(s, fps)
    moving = np.zeros(len(points), bool)
    noise = np.full((len(points), 2), np.nan)
    if tracked.any():
        moving[tracked], noise[tracked] = moving_points(d[:, tracked], fps, (lo or 0.0, hi))
    if moving.sum() < 2:
        notes.append(f"{int(moving.sum())} point(s) move above their noise: the video shows no motion to analyse")
        return Video2DResult(take, view, fps, n_frames, s.tracker, s.window_px, points, moving, noise, crlb, camera,
                             d.astype(np.float32), (), None, scale, tuple(notes))
    x = (d[:, moving] - d[:, moving].mean(axis=0)).reshape(len(d), -1).astype(np.float64)
    oma = identify(x, fps, fmin_hz=lo, fmax_hz=hi, n_modes=s.n_modes, approx_freq_hz=s.approx_freq_hz)
    modes = []
    for m in oma.modes:
        floor = floor_mac(m.snr)
        modes.append(Mode2D(m.freq_hz, m.damping, m.mpc, m.snr, floor, floor >= FLOOR_MAC,
                            _amplitude(x, fps, m.freq_hz, m.shape), m.shape.reshape(-1, 2)))
    modes += _peaks(x, fps, oma, [m.freq_hz for m in modes])
    below = [m for m in modes if not m.above_floor]
    if below:
        notes.append(f"{len(below)} mode(s) below the floor ({', '.join(f'{m.freq_hz:.1f}' for m in below)} Hz): "
                     f"the noise leaves their shapes known to a MAC under {FLOOR_MAC}; their frequencies stand, their "
                     "shapes are not judged")
    if oma.harmonics:
        notes.append("steady sines at " + ", ".join(f"{h.freq_hz:.2f}" for h in oma.harmonics)
                     + " Hz look like forced harmonics, not modes (their coordinate as flat as a sine's, its envelope "
                       "steady): left out")
    return Video2DResult(take, view, fps, n_frames, s.tracker, s.window_px, points, moving, noise, crlb, camera,
                         d.astype(np.float32), tuple(modes), oma, scale, tuple(notes))


# ------------------------------------------------------------------------------------------------ the files

def _doc(result: Video2DResult, capture: Capture, s: Any) -> dict:
    prov = describe(capture.id, KIND, SCHEMA, s)
    modes = [dict(kind=m.kind, freq_hz=m.freq_hz, damping=m.damping if np.isfinite(m.damping) else None,
                  mpc=m.mpc, snr=m.snr, floor_mac=m.floor_mac,
                  above_floor=m.above_floor, amplitude_px=m.amplitude_px,
                  amplitude_m=None if result.scale_m_per_px is None else m.amplitude_px * result.scale_m_per_px,
                  clip=m.clip, clip_alpha=m.clip_alpha) for m in result.modes]
    return {**prov.header(), "created_utc": utc_now(), "capture": capture.root.name, "take": result.take,
            "view": result.view, "fps": result.fps, "n_frames": result.n_frames, "tracker": result.tracker,
            "window_px": result.window_px, "n_points": int(len(result.moving)), "n_moving": int(result.moving.sum()),
            "scale_m_per_px": result.scale_m_per_px, "floor_mac": FLOOR_MAC, "modes": modes,
            "camera_noise": result.camera_noise, **_floors(result),
            "band_hz": None if result.oma is None else list(result.oma.band_hz),
            "notes": list(result.notes), "files": dict(result.files), "settings": plain(s),
            "sensor_view": None if result.sensor_view is None else result.sensor_view.document()}


def _floors(result: Video2DResult) -> dict:
    """The moving points' noise floor against their Cramér-Rao bound: medians over the points, px and ratio."""
    m = result.moving & np.isfinite(result.noise_px).all(axis=1) & np.isfinite(result.crlb_px).all(axis=1)
    if not m.any():
        return {"noise_px_median": None, "crlb_px_median": None, "noise_over_crlb_median": None}
    noise, bound = np.hypot(*result.noise_px[m].T), np.hypot(*result.crlb_px[m].T)
    return {"noise_px_median": float(np.median(noise)), "crlb_px_median": float(np.median(bound)),
            "noise_over_crlb_median": float(np.median(noise / np.maximum(bound, 1e-12)))}


def write_video2d(capture: Capture, result: Video2DResult, settings: Any, files: dict[str, str]) -> Video2DResult:
    """derived/analysis/video2d.npz (points, tracks, shapes, spectrum) and video2d.json (last: it lists them)."""
    capture.paths.ensure(capture.paths.analysis_dir)
    arrays = dict(points_px=result.points_px, moving=result.moving, noise_px=result.noise_px, crlb_px=result.crlb_px,
                  displacement_px=result.displacement_px,
                  freq_hz=np.array([m.freq_hz for m in result.modes], float),
                  shapes=np.array([m.shape for m in result.modes], complex).reshape(
                      len(result.modes), int(result.moving.sum()), 2))
    if result.oma is not None:
        arrays.update(fdd_freq_hz=result.oma.fdd.freqs_hz, fdd_singular_values=result.oma.fdd.singular_values,
                      noise_psd=result.oma.noise_psd)
    with atomic_open(capture.paths.video2d_npz, "wb") as f:
        np.savez_compressed(f, **arrays)
    result = Video2DResult(**{**result.__dict__, "files": {**files, "data": "video2d.npz"}})
    atomic_write_text(capture.paths.video2d_json, json.dumps(_doc(result, capture, settings), indent=1, allow_nan=False,
                                                        default=_json_default) + "\n")
    return result


def _json_default(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    raise TypeError(f"not JSON: {type(v).__name__}")


def read_video2d(capture: Capture) -> tuple[dict, dict[str, np.ndarray]]:
    """video2d.json and the arrays of video2d.npz, checked (kind, schema, capture)."""
    path = capture.paths.video2d_json
    doc = load_json(path, missing="no 2D analysis (run `odsplat analyze` first)")
    check(doc, path, kind=KIND, schema_version=SCHEMA, capture_id=capture.id)
    with np.load(capture.paths.video2d_npz) as z:
        arrays = {k: z[k] for k in z.files}
    return doc, arrays


def has_video2d(capture: Capture) -> bool:
    return capture.paths.video2d_json.is_file()


def discard_video2d(capture: Capture) -> None:
    """Remove an earlier 2D result (the input-output path ran instead)."""
    for p in (capture.paths.video2d_json, capture.paths.video2d_npz):
        if p.is_file() and not p.is_symlink():
            p.unlink()


def plots_dir(capture: Capture) -> Path:
    return capture.paths.ensure(capture.paths.analysis_dir / "plots")


__all__ = ["FLOOR_MAC", "KIND", "Mode2D", "Video2DResult", "Video2DSettings", "analyze_video", "discard_video2d",
           "first_frame", "frames", "has_video2d", "mono", "pick_points", "read_video2d",
           "write_video2d"]
