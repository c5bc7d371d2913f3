"""The analysis result: everything its writers (exports, plots, report) need, computed once by the analysis."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from odsplat.spine.contract import Provenance

from .correlation import Correlation, mac
from .crlb import DirectionFloor, DisplacementBound, physical_limit
from .crosscheck import ViewCheck
from .document import (
    AnalysisDocument,
    CorrelationSection,
    ImagePolesSection,
    ModeEntry,
    NoiseFloorSection,
    NoiseModeEntry,
    OdsEntry,
    PairEntry,
    RealModeEntry,
    RejectedHit,
    VideoSection,
)
from .ema import ModalFit
from .frf import FRFResult
from .imagepoles import ImagePoles
from .noise import FLOOR_MAC, FLOOR_SIGMAS, NoiseFloor, RealModes
from .notes import Note
from .sensorview import SensorView
from .triangulate import Triangulation
from .verdict import Verdict


@dataclass(frozen=True)
class Sensor:
    """A response channel, and where it sits: position and direction are None until the user gives them (an
    imported recording without geometry still gives FRFs, frequencies and damping; shapes need both)."""

    name: str
    position_m: np.ndarray | None = None   # (3,)
    direction: np.ndarray | None = None    # (3,) unit

    @property
    def placed(self) -> bool:
        return self.position_m is not None and self.direction is not None


@dataclass(frozen=True)
class VideoModes:
    """The video's modal amplitudes with the accelerometer poles, at the sensors and on the whole surface."""

    poles_rad_s: np.ndarray          # (R,) the accelerometer poles inside the camera's band
    mode_index: np.ndarray           # (R,) their index in the accelerometer fit
    sensor_residues: np.ndarray      # (R, S) m/N along the sensor directions
    surface_points_m: np.ndarray     # (N, 3) the Gaussians (or the linear model's nodes: `shapes_from`)
    surface_residues: np.ndarray     # (R, N, 3) m/N
    sensor_r2: np.ndarray            # (S,) share of each sensor point's motion the modes explain
    condition: float
    freq_hz: np.ndarray              # poles found in the video alone (matrix pencil, stable over ranks)
    damping: np.ndarray
    times_s: np.ndarray              # the trained window
    sensor_displacement_m: np.ndarray  # (T, S) the video's motion at the sensors, along their directions
    crosscheck: tuple[ViewCheck, ...] = ()   # the 3D motion against 2D tracks in single views
    shapes_from: str = "trajectories"        # the motion the residues are fitted to: or "measured" (unfiltered)
    noise: NoiseFloor | None = None          # that motion's noise floor, and each mode's amplitude against it
    # The surface above is the structure's; the background (the floor, what does not move) was fitted too and
    # left out of the shapes, exports and figures: how many points, why, and how much they move (rms, metres,
    # the video's noise in the open).
    n_background: int = 0
    background_rms_m: float = float("nan")
    structure_rule: str = ""
    # the background's median modal amplitude (metres, the modes above the noise floor) where it is seen by as
    # many views as the structure, that over the structure's, the same ratio over all of it, and how many points
    # the first takes (analyze.background_ratio)
    background_amplitude_m: float = float("nan")
    background_ratio: float = float("nan")
    background_ratio_all: float = float("nan")
    n_background_reference: int = 0
    real_modes: RealModes | None = None      # the shapes as real modes where the noise allows (noise.real_modes)
    bound: DisplacementBound | None = None   # the camera's Cramér-Rao bound against the floor (crlb.py)
    direction: DirectionFloor | None = None  # each mode's motion against a floor per point and direction
    triangulation: Triangulation | None = None  # several views' 2D tracks triangulated against the 3D motion


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None   # JSON has no NaN


def _floats(x) -> tuple[float, ...]:
    return tuple(float(v) for v in np.ravel(x))


def _matrix(m: np.ndarray | None) -> tuple[tuple[float, ...], ...] | None:
    """A square matrix as rows of floats (JSON), None where there is none."""
    return None if m is None else tuple(_floats(row) for row in np.asarray(m, float))


