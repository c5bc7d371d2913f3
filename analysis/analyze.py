"""`analyze_capture`: FRFs and modes from the hammer and accelerometers of every take, the video's 3D shapes
from the dynamic Gaussians with the accelerometer poles, their correlation, and the exports in derived/analysis/.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from odsplat.spine.checks import (
    DURATION_S,
    FRACTION,
    FREQUENCY_HZ,
    MAX_DURATION_S,
    MAX_FREQUENCY_HZ,
    MAX_LENGTH_M,
    NEIGHBOURS,
    RANK,
    Range,
    check_choice,
    check_fields,
    maybe,
    shown,
)
from odsplat.spine.contract import describe, plain
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import utc_now
from odsplat.spine.store import Capture
from odsplat.sync import load_sync

from .band import default_band_hz, frf_peaks
from .correlation import Correlation, auto_mac, correlate
from .crlb import direction_floor, displacement_bound
from .crosscheck import crosscheck_views, views_seeing
from .document import KIND, SCHEMA
from .ema import ModalFit, fit_modes, pole_freq_hz
from .frf import FRFResult, FRFSettings, check_frf_hit, estimate_frf
from .imagepoles import ImagePoles, image_poles
from .noise import (
    FLOOR_MAC,
    MAX_SEPARATION_GAIN,
    NoiseFloor,
    design_gains,
    full_field_expected_mac,
    noise_floor,
    real_modes,
)
from .notes import (
    MIN_SENSOR_R2,
    BelowNoiseFloor,
    ComplexMode,
    ModesAboveVideoBand,
    ModesNotDiscriminated,
    ModesNotSeparated,
    Note,
    OdsCarriedByNoise,
    SensorsNotSeen,
    UnplacedSensors,
    WindowTooShort,
    band_findings,
)
from .ods import (
    DECAY_T_MIN_S,
    POLE_MIN_SIGNIFICANCE,
    DecayFit,
    SurfaceMotion,
    adjusted_r2,
    fit_decay,
    receptance,
    record_ranks,
    stable_poles,
)
from .outputs import write_outputs
from .plots2d import write_clips, write_figures
from .result import AnalysisResult, Sensor, VideoModes
from .sensorview import sensor_ods, sensor_view, take_force
from .triangulate import MIN_VIEWS, triangulation_check
from .verdict import DISCRIMINATION, NOT_DISCRIMINATED, Verdict, crosscheck_verdict, mac_verdict
from .video2d import (
    Video2DResult,
    Video2DSettings,
    analyze_video,
    discard_video2d,
    first_frame,
    frames,
    write_video2d,
)

log = logging.getLogger(__name__)


VIDEO_BAND = 0.45     # the camera's poles are sought below this fraction of its frame rate


MIN_CYCLES = 0.5    # below this share of a mode's period in the video's window its shape cannot be read
# A point the structure rules keep is left out as isolated when its ISOLATED_K-th nearest kept neighbour lies further
# than ISOLATED_FACTOR times the median such distance: the rules above keep whatever stands above the floor, and on
# the demo two nodes on the floor's tag boards (2-3 cm up, half a metre from the structure) floated in the figures.
ISOLATED_K = 3
ISOLATED_FACTOR = 5.0
# ... and, the rule above taking out one point at a time, a clump of kept points apart from the rest (no kept point
# within FLOATER_GAP times their spacing, the median distance to the FLOATER_K-th neighbour) that holds under
# FLOATER_SHARE of them is left out as a floater: the stray Gaussians a fit leaves beside the structure (on the
# demo, 124 of 2249 in the viewer's structure-only view; the report's 3D surface drops them as well).
FLOATER_K = 8
FLOATER_GAP = 2.0
FLOATER_SHARE = 0.01


@dataclass(frozen=True)
class AnalyzeSettings:
    force_channel: str | None = None                 # None: the capture's one force channel
    response_channels: tuple[str, ...] | None = None  # None: every acceleration channel placed on the structure
    takes: str = "accepted"                          # or "all"
    frf: FRFSettings = field(default_factory=FRFSettings)
    pretrigger_s: float = 0.005                      # kept before each hit's onset
    record_s: float | None = None                    # each hit's segment; None: as long as every take allows
    fmin_hz: float | None = None                     # modal fit band; None: 3 frequency lines
    fmax_hz: float | None = None                     # None: where the force spectrum is 20 dB down, at most
                                                     # 0.4 x the DAQ rate (analysis/band.py)
    max_order: int | None = None                     # LSCF; None: 120, at most half the band's lines (ema.py)
    approx_freq_hz: tuple[float, ...] | None = None  # pick these poles instead of automatic selection
    ods_freq_hz: tuple[float, ...] | None = None     # ODS lines; None: the modal frequencies
    video: bool = True                               # use derived/reconstruction when it is there
    floor_margin_m: float | None = 0.01              # the structure's points: above the floor (z = 0) by this
    structure_box_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None  # min, max corner
    structure_motion: bool | None = None             # ... and moving above their noise; None: only where no box
                                                     # is given and the capture has no floor tags
    measured_motion: bool = True                     # fit the shapes to its unfiltered motion when it has one
    real_modes: bool = True                          # each mode's shape on its common phase where what lies out
    #                                                  of it is noise (noise.real_modes; complex modes stay)
    direction_floor: bool = True                     # a mode's motion along a world axis that lies below the floor
    #                                                  in that direction nearly everywhere (crlb.DirectionFloor
    #                                                  .noise_axes) is the noise's: left out of its shape (zero), as
    #                                                  the report says, for the modes above the floor (those below
    #                                                  it are flagged whole); the sensors' reading stays
    min_opacity: float = 0.5
    k_neighbours: int = 16                           # Gaussians read at each sensor
    outlier_factor: float | None = 2.0               # drop those whose motion strays this far (SurfaceMotion.at_points)
    video_ranks: tuple[int, ...] | None = None       # the matrix pencil's, for the video's own poles; None:
    #                                                  ods.record_ranks (24/32/40 where the record holds them, else
    #                                                  16/20/24, lowered where the timesteps cannot hold them)
    crosscheck_views: int = 6                        # takes whose 2D tracks check the 3D motion (0: none)
    crosscheck_points: int = 30
    triangulate_views: int = 8                       # posed, synced takes whose 2D tracks are triangulated to 3D
    #                                                  as a check of the Gaussians' shapes (triangulate.py; under
    #                                                  3: none)
    triangulate_points: int = 24
    image_poles: bool = True                         # poles from the synced takes' raw frames (imagepoles.py)
    plots: bool = True                               # the figures and animations (plots/); the report inlines them
    image_ranks: tuple[int, ...] | None = None       # None: as video_ranks, from the frames after the impact
    image_pixel_fraction: float = 0.05               # the most textured pixels of each view
    video2d: Video2DSettings = field(default_factory=Video2DSettings)  # a capture without force: the 2D path
    sensor_view: bool = True                         # without a 3D video side, the accelerometers one synced view
    #                                                  sees against its 2D tracks there (sensorview.py)
    sensor_view_takes: int = 4                       # that view's takes fitted and averaged
    sensor_view_max_tilt_deg: float = 15.0           # a sensor's axis may lie this far out of the image plane

    def __post_init__(self) -> None:
        check_choice("AnalyzeSettings.takes", self.takes, ("accepted", "all"))
        # max_order: LSCF fits every order up to it, and 120 already over-fits any band; the ranks: the matrix
        # pencil's, each at most half the timesteps; the cross-check tracks points in takes, a few tens of each;
        # outlier_factor: below 1 it can leave no Gaussian.
        check_fields(self, {
            "pretrigger_s": Range(at_least=0, at_most=MAX_DURATION_S), "record_s": maybe(DURATION_S),
            "fmin_hz": maybe(Range(at_least=0, at_most=MAX_FREQUENCY_HZ)), "fmax_hz": maybe(FREQUENCY_HZ),
            "max_order": maybe(Range(at_least=1, at_most=500, integer=True)), "approx_freq_hz": maybe(FREQUENCY_HZ),
            "ods_freq_hz": maybe(FREQUENCY_HZ), "min_opacity": FRACTION, "k_neighbours": NEIGHBOURS,
            "video_ranks": maybe(RANK), "crosscheck_views": Range(at_least=0, at_most=1000, integer=True),
            "crosscheck_points": Range(at_least=1, at_most=10_000, integer=True), "image_ranks": maybe(RANK),
            "triangulate_views": Range(at_least=0, at_most=1000, integer=True),
            "triangulate_points": Range(at_least=3, at_most=10_000, integer=True),
            "sensor_view_takes": Range(at_least=1, at_most=1000, integer=True),
            "sensor_view_max_tilt_deg": Range(at_least=0, at_most=90),
            "image_pixel_fraction": Range(above=0, at_most=1),
            "floor_margin_m": maybe(Range(at_least=0, at_most=MAX_LENGTH_M)),
            "outlier_factor": maybe(Range(at_least=1, at_most=1e6))})
        if self.structure_box_m is not None:
            try:
                box = np.asarray(self.structure_box_m, float)
            except (TypeError, ValueError, OverflowError):
                box = None
            if (box is None or box.shape != (2, 3) or not np.all(np.abs(box) <= MAX_LENGTH_M)
                    or np.any(box[0] >= box[1])):
                raise InputError("AnalyzeSettings.structure_box_m", "expected [[x, y, z] min, [x, y, z] max] in "
                                 f"metres, each within +-{MAX_LENGTH_M:g} and min below max on every axis; got "
                                 f"{shown(self.structure_box_m)}")
        if self.fmin_hz is not None and self.fmax_hz is not None and not self.fmin_hz < self.fmax_hz:
            raise InputError("AnalyzeSettings.fmin_hz",
                             f"expected below fmax_hz={self.fmax_hz:g}; got {self.fmin_hz:g}")


# ------------------------------------------------------------------------------------------- accelerometers

def _channels(capture: Capture, s: AnalyzeSettings) -> tuple[str, tuple[Sensor, ...]]:
    chans = capture.manifest.channels
    where = f"{capture.root / 'capture.json'}: channels"
    if s.force_channel is None:
        forces = [c.name for c in chans if c.kind == "force"]
        if len(forces) != 1:
            raise InputError(where, f"expected exactly one force channel (or name one); found {forces}")
        force = forces[0]
    else:
        force = s.force_channel
        if force not in [c.name for c in chans]:
            raise InputError(where, f"no force channel {force!r}; channels are {[c.name for c in chans]}")
    names = s.response_channels or tuple(c.name for c in chans if c.kind == "acceleration")
    if not names:
        raise InputError(where, "no acceleration channel to analyse")
    sensors = []
    for n in names:
        try:
            c = capture.manifest.channel(n)
        except KeyError:
            raise InputError(where, f"no response channel {n!r}; channels are {[c.name for c in chans]}") from None
        if c.kind != "acceleration":
            raise InputError(f"{where}: {n}", f"a {c.kind} channel; the responses must be acceleration channels")
        if c.position_m is None or c.direction is None:
            sensors.append(Sensor(n))
            continue
        d = np.asarray(c.direction, float)
        sensors.append(Sensor(n, np.asarray(c.position_m, float), d / np.linalg.norm(d)))
    return force, tuple(sensors)


def _reference(capture: Capture, force: str) -> Sensor:
    """The hammer as the manifest's force channel places it: impact point and force direction, where recorded."""
    c = capture.manifest.channel(force)
    d = None if c.direction is None else np.asarray(c.direction, float) / np.linalg.norm(c.direction)
    return Sensor(force, None if c.position_m is None else np.asarray(c.position_m, float), d)


