"""One camera, one view, no DAQ: a video of a structure in operation, as a phone or a lone high-speed camera films it,
written as files `odsplat import` reads (a `.npy` of frames and a rig file), with its ground truth beside them.

The structure is excited either by a train of random hammer pulses at the rig's hammer point (`excitation =
"ambient"`: unmeasured, broadband, what an operating machine gets) or by one hit (`"hit"`) that nobody records. The
truth holds the camera, the rest depth of every pixel and the modal coordinates at every frame, so the image
motion of each mode at any pixel is known exactly to first order (`VideoTruth.image_shapes`)."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from odsplat.analysis import project_displacement
from odsplat.spine.atomic import atomic_open, atomic_write_text
from odsplat.spine.errors import InputError

from .camera import SimCameraConfig
from .render import PinholeCamera
from .rig import HAMMER, make_rig, open_truth, read_fields, save_fields
from .scene import STRUCTURE, STRUCTURE_TAG
from .structure import STRUCTURES, Impact, make_structure

log = logging.getLogger(__name__)

EXCITATIONS = ("ambient", "hit")
PAD_S = 0.01      # the accelerometers' record starts this much before the first frame and ends this much after
# A view of each rig from the side and a little above, so that every mode moves across the image somewhere.
VIEWS = {"arm": ((1.25, 0.95, 0.95), (0.2, 0.0, 0.45)),
         "plate": ((0.9, 0.75, 0.75), (0.0, 0.0, 0.1)),
         "frame": ((1.1, 1.0, 0.8), (0.2, 0.0, 0.35)),
         "mast": ((1.0, 0.85, 0.55), (0.2, 0.0, 0.35))}


@dataclass(frozen=True)
class VideoSimSettings:
    structure: str = "arm"
    width_px: int = 256
    height_px: int = 192
    fov_deg: float = 28.0
    fps: float = 2000.0
    n_frames: int = 1024
    excitation: str = "ambient"
    pulses_per_s: float = 400.0   # ambient: mean rate of the random pulses
    peak_n: float = 60.0          # ambient: rms peak of a pulse; hit: the hit's peak
    supersample: int = 3          # the renderer's samples per pixel side (anti-aliasing)
    seed: int = 0
    accelerometers: bool = False  # also record the rig's accelerometers (signals.csv), on the camera's clock
    daq_rate_hz: float = 16000.0
    eye_m: tuple[float, float, float] | None = None     # the camera's centre; None: VIEWS[structure]
    target_m: tuple[float, float, float] | None = None  # where it looks; None: VIEWS[structure]

    def __post_init__(self) -> None:
        if self.structure not in STRUCTURES:
            raise InputError("VideoSimSettings.structure", f"expected one of {', '.join(STRUCTURES)}; "
                                                            f"got {self.structure!r}")
        if self.excitation not in EXCITATIONS:
            raise InputError("VideoSimSettings.excitation", f"expected one of {', '.join(EXCITATIONS)}; "
                                                             f"got {self.excitation!r}")
        if not (16 <= self.width_px <= 4096 and 16 <= self.height_px <= 4096):
            raise InputError("VideoSimSettings.width_px", f"expected 16 to 4096 px; got {self.width_px}x"
                                                           f"{self.height_px}")
        if not (self.n_frames >= 16 and self.fps > 0 and self.pulses_per_s > 0 and self.peak_n > 0):
            raise InputError("VideoSimSettings", "expected n_frames >= 16 and fps, pulses_per_s, peak_n > 0")
        if not self.daq_rate_hz >= 2 * self.fps:
            raise InputError("VideoSimSettings.daq_rate_hz", f"expected at least twice the frame rate; got "
                                                              f"{self.daq_rate_hz}")


@dataclass(frozen=True)
class VideoTruth:
    """What the video really shows: the camera, each pixel's rest depth, the structure's modes and the modal
    coordinates at the middle of every frame's exposure."""

    structure: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    depth_m: np.ndarray          # (H, W) rest depth (camera z) at pixel centres, inf off the structure's scene
    on_structure: np.ndarray     # (H, W) bool: the pixel sees a moving part of the structure
    fps: float
    freqs_hz: np.ndarray
    dampings: np.ndarray
    mode_names: np.ndarray
    modal_q: np.ndarray          # (n_modes, T)

    def rest_points_m(self, points_px: np.ndarray) -> np.ndarray:
        """The world points (P, 3) that pixels (P, 2) (x, y) see at rest (nearest pixel's depth)."""
        p = np.asarray(points_px, float)
        ix = np.clip(np.rint(p[:, 0]).astype(int), 0, self.depth_m.shape[1] - 1)
        iy = np.clip(np.rint(p[:, 1]).astype(int), 0, self.depth_m.shape[0] - 1)
        z = self.depth_m[iy, ix]
        ray = np.linalg.solve(self.K, np.stack([p[:, 0], p[:, 1], np.ones(len(p))]))  # (3, P)
        cam = ray * z
        return (self.R.T @ (cam - self.t[:, None])).T

    def image_shapes(self, points_px: np.ndarray) -> np.ndarray:
        """Each mode's first-order image motion (n_modes, P, 2) (x, y) in px per unit modal coordinate at pixels
        (P, 2); zero where the pixel does not see the structure."""
        p = np.asarray(points_px, float)
        X = self.rest_points_m(p)
        ok = np.isfinite(X).all(axis=1)
        phi = np.zeros((len(p), len(self.freqs_hz), 3))
        phi[ok] = make_structure(self.structure).mode_shapes(X[ok])
        out = np.zeros((len(self.freqs_hz), len(p), 2))
        if ok.any():
            out[:, ok] = project_displacement(np.moveaxis(phi[ok], 1, 0), X[ok], self.K, self.R, self.t)
        return out

    def save(self, path: str | Path) -> Path:
        return save_fields(self, path)

    @classmethod
    def load(cls, path: str | Path) -> VideoTruth:
        with open_truth(path) as data:
            return cls(**read_fields(cls, data, path))


