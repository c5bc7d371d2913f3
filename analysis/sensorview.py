"""One view against the accelerometers it sees: the 2D check of a capture filmed from a single viewpoint.

With one view there is no 3D motion, but the camera still sees the accelerometers. Its pose comes from the
pose stage where there is one, else from the floor's AprilTags in the take's first frame (PnP on the capture's
intrinsics; tags on the structure too where that frame precedes the hit, the structure then at rest). Each placed
accelerometer is projected into the view. Windows are tracked through the synced, aligned frames at its pixel and
around it, up to one window's side away; those on the structure (moving at least half as much as the one that
moves most, their motion the modes') are kept and their median is the reading. A sensor whose axis lies in the
image plane usually sits on a face seen edge-on, on the structure's silhouette, where a window on the pixel itself
holds the static background too and reads part of the motion (0.39 of it at hil_sim's column; the one window the
modes explained best read 1.11-1.16x). Its image motion along the sensor's projected axis, divided by that axis'
image scale (px per metre, the projection's Jacobian), is the video's reading of the sensor's channel in metres. A
decay fit at the accelerometer poles, divided by each take's force at the poles, gives the video's residues (m/N)
beside the accelerometers'; their MAC and scale say whether one camera and the sensors agree on each mode. Without
force (`sensor_ods`), the readings and the accelerometers share one FDD at the 2D path's modes instead.

What it reads: the view sees two components of the motion and a uniaxial sensor one. Where the sensor's axis d
lies in the image plane, the image motion along its projected axis is exactly d . u, whatever else the structure
does (motion across the axis projects across it; motion along the line of sight projects to nothing). Tilted by
an angle out of the image plane, the reading gains sin(tilt) of the motion along the line of sight, which one view
cannot see: on the hil_sim arm filmed from 34 degrees above, the tip's z sensor (tilt 19 degrees) reads 1.49x in
its first mode, the tip moving along the line of sight. So a sensor tilted more than `max_tilt_deg` (15 by
default, error <= 0.26 of the line-of-sight motion) is left out and the tilt of each one compared is reported:
film the plane the sensors measure in, as one would for any 2D check. A sensor on a face
the camera does not see is tracked on what covers it: its motion then hardly fits the modes, and it is named
and left out of the MAC (`MIN_SENSOR_R2`). A mode that hardly moves the sensors compared (under `MIN_SEEN` of its
motion over all the sensors, as the accelerometers measure it) is not judged: the view's sensors do not see it.
Each mode's shape is known to the MAC its noise allows (snr / (1 + snr), the tracks' noise before the impact
through the decay fit's gain): under FLOOR_MAC it is below the floor, reported and not judged.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from odsplat.reconstruction import PoseResult
from odsplat.spine.store import Capture
from odsplat.spine.tags import camera_pose_from_tags, detect_tags
from odsplat.sync import AlignedTake, load_sync

from .correlation import mac as mac_matrix
from .correlation import modal_scale_factor
from .noise import design_gains
from .notes import MIN_SENSOR_R2
from .ods import DECAY_T_MIN_S, adjusted_r2, fit_decay, force_transform
from .tracking import project_displacement, track_points
from .video2d import FLOOR_MAC, first_frame, floor_mac, frames

if TYPE_CHECKING:
    from .result import Sensor

log = logging.getLogger(__name__)

MAX_TILT_DEG = 15.0       # a sensor's axis out of the image plane by more than this is left out (module doc)
BAND = 0.8                # modes below this fraction of the frame rate's Nyquist frequency are fitted
ON_STRUCTURE = 0.5        # a window moving less than this share of its sensor's most moving one is astride an edge
MIN_SEEN = 0.3           # a mode moves the sensors compared by at least this share of its motion over all of them
MIN_PRE_FRAMES = 8        # the tracks' noise is read before the impact where there are this many frames, else from
#                           the decay fit's residual


@dataclass(frozen=True)
class SensorView:
    """The accelerometers one view sees, and the video's modes there against theirs."""

    view: int | None
    takes: tuple[str, ...]           # the view's synced takes, each fitted and the residues averaged
    pose: str                        # where the pose came from, in words
    sensors: tuple[str, ...]         # those compared
    pixels_px: np.ndarray            # (S, 2) where each sits in the view
    n_windows: np.ndarray            # (S,) windows on the structure around it whose median is its reading
    px_per_m: np.ndarray             # (S,) the image scale of its axis: |J d|
    tilt_deg: np.ndarray             # (S,) its axis out of the image plane (0: in it; the reading is exact)
    left_out: tuple[tuple[str, str], ...]   # sensors not compared, and why
    mode_index: np.ndarray           # (R,) the accelerometer modes fitted (those in the camera's band)
    freq_hz: np.ndarray              # (R,)
    video_residues: np.ndarray       # (R, S) complex along each sensor's axis: m/N (decay), m/sqrt(Hz) (ods)
    accel_residues: np.ndarray       # (R, S) complex, the same unit
    r2: np.ndarray                   # (S,) adjusted: the share of the track's motion the modes explain
    noise_m: np.ndarray              # (S,) the tracks' rms noise along each axis, in metres
    noise_from: str                  # "pre-impact frames" or "fit residual"
    mac: np.ndarray                  # (R,) over the sensors seen moving (NaN with fewer than 2)
    scale: np.ndarray                # (R,) complex: video ~ scale x accelerometers, least squares
    expected_mac: np.ndarray         # (R,) what the noise allows: snr / (1 + snr)
    seen_share: np.ndarray           # (R,) the mode's accelerometer motion at the sensors compared / at them all
    method: str = "decay"            # "decay": residues (m/N) at the accelerometer poles after a hit; "ods": without
    #                                  force, the joint ODS at the video's modes (m/sqrt(Hz), one phase reference)
    labels: tuple[str, ...] = ()     # each mode's name in the text (default: "mode k" from mode_index)

    @property
    def below_floor(self) -> np.ndarray:
        return self.expected_mac < FLOOR_MAC

    @property
    def judged(self) -> np.ndarray:
        """(R,) modes the check judges: above the floor, moving the sensors compared, over two sensors or more."""
        return ~self.below_floor & (self.seen_share >= MIN_SEEN) & np.isfinite(self.mac)

    @property
    def seen(self) -> np.ndarray:
        """(S,) the sensors whose tracks the modes explain: those the MAC is over."""
        return self.r2 >= MIN_SENSOR_R2

    def text(self) -> str:
        lines = [f"one view against the accelerometers (view {self.view}, {len(self.takes)} take(s), pose from "
                 f"{self.pose}): " + ", ".join(f"{n} at {p[0]:.0f},{p[1]:.0f} px ({s:.0f} px/m, tilt {a:.0f} deg)"
                                               for n, p, s, a in zip(self.sensors, self.pixels_px, self.px_per_m,
                                                                     self.tilt_deg))]
        for n, why in self.left_out:
            lines.append(f"  {n} left out: {why}")
        for k in np.flatnonzero(~self.seen):
            lines.append(f"  {self.sensors[k]}: the modes explain {100 * max(self.r2[k], 0):.0f} % of its track; "
                         "the view does not see it move (left out of the MAC)")
        for r, i in enumerate(self.mode_index):
            name = self.labels[r] if self.labels else f"mode {i + 1}"
            state = self.state(r)
            lines.append(f"  {name} ({self.freq_hz[r]:.2f} Hz): MAC {self.mac[r]:.3f}, scale "
                         f"{abs(self.scale[r]):.3f} at {np.degrees(np.angle(self.scale[r])):+.0f} deg; the noise "
                         f"allows MAC {self.expected_mac[r]:.3f}: "
                         + ("BELOW THE FLOOR (not judged)" if state.startswith("below") else state))
        return "\n".join(lines)

    def state(self, r: int) -> str:
        """Mode r judged, or why not, in words (the summary, analysis.json and the reports)."""
        if self.judged[r]:
            return "judged"
        if self.below_floor[r]:
            return "below the floor (not judged)"
        if self.seen_share[r] < MIN_SEEN:
            return f"not judged: the sensors compared carry {100 * self.seen_share[r]:.0f} % of its motion"
        return "not judged: fewer than 2 sensors"

    def document(self) -> dict[str, Any]:
        """Plain data for analysis.json (residues in micrometres per newton)."""
        def fin(x):
            return float(x) if np.isfinite(x) else None
        unit = "um/N" if self.method == "decay" else "um/sqrt(Hz)"
        return {"view": self.view, "takes": list(self.takes), "pose": self.pose, "method": self.method,
                "unit": unit,
                "sensors": [{"name": n, "pixel_px": [float(p[0]), float(p[1])], "n_windows": int(o),
                             "px_per_m": float(s),
                             "tilt_deg": float(ip), "r2": float(r2), "noise_um": fin(1e6 * nz), "seen": bool(sn)}
                            for n, p, o, s, ip, r2, nz, sn in zip(self.sensors, self.pixels_px, self.n_windows,
                                                                  self.px_per_m,
                                                               self.tilt_deg, self.r2, self.noise_m, self.seen)],
                "left_out": [{"name": n, "why": w} for n, w in self.left_out], "noise_from": self.noise_from,
                "floor_mac": FLOOR_MAC,
                "modes": [{"mode": int(i) + 1, "label": self.labels[k] if self.labels else f"mode {int(i) + 1}",
                           "freq_hz": float(f), "mac": fin(m), "scale": fin(abs(sc)),
                           "scale_phase_deg": fin(np.degrees(np.angle(sc))), "expected_mac": float(e),
                           "below_floor": bool(e < FLOOR_MAC), "seen_share": float(sh), "judged": bool(j),
                           "state": self.state(k),
                           "video": [[float(1e6 * v.real), float(1e6 * v.imag)] for v in vr],
                           "accel": [[float(1e6 * a.real), float(1e6 * a.imag)] for a in ar]}
                          for k, (i, f, m, sc, e, vr, ar, sh, j) in enumerate(zip(
                              self.mode_index, self.freq_hz, self.mac, self.scale, self.expected_mac,
                              self.video_residues, self.accel_residues, self.seen_share, self.judged))]}