def _take_names(capture: Capture, s: AnalyzeSettings) -> list[str]:
    takes = [t.name for t in capture.select_takes(s.takes) if t.n_samples > 0]
    if not takes:
        raise InputError(capture.root / "capture.json", f"no {s.takes} take with DAQ samples to analyse"
                         + ("" if s.takes == "all" else capture.unchecked_hint()))
    return takes


def _hit_segments(capture: Capture, takes: list[str], force: str, sensors, s: AnalyzeSettings):
    """Every take's hit, cut from pretrigger_s before its onset, all to one length: (H, n), (H, S, n), rate."""
    records, rate = [], None
    for name in takes:
        with capture.open_take(name) as r:
            fs = r.sample_rate_hz
            if rate is not None and abs(fs - rate) > 1e-9 * rate:
                raise InputError(f"takes/{name}.h5", f"DAQ rate {fs} Hz differs from the first take's {rate} Hz")
            rate = fs
            f = r.channel(force).astype(float)
            x = np.stack([r.channel(sn.name).astype(float) for sn in sensors])
        onset = check_frf_hit(f, fs, impacts=s.frf.impacts).onset_index
        if not np.isfinite(onset):
            raise InputError(f"takes/{name}.h5: {force}", "no hammer impact found in the force channel")
        records.append((name, f, x, int(np.floor(onset))))
    pre = int(round(s.pretrigger_s * rate))
    avail = min(len(f) - max(o - pre, 0) for _, f, _, o in records)
    n = avail if s.record_s is None else min(avail, int(round(s.record_s * rate)))
    if n < 64:
        raise InputError("AnalyzeSettings.record_s", f"only {n} samples per hit; the takes are too short")
    F = np.stack([f[max(o - pre, 0):max(o - pre, 0) + n] for _, f, _, o in records])
    X = np.stack([x[:, max(o - pre, 0):max(o - pre, 0) + n] for _, _, x, o in records])
    return F, X, float(rate)