def _triangulation(tri: Triangulation | None, freq_hz: np.ndarray) -> dict | None:
    """The triangulation check as plain data (metres as micrometres), each mode's MAC and scale by frequency."""
    if tri is None:
        return None
    return {"n_points": tri.n_points, "n_views": tri.n_views, "views_per_point": tri.views_per_point,
            "gain": _finite(tri.gain), "correlation": _finite(tri.correlation),
            "motion_rms_um": _finite(1e6 * tri.motion_rms_m), "residual_rms_um": _finite(1e6 * tri.residual_rms_m),
            "condition_median": _finite(tri.condition_median), "motion_px": _finite(tri.motion_px),
            "noise_px": _finite(tri.noise_px), "expected_correlation": _finite(tri.expected_correlation),
            "modes": [{"freq_hz": float(f), "mac": _finite(m), "scale": _finite(sc)}
                      for f, m, sc in zip(freq_hz, tri.mode_mac, tri.mode_scale)]}


def _noise_section(nf: NoiseFloor, freq_hz: np.ndarray) -> NoiseFloorSection:
    """The video's noise floor in micrometres, with each fitted mode (at freq_hz) against it."""
    return NoiseFloorSection(
        sigma_um=float(1e6 * nf.sigma_m), static_sigma_um=_finite(1e6 * nf.static_sigma_m),
        n_static_points=int(nf.n_static), pre_impact_sigma_um=_finite(1e6 * nf.pre_impact_sigma_m),
        n_pre_impact=int(nf.n_pre_impact), sensor_sigma_um=_floats(1e6 * nf.sensor_sigma_m),
        point_sigma_um_p10_p90=(float(1e6 * np.percentile(nf.point_sigma_m, 10)),
                                float(1e6 * np.percentile(nf.point_sigma_m, 90))),
        floor_sigmas=float(FLOOR_SIGMAS), floor_mac=float(FLOOR_MAC),
        modes=tuple(NoiseModeEntry(float(f), float(1e6 * a), float(1e6 * fl), float(g), bool(b),
                                   separation_gain=None if sg is None else float(sg), not_separated=bool(u),
                                   record_needed_s=_finite(rn) if rn is not None else None,
                                   full_field_mac=None if ff is None else float(ff), below_at_sensors=bool(bs))
                    for f, a, fl, g, b, bs, sg, u, rn, ff in zip(
                        freq_hz, nf.mode_amplitude_m, nf.mode_floor_m, nf.spectrum_gain, nf.below, nf.below_at_sensors,
                        _each(nf.separation_gain, len(freq_hz)), nf.unseparated,
                        _each(nf.record_needed_s, len(freq_hz)), _each(nf.full_field_mac, len(freq_hz)))))


def _each(values: np.ndarray | None, n: int) -> list:
    """values as a list, or n Nones where there are none."""
    return [None] * n if values is None else list(values)


def _video_section(result: AnalysisResult) -> VideoSection:
    v = result.video
    freq = result.modes.freq_hz[v.mode_index]
    gains, corrs = [c.gain for c in v.crosscheck], [c.correlation for c in v.crosscheck]
    return VideoSection(
        modes_fitted=tuple(int(i) for i in v.mode_index), sensor_r2=_floats(v.sensor_r2),
        condition=float(v.condition), freq_hz=_floats(v.freq_hz), damping=_floats(v.damping),
        window_s=(float(v.times_s[0]), float(v.times_s[-1])), n_surface_points=int(len(v.surface_points_m)),
        shapes_from=v.shapes_from, n_background_points=int(v.n_background), structure_rule=v.structure_rule,
        background_rms_um=_finite(1e6 * v.background_rms_m),
        background_amplitude_um=_finite(1e6 * v.background_amplitude_m),
        background_amplitude_ratio=_finite(v.background_ratio),
        background_amplitude_ratio_all=_finite(v.background_ratio_all),
        n_background_reference_points=int(v.n_background_reference), crosscheck=tuple(v.crosscheck),
        noise_floor=_noise_section(v.noise, freq) if v.noise is not None else None,
        real_modes=tuple(RealModeEntry(float(f), float(m), float(q), float(x), bool(r)) for f, m, q, x, r in zip(
            freq, v.real_modes.mpc, v.real_modes.quadrature_ratio, v.real_modes.lost, v.real_modes.real))
        if v.real_modes is not None else None,
        crosscheck_verdict=result.crosscheck_verdict,
        crosscheck_gain_median=float(np.median(gains)) if gains else None,
        crosscheck_correlation_median=float(np.median(corrs)) if corrs else None,
        physical_limit=physical_limit(v.bound, v.direction, freq, v.noise.below) if v.bound is not None and
        v.noise is not None else None,
        triangulation=_triangulation(v.triangulation, freq))