# ------------------------------------------------------------------------------------------------- force

def take_force(capture: Capture, force: str, take, poles_rad_s: np.ndarray) -> np.ndarray:
    """F(lambda_r) of one synced take's hammer pulse on the impact-locked timeline (scaled as sync scaled the
    take's motion when it normalised the impulses)."""
    with capture.open_take(take.name) as r:
        f = r.channel(force).astype(float)
        t0 = r.daq_t0_s - take.hit_daq_time_s
        fs = r.sample_rate_hz
    k0 = max(int((-t0 - 0.005) * fs), 0)                # the pulse and a little either side
    k1 = min(int((-t0 + 0.02) * fs), len(f))
    seg = f[k0:k1] - np.median(f[:max(k0, 1)])
    return force_transform(seg, fs, t0 + k0 / fs, poles_rad_s) * (take.impulse_scale or 1.0)


# -------------------------------------------------------------------------------------------------- pose

def view_pose(capture: Capture, take: str, *, at_rest: bool = False
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str] | None:
    """(K, R, t, where from) of the camera that filmed `take`: the pose stage's where it posed it, else the floor
    tags' in its first frame (the capture's intrinsics), else the structure's tags' there (`at_rest`: that frame
    precedes the hit); None where neither can."""
    if capture.paths.poses_json.exists():
        for v in PoseResult.read(capture).views:
            if v.name == take:
                return np.asarray(v.K, float), np.asarray(v.R, float), np.asarray(v.t, float), "the pose stage"
    cam, layout = capture.manifest.camera, capture.manifest.tags
    if cam.intrinsics is None or layout is None:
        log.info("%s: no pose (%s)", take, "no camera intrinsics" if cam.intrinsics is None else "no tag layout")
        return None
    K = cam.intrinsics.matrix()
    dist = np.asarray(cam.intrinsics.dist, float) if cam.intrinsics.dist else None
    frame = first_frame(capture, take)
    top = float(np.percentile(frame, 99.9)) or 1.0
    found = detect_tags(np.clip(frame / top * 255, 0, 255).astype(np.uint8), family=layout.family)
    pose = camera_pose_from_tags(found, layout, K, dist, min_tags=1)
    where = "floor "
    if pose is None or pose.center_m[2] <= 0:
        # the structure's own tags: at rest before a hit; in operation they move, by far less than the pose's error
        pose = camera_pose_from_tags(found, layout, K, dist, min_tags=1, use_structure_tags=True)
        where = "" if at_rest else "structure (moving: its motion is far below the pose's error) "
    if pose is None or pose.center_m[2] <= 0:
        log.info("%s: no pose from the tags in its first frame", take)
        return None
    return K, pose.R, pose.t, (f"{where}tags {', '.join(str(i) for i in pose.tag_ids)} in its first frame (PnP, "
                               f"{pose.rms_px:.2f} px rms)")