def _band(frf: FRFResult, s: AnalyzeSettings) -> tuple[float, float]:
    """The modal fit band: the DAQ's (analysis/band.py) unless given; the camera's band is the video side's."""
    lo, hi = default_band_hz(frf)
    top = float(frf.freq_hz[-1])
    if s.fmax_hz is not None and s.fmax_hz > top:
        raise InputError("AnalyzeSettings.fmax_hz", f"expected at most the FRF's last line, {top:g} Hz (the DAQ's "
                         f"Nyquist frequency is {frf.sample_rate_hz / 2:g} Hz); got {s.fmax_hz:g}")
    fmax = s.fmax_hz if s.fmax_hz is not None else min(hi, top)
    fmin = s.fmin_hz if s.fmin_hz is not None else lo
    if fmin >= fmax:
        raise InputError("AnalyzeSettings.fmin_hz", f"expected below fmax_hz={fmax:g}; got {fmin:g}")
    for name in ("approx_freq_hz", "ods_freq_hz"):
        outside = [f for f in getattr(s, name) or () if not 0 < f <= top]
        if outside:
            raise InputError(f"AnalyzeSettings.{name}", f"expected frequencies inside the FRF's band, 0 to {top:g} Hz; "
                             f"got {', '.join(f'{f:g}' for f in outside)}")
    return fmin, fmax


# -------------------------------------------------------------------------------------------------- video

def _sync_force(capture: Capture, force: str, poles: np.ndarray) -> np.ndarray:
    """F(lambda_r) of the hammer pulse on the impact-locked timeline, averaged over the synced takes (scaled as
    sync scaled each take's motion when it normalised the impulses)."""

    sync = load_sync(capture)
    if not sync.ok:
        raise InputError(capture.paths.sync_json, "no synced take to take the force pulse from")
    return np.mean([take_force(capture, force, t, poles) for t in sync.ok], axis=0)