def _image_section(im: ImagePoles) -> ImagePolesSection:
    return ImagePolesSection(freq_hz=_floats(im.freq_hz), damping=_floats(im.damping), n_views=int(im.n_views),
                             n_pixels=int(im.n_pixels), window_s=(float(im.window_s[0]), float(im.window_s[1])),
                             component_snr=_floats(im.snr))


def _correlation_section(result: AnalysisResult) -> CorrelationSection:
    """The pairs (each against the video's noise floor where it has one: b indexes the video's fitted modes), the
    CoMAC and the MAC verdict."""
    c = result.correlation
    nf = result.video.noise if result.video is not None else None
    freqs = c.freq_a_hz is not None and c.freq_b_hz is not None
    pairs = []
    for k, (i, j) in enumerate(c.pairs):
        p = PairEntry(a=int(i), b=int(j), mac=float(c.pair_mac[k]), scale_factor_abs=float(abs(c.scale_factor[k])),
                      scale_factor_phase_deg=float(np.degrees(np.angle(c.scale_factor[k]))))
        if freqs:
            p = dataclasses.replace(p, freq_a_hz=_finite(c.freq_a_hz[k]), freq_b_hz=_finite(c.freq_b_hz[k]),
                                    freq_diff_rel=_finite(c.freq_diff_rel[k]))
        if nf is not None:
            p = dataclasses.replace(p, video_amplitude_um=float(1e6 * nf.mode_amplitude_m[j]),
                                    noise_floor_um=float(1e6 * nf.mode_floor_m[j]), below_noise_floor=bool(nf.below[j]),
                                    expected_mac=float(nf.expected_mac[j]))
        pairs.append(p)
    return CorrelationSection(pairs=tuple(pairs), comac=_floats(c.comac), verdict=result.mac_verdict,
                              mac_matrix=_matrix(c.mac), reference_automac=_matrix(result.reference_automac),
                              video_cross_mac=_matrix(result.video_cross_mac))