def _place(sensors: list[Sensor], K, R, t, shape: tuple[int, int], margin_px: int, max_tilt_deg: float
           ) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray, list[tuple[str, str]]]:
    """The sensors the view sees: their index, pixel (S, 2), axis image direction (S, 2, px per m) and tilt out of
    the image plane (S, degrees); the others with why."""
    h, w = shape
    keep, uvs, axes, tilts, out = [], [], [], [], []
    for i, sn in enumerate(sensors):
        if not sn.placed:
            out.append((sn.name, "no position or direction in the capture"))
            continue
        c = R @ sn.position_m + t
        if c[2] <= 0:
            out.append((sn.name, "behind the camera"))
            continue
        uv = (K @ c)[:2] / c[2]
        if not (margin_px <= uv[0] < w - margin_px and margin_px <= uv[1] < h - margin_px):
            out.append((sn.name, f"outside the frame (at {uv[0]:.0f},{uv[1]:.0f} px)"))
            continue
        j = project_displacement(sn.direction[None, None], sn.position_m[None], K, R, t)[0, 0]
        sight = (sn.position_m + R.T @ t) / np.linalg.norm(sn.position_m + R.T @ t)   # from the camera's centre
        tilt = float(np.degrees(np.arcsin(min(abs(float(sight @ sn.direction)), 1.0))))
        if tilt > max_tilt_deg:
            out.append((sn.name, f"its axis is {tilt:.0f} deg out of the image plane (at most {max_tilt_deg:g}): the "
                                 "view would read the motion along its line of sight into it"))
            continue
        keep.append(i)
        uvs.append(uv)
        axes.append(j)
        tilts.append(tilt)
    return keep, np.reshape(uvs, (-1, 2)), np.reshape(axes, (-1, 2)), np.asarray(tilts, float), out