def video_modes(capture: Capture, modes: ModalFit, sensors, force: str, s: AnalyzeSettings) -> VideoModes | None:
    path = capture.paths.trajectories_npz
    if not s.video or not path.is_file():
        log.info("no video side: %s", "disabled" if not s.video else f"{path} not found")
        return None
    model = SurfaceMotion.read(path, min_opacity=s.min_opacity, capture_id=capture.id)
    motion, shapes_from = model, "trajectories"
    measured = capture.paths.measured_motion_npz
    if s.measured_motion and measured.is_file():
        # The linear model's unfiltered motion: the fit with known poles below is itself the filter, and recovers
        # modes the model's basis leaves below its noise floor. The model (denoised) still gives the video's own
        # poles and the 2D cross-check.
        m = SurfaceMotion.read(measured, min_opacity=0.0, capture_id=capture.id)
        if len(m.times_s) == len(model.times_s) and np.allclose(m.times_s, model.times_s, rtol=0, atol=1e-7):
            motion, shapes_from = m, "measured"
        else:
            log.warning("%s: its timesteps are not those of %s (a stale file); the shapes come from the model",
                        measured, path)
    t = motion.times_s
    if len(t) < 8:
        log.warning("%s: %d timesteps are too few for a decay fit; no video side", path, len(t))
        return None
    dt = float(np.median(np.diff(t)))
    nyq = 0.5 / dt
    use = modes.freq_hz < 0.8 * nyq
    if not use.any():
        log.warning("no accelerometer mode below the trained timesteps' band (%.0f Hz)", 0.8 * nyq)
        return None
    poles = modes.poles_rad_s[use]
    pos = np.stack([sn.position_m for sn in sensors])
    dirs = np.stack([sn.direction for sn in sensors])
    at_sensors = motion.at_points(pos, dirs, k=s.k_neighbours, outlier_factor=s.outlier_factor)  # (T, S)
    surface = motion.displacement_m.reshape(len(t), -1)                             # (T, N*3)
    t_min = DECAY_T_MIN_S
    n_s = at_sensors.shape[1]
    fit = fit_decay(t, np.concatenate([at_sensors, surface], axis=1), poles, t_min_s=t_min)  # one design matrix
    noise = noise_floor(t, at_sensors, surface, fit)
    F = _sync_force(capture, force, poles)
    keep, rule = structure_mask(capture, motion.points_m, s, moving=noise.moving if noise is not None else None)
    # The video's own poles: the structure's motion (the background's only adds noise), unfiltered where the
    # linear model left it (its basis keeps the components above 4x the noise, and a pencil on those finds stable
    # poles of the noise they carry: 47 Hz on the demo); a pole counts where it explains 4x what the noise would.
    after = t >= t_min
    ranks = s.video_ranks or record_ranks(int(after.sum()))
    f_hz, zeta = stable_poles(t[after], motion.displacement_m[after][:, keep].reshape(int(after.sum()), -1), ranks,
                              nyq * 0.8, min_significance=POLE_MIN_SIGNIFICANCE) \
        if ranks else (np.zeros(0), np.zeros(0))
    checks = crosscheck_views(capture, model, max_views=s.crosscheck_views, n_points=s.crosscheck_points,
                              k=s.k_neighbours, outlier_factor=s.outlier_factor) \
        if s.crosscheck_views > 0 else []
    triangulation = triangulation_check(capture, motion, poles, max_views=s.triangulate_views,
                                        n_points=s.triangulate_points, k=s.k_neighbours,
                                        outlier_factor=s.outlier_factor, t_min_s=t_min) \
        if s.triangulate_views >= MIN_VIEWS else None
    # Real (normal) modes where the structure's shapes are real within the noise: half the noise power goes
    shapes = None
    if s.real_modes and noise is not None:
        on = np.flatnonzero(keep) if keep.any() else np.arange(len(keep))
        shapes = real_modes(fit, t, (n_s + 3 * on[:, None] + np.arange(3)).ravel(),
                            np.repeat(noise.point_sigma_m[on], 3), noise.spectrum_gain)
        fit = dataclasses.replace(fit, amplitudes=shapes.apply(fit.amplitudes))
    # The physical limit: the camera's Cramér-Rao bound on every point against the measured floor, and each mode's
    # motion against a floor per direction (analysis/crlb.py).
    bound = direction = kept_axes = None
    amplitudes = fit.amplitudes          # the shapes': the fit's, less the axes the direction floor calls noise
    if noise is not None:
        R = len(poles)
        gain = design_gains(t, poles, t_min) * np.sqrt(noise.spectrum_gain)   # each mode's sd per unit noise
        bound = displacement_bound(capture, motion.points_m, noise.point_sigma_m, structure=keep, noise=noise,
                                   sensors_m=pos, sensor_dirs=dirs, k=s.k_neighbours, outlier_factor=s.outlier_factor)
        if bound is not None:
            direction = direction_floor(bound, fit.amplitudes[:, n_s:].reshape(R, -1, 3), gain)
            if s.direction_floor:
                # modes below the floor keep their shape as fitted: it is flagged as the noise's as a whole
                kept_axes = ~(direction.noise_axes() & ~noise.below[:, None])                    # (R, 3)
                amplitudes = amplitudes.copy()
                amplitudes[:, n_s:] = (amplitudes[:, n_s:].reshape(R, -1, 3) * kept_axes[:, None, :]).reshape(R, -1)
        if keep.any():
            noise, amplitudes = _full_field_floor(noise, fit, amplitudes, keep, n_s, gain,
                                                  shapes.real if shapes is not None else None, kept_axes)
    residues = dataclasses.replace(fit, amplitudes=amplitudes).residues(F)
    disp = motion.displacement_m[:, ~keep]                                          # (T, N_bg, 3)
    background = float(np.median(np.sqrt(np.mean((disp - disp.mean(axis=0)) ** 2, axis=(0, 2))))) \
        if disp.shape[1] else float("nan")
    log.info("video: %d of %d surface points on the structure (%s); the background's %d move %.3g um rms",
             keep.sum(), len(keep), rule, (~keep).sum(), 1e6 * background)
    ratio = background_ratio(capture, motion.points_m, fit.amplitudes[:, n_s:], keep,
                             noise.below if noise is not None else np.zeros(len(poles), bool))
    return VideoModes(poles, np.flatnonzero(use), residues[:, :n_s], motion.points_m[keep],
                      residues[:, n_s:].reshape(len(poles), -1, 3)[:, keep], fit.r2[:n_s], fit.condition, f_hz,
                      zeta, t, at_sensors, tuple(checks), shapes_from, noise, int((~keep).sum()), background, rule,
                      *ratio, real_modes=shapes, bound=bound, direction=direction, triangulation=triangulation)


