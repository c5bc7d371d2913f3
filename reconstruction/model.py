"""Reconstruct a capture: posed views -> Gaussians at rest -> per-timestep motion; the saved model and its renders.

Output in `derived/reconstruction/`, every path from `Capture.paths` (odsplat.spine.paths, the one place that names
them):
- `gaussians_t0.ply`: the rest state in the INRIA layout (world frame, metres), for standard splat viewers;
- `trajectories.npz`: everything needed to render any time (see `DynamicScene`), world frame, metres;
- `measured_motion.npz` (the linear motion model only): the node graph's motion with every temporal component
  kept, in the same keys as `trajectories.npz`'s motion (`times_s`, `means_rest_m`, `displacement_m`,
  `opacity_logits`, `source_alpha`); the analysis fits its mode shapes to this;
- `reconstruction.json`: settings, views, timesteps, per-stage figures.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from odsplat.spine.atomic import atomic_path, atomic_write_text
from odsplat.spine.checks import (
    FRAME_INDEX,
    MAX_FRAMES,
    WIDTH_PX,
    WORKERS,
    Range,
    check_choice,
    check_fields,
    maybe,
    shown,
)
from odsplat.spine.contract import CAPTURE_KEY, check, describe, numeric, plain, read_npz
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import look_at
from odsplat.spine.manifest import load_json, utc_now
from odsplat.spine.mp4 import write_mp4
from odsplat.spine.paths import DerivedPaths
from odsplat.spine.store import Capture

from .dynamic import FitSettings, Trajectory, fit_dynamic, fit_static, render
from .gaussians import Gaussians, save_ply
from .linear import LinearSettings, NodeMotion, fit_linear, median_footprint_m, node_spacing
from .modal import ModalMotion, ModalSettings, fit_modal
from .pose_result import PoseResult
from .quaternion import quat_conjugate, quat_from_rotvec, quat_multiply, quat_normalize, quat_to_rotvec
from .views import Camera, SceneFrame, ViewSet, load_views, pose_camera

log = logging.getLogger(__name__)

KIND = "odsplat.reconstruction"
SCHEMA = 2
MOTIONS = ("modal", "timestep", "linear")
# The timesteps when n_timesteps is not given. The linear model fits the whole record in one solve (the analysis
# needs cycles of the lowest mode: on the demo, 32 ms of 23.5 Hz read its scale 0.75 and the video's own poles 1 of
# 6; the record's 122 ms read 0.86-0.94 and 4 of 6, docs/reconstruction.md), capped so that a long record's frames
# at training width stay within memory; a per-timestep fit costs seconds per timestep.
RECORD_TIMESTEPS = 512
TIMESTEP_DEFAULT = 32
MIN_WORKING_PX = 128   # the rest fit's narrowest working width (the default until 2026-11-28)


def default_source(motion: str) -> str:
    """The frames a motion model fits unless told otherwise: the paper's per-timestep order the 2D-magnified
    ones, the others the raw frames on the common grid (they magnify in 3D, at render time)."""
    return "magnified/phase" if motion == "timestep" else "sync"


@dataclass(frozen=True)
class ReconstructSettings:
    source: str | None = None            # "sync" (unmagnified, on the common grid) or "magnified/METHOD";
    #                                      None: default_source(motion)
    width_px: int | None = None          # the rest fit's image width (height by aspect); None: from the views'
    #                                      footprint (working_width)
    n_timesteps: int | None = None       # None: the record (every timestep from start to the grid's end, at most
    #                                      RECORD_TIMESTEPS) for the linear and modal models, which fit every
    #                                      timestep at once; TIMESTEP_DEFAULT for the per-timestep fits (their cost)
    step: int = 1                        # grid frames between timesteps
    start: int | None = None             # first grid frame (default: the last before the impact, at rest)
    holdout: tuple[str, ...] = ()        # takes never used in training (for evaluation)
    use_static: bool = True              # condition the t=0 fit on static photos too
    init_opacity: float = 0.1
    threads: int | None = None          # torch threads (default: torch's)
    motion: str = "linear"               # "linear" (linear.py: one linear solve on the raw frames; measures best,
    #                                      docs/reconstruction.md), "modal" (modal.py: one basis, all at once) or
    #                                      "timestep" (a fit per timestep, the paper's)
    fit: FitSettings = FitSettings()     # the rest fit, and the per-timestep fits when motion == "timestep"
    modal: ModalSettings = ModalSettings()
    linear: LinearSettings = LinearSettings()

    @property
    def timesteps(self) -> int | None:
        """The timesteps to fit: n_timesteps as given, else None (the record, capped) for the models that fit every
        timestep at once, TIMESTEP_DEFAULT for the per-timestep fits."""
        if self.n_timesteps is not None:
            return self.n_timesteps
        return TIMESTEP_DEFAULT if self.motion == "timestep" else None

    def __post_init__(self) -> None:
        check_choice("ReconstructSettings.motion", self.motion, MOTIONS)
        # n_timesteps: a second at 100k frames/s; every model holds all of them in memory at once.
        check_fields(self, {"width_px": maybe(WIDTH_PX),
                            "n_timesteps": maybe(Range(at_least=1, at_most=100_000, integer=True)),
                            "step": Range(at_least=1, at_most=MAX_FRAMES, integer=True), "start": maybe(FRAME_INDEX),
                            "init_opacity": Range(above=0, below=1), "threads": maybe(WORKERS)})
        if self.source is None:
            object.__setattr__(self, "source", default_source(self.motion))
        # METHOD names a folder of derived/magnified/: a word, never a path.
        kind, _, method = self.source.partition("/") if isinstance(self.source, str) else ("", "", "")
        if self.source != "sync" and not (kind == "magnified" and method.isidentifier() and len(method) <= 32):
            raise InputError("source", f"expected 'sync' or 'magnified/METHOD', got {shown(self.source)}")
        if self.motion == "linear" and self.source != "sync":
            raise InputError("source", f"the linear motion model reads the raw frames: expected 'sync', got "
                                       f"{shown(self.source)} (it magnifies in 3D, at render time)")


def _poses(capture: Capture):

    return PoseResult.read(capture)


def initial_points(poses, scene: SceneFrame, n_colors: int, rng: np.random.Generator,
                   n_random: int = 5000) -> tuple[np.ndarray, np.ndarray, str]:
    """SfM points in scene coordinates with their colours; random points in the cameras' common view when none."""
    pts = np.asarray(getattr(poses, "points_m", np.zeros((0, 3))), float).reshape(-1, 3)
    if len(pts) >= 16:
        col = np.asarray(poses.points_color, float).reshape(len(pts), -1)
        if col.shape[1] != n_colors:
            col = np.repeat(col.mean(axis=1, keepdims=True), n_colors, axis=1)
        return scene.to_scene(pts), col, "sfm"
    # Without points (tag-only poses and no triangulation), a uniform cloud around the cameras' look-at point.
    target = look_at_point([v.R for v in poses.views], [v.t for v in poses.views])
    dist = np.median([np.linalg.norm(v.center_m - target) for v in poses.views])
    box = rng.uniform(-0.5, 0.5, (n_random, 3)) * dist
    return scene.to_scene(target + box), np.full((n_random, n_colors), 0.5), "random"