# ---------------------------------------------------------------------------------------------- the check

def _view_takes(capture: Capture, max_takes: int) -> tuple[Any, list]:
    """The sync result and the synced takes with aligned frames of the first such view, up to max_takes."""
    if not capture.paths.sync_json.exists():       # sync did not apply (no take with frames): nothing to check
        return None, []
    sync = load_sync(capture)
    takes = [tk for tk in sync.ok if tk.aligned_file and capture.paths.listed(tk.aligned_file).is_file()]
    if not takes:
        return sync, []
    views = sorted({tk.view for tk in takes if tk.view is not None})
    first = [tk for tk in takes if tk.view == views[0]] if views else takes
    return sync, first[:max_takes]


def _box(points: np.ndarray, shape: tuple[int, int], window_px: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the pixels of a frame of `shape` (H, W) that windows at the points (P, 2) need, padded."""
    pad = window_px + 8
    h, w = shape
    return (max(int(points[:, 0].min()) - pad, 0), max(int(points[:, 1].min()) - pad, 0),
            min(int(points[:, 0].max()) + pad + 1, w), min(int(points[:, 1].max()) + pad + 1, h))


def _track(capture: Capture, sync, take, uv: np.ndarray, window_px: int, method: str
           ) -> tuple[np.ndarray, np.ndarray]:
    """The take's aligned frames in the sensors' box, tracked at uv: displacement (T, S, 2) px and times (T,)."""
    with AlignedTake(capture, capture.paths.listed(take.aligned_file), sync.generation) as ff:
        x0, y0, x1, y1 = _box(uv, ff.frame_shape[:2], window_px)

        def box(frame: np.ndarray) -> np.ndarray:
            frame = frame[y0:y1, x0:x1]
            return frame.mean(axis=-1) if frame.ndim == 3 else frame

        frames, times = ff.read_frames(spatial=box), ff.times_s
    tracks = track_points(frames, uv - [x0, y0], method=method, window_px=window_px)
    return tracks.displacement_px, times


def _exposure_gain(poles: np.ndarray, exposure_s: float | None) -> np.ndarray:
    """(R,) what a frame's exposure does to a mode's complex amplitude at mid-exposure: the mean of e^(s t) over
    the exposure, sinh(s T / 2) / (s T / 2)."""
    if not exposure_s:
        return np.ones(len(poles), complex)
    x = 0.5 * poles * exposure_s
    return np.sinh(x) / x


def _posed_sensors(capture: Capture, take: str, sensors, window_px: int, max_tilt_deg: float, *,
                   at_rest: bool = False):
    """The take's pose (view_pose) and the sensors it sees (_place, two windows from the border): (where the pose
    came from, index, pixel, axis image direction, tilt, the others with why); None without a pose."""
    pose = view_pose(capture, take, at_rest=at_rest)
    if pose is None:
        return None
    K, R, t, pose_from = pose
    cam = capture.manifest.camera
    shape = (cam.height_px or int(2 * K[1, 2] + 1), cam.width_px or int(2 * K[0, 2] + 1))
    placed = _place(list(sensors), K, R, t, shape, 2 * window_px + 3, max_tilt_deg)
    for n, why in placed[-1]:
        log.info("single view: %s left out: %s", n, why)
    return (pose_from, *placed)


def _candidates(uv: np.ndarray, window_px: int) -> np.ndarray:
    """(S, C, 2) the windows tried for each sensor: its pixel first, then a 5 x 5 grid up to a window's side away."""
    steps = np.array([0.0, -0.5, 0.5, -1.0, 1.0]) * window_px
    grid = np.array([(dx, dy) for dy in steps for dx in steps])
    return uv[:, None, :] + grid[None]