def _full_field_floor(noise: NoiseFloor, fit: DecayFit, amplitudes: np.ndarray, keep: np.ndarray, n_s: int,
                      mode_sd: np.ndarray, real: np.ndarray | None,
                      kept_axes: np.ndarray | None) -> tuple[NoiseFloor, np.ndarray]:
    """The floor over the full structure (noise.full_field_expected_mac) on the shapes as kept (amplitudes (R, M):
    the sensors' n_s channels, then the points'; kept_axes (R, 3) the axes the direction floor left them, None:
    all): a mode above the floor at the sensors may be small over most of the structure, where its shape is the
    noise's (the plate hit at 600 N: its (3,2) mode 1.04x its floor at the sensors, 0.81 allowed over the plate,
    0.84 measured against the truth, docs/fidelity.md). A mode it puts below keeps its shape as fitted, as the
    others below do. The noise floor with it, and the amplitudes."""
    R = len(mode_sd)
    fitted = fit.amplitudes[:, n_s:].reshape(R, -1, 3)[:, keep]
    kept = None if kept_axes is None else kept_axes[:, None, :]                                   # (R, 1, 3)
    sigma = noise.component_sigma_m if noise.component_sigma_m is not None else noise.point_sigma_m
    ff = full_field_expected_mac(fitted, sigma[keep], mode_sd, real, kept)
    newly = ~noise.below & (ff < FLOOR_MAC)
    if newly.any():
        amplitudes = amplitudes.copy()
        amplitudes[newly] = fit.amplitudes[newly]
    log.info("the MAC the noise allows each mode over the full structure: %s", ", ".join(
        f"{f:.1f} Hz {m:.3f}" for f, m in zip(pole_freq_hz(fit.poles_rad_s), ff)))
    return dataclasses.replace(noise, full_field_mac=ff), amplitudes


def background_ratio(capture: Capture, points_m: np.ndarray, amplitudes: np.ndarray, keep: np.ndarray,
                     below: np.ndarray) -> tuple[float, float, float, int]:
    """How far the background (which does not move) reads as moving in the modes above the noise floor: its
    median modal amplitude (metres, root sum of squares over those modes and the three axes) and that over the
    structure's, where it is seen by as many views as the median structure point (the floor under and around the
    structure, observed as well as it is); the same ratio over the whole background; and how many points the
    first takes. On the demo the floor's far edges are in 28-48 % fewer views and carry 2-4x the noise."""
    if keep.all() or not keep.any():
        return float("nan"), float("nan"), float("nan"), 0
    a = np.asarray(amplitudes).reshape(len(below), -1, 3)[~np.asarray(below, bool)]
    amp = 2 * np.sqrt(np.sum(np.abs(a) ** 2, axis=(0, 2)))                         # (N,) metres
    seen = views_seeing(capture, points_m)
    ref = ~keep if seen is None else ~keep & (seen >= np.median(seen[keep]))
    if not ref.any():
        ref = ~keep
    structure = max(float(np.median(amp[keep])), 1e-300)
    amp_ref = float(np.median(amp[ref]))
    ratio, ratio_all = amp_ref / structure, float(np.median(amp[~keep])) / structure
    log.info("the background moves %.3g um in the modes above the noise floor, %.3g of the structure's median (%d "
             "points seen by as many views; %.3g over all %d)", 1e6 * amp_ref, ratio, ref.sum(), ratio_all,
             (~keep).sum())
    return amp_ref, ratio, ratio_all, int(ref.sum())


def structure_mask(capture: Capture, points_m: np.ndarray, s: AnalyzeSettings | None = None, *,
                   moving: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """Which points (N, 3), metres, are the structure's, and the rule in words: inside the box the user gave
    (`structure_box_m`), above the floor (z = 0 in the tag layout's frame) by floor_margin_m where the capture has
    floor tags, and, where neither rule applies (or structure_motion says so), `moving` (N,) bool: above their own
    noise (the analysis: analysis/noise.py; the viewer: the Gaussians' motion); and neither isolated from the other
    points kept (ISOLATED_FACTOR x their median spacing) nor in a small clump apart from them (`floaters`). The rest
    is background: fitted,
    kept out of the shapes. The motion test alone would also drop the structure's quiet parts (a column's foot).
    The analysis's rule, public so that the viewer hides what the analysis leaves out."""
    s = s or AnalyzeSettings()
    p = np.asarray(points_m, float)
    keep = np.ones(len(p), bool)
    rules = []
    if s.structure_box_m is not None:
        lo, hi = np.asarray(s.structure_box_m, float)
        keep &= np.all((p >= lo) & (p <= hi), axis=1)
        rules.append("inside the box given")
    tags = capture.manifest.tags
    if s.floor_margin_m is not None and tags is not None and any(not t.on_structure for t in tags.tags):
        keep &= p[:, 2] > s.floor_margin_m
        rules.append(f"more than {1e3 * s.floor_margin_m:g} mm above the floor")
    by_motion = s.structure_motion if s.structure_motion is not None else not rules
    if by_motion and moving is not None and (keep & moving).any():
        keep &= moving
        rules.append("moving above their noise")
    if not keep.any():
        log.warning("no surface point passes the structure rules (%s); the shapes keep every point",
                    ", ".join(rules))
        return np.ones(len(p), bool), "every point (the structure rules left none)"
    if keep.sum() > 4 * ISOLATED_K:
        idx = np.flatnonzero(keep)
        d = cKDTree(p[idx]).query(p[idx], k=ISOLATED_K + 1)[0][:, -1]
        isolated = d > ISOLATED_FACTOR * max(float(np.median(d)), 1e-12)
        if isolated.any():
            keep[idx[isolated]] = False
            rules.append(f"not isolated ({int(isolated.sum())} left out)")
    idx = np.flatnonzero(keep)
    apart = floaters(p[idx])
    if apart.any():
        keep[idx[apart]] = False
        rules.append(f"not in a clump apart ({int(apart.sum())} left out: floaters)")
    return keep, ", ".join(rules) or "every point"


def floaters(points_m: np.ndarray) -> np.ndarray:
    """(N,) bool: the points in clusters apart from the rest (FLOATER_GAP x their spacing) that hold under
    FLOATER_SHARE of them (none where there are too few points to tell)."""
    p = np.asarray(points_m, float)
    if len(p) < 4 * FLOATER_K:
        return np.zeros(len(p), bool)
    tree = cKDTree(p)
    spacing = float(np.median(tree.query(p, k=FLOATER_K + 1)[0][:, -1]))
    pairs = tree.query_pairs(FLOATER_GAP * max(spacing, 1e-12), output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(p), len(p)))
    _, label = connected_components(graph, directed=False)
    return (np.bincount(label) < FLOATER_SHARE * len(p))[label]