def _pulses(s: VideoSimSettings, t0_s: float, t1_s: float) -> list[Impact]:
    point, d = HAMMER[s.structure]
    direction = tuple(float(v) for v in np.asarray(d, float) / np.linalg.norm(d))
    if s.excitation == "hit":
        return [Impact(t0_s + 0.1 * (t1_s - t0_s), point, direction, peak_n=s.peak_n)]
    rng = np.random.default_rng(s.seed)
    n = rng.poisson(s.pulses_per_s * (t1_s - t0_s))
    times = np.sort(rng.uniform(t0_s, t1_s, n))
    peaks = rng.normal(0.0, s.peak_n, n)
    return [Impact(float(t), point, direction, peak_n=float(f)) for t, f in zip(times, peaks)]


def simulate_video(out: str | Path, settings: VideoSimSettings | None = None, *, progress: bool = False) -> Path:
    """Film the structure with one camera into the folder `out` (created): `video.npy` (T, H, W) uint16 12-bit
    frames, `rig.toml` (for `odsplat import rig.toml -o CAPTURE`) and `truth.npz` (`VideoTruth`). Returns the rig
    file's path. Ambient excitation starts 1 s before the first frame, so the record is stationary."""
    s = settings or VideoSimSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rig = make_rig(s.structure, seed=s.seed)
    eye, target = VIEWS[s.structure]
    eye, target = s.eye_m or eye, s.target_m or target
    pin = PinholeCamera.look_at(eye, target, fov_deg=s.fov_deg, width_px=s.width_px, height_px=s.height_px)
    cam = rig.mount_camera(pin, SimCameraConfig(fps=s.fps, supersample=s.supersample), seed=s.seed)
    lead_s = 1.0 if s.excitation == "ambient" else 0.0
    t_start_s = 0.01 + lead_s
    duration_s = s.n_frames / s.fps
    rig.add_impacts(_pulses(s, 0.0 if lead_s else t_start_s, t_start_s + duration_s))
    cam.arm(n_frames=s.n_frames, pretrigger=0, trigger="internal", at_s=t_start_s)
    frames = np.empty((s.n_frames, s.height_px, s.width_px), np.uint16)
    for i, frame in enumerate(tqdm(cam.frames(), total=s.n_frames, desc="sim video", disable=not progress)):
        frames[i] = frame.image
    rec = cam.recording
    mid = rec.exposure_start_s + 0.5 * cam.config.exposure
    rest = cam.truth(t_start_s, alpha=0.0)
    moving = np.isin(rest.object_id, (STRUCTURE, STRUCTURE_TAG))
    st = rig.structure
    truth = VideoTruth(s.structure, pin.K, pin.R, pin.t, rest.depth_m, moving, s.fps, st.freqs_hz, st.dampings,
                       np.array([m.name for m in st.modes]), st.modal_response(rig.impacts, mid).q)
    truth.save(out / "truth.npz")
    with atomic_open(out / "video.npy", "wb") as f:
        np.save(f, frames)
    signals = ""
    if s.accelerometers:
        signals = _record_accelerometers(out / "signals.csv", rig, s, t_start_s - PAD_S, duration_s + 2 * PAD_S,
                                         float(rec.exposure_start_s[0]))
    atomic_write_text(out / "rig.toml", _rig_toml(s, pin.K, cam.config.exposure) + signals + _tags_toml(rig.scene.tags))
    log.info("simulated %d frames of the %s at %g fps (%s) into %s", s.n_frames, s.structure, s.fps, s.excitation,
             out)
    return out / "rig.toml"