def _adjusted_r2(fit, times: np.ndarray) -> np.ndarray:
    """The decay fit's share of each channel's motion, less what as many parameters explain of pure noise."""
    return adjusted_r2(fit.r2, int(np.sum(times >= DECAY_T_MIN_S)), len(fit.poles_rad_s))


@dataclass
class _Fitted:
    residues: np.ndarray     # (R, S) m/N, averaged over the takes
    r2: np.ndarray           # (S,)
    noise_m: np.ndarray      # (S,) of the average
    noise_from: str
    force_abs: np.ndarray    # (R,) |F(lambda_r)|, averaged
    gain: np.ndarray         # (R,) design_gains


def _fit(capture: Capture, force: str, records, poles: np.ndarray, exposure_s: float | None) -> _Fitted:
    """Each take's readings (T, S) fitted at the poles, divided by its force; averaged over the takes."""
    residues, r2s, noises, forces, pre_ok = [], [], [], [], True
    for tk, x, times in records:
        fit = fit_decay(times, x, poles, t_min_s=DECAY_T_MIN_S)
        amps = fit.amplitudes / _exposure_gain(poles, tk.exposure_s or exposure_s)[:, None]
        forces.append(take_force(capture, force, tk, poles))
        residues.append(amps / forces[-1][:, None])
        r2s.append(_adjusted_r2(fit, times))
        pre = times < 0
        if pre.sum() >= MIN_PRE_FRAMES:
            noises.append(np.sqrt(np.mean((x[pre] - x[pre].mean(axis=0)) ** 2, axis=0)))
        else:
            pre_ok = False
            after = times >= DECAY_T_MIN_S
            noises.append(np.sqrt(np.mean((x[after] - fit.synthesize(times[after])) ** 2, axis=0)))
    return _Fitted(np.mean(residues, axis=0), np.mean(r2s, axis=0),
                   np.sqrt(np.mean(np.square(noises), axis=0)) / np.sqrt(len(records)),
                   "pre-impact frames" if pre_ok else "fit residual", np.mean(np.abs(forces), axis=0),
                   design_gains(records[0][2], poles, DECAY_T_MIN_S))


def _median(fitted: _Fitted, on: np.ndarray) -> _Fitted:
    """Each sensor's reading (S of them, C windows each; `on` (S, C) the windows kept) as its windows' median: of the
    residues (real and imaginary parts), the fit's share and the noise."""
    S, C = on.shape
    res = fitted.residues.reshape(len(fitted.residues), S, C)
    r2, noise = fitted.r2.reshape(S, C), fitted.noise_m.reshape(S, C)
    out_res = np.zeros((len(res), S), complex)
    out_r2, out_noise = np.full(S, -np.inf), np.full(S, np.nan)
    for k in range(S):
        w = on[k]
        if not w.any():
            continue
        out_res[:, k] = np.median(res[:, k, w].real, axis=1) + 1j * np.median(res[:, k, w].imag, axis=1)
        out_r2[k], out_noise[k] = np.median(r2[k, w]), np.median(noise[k, w])
    return dataclasses.replace(fitted, residues=out_res, r2=out_r2, noise_m=out_noise)