# ---------------------------------------------------------------------------------------------- the stage

def _nearest(f_ref: np.ndarray, f: np.ndarray, tol: float) -> np.ndarray:
    """Per reference frequency, the nearest of f within tol (relative), else NaN."""
    out = np.full(len(f_ref), np.nan)
    for i, fr in enumerate(f_ref):
        if len(f):
            j = int(np.argmin(np.abs(f - fr)))
            if abs(f[j] - fr) <= tol * fr:
                out[i] = f[j]
    return out


@dataclass(frozen=True)
class _Inputs:
    """What the analysis reads of the capture: the channels, and every take's hit cut to one length."""

    force: str
    sensors: tuple[Sensor, ...]
    takes: tuple[str, ...]
    force_n: np.ndarray        # (H, n)
    response: np.ndarray       # (H, S, n) m/s^2
    rate_hz: float
    reference: Sensor          # the hammer, where the manifest places it


@dataclass(frozen=True)
class _Comparison:
    """The video against the accelerometers: MAC, the ODS lines (m/N) and the verdicts."""

    ods_freq_hz: np.ndarray
    ods_accel: np.ndarray                                   # (L, S) measured H1
    ods_video: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), complex))      # (L, S) synthesised
    ods_surface: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), complex))  # (L, N, 3)
    correlation: Correlation | None = None
    mac_verdict: Verdict | None = None
    crosscheck_verdict: Verdict | None = None
    reference_automac: np.ndarray | None = None      # (R, R) the accelerometer shapes' AutoMAC at the sensors
    video_cross_mac: np.ndarray | None = None        # (R, R) the video's shapes' over every surface point


def _read_inputs(capture: Capture, s: AnalyzeSettings) -> _Inputs:
    force, sensors = _channels(capture, s)
    takes = _take_names(capture, s)
    F, X, rate = _hit_segments(capture, takes, force, sensors, s)
    return _Inputs(force, sensors, tuple(takes), F, X, rate, _reference(capture, force))


def _accelerometers(inputs: _Inputs, s: AnalyzeSettings) -> tuple[FRFResult, ModalFit, list[Note]]:
    """The FRFs, the modes fitted in the band, and what the FRFs say of the band and the poles."""
    names = [sn.name for sn in inputs.sensors]
    frf = estimate_frf(inputs.force_n, inputs.response, inputs.rate_hz, s.frf, input_name=inputs.force,
                       output_names=names, output_unit="m/s^2")
    log.info("FRFs from %d of %d hits, %d lines", frf.n_averages, len(inputs.takes), len(frf.freq_hz))
    fmin, fmax = _band(frf, s)
    peaks = frf_peaks(frf, fmin, fmax)
    modes = fit_modes(frf.freq_hz, frf.h1, frf_kind="accelerance", fmin_hz=fmin, fmax_hz=fmax,
                      max_order=s.max_order, approx_freq_hz=s.approx_freq_hz, output_names=names,
                      peaks_hz=[p.freq_hz for p in peaks])
    if frf.exp_tau_s:
        modes = modes.with_corrected_damping(frf.exp_tau_s)
    log.info("modes: %s Hz", ", ".join(f"{f:.2f}" for f in modes.freq_hz))
    findings = band_findings(frf, (fmin, fmax), modes.freq_hz, inside=peaks,
                             given=s.fmax_hz is not None or s.fmin_hz is not None)
    return frf, modes, findings


def _below_floor(video: VideoModes) -> np.ndarray:
    """(R,) bool: the video's modes below its noise floor (none where it has none)."""
    return video.noise.below if video.noise is not None else np.zeros(len(video.mode_index), bool)


def _unseparated(video: VideoModes) -> np.ndarray:
    """(R,) bool: the video's modes above its floor that its record cannot separate from a neighbour."""
    return video.noise.unseparated if video.noise is not None else np.zeros(len(video.mode_index), bool)