@dataclass(frozen=True)
class AnalysisResult:
    frf: FRFResult
    modes: ModalFit
    sensors: tuple[Sensor, ...]
    takes: tuple[str, ...]
    video: VideoModes | None = None
    correlation: Correlation | None = None
    ods_freq_hz: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ods_accel: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), complex))   # (L, S) m/N, measured H1
    ods_video: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), complex))   # (L, S) m/N, synthesised
    ods_surface: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), complex))  # (L, N, 3) m/N, the
    #                                    video's ODS at every surface point (video.surface_points_m), synthesised
    image: ImagePoles | None = None      # poles from the raw frames of every synced take
    files: dict[str, str] = field(default_factory=dict)
    findings: tuple[Note, ...] = ()      # what the numbers cannot show: peaks with no mode, a band that cuts one,
    #                                      modes below the video's noise floor (`notes`: in words)
    mac_verdict: Verdict | None = None         # MAC target over the modes above the video's noise floor
    crosscheck_verdict: Verdict | None = None  # the 2D cross-check's gain and correlation against thresholds
    reference: Sensor | None = None      # the hammer (the force channel): the impact point and the force's direction
    #                                      on the structure where the capture records them (exports: node 100)
    reference_automac: np.ndarray | None = None   # (R, R) the accelerometer shapes of the video's modes, AutoMAC at
    #                                               the sensors: where two exceed verdict.DISCRIMINATION the MAC
    #                                               cannot tell those modes apart
    video_cross_mac: np.ndarray | None = None     # (R, R) the video's shapes' cross-MAC over every surface point
    sensor_view: SensorView | None = None         # without a 3D side: one view's 2D tracks at the sensors it sees

    @property
    def notes(self) -> tuple[str, ...]:
        """The findings in words (analysis/notes.py)."""
        return tuple(n.text for n in self.findings)

    def document(self, provenance: Provenance, *, capture: str, created_utc: str, settings: dict,
                 files: dict[str, str]) -> AnalysisDocument:
        """The key numbers as analysis.json holds them, under `provenance`'s header; `capture` is the capture's
        folder name, `settings` the analysis's as plain data, `files` what it wrote."""
        m = self.modes
        return AnalysisDocument(
            provenance=provenance, capture=capture, created_utc=created_utc, settings=settings,
            takes=tuple(self.takes), n_averages=int(self.frf.n_averages),
            rejected_hits=tuple(RejectedHit(t, tuple(h.reasons)) for t, h in zip(self.takes, self.frf.hits)
                                if not h.accepted),
            sensors=tuple(s.name for s in self.sensors),
            exp_tau_s=None if self.frf.exp_tau_s is None else float(self.frf.exp_tau_s),
            modes=tuple(ModeEntry(float(f), float(z)) for f, z in zip(m.freq_hz, m.damping)),
            band_hz=(float(m.band_hz[0]), float(m.band_hz[1])), notes=self.notes,
            video=_video_section(self) if self.video is not None else None,
            image_poles=_image_section(self.image) if self.image is not None else None,
            correlation=_correlation_section(self) if self.correlation is not None else None,
            ods=tuple(OdsEntry(float(f), float(mac(a, b)[0, 0]))
                      for f, a, b in zip(self.ods_freq_hz, self.ods_accel, self.ods_video))
            if len(self.ods_freq_hz) and self.ods_video.size else (),
            sensor_view=self.sensor_view.document() if self.sensor_view is not None else None,
            files=dict(files))

    def text(self) -> str:
        """A few lines for the terminal."""
        m = self.modes
        lines = [f"FRFs: {self.frf.n_averages} of {len(self.takes)} hits averaged, outputs "
                 f"{', '.join(s.name for s in self.sensors)}",
                 "modes (accelerometers): " + ", ".join(f"{f:.2f} Hz ({100 * z:.2f} %)"
                                                        for f, z in zip(m.freq_hz, m.damping))]
        if self.video is not None:
            v = self.video
            lines.append(f"video ({v.shapes_from} motion): {len(v.surface_points_m)} surface points, "
                         f"{len(v.times_s)} timesteps; modes "
                         f"{', '.join(str(int(k) + 1) for k in v.mode_index)} fitted (sensor r2 "
                         f"{', '.join(f'{r:.2f}' for r in v.sensor_r2)}); video-only poles "
                         + (", ".join(f"{f:.1f}" for f in v.freq_hz) or "none") + " Hz")
            if v.noise is not None:
                lines.append(f"video noise floor: {1e6 * v.noise.sigma_m:.3g} um per point and timestep "
                             f"({1e6 * float(np.median(v.noise.sensor_sigma_m)):.3g} um at the sensors)")
            if v.crosscheck:
                lines.append(f"2D cross-check ({len(v.crosscheck)} views): gain tracked/3D median "
                             f"{np.median([c.gain for c in v.crosscheck]):.2f}, correlation median "
                             f"{np.median([c.correlation for c in v.crosscheck]):.2f}")
            if self.crosscheck_verdict is not None:
                lines.append(f"verdict ({self.crosscheck_verdict.status}): {self.crosscheck_verdict.line}")
        if self.image is not None:
            im = self.image
            lines.append(f"image poles ({im.n_views} views, {im.n_pixels} px, {1e3 * im.window_s[0]:.1f}-"
                         f"{1e3 * im.window_s[1]:.1f} ms): " + (", ".join(f"{f:.2f}" for f in im.freq_hz) or "none")
                         + " Hz")
        if self.correlation is not None:
            c = self.correlation
            below = self.video.noise.below if self.video is not None and self.video.noise is not None else None
            lines.append("MAC video/accelerometers: " + ", ".join(
                f"mode {i + 1} {c.pair_mac[k]:.3f} (scale {abs(c.scale_factor[k]):.2f}"
                + ("; below the noise floor" if below is not None and below[j] else "") + ")"
                for k, (i, j) in enumerate(c.pairs)))
            if self.mac_verdict is not None:
                lines += [f"  mode {s.mode} ({s.freq_hz:.1f} Hz): {s.text}" for s in self.mac_verdict.modes]
                lines.append(f"verdict ({self.mac_verdict.status}): {self.mac_verdict.line}")
        if self.sensor_view is not None:
            lines.append(self.sensor_view.text())
        lines += [f"note: {n}" for n in self.notes]
        lines.append(f"-> {', '.join(self.files.values())}")
        return "\n".join(lines)