def sensor_view(capture: Capture, modes, sensors, force: str, *, max_takes: int = 4, window_px: int = 11,
                method: str = "gradient", max_tilt_deg: float = MAX_TILT_DEG) -> SensorView | None:
    """The accelerometers the first synced view sees, against the video there (module doc); None where no view
    has aligned frames, no pose can be had, no sensor is in view or no mode is in the camera's band."""
    sync, takes = _view_takes(capture, max_takes)
    if not takes:
        log.info("no single-view check: no synced take with aligned frames")
        return None
    placed = _posed_sensors(capture, takes[0].name, sensors, window_px, max_tilt_deg,
                            at_rest=takes[0].offset_s is not None and takes[0].offset_s < 0)
    if placed is None:
        return None
    pose_from, idx, uv, axes, tilts, left_out = placed
    cam = capture.manifest.camera
    if not idx:
        log.info("no single-view check: no accelerometer in view %s", takes[0].view)
        return None
    scale_px = np.linalg.norm(axes, axis=1)
    e = axes / scale_px[:, None]
    cand = _candidates(uv, window_px)                                              # (S, C, 2)
    S, C = cand.shape[:2]
    records = []
    for tk in takes:
        d_px, times = _track(capture, sync, tk, cand.reshape(-1, 2), window_px, method)
        x = np.einsum("tsci,si->tsc", d_px.reshape(len(times), S, C, 2), e) / scale_px[:, None]   # m along axes
        records.append((tk, x.reshape(len(times), -1), times))
    nyquist_hz = 0.5 / float(np.median(np.diff(records[0][2])))
    use = modes.freq_hz < BAND * nyquist_hz
    if not use.any():
        log.info("no single-view check: no accelerometer mode below %.0f Hz", BAND * nyquist_hz)
        return None
    poles = modes.poles_rad_s[use]
    # each sensor's windows: those tracked throughout whose motion the modes explain, moving at least half as much as
    # the one that moves most (on the structure, not astride its edge); their median is the sensor's reading
    fit0 = fit_decay(records[0][2], np.nan_to_num(records[0][1]), poles, t_min_s=DECAY_T_MIN_S)
    lost = ~np.all([np.isfinite(x).all(axis=0) for _, x, _ in records], axis=0)          # (S * C,)
    amp = np.where(lost | (_adjusted_r2(fit0, records[0][2]) < MIN_SENSOR_R2), 0.0,
                   np.linalg.norm(fit0.amplitudes, axis=0)).reshape(S, C)
    on = (amp >= ON_STRUCTURE * amp.max(axis=1, keepdims=True)) & (amp > 0)
    fitted = _fit(capture, force, [(tk, np.nan_to_num(x), times) for tk, x, times in records], poles, cam.exposure_s)
    fitted = _median(fitted, on)
    video, accel_all = fitted.residues, np.asarray(modes.shapes)[use]
    accel = accel_all[:, idx]
    seen = fitted.r2 >= MIN_SENSOR_R2
    mac, scale = _compare(video[:, seen], accel[:, seen])
    # the noise's share of each mode's fitted amplitude: sd of 2|C| per unit noise (design_gains), per channel
    signal = np.sum(np.abs(2 * video[:, seen]) ** 2, axis=1)
    noise_power = np.sum((fitted.gain[:, None] * fitted.noise_m[seen][None] / fitted.force_abs[:, None]) ** 2, axis=1)
    expected = np.array([floor_mac(s / max(nz, 1e-300)) for s, nz in zip(signal, noise_power)])
    placed = [k for k, sn in enumerate(sensors) if sn.placed]
    share = np.linalg.norm(accel[:, seen], axis=1) / np.maximum(np.linalg.norm(accel_all[:, placed], axis=1), 1e-300)
    out = SensorView(takes[0].view, tuple(tk.name for tk in takes), pose_from, tuple(sensors[i].name for i in idx),
                     uv, on.sum(axis=1), scale_px, tilts, tuple(left_out), np.flatnonzero(use),
                     modes.freq_hz[use], video, accel, fitted.r2, fitted.noise_m, fitted.noise_from, mac, scale,
                     expected, share)
    log.info("%s", out.text())
    return out


# ------------------------------------------------------------------------------------------ without force