def _compare(frf: FRFResult, modes: ModalFit, video: VideoModes | None, image: ImagePoles | None,
             s: AnalyzeSettings) -> _Comparison:
    """The ODS lines of the accelerometers and, with a video side, the video's; its shapes' MAC against the
    accelerometers' (each video residue was fitted with that accelerometer pole: paired as given) and the
    verdicts."""
    ods_f = np.asarray(s.ods_freq_hz if s.ods_freq_hz is not None else modes.freq_hz, float)
    rec = frf.to_receptance()
    lines = np.clip(np.searchsorted(rec.freq_hz, ods_f), 0, len(rec.freq_hz) - 1)
    ods_accel = rec.h1[lines]
    if video is None:
        return _Comparison(ods_f, ods_accel)
    f_acc = modes.freq_hz[video.mode_index]
    # the camera's frequency of each mode: from the raw frames (the whole take) where found, else from the
    # reconstruction's window
    f_cam = _nearest(f_acc, image.freq_hz, 0.05) if image is not None else np.full(len(f_acc), np.nan)
    f_cam = np.where(np.isnan(f_cam), _nearest(f_acc, video.freq_hz, 0.05), f_cam)
    corr = correlate(modes.shapes[video.mode_index], video.sensor_residues, freq_a_hz=f_acc, freq_b_hz=f_cam,
                     paired=True)
    paired = [j for _, j in corr.pairs]
    # Whether the sensors can tell the modes apart (the reference's AutoMAC), and whether the video's full field
    # does (its shapes' cross-MAC over every surface point): the verdict judges a mode only where the first holds.
    automac = auto_mac(modes.shapes[video.mode_index])
    surface = video.surface_residues
    cross = auto_mac(surface) if surface.size and np.all(np.isfinite(surface)) else None
    pick = np.ix_(paired, paired)
    verdict = mac_verdict(f_acc[paired], corr.pair_mac, _below_floor(video)[paired], reference_automac=automac[pick],
                          video_cross_mac=None if cross is None else cross[pick],
                          modes=np.asarray(video.mode_index)[paired] + 1, unseparated=_unseparated(video)[paired])
    return _Comparison(ods_f, ods_accel, receptance(video.sensor_residues, video.poles_rad_s, ods_f),
                       receptance(video.surface_residues, video.poles_rad_s, ods_f), corr, verdict,
                       crosscheck_verdict(video.crosscheck), automac, cross)


def _image(capture: Capture, s: AnalyzeSettings) -> ImagePoles | None:
    """Poles from the raw frames of every synced take, where the capture has a camera and they are asked for."""
    fps = capture.manifest.camera.fps
    if not (s.video and s.image_poles and fps):
        return None
    return image_poles(capture, fmax_hz=VIDEO_BAND * fps, ranks=s.image_ranks, pixel_fraction=s.image_pixel_fraction)


def analyze_capture(capture: Capture | str | Path, settings: AnalyzeSettings | None = None
                    ) -> AnalysisResult | Video2DResult:
    """The whole analysis, written to derived/analysis/ (results.h5, analysis.uff, analysis.json, plots); a capture
    without a force channel gets the 2D output-only path instead (`video_only`)."""
    capture = capture if isinstance(capture, Capture) else Capture.open(capture)
    s = settings or AnalyzeSettings()
    if s.force_channel is None and not capture.manifest.has_force:
        return video_only(capture, s)
    discard_video2d(capture)
    inputs = _read_inputs(capture, s)
    frf, modes, findings = _accelerometers(inputs, s)
    unplaced = tuple(sn.name for sn in inputs.sensors if not sn.placed)
    if unplaced:
        findings.append(UnplacedSensors(unplaced))
    video = video_modes(capture, modes, inputs.sensors, inputs.force, s) if not unplaced else None
    image = _image(capture, s)
    single = sensor_view(capture, modes, inputs.sensors, inputs.force, max_takes=s.sensor_view_takes,
                         window_px=s.video2d.window_px, method=s.video2d.tracker,
                         max_tilt_deg=s.sensor_view_max_tilt_deg) \
        if video is None and s.video and s.sensor_view and not unplaced else None
    cmp = _compare(frf, modes, video, image, s)
    findings += _video_findings(modes, video, cmp, tuple(sn.name for sn in inputs.sensors))
    for note in findings:
        log.info("note: %s", note.text)
    result = AnalysisResult(frf, modes, inputs.sensors, inputs.takes, video, cmp.correlation, cmp.ods_freq_hz,
                            cmp.ods_accel, cmp.ods_video, cmp.ods_surface, image, findings=tuple(findings),
                            mac_verdict=cmp.mac_verdict, crosscheck_verdict=cmp.crosscheck_verdict,
                            reference=inputs.reference, reference_automac=cmp.reference_automac,
                            video_cross_mac=cmp.video_cross_mac, sensor_view=single)
    return _write(capture, result, s)


def _placed_accelerometers(capture: Capture) -> tuple[Sensor, ...]:
    """The capture's acceleration channels with a position and a direction."""
    return tuple(Sensor(c.name, np.asarray(c.position_m, float), np.asarray(c.direction, float)
                        / np.linalg.norm(c.direction)) for c in capture.manifest.channels
                 if c.kind == "acceleration" and c.position_m is not None and c.direction is not None)


def video_only(capture: Capture, s: AnalyzeSettings) -> Video2DResult:
    """A capture without force: the 2D output-only path on its first view (video2d.py), its figures and clips."""
    result = analyze_video(capture, s.video2d, takes=s.takes)
    if s.sensor_view:
        sensors = _placed_accelerometers(capture)
        result = dataclasses.replace(result, sensor_view=sensor_ods(
            capture, result, sensors, window_px=s.video2d.window_px, method=s.video2d.tracker,
            max_tilt_deg=s.sensor_view_max_tilt_deg) if sensors else None)
    dest = capture.paths.ensure(capture.paths.analysis_dir)
    files: dict[str, str] = {}
    if s.plots:
        frame = first_frame(capture, result.take)
        files = write_figures(dest, result, frame)
        if s.video2d.clips:
            clips = write_clips(dest, result, lambda: frames(capture, result.take), frame.shape,
                                s.video2d.clip_frames)
            result = dataclasses.replace(result, modes=tuple(
                dataclasses.replace(m, clip=clips[k][0], clip_alpha=clips[k][1]) if k in clips else m
                for k, m in enumerate(result.modes)))
            files.update({f"clip_{k + 1:02d}": v[0] for k, v in clips.items()})
    return write_video2d(capture, result, s, files)