def look_at_point(Rs, ts) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares): what the views look at."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for R, t in zip(Rs, ts):
        R, t = np.asarray(R, float), np.asarray(t, float)
        c, d = -R.T @ t, R[2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    return np.linalg.lstsq(A, b, rcond=None)[0]


@dataclass(frozen=True)
class WorkingWidth:
    """The rest fit's image width and why: as set, or from the views' footprint."""

    width_px: int
    why: str


def working_width(poses, s: ReconstructSettings) -> WorkingWidth:
    """The rest fit's image width. As set; else, for the linear motion model, wide enough that a working pixel is
    at most half the motion's node spacing (the spacing `node_spacing` gives at full resolution: NODE_PX of the
    views' footprint, at least the scene radius / 100), so the rest geometry resolves every node; at least
    MIN_WORKING_PX, at most the views' width, a multiple of 16. The motion itself is read at full resolution.
    The other models fit at MIN_WORKING_PX (their per-timestep cost)."""
    if s.width_px is not None:
        return WorkingWidth(s.width_px, "as set (reconstruct.width_px)")
    if s.motion != "linear":
        return WorkingWidth(MIN_WORKING_PX, f"the {s.motion} model's default")
    views = [v for v in poses.views if v.kind == "take" and v.name not in s.holdout]
    if not views:
        return WorkingWidth(MIN_WORKING_PX, "no posed takes")
    cams = [Camera(np.asarray(v.K, float), np.asarray(v.R, float), np.asarray(v.t, float), v.width_px,
                   v.height_px, v.name) for v in views]
    pts = np.asarray(getattr(poses, "points_m", np.zeros((0, 3))), float).reshape(-1, 3)
    if len(pts) < 16:          # tag-only poses: what the views look at stands for the structure
        pts = look_at_point([c.R for c in cams], [c.t for c in cams])[None]
    scene = SceneFrame.fit(np.array([c.center for c in cams]))
    # Not widened for max_nodes: the pose stage's points (the floor, outliers) fill more cells than the rest
    # fit's opaque Gaussians do; where the fit widens it, the width errs on the fine side.
    spacing = node_spacing(pts, cams, scene, s.linear, widen=False)
    footprint = median_footprint_m(pts, cams)
    native = int(np.median([c.width_px for c in cams]))
    if not np.isfinite(footprint):
        return WorkingWidth(MIN_WORKING_PX, "no structure point in front of the views")
    spacing_px = spacing / footprint          # in the views' own pixels
    need = 16 * int(np.ceil(2 * native / spacing_px / 16))
    width = int(min(max(need, MIN_WORKING_PX), max(native, MIN_WORKING_PX)))
    return WorkingWidth(width, f"node spacing {spacing * 1e3:.1f} mm = {spacing_px:.1f} px of the {native} px views; "
                               f"2 working px a node needs {need} px (at least {MIN_WORKING_PX}, at most the views')")


@dataclass
class ReconstructResult:
    out_dir: Path
    n_gaussians: int
    n_views: int
    n_static: int
    n_timesteps: int
    seconds_t0: float
    seconds_dynamic: float
    psnr_t0_db: float
    psnr_last_db: float
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        return (f"{self.n_gaussians} Gaussians from {self.n_views} views (+{self.n_static} static) over "
                f"{self.n_timesteps} timesteps: t=0 fit {self.seconds_t0:.0f} s (train PSNR {self.psnr_t0_db:.1f} dB), "
                f"dynamic {self.seconds_dynamic:.0f} s (last timestep {self.psnr_last_db:.1f} dB) -> {self.out_dir}")

    @classmethod
    def read(cls, capture: Capture) -> ReconstructResult:
        """The last reconstruction's figures from reconstruction.json (the model itself: `DynamicScene.load`);
        a file of another kind, schema or capture is refused with one line."""
        path = capture.paths.reconstruction_json
        doc = load_json(path, missing="no reconstruction here (run `odsplat reconstruct` first)")
        check(doc, path, kind=KIND, schema_version=SCHEMA, capture_id=capture.id)
        r = doc.get("result")
        if not isinstance(r, dict):
            raise InputError(f"{path}: result", f"expected an object, got {type(r).__name__}; run `odsplat "
                                                "reconstruct` again")
        counts, figures = ("n_gaussians", "n_views", "n_static", "n_timesteps"), ("seconds_t0", "seconds_dynamic",
                                                                                  "psnr_t0_db", "psnr_last_db")
        bad = [k for k in counts if not isinstance(r.get(k), int) or isinstance(r.get(k), bool)]
        bad += [k for k in figures if not isinstance(r.get(k), (int, float)) or isinstance(r.get(k), bool)]
        bad += [k for k, kind in (("out_dir", str), ("notes", list)) if not isinstance(r.get(k, []), kind)]
        if bad or "out_dir" not in r:
            raise InputError(f"{path}: result", f"{', '.join(bad or ['out_dir'])}: missing or of the wrong type; run "
                                                "`odsplat reconstruct` again")
        return cls(Path(r["out_dir"]), *(r[k] for k in counts), *(float(r[k]) for k in figures),
                   [str(n) for n in r.get("notes", [])])


def _psnr(g: Gaussians, views, t: int, means=None, quats=None, background=0.0) -> float:
    with torch.no_grad():
        errs = [float(((render(g, v.camera, means=means, quats=quats, background=background).image - v.images[t]) ** 2)
                      .mean()) for v in views]
    return float(10 * np.log10(1.0 / max(np.mean(errs), 1e-12)))


@dataclass
class Model:
    """A trained model in scene coordinates: the rest Gaussians, their motion, and what it was trained on."""

    g0: Gaussians
    trajectory: Trajectory
    views: ViewSet
    stats_t0: dict
    seconds_dynamic: float
    init: str
    background: torch.Tensor
    modal: ModalMotion | None = None
    linear: dict | None = None           # the linear solve's figures
    measured: NodeMotion | None = None   # the linear solve's unfiltered node motion

    def scene(self) -> DynamicScene:
        return DynamicScene.from_model(self.g0, self.trajectory, self.views, self.background, self.modal)


def train(vs: ViewSet, poses, settings: ReconstructSettings, capture: Capture | None = None) -> Model:
    """Fit the rest state to every view's rest frames (and static photos), then the motion (modal, per timestep, or
    linear: that one reads the capture's full-resolution raw frames)."""
    s = settings
    if s.threads:
        torch.set_num_threads(s.threads)
    rng = np.random.default_rng(s.fit.seed)
    pts, col, init = initial_points(poses, vs.scene, vs.n_colors, rng)
    g = Gaussians.from_points(pts, col, opacity=s.init_opacity)
    rest = [(v.camera, v.rest_image) for v in vs.views] + [(v.camera, v.images[0]) for v in vs.static]
    g0, stats0 = fit_static(g, rest, s.fit)
    log.info("t=0: %d Gaussians in %.0f s", len(g0), stats0["seconds"])
    background = torch.tensor(stats0["background"], dtype=g0.means.dtype)
    t1 = time.perf_counter()
    modal = linear = measured = None
    if s.motion == "modal":
        modal = fit_modal(g0, vs.views, s.modal, background)
        traj = modal.trajectory(g0)
    elif s.motion == "linear":
        if capture is None:
            raise InputError("motion", "the linear motion model needs the capture (its raw frames)")
        modal, linear, measured = fit_linear(capture, poses, vs, g0, background, s.linear)
        traj = modal.trajectory(g0)
    else:
        traj = fit_dynamic(g0, vs.views, s.fit, background)
    return Model(g0, traj, vs, stats0, time.perf_counter() - t1, init, background, modal, linear, measured)


@dataclass(frozen=True)
class MotionRecord:
    """The motion keys `trajectories.npz` and `measured_motion.npz` share, the one reader of both (the analysis
    reads the video's motion through it): world frame, metres, as trained (x `source_alpha`)."""

    times_s: np.ndarray           # (T,) after the impact onset
    means_rest_m: np.ndarray      # (N, 3)
    displacement_m: np.ndarray    # (T, N, 3)
    opacity_logits: np.ndarray    # (N,)
    source_alpha: float = 1.0     # the frames' own magnification (1: raw frames)
    extra: dict = field(default_factory=dict, repr=False)   # the file's other arrays (the model's rest state)

    KEYS = ("times_s", "means_rest_m", "opacity_logits")   # and displacement_m, or a modal model's basis and shapes

    @classmethod
    def read(cls, path: str | Path, capture_id: str | None = None) -> MotionRecord:
        """The motion in a `trajectories.npz` or `measured_motion.npz`; given the capture's id, a file of another
        capture is refused. Whatever is wrong with the file (empty, cut short, not an .npz, damaged, an array
        missing, of text or of the wrong shape) is one line naming it."""
        path = Path(path)
        d = read_npz(path, missing="no reconstruction motion here (run `odsplat reconstruct` first)",
                     capture_id=capture_id)
        missing = [k for k in cls.KEYS if k not in d]
        if "displacement_m" not in d and not {"basis", "shapes_m"} <= d.keys():
            missing.append("displacement_m")
        if missing:
            raise InputError(path, f"not a reconstruction's motion file: no {', '.join(missing)}; run "
                                   "`odsplat reconstruct` again")
        times = numeric(d, "times_s", path, (None,)).astype(float)
        rest = numeric(d, "means_rest_m", path, (None, 3)).astype(float)
        logits = numeric(d, "opacity_logits", path, (len(rest),)).astype(float)
        if not len(times) or not np.all(np.isfinite(times)):
            raise InputError(f"{path}: times_s", f"expected finite times, got {len(times)} with "
                                                 f"{int(np.sum(~np.isfinite(times)))} not finite")
        if "displacement_m" in d:
            disp = numeric(d, "displacement_m", path, (len(times), len(rest), 3))
        else:
            disp = modal_displacement(path, numeric(d, "basis", path), numeric(d, "shapes_m", path), len(times),
                                      len(rest))
        for k in ("times_s", "means_rest_m", "opacity_logits", "displacement_m"):
            d.pop(k, None)
        alpha = float(numeric(d, "source_alpha", path, ())) if "source_alpha" in d else 1.0
        d.pop("source_alpha", None)
        if not 0 < alpha < np.inf:
            raise InputError(f"{path}: source_alpha", f"expected a positive magnification; got {alpha}")
        return cls(times, rest, disp, logits, alpha, d)

    def write(self, path: Path, capture_id: str | None = None) -> None:
        """A modal model's motion is written as its basis and shapes (in `extra`), not as the (T, N, 3) field they
        multiply out to: on the demo 22k Gaussians x 247 timesteps, 159 MB with the quaternions against 6-7 MB.
        `capture_id`: the capture's, recorded in the file (`odsplat.spine.contract.CAPTURE_KEY`)."""
        arrays = dict(times_s=np.asarray(self.times_s, float), means_rest_m=self.means_rest_m,
                      opacity_logits=self.opacity_logits, source_alpha=self.source_alpha, **self.extra)
        if not {"basis", "shapes_m"} <= self.extra.keys():
            arrays["displacement_m"] = np.asarray(self.displacement_m, np.float32)
        if capture_id is not None:
            arrays[CAPTURE_KEY] = np.asarray(capture_id)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def modal_displacement(path, basis, shapes_m, n_times: int, n_points: int) -> np.ndarray:
    """(T, N, 3) a modal model's displacement, basis (T, K) times shapes (N, K, 3)."""
    basis, shapes_m = np.asarray(basis, float), np.asarray(shapes_m, float)
    if basis.ndim != 2 or basis.shape[0] != n_times or shapes_m.shape != (n_points, basis.shape[1], 3):
        raise InputError(f"{path}: basis, shapes_m", f"expected ({n_times}, K) and ({n_points}, K, 3); got "
                         f"{basis.shape} and {shapes_m.shape}")
    return modal_product(basis, shapes_m)


def modal_product(basis: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """(T, N, 3): basis (T, K) times shapes (N, K, 3), as one matrix product (BLAS: on the demo's 247 x 22k x K, 0.04
    s against 0.4 s for numpy's einsum of the same sum)."""
    basis, shapes = np.asarray(basis, float), np.asarray(shapes, float)
    n, k = shapes.shape[:2]
    return (basis @ shapes.transpose(1, 0, 2).reshape(k, 3 * n)).reshape(len(basis), n, 3)


def modal_quats(basis, rot_shapes_rad, quats_rest, chunk: int = 16) -> np.ndarray:
    """(T, N, 4) a modal model's orientations: each Gaussian's rest quaternion turned by basis @ rot_shapes.
    `chunk` timesteps at a time: on the demo (247 x 22k) 0.45 s, against 1.75 s for the whole field in one go."""
    basis, rot = np.asarray(basis, float), np.asarray(rot_shapes_rad, float)
    n, k = rot.shape[0], basis.shape[1]
    b, r = torch.as_tensor(basis), torch.as_tensor(rot.transpose(1, 0, 2).reshape(k, 3 * n))
    q0 = torch.as_tensor(np.asarray(quats_rest, float))[None]
    out = torch.empty((len(basis), n, 4), dtype=torch.float64)
    for i in range(0, len(basis), chunk):
        turn = (b[i:i + chunk] @ r).reshape(-1, n, 3)
        out[i:i + chunk] = quat_normalize(quat_multiply(quat_from_rotvec(turn), q0))
    return out.numpy()


def save_measured(paths: DerivedPaths, times_s: np.ndarray, measured: NodeMotion | None,
                  capture_id: str | None = None) -> None:
    """`measured_motion.npz` from the linear solve (recording `capture_id`), or none: a stale one from an earlier
    linear run goes, so that the analysis never pairs it with another model."""
    path = paths.measured_motion_npz
    if measured is None:
        path.unlink(missing_ok=True)
        return
    MotionRecord(times_s, measured.points_m, measured.displacement_m, np.full(len(measured.points_m), 10.0), 1.0,
                 {"kind": "linear nodes"}).write(path, capture_id)


def reconstruct(capture: Capture, settings: ReconstructSettings | None = None) -> ReconstructResult:
    """Train the dynamic Gaussians on the capture's posed views; writes derived/reconstruction/."""
    s = settings or ReconstructSettings()
    poses = _poses(capture)
    width = working_width(poses, s)
    log.info("rest fit at %d px wide: %s", width.width_px, width.why)
    vs = load_views(capture, poses, source=s.source, width_px=width.width_px, n_timesteps=s.timesteps, step=s.step,
                    start=s.start, max_timesteps=RECORD_TIMESTEPS, holdout=s.holdout, use_static=s.use_static,
                    ends_only=s.motion == "linear")
    m = train(vs, poses, s, capture)
    last = vs.n_timesteps - 1
    bg = m.background
    psnr0 = _psnr(m.g0, vs.views, 0, background=bg)
    psnr_last = _psnr(m.g0, vs.views, -1, m.trajectory.means[last], m.trajectory.quats[last], bg)  # -1: the last
    m.scene().save(capture.paths, capture.id)
    save_measured(capture.paths, vs.times_s, m.measured, capture.id)
    result = ReconstructResult(capture.paths.reconstruction_dir, len(m.g0), len(vs.views), len(vs.static),
                               vs.n_timesteps, m.stats_t0["seconds"], m.seconds_dynamic, psnr0, psnr_last,
                               vs.notes + [f"initialised from {m.init} points"])
    report = dict(**describe(capture.id, KIND, SCHEMA, s).header(), created_utc=utc_now(), settings=plain(s),
                  views=[v.name for v in vs.views], static=[v.name for v in vs.static], holdout=list(s.holdout),
                  working_width=asdict(width), frame_index=vs.frame_index.tolist(), times_s=vs.times_s.tolist(),
                  source_alpha=vs.source_alpha,
                  t0=m.stats_t0, motion=s.motion, dynamic=m.trajectory.losses, result=asdict(result))
    if m.modal is not None:
        report["modal"] = dict(motion_scale_m=m.modal.scale * vs.scene.radius,
                               energy_share=m.modal.principal()[3].tolist())
    if m.linear is not None:
        report["linear"] = m.linear
    # Last: a reader that finds it finds the model it describes.
    atomic_write_text(capture.paths.reconstruction_json, json.dumps(report, indent=1, default=str))  # str: paths
    log.info(result.summary())
    return result


@dataclass
class DynamicScene:
    """A trained model, in world coordinates: renders any camera at any time within the trained range, at any
    magnification.

    `displacement_m` is the motion as trained: it holds the frames' own magnification `source_alpha` (1 for
    sync's frames, the 2D factor for magnified ones); `physical_displacement_m()` divides it out. A modal model
    also keeps its basis and shape vectors (`basis`, `shapes_m`, `rot_shapes_rad`); the per-timestep model has
    None there."""

    times_s: np.ndarray
    frame_index: np.ndarray       # (T,) the grid frames trained on
    means_rest_m: np.ndarray      # (N, 3)
    displacement_m: np.ndarray    # (T, N, 3) as trained (x source_alpha)
    quats: np.ndarray             # (T, N, 4)
    rest: Gaussians               # scene coordinates, at rest
    scene: SceneFrame
    bit_depth: int
    background: np.ndarray        # (C,) what shows beyond the scene
    source_alpha: float = 1.0
    basis: np.ndarray | None = None           # (T, K) modal model: displacement = basis @ shapes
    shapes_m: np.ndarray | None = None        # (N, K, 3) as trained (x source_alpha)
    rot_shapes_rad: np.ndarray | None = None  # (N, K, 3)

    @property
    def motion(self) -> str:
        return "timestep" if self.basis is None else "modal"

    @classmethod
    def load(cls, capture: Capture) -> DynamicScene:
        """The capture's model (derived/reconstruction/trajectories.npz); a file of another capture is refused."""
        return cls.read(capture.paths.trajectories_npz, capture.id)

    @classmethod
    def read(cls, path: Path, capture_id: str | None = None) -> DynamicScene:
        """A model saved by `save` (its trajectories.npz); given the capture's id, a file of another capture is
        refused. A file that is not a whole model (`MotionRecord.read`'s refusals, a rest-state array missing or of
        the wrong shape) is one line naming it."""
        path = Path(path)
        m = MotionRecord.read(path, capture_id)
        d = m.extra
        missing = [k for k in ("log_scales_m", "color_logits", "scene_center_m", "scene_radius_m",
                               "frame_index", "bit_depth", "background") if k not in d]
        if "quats" not in d and not {"quats_rest", "basis", "rot_shapes_rad"} <= d.keys():
            missing.insert(0, "quats")
        if missing:
            raise InputError(path, f"not a trained model's trajectories: no {', '.join(missing)}; run "
                                   "`odsplat reconstruct` again")
        n, n_t = len(m.means_rest_m), len(m.times_s)
        color = numeric(d, "color_logits", path, (n, None))
        checked = dict(log_scales_m=numeric(d, "log_scales_m", path, (n, 3)), color_logits=color,
                       scene_center_m=numeric(d, "scene_center_m", path, (3,)),
                       frame_index=numeric(d, "frame_index", path, (n_t,)),
                       background=numeric(d, "background", path, (color.shape[1],)))
        radius, bit_depth = float(numeric(d, "scene_radius_m", path, ())), numeric(d, "bit_depth", path, ())
        if not 0 < radius < np.inf or not 1 <= bit_depth <= 32 or bit_depth != int(bit_depth):
            raise InputError(f"{path}: scene_radius_m, bit_depth", f"expected a positive radius and a bit depth of 1 "
                                                                   f"to 32; got {radius} and {bit_depth}")
        d.update(checked)
        if "quats" not in d:                     # a modal model: its rotations from the rest state and the basis
            rot = numeric(d, "rot_shapes_rad", path, np.shape(d["shapes_m"]))
            d["quats"] = modal_quats(d["basis"], rot, numeric(d, "quats_rest", path, (n, 4)))
            d.pop("quats_rest")
        else:
            d["quats"] = numeric(d, "quats", path, (n_t, n, 4))
        d.update(times_s=m.times_s, means_rest_m=m.means_rest_m, displacement_m=m.displacement_m,
                 opacity_logits=m.opacity_logits, source_alpha=m.source_alpha)
        scene = SceneFrame(d["scene_center_m"], radius)
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
        rest = Gaussians(means=t(scene.to_scene(d["means_rest_m"])), quats=t(d["quats"][0]),
                         log_scales=t(d["log_scales_m"] - np.log(scene.radius)), opacity_logits=t(d["opacity_logits"]),
                         color_logits=t(d["color_logits"]))
        return cls(d["times_s"], d["frame_index"].astype(int), d["means_rest_m"], d["displacement_m"], d["quats"],
                   rest, scene, int(bit_depth), d["background"], float(d.get("source_alpha", 1.0)), d.get("basis"),
                   d.get("shapes_m"), d.get("rot_shapes_rad"))

    @classmethod
    def from_model(cls, g0: Gaussians, traj: Trajectory, vs: ViewSet, background: torch.Tensor,
                   modal: ModalMotion | None = None) -> DynamicScene:
        sc = vs.scene
        means = traj.means.double().numpy()
        rest = g0.detached()
        if modal is None:
            extra, disp, quats = {}, (means - means[:1]) * sc.radius, traj.quats.double().numpy()
        else:                   # the motion as the file keeps it: the basis times the shapes, in double precision
            extra = dict(basis=modal.basis.double().numpy(), shapes_m=modal.shapes.double().numpy() * sc.radius,
                         rot_shapes_rad=modal.rot_shapes.double().numpy())
            disp = modal_displacement("model", extra["basis"], extra["shapes_m"], len(means), means.shape[1])
            quats = modal_quats(extra["basis"], extra["rot_shapes_rad"], traj.quats[0].double().numpy())
        return cls(np.asarray(vs.times_s, float), np.asarray(vs.frame_index), sc.to_world(means[0]), disp, quats,
                   rest, sc, vs.bit_depth, background.double().numpy(), float(vs.source_alpha), **extra)

    def save(self, paths: DerivedPaths, capture_id: str | None = None) -> None:
        """The rest state as `gaussians_t0.ply` and the whole motion as `trajectories.npz` in `paths`' reconstruction
        folder (a capture's `capture.paths`, or `DerivedPaths(folder)` elsewhere), world frame (metres), each
        recording `capture_id` (the capture's) where given."""
        ply, npz = paths.gaussians_ply, paths.trajectories_npz
        DerivedPaths.ensure(npz.parent)
        sc = self.scene
        world = self.rest.transformed(sc.radius, sc.center)
        save_ply(world, ply, capture_id=capture_id)
        # a modal model's orientations follow from its rest state and basis, as its displacement does
        modal = dict(quats=self.quats.astype(np.float32)) if self.basis is None else dict(
            basis=self.basis, shapes_m=self.shapes_m, rot_shapes_rad=self.rot_shapes_rad, quats_rest=self.quats[0])
        rest = dict(frame_index=self.frame_index,
                    log_scales_m=world.log_scales.double().numpy(),
                    color_logits=self.rest.color_logits.double().numpy(), scene_center_m=sc.center,
                    scene_radius_m=sc.radius, bit_depth=self.bit_depth, background=self.background, **modal)
        MotionRecord(self.times_s, self.means_rest_m, self.displacement_m, self.rest.opacity_logits.double().numpy(),
                     self.source_alpha, rest).write(npz, capture_id)

    def physical_displacement_m(self) -> np.ndarray:
        """(T, N, 3) displacement of every Gaussian in metres, the frames' magnification divided out."""
        return self.displacement_m / self.source_alpha

    def turns_rad(self) -> np.ndarray:
        """(T, N, 3) each Gaussian's rotation from rest as trained (x source_alpha), as a rotation vector: a modal
        model's basis times its rotation shapes, the per-timestep model's from its orientations."""
        if self.basis is not None:
            return modal_product(self.basis, self.rot_shapes_rad)
        q = quat_normalize(torch.as_tensor(self.quats, dtype=torch.float64))
        return quat_to_rotvec(quat_multiply(q, quat_conjugate(q[:1]))).numpy()

    def state(self, time_s: float, alpha: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Scene-coordinate means and quaternions at time_s: linear between timesteps, clamped to the trained
        range. alpha: the magnification to show (None: as trained); displacements and rotation vectors from rest
        are scaled by alpha / source_alpha."""
        ts = self.times_s
        if len(ts) == 1 or time_s <= ts[0]:
            k, w = 0, 0.0
        elif time_s >= ts[-1]:
            k, w = len(ts) - 2, 1.0
        else:
            k = int(np.searchsorted(ts, time_s, side="right") - 1)
            w = float((time_s - ts[k]) / (ts[k + 1] - ts[k]))
        k1 = min(k + 1, len(ts) - 1)
        gain = 1.0 if alpha is None else float(alpha) / self.source_alpha
        disp = gain * ((1 - w) * self.displacement_m[k] + w * self.displacement_m[k1])
        q = torch.as_tensor((1 - w) * self.quats[k] + w * self.quats[k1], dtype=torch.float64)
        if gain != 1.0:
            q0 = torch.as_tensor(self.quats[0], dtype=torch.float64)
            turn = quat_to_rotvec(quat_multiply(quat_normalize(q), quat_conjugate(quat_normalize(q0))))
            q = quat_multiply(quat_from_rotvec(gain * turn), q0)
        means = self.scene.to_scene(self.means_rest_m + disp)
        return torch.as_tensor(means, dtype=torch.float32), q.float()

    def render(self, camera: Camera, time_s: float, *, alpha: float | None = None, backend: str = "auto") -> np.ndarray:
        """(H, W, C) image in [0, 1] of `camera` (world frame) at time_s, magnified by alpha (None: as trained)."""
        means, quats = self.state(time_s, alpha)
        with torch.no_grad():
            out = render(self.rest, camera.in_scene(self.scene), means=means, quats=quats,
                         background=torch.as_tensor(self.background, dtype=torch.float32),
                         backend=backend)
        return out.image.clamp(0, 1).numpy()


def orbit(poses, n: int, *, elevation_deg: float = 30.0, distance_m: float | None = None,
          width_px: int | None = None) -> list[Camera]:
    """n cameras on a circle around what the posed views look at, with the first view's intrinsics."""
    views = [v for v in poses.views if v.kind == "take"] or list(poses.views)
    target = look_at_point([v.R for v in views], [v.t for v in views])
    dist = distance_m or float(np.median([np.linalg.norm(v.center_m - target) for v in views]))
    v0 = views[0]
    cams = []
    for k in range(n):
        az = 2 * np.pi * k / n
        el = np.radians(elevation_deg)
        eye = target + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        R, t = look_at(eye, target)
        cam = Camera(np.asarray(v0.K, float), R, t, v0.width_px, v0.height_px, f"orbit_{k:03d}")
        cams.append(cam.resized(width_px) if width_px else cam)
    return cams


def cameras_from_json(path: Path, width_px: int | None = None) -> list[Camera]:
    """A camera path: a JSON list of {K, R, t, width_px, height_px} (world-to-camera, OpenCV axes)."""
    data = load_json(path, missing="no such camera-path file")
    if not isinstance(data, list) or not data:
        raise InputError(path, "expected a JSON list of cameras {K, R, t, width_px, height_px}")
    cams = []
    for i, c in enumerate(data):
        try:
            cam = Camera(np.asarray(c["K"], float).reshape(3, 3), np.asarray(c["R"], float).reshape(3, 3),
                         np.asarray(c["t"], float).reshape(3), int(c["width_px"]), int(c["height_px"]), f"path_{i:03d}")
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{path}[{i}]", f"expected K (3x3), R (3x3), t (3), width_px, height_px: {e}") from None
        cams.append(cam.resized(width_px) if width_px else cam)
    return cams


def parse_times(spec: str, trained_s: np.ndarray) -> np.ndarray:
    """'all' (the trained timesteps), 'A:B:N' (N times from A to B s), or 'a,b,c' (s); every time inside the trained
    span (outside it the model would only repeat its first or last state)."""
    spec = spec.strip()
    try:
        if spec == "all":
            return np.asarray(trained_s, float)
        if ":" in spec:
            a, b, n = spec.split(":")
            if int(n) < 1:
                raise ValueError
            times = np.linspace(float(a), float(b), int(n))
        else:
            times = np.array([float(x) for x in spec.split(",")])
    except ValueError:
        raise InputError("--times", f"expected 'all', 'A:B:N' or 'a,b,c' in seconds, got {spec!r}") from None
    if not np.all(np.isfinite(times)):
        raise InputError("--times", f"expected finite times in seconds, got {spec!r}")
    lo, hi = float(np.min(trained_s)), float(np.max(trained_s))
    slack = 1e-9 + 1e-9 * max(abs(lo), abs(hi))
    outside = times[(times < lo - slack) | (times > hi + slack)]
    if len(outside):
        raise InputError("--times", f"expected times inside the reconstruction's span, {lo:g} to {hi:g} s; got "
                         f"{', '.join(f'{t:g}' for t in outside[:3])}{' ...' if len(outside) > 3 else ''}")
    return times


def check_camera_spec(spec: str) -> tuple[int | None, float, float | None] | None:
    """An orbit spec's (N or None, elevation, distance or None), checked: N >= 1, the elevation within +-90 degrees,
    the distance finite and > 0; None for a take name or a JSON path."""
    if spec.split(":")[0] != "orbit":
        return None
    parts = spec.split(":")[1:]
    if len(parts) > 3:
        raise InputError("--camera", f"expected orbit[:N[:ELEVATION_DEG[:DISTANCE_M]]], got {spec!r}")
    try:
        n = int(parts[0]) if parts else None
        elev = float(parts[1]) if len(parts) > 1 else 30.0
        dist = float(parts[2]) if len(parts) > 2 else None
    except ValueError:
        raise InputError("--camera", f"expected orbit[:N[:ELEVATION_DEG[:DISTANCE_M]]], got {spec!r}") from None
    if (n is not None and n < 1) or not -90 <= elev <= 90 or (dist is not None and not 0 < dist < np.inf):
        raise InputError("--camera", "expected orbit:N:ELEVATION_DEG:DISTANCE_M with N >= 1, an elevation within "
                                     f"+-90 degrees and a distance > 0 m; got {spec!r}")
    return n, elev, dist


def camera_path(capture: Capture, spec: str, n_times: int, width_px: int | None = None) -> list[Camera]:
    """The cameras to render from a spec: a take name (its estimated pose), orbit[:N[:ELEVATION_DEG[:DISTANCE_M]]]
    (N: one camera per time by default) or a JSON camera path file."""
    if spec.endswith(".json"):
        return cameras_from_json(Path(spec), width_px)
    orbit_spec = check_camera_spec(spec)
    if orbit_spec is not None:
        n, elev, dist = orbit_spec
        return orbit(_poses(capture), n or max(2, n_times), elevation_deg=elev, distance_m=dist, width_px=width_px)
    return [pose_camera(_poses(capture), spec, width_px)]


def render_sequence(scene: DynamicScene, cameras: list[Camera], times_s: np.ndarray, out: Path, *,
                    alpha: float | None = None, fps: float = 30.0, mp4: bool = True,
                    progress: bool = True) -> list[Path]:
    """PNG frames (and an mp4) of cameras x times: one camera over all times, one time over all cameras, or pairs;
    magnified by alpha (None: as trained)."""
    import cv2
    from tqdm import tqdm

    if len(cameras) == 1:
        cameras = cameras * len(times_s)
    elif len(times_s) == 1:
        times_s = np.repeat(times_s, len(cameras))
    elif len(cameras) != len(times_s):
        raise InputError("--camera/--times", f"{len(cameras)} cameras and {len(times_s)} times: give one camera, "
                                             "one time, or as many of each")
    out.mkdir(parents=True, exist_ok=True)
    paths, frames = [], []
    for k, (cam, t) in enumerate(tqdm(list(zip(cameras, times_s)), desc="render", unit="frame", disable=not progress)):
        img = scene.render(cam, float(t), alpha=alpha)
        u8 = np.round(img * 255).astype(np.uint8)
        u8 = cv2.cvtColor(u8, cv2.COLOR_RGB2BGR) if u8.shape[-1] == 3 else u8[..., 0]
        path = out / f"frame_{k:04d}.png"
        if not cv2.imwrite(str(path), u8):
            raise InputError(path, "could not write the PNG frame")
        paths.append(path)
        frames.append(u8)
    if mp4 and frames:
        rgb = (cv2.cvtColor(f, cv2.COLOR_BGR2RGB) if f.ndim == 3 else f for f in frames)
        paths.append(write_mp4(out / "render.mp4", rgb, fps, comment=f"odsplat render at {fps:g} frames/s").path)
    return paths


__all__ = ["DynamicScene", "Model", "train", "ReconstructResult", "ReconstructSettings", "cameras_from_json",
           "initial_points", "look_at_point", "orbit", "parse_times", "pose_camera", "reconstruct",
           "render_sequence", "save_measured"]