def _daq_clock(capture: Capture, take: str):
    """The take's sync record where sync put its frames on its DAQ's clock (flag "daq_clock"), else None."""
    if not capture.paths.sync_json.exists():
        return None
    return next((tk for tk in load_sync(capture).ok if tk.name == take and "daq_clock" in tk.flags), None)


def _at_frames(a: np.ndarray, fs: float, t0_s: float, frame_mid_s: np.ndarray, fps: float,
               exposure_s: float) -> np.ndarray:
    """Samples a (N, C) at fs from t0_s, as the camera sees them: low-passed under 0.45 fps (zero phase), averaged
    over each frame's exposure and read at its middle (T, C)."""
    from scipy.interpolate import CubicSpline
    from scipy.signal import butter, sosfiltfilt
    x = sosfiltfilt(butter(8, 0.45 * fps, fs=fs, output="sos"), a, axis=0)
    n = max(int(round(exposure_s * fs)), 1)
    if n > 1:
        c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
        x = (c[n:] - c[:-n]) / n
        t0_s += 0.5 * (n - 1) / fs                      # the mean over samples k..k+n-1 stands at their middle
    t = t0_s + np.arange(len(x)) / fs
    return CubicSpline(t, x, axis=0, extrapolate=False)(frame_mid_s)


def _raw_tracks(capture: Capture, take: str, points: np.ndarray, window_px: int, method: str) -> np.ndarray:
    """The take's raw frames (mono, in the points' box) tracked at points (P, 2): displacement (T, P, 2) px."""
    cam = capture.manifest.camera
    x0, y0, x1, y1 = _box(points, (cam.height_px or 1 << 30, cam.width_px or 1 << 30), window_px)
    boxed = (f[y0:y1, x0:x1] for f in frames(capture, take))
    return track_points(boxed, points - [x0, y0], method=method, window_px=window_px).displacement_px