def _record_accelerometers(path: Path, rig, s: VideoSimSettings, t0_s: float, duration_s: float,
                           frame0_s: float) -> str:
    """The rig's DAQ accelerometers from t0_s for duration_s at s.daq_rate_hz into the CSV `path` (a time column in
    the camera's time base, then m/s^2 with 0.1 % of each one's rms as noise), and the rig file's lines for them: the
    channels, and the take's signals with the time of frame 0's exposure start on that clock."""
    acc = rig.config.accelerometers
    t = t0_s + np.arange(int(round(duration_s * s.daq_rate_hz))) / s.daq_rate_hz
    a = rig.accelerations_m_s2(t).T
    rng = np.random.default_rng(s.seed + 1)
    a = a + rng.normal(size=a.shape) * 1e-3 * np.sqrt(np.mean(a ** 2, axis=0))
    lines = ["time_s," + ",".join(x.name for x in acc)]
    lines += [f"{ti:.9f}," + ",".join(f"{v:.7g}" for v in row) for ti, row in zip(t, a)]
    atomic_write_text(path, "\n".join(lines) + "\n")
    out = f'signals = "{path.name}"\ncamera_trigger_time_s = {frame0_s!r}\ntrigger_frame = 0\n'
    for x in acc:
        out += (f'\n[[channels]]\nname = "{x.name}"\nkind = "acceleration"\nunit = "m/s^2"\n'
                f"position_m = {list(map(float, x.point_m))}\ndirection = {list(map(float, x.direction))}\n")
    return out


def _rig_toml(s: VideoSimSettings, K: np.ndarray, exposure_s: float) -> str:
    daq = "its accelerometers on the camera's clock" if s.accelerometers else "no DAQ"
    return (f'name = "video-{s.structure}"\n'
            f'notes = "hil_sim: one camera, {s.excitation} excitation, {daq}"\n\n'
            f'[camera]\nmodel = "simulated"\nbit_depth = 12\nexposure_s = {float(exposure_s)!r}\n'
            f'intrinsics = {{ fx_px = {float(K[0, 0])!r}, fy_px = {float(K[1, 1])!r}, cx_px = {float(K[0, 2])!r}, '
            f'cy_px = {float(K[1, 2])!r} }}\n\n'
            f'[[takes]]\nname = "video"\nview = 0\nvideo = "video.npy"\nfps = {s.fps!r}\n')


def _tags_toml(layout) -> str:
    """The scene's tags as the rig file's [tags] table: the scale can come from one on the structure."""
    out = f'\n[tags]\nfamily = "{layout.family}"\nsize_m = {layout.size_m!r}\n'
    for t in layout.tags:
        corners = ", ".join("[" + ", ".join(repr(float(v)) for v in c) + "]" for c in t.corners_m)
        out += (f"\n[[tags.tags]]\nid = {t.id}\ncorners_m = [{corners}]\n"
                f"on_structure = {'true' if t.on_structure else 'false'}\n")
        if t.size_m:
            out += f"size_m = {t.size_m!r}\n"
    return out


__all__ = ["EXCITATIONS", "VIEWS", "VideoSimSettings", "VideoTruth", "simulate_video"]