# ---------------------------------------------------------------------------------------------- the notes

def _video_findings(modes: ModalFit, video: VideoModes | None, cmp: _Comparison,
                    sensor_names: tuple[str, ...]) -> list[Note]:
    """What the video's numbers cannot show (analysis/notes.py words each): modes above its band, modes below its
    noise floor (for want of cycles in its window, or of amplitude), complex shapes, ODS lines those modes carry,
    and modes whose MAC the sensors cannot judge (alike at the sensors: verdict.NOT_DISCRIMINATED); sensors where
    the video does not see the structure move (the modes explain under MIN_SENSOR_R2 of its motion there)."""
    if video is None:
        return []
    out: list[Note] = []
    if len(video.mode_index) < modes.n_modes:
        fitted = set(video.mode_index.tolist())
        out.append(ModesAboveVideoBand(tuple(float(f) for i, f in enumerate(modes.freq_hz) if i not in fitted)))
    # The share of each sensor's motion the modes explain, less what a fit of that many parameters explains of pure
    # noise (adjusted R^2: 0 for noise alone, whatever the record's length)
    adjusted = adjusted_r2(video.sensor_r2, int(np.sum(video.times_s >= DECAY_T_MIN_S)), len(video.poles_rad_s))
    unseen = np.flatnonzero(adjusted < MIN_SENSOR_R2)
    if len(unseen):
        out.append(SensorsNotSeen(tuple(sensor_names[i] for i in unseen),
                                  tuple(float(max(adjusted[i], 0.0)) for i in unseen)))
    f_acc = modes.freq_hz[video.mode_index]
    below = _below_floor(video)
    window_s = float(np.ptp(video.times_s)) if len(video.times_s) > 1 else 0.0
    nf, rm = video.noise, video.real_modes
    for r in np.flatnonzero(below):
        mode, f = int(video.mode_index[r]) + 1, float(f_acc[r])
        if window_s * f < MIN_CYCLES:
            # Then the fit's amplitude and its floor are both ill-conditioned (metres for micrometres): the cause,
            # not the numbers, is what the engineer can act on.
            out.append(WindowTooShort(mode, f, window_s, MIN_CYCLES))
            continue
        whole = None if nf.below_at_sensors[r] or nf.full_field_mac is None else float(nf.full_field_mac[r])
        out.append(BelowNoiseFloor(mode, f, float(nf.mode_amplitude_m[r]), float(nf.mode_floor_m[r]),
                                   float(nf.expected_mac[r]), rm is not None and bool(rm.real[r]), whole))
    apart = np.flatnonzero(_unseparated(video))
    if len(apart):
        out.append(ModesNotSeparated(tuple(int(video.mode_index[r]) + 1 for r in apart),
                                     tuple(float(f_acc[r]) for r in apart),
                                     tuple(float(nf.separation_gain[r]) for r in apart),
                                     tuple(float(nf.record_needed_s[r]) for r in apart), window_s,
                                     MAX_SEPARATION_GAIN))
    for r in np.flatnonzero(~rm.real if rm is not None else np.zeros(0, bool)):
        out.append(ComplexMode(int(video.mode_index[r]) + 1, float(f_acc[r]), float(rm.mpc[r]), float(rm.lost[r]),
                               float(rm.quadrature_ratio[r])))
    ods_f = cmp.ods_freq_hz
    if below.any() and len(ods_f):
        # An ODS line is the sum of every mode's term: where the terms of modes below the floor carry most of it
        # at the sensors, the video's ODS there is their noise too.
        noisy = receptance(video.sensor_residues[below], video.poles_rad_s[below], ods_f)
        share = np.linalg.norm(noisy.reshape(len(ods_f), -1), axis=1) / np.maximum(
            np.linalg.norm(cmp.ods_video.reshape(len(ods_f), -1), axis=1), 1e-300)
        out += [OdsCarriedByNoise(int(li) + 1, float(ods_f[li]), float(share[li]))
                for li in np.flatnonzero(share > 0.5)]
    alike = [s for s in (cmp.mac_verdict.modes if cmp.mac_verdict is not None else ())
             if s.status == NOT_DISCRIMINATED]
    if alike:
        pairs = {(min(s.mode, j), max(s.mode, j)): a for s in alike for j, a in zip(s.confused_with, s.automac)}
        out.append(ModesNotDiscriminated(tuple(s.mode for s in alike),
                                         tuple((i, j, float(a)) for (i, j), a in sorted(pairs.items())),
                                         int(video.sensor_residues.shape[1]), DISCRIMINATION))
    return out


# ---------------------------------------------------------------------------------------------- the outputs

def _write(capture: Capture, result: AnalysisResult, s: AnalyzeSettings) -> AnalysisResult:
    dest = capture.paths.ensure(capture.paths.analysis_dir)
    files = write_outputs(dest, result, plots=s.plots, capture_id=capture.id)
    document = result.document(describe(capture.id, KIND, SCHEMA, s), capture=capture.root.name,
                               created_utc=utc_now(), settings=plain(s), files=files)
    document.write(capture)      # last: a reader that finds it finds the files it lists
    return dataclasses.replace(result, files={**files, "summary": "analysis.json"})