def sensor_ods(capture: Capture, video2d, sensors, *, window_px: int = 11, method: str = "gradient",
               max_tilt_deg: float = MAX_TILT_DEG) -> SensorView | None:
    """Without force: the accelerometers the 2D path's view sees against the video there, at the 2D path's modes
    (video2d: its Video2DResult). Where sync put the take's frames on its DAQ's clock, each sensor's reading (the
    median over its windows on the structure, as with force) and every accelerometer, filtered and sampled as the
    camera sees it, share one FDD: the ODS at each mode's line (`oma.ods_at`, the 2D path's segment length) holds
    both on one phase, the accelerometers' in metres (over -(2 pi f)^2). Per mode: MAC, scale, what the readings'
    noise allows, the share of its motion the sensors compared carry; per sensor, the coherence of its reading with
    its accelerometer near the modes (its `r2`). None where there is nothing to compare."""
    from .oma import default_nperseg, noise_psd, ods_lines
    placed = [sn for sn in sensors if sn.placed]
    if not video2d.modes or not placed:
        return None
    tk = _daq_clock(capture, video2d.take)
    if tk is None:
        log.info("no single-view check: %s's frames are not on its DAQ's clock", video2d.take)
        return None
    seen = _posed_sensors(capture, video2d.take, sensors, window_px, max_tilt_deg)
    if seen is None:
        return None
    pose_from, idx, uv, axes, tilts, left_out = seen
    if not idx:
        log.info("no single-view check: no accelerometer in view %s", video2d.view)
        return None
    fps = video2d.fps
    scale_px = np.linalg.norm(axes, axis=1)
    cand = _candidates(uv, window_px)
    S, C = cand.shape[:2]
    d = _raw_tracks(capture, video2d.take, cand.reshape(-1, 2), window_px, method)
    x = np.einsum("tsci,si->tsc", d.reshape(len(d), S, C, 2), axes / scale_px[:, None]) / scale_px[:, None]
    with capture.open_take(video2d.take) as r:
        counters = r.frame_counter.astype(float)
        a = np.stack([r.channel(sn.name).astype(float) for sn in placed], axis=1)
        t_daq0, fs = r.daq_t0_s - tk.frame0_daq_time_s, r.sample_rate_hz
    mid = counters * tk.period_s + tk.offset_s                                   # the frames' mid-exposure times
    acc = _at_frames(a, fs, t_daq0, mid, fps, tk.exposure_s or 0.0)
    lost = ~np.all(np.isfinite(x), axis=0)                                       # (S, C) windows lost somewhere
    ok = np.all(np.isfinite(acc), axis=1)                                        # frames the DAQ's record covers
    x, acc = np.nan_to_num(x[ok]), acc[ok]
    if ok.sum() < 64:
        log.info("no single-view check: %d frames have the DAQ's samples around them", ok.sum())
        return None
    nperseg = video2d.oma.fdd.nperseg if video2d.oma is not None else default_nperseg(len(x))
    nperseg = min(nperseg, len(x))
    f_hz = np.array([m.freq_hz for m in video2d.modes])
    # each sensor's windows on the structure: those that move at least half as much as its most moving one
    amp = np.linalg.norm(ods_lines(x.reshape(len(x), -1), fps, f_hz, nperseg=nperseg), axis=0).reshape(S, C)
    amp = np.where(lost, 0.0, amp)
    on = (amp >= ON_STRUCTURE * amp.max(axis=1, keepdims=True)) & (amp > 0)
    if not on.any(axis=1).all():
        log.info("no single-view check: %s: no window tracked around it", [sensors[i].name for i in
                                                                          np.array(idx)[~on.any(axis=1)]])
        return None
    reading = np.stack([np.median(x[:, k, on[k]], axis=1) for k in range(S)], axis=1)        # (T, S) m
    joint = np.concatenate([reading, acc], axis=1)
    pos = [placed.index(sensors[i]) for i in idx]
    v = ods_lines(joint, fps, f_hz, nperseg=nperseg)                                    # (R, S + all accelerometers)
    video, am = v[:, :S], v[:, S:] / -(2 * np.pi * f_hz[:, None]) ** 2                  # accelerations in metres
    accel = am[:, pos]
    share = np.linalg.norm(accel, axis=1) / np.maximum(np.linalg.norm(am, axis=1), 1e-300)
    coherence = _coherence(reading, acc[:, pos], fps, f_hz, nperseg)
    seen = coherence >= MIN_SENSOR_R2
    mac, scale = _compare(video[:, seen], accel[:, seen])
    lo, hi = video2d.oma.band_hz if video2d.oma is not None else (0.0, 0.45 * fps)
    level = noise_psd(reading, fps, nperseg=nperseg, fmin_hz=lo, fmax_hz=hi, exclude_hz=f_hz)      # m^2/Hz
    expected = np.array([floor_mac(np.sum(np.abs(vr[seen]) ** 2) / max(np.sum(level[seen]), 1e-300))
                         for vr in video])
    labels = tuple(f"{m.label} {k + 1}" for k, m in enumerate(video2d.modes))
    out = SensorView(video2d.view, (video2d.take,), pose_from, tuple(sensors[i].name for i in idx), uv,
                     on.sum(axis=1), scale_px, tilts, tuple(left_out), np.arange(len(f_hz)), f_hz, video, accel,
                     coherence, np.sqrt(level * (hi - lo)), "noise PSD between the modes", mac, scale, expected,
                     share, method="ods", labels=labels)
    log.info("%s", out.text())
    return out


def _coherence(reading: np.ndarray, acc: np.ndarray, fps: float, f_hz: np.ndarray, nperseg: int) -> np.ndarray:
    """(S,) each reading's magnitude-squared coherence with its accelerometer, averaged over the lines within 3
    lines of the modes (segments an eighth of the record, at most nperseg: coherence needs averages)."""
    from scipy.signal import coherence
    n = max(min(nperseg, len(reading) // 8), 16)
    f, c = coherence(reading, acc, fs=fps, nperseg=n, axis=0)
    near = np.zeros(len(f), bool)
    for f0 in f_hz:
        near |= np.abs(f - f0) <= 3 * fps / n
    return c[near].mean(axis=0) if near.any() else np.zeros(reading.shape[1])


def _compare(video: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R,) MAC (NaN over fewer than 2 sensors) and complex scale (video ~ scale x accel) per mode."""
    R = video.shape[0]
    if video.shape[1] == 0:
        return np.full(R, np.nan), np.full(R, np.nan, complex)
    mac = np.diag(mac_matrix(accel, video)) if video.shape[1] >= 2 else np.full(R, np.nan)
    return mac, modal_scale_factor(video, accel)


__all__ = ["SensorView", "sensor_ods", "sensor_view", "take_force", "view_pose"]
