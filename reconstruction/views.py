"""Training views for the Gaussians: posed cameras, their frames at the chosen timesteps, and the scene's normalisation.

Frames come from a derived frame file per take (`derived/sync/NAME.h5`, or the magnified takes in
`derived/magnified/METHOD/NAME.h5`), all on sync's common grid; static photos add views at rest. Images are
resampled to the training width (area filter) and the intrinsics with them, keeping the pixel-centre convention.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from odsplat.processing import MagnifiedVideo, MagnifyResult
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import camera_center_m
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, load_sync

log = logging.getLogger(__name__)

def open_frames(capture: Capture, source: str, name: str, generation: str | None) -> AlignedTake | MagnifiedVideo:
    """A take's frames on the common grid: sync's aligned take or processing's magnified one (`read_frames`,
    `iter_frames`, `times_s`, `frame_shape`, `attrs`)."""
    path = source_path(capture, source, name)
    if source == "sync":
        return AlignedTake(capture, path, generation)
    return MagnifiedVideo(path, generation, capture.id)


def source_generation(capture: Capture, source: str) -> str:
    """The run id the source's index records (sync.json, magnify.json): its frame files must carry it."""
    if source == "sync":

        return load_sync(capture).generation

    source_path(capture, source, "")  # checks the name
    return MagnifyResult.read(capture, source.split("/", 1)[1]).generation


def source_path(capture: Capture, source: str, name: str) -> Path:
    """'sync' -> derived/sync/NAME.h5; 'magnified/METHOD' -> derived/magnified/METHOD/NAME.h5."""
    if source == "sync" or source.startswith("magnified/"):
        return capture.paths.frames(source, name)
    raise InputError("source", f"expected 'sync' or 'magnified/METHOD' (e.g. magnified/phase), got {source!r}")


@dataclass(frozen=True)
class SceneFrame:
    """x_scene = (x_world - center) / radius: the training coordinates, about unit size whatever the units."""

    center: np.ndarray
    radius: float

    @classmethod
    def fit(cls, camera_centers: np.ndarray, margin: float = 1.1) -> SceneFrame:
        """Centred on the cameras, radius 1.1 x their farthest distance from that centre (as 3DGS does)."""
        c = np.asarray(camera_centers, float)
        center = c.mean(axis=0)
        radius = margin * float(np.max(np.linalg.norm(c - center, axis=1))) if len(c) > 1 else 1.0
        return cls(center, radius if radius > 0 else 1.0)

    def to_scene(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, float) - self.center) / self.radius

    def to_world(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, float) * self.radius + self.center

    def pose_to_scene(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera (R, t) as scene-to-camera, with the camera's frame also scaled by 1/radius."""
        return np.asarray(R, float), (np.asarray(t, float) + np.asarray(R, float) @ self.center) / self.radius


@dataclass
class Camera:
    """A pinhole camera, world-to-camera (OpenCV axes), pixel (0, 0)'s centre at (0, 0)."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width_px: int
    height_px: int
    name: str = ""

    @property
    def center(self) -> np.ndarray:
        return camera_center_m(self.R, self.t)

    def resized(self, width_px: int, height_px: int | None = None) -> Camera:
        """The same camera with its image resampled to width_px (height by aspect): K keeps pixel centres aligned."""
        height_px = height_px or max(1, round(self.height_px * width_px / self.width_px))
        sx, sy = width_px / self.width_px, height_px / self.height_px
        K = np.array(self.K, float)
        K[0, 0], K[0, 2] = K[0, 0] * sx, (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1], K[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
        K[0, 1] *= sx
        return Camera(K, self.R, self.t, width_px, height_px, self.name)

    def in_scene(self, frame: SceneFrame) -> Camera:
        R, t = frame.pose_to_scene(self.R, self.t)
        return Camera(self.K, R, t, self.width_px, self.height_px, self.name)

    def viewmat(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return torch.as_tensor(m, dtype=dtype)

    def K_tensor(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        return torch.as_tensor(np.asarray(self.K, float), dtype=dtype)


@dataclass
class TrainView:
    """One posed view and its images (T, H, W, C) in [0, 1]; a static photo has T = 1 and is at rest. Loaded with
    `ends_only`, a take's images are its first and last timesteps' (images[0] and images[-1] are those either way)."""

    camera: Camera
    images: torch.Tensor
    kind: str = "take"
    rest: torch.Tensor | None = None  # (H, W, C) mean of the take's frames before the impact (less noise than one)

    @property
    def rest_image(self) -> torch.Tensor:
        """The image at rest: the mean of the frames before the impact when known, else timestep 0's."""
        return self.images[0] if self.rest is None else self.rest

    @property
    def name(self) -> str:
        return self.camera.name


@dataclass
class ViewSet:
    """The training views on the selected timesteps, in scene coordinates."""

    views: list[TrainView]
    static: list[TrainView]
    frame_index: np.ndarray      # the grid frames used, (T,)
    times_s: np.ndarray          # their times after the impact onset, (T,)
    scene: SceneFrame
    bit_depth: int
    notes: list[str] = field(default_factory=list)
    source_alpha: float = 1.0    # the magnification already in the frames (1 for sync's, alpha for magnified ones)

    @property
    def n_timesteps(self) -> int:
        return len(self.frame_index)

    @property
    def n_colors(self) -> int:
        return int(self.views[0].images.shape[-1])


def select_frames(times_s: np.ndarray, n_timesteps: int | None, step: int = 1, start: int | None = None,
                  max_timesteps: int | None = None) -> np.ndarray:
    """Grid frames start, start+step, ...; start defaults to the last frame before the impact (the rest state).
    n_timesteps None: to the grid's end (the record), at most max_timesteps."""
    times_s = np.asarray(times_s, float)
    if start is None:
        before = np.flatnonzero(times_s < 0)
        start = int(before[-1]) if len(before) else 0
    if n_timesteps is None:
        n_timesteps = max((len(times_s) - 1 - start) // max(step, 1) + 1, 1)
        if max_timesteps is not None and n_timesteps > max_timesteps:
            log.info("the record holds %d timesteps from frame %d; the first %d are fitted (n_timesteps sets it)",
                     n_timesteps, start, max_timesteps)
            n_timesteps = max_timesteps
    if step < 1 or n_timesteps < 1:
        raise InputError("timesteps", f"expected n_timesteps >= 1 and step >= 1, got {n_timesteps} and {step}")
    idx = start + step * np.arange(n_timesteps)
    if start < 0 or idx[-1] >= len(times_s):
        raise InputError("timesteps",
                         f"frames {start}..{idx[-1]} (step {step}) run past the grid's {len(times_s)} frames")
    return idx


def _read_selected(ff, frames: np.ndarray, spatial, chunk_frames: int = 32) -> np.ndarray:
    """The frames at the (increasing) grid indices `frames`, each through `spatial`, read chunk by chunk over their
    span."""
    out, frames = [], np.asarray(frames, int)
    for a in range(int(frames[0]), int(frames[-1]) + 1, chunk_frames):
        b = min(a + chunk_frames, int(frames[-1]) + 1)
        wanted = frames[(frames >= a) & (frames < b)]
        if len(wanted):
            out.append(ff.read_frames(a, b, spatial)[wanted - a])
    return np.concatenate(out)


def _resize(image: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    out = cv2.resize(image, (width_px, height_px), interpolation=cv2.INTER_AREA)
    return out[..., None] if out.ndim == 2 else out


def load_views(capture: Capture, poses, *, source: str, width_px: int, n_timesteps: int | None, step: int = 1,
               start: int | None = None, max_timesteps: int | None = None, holdout: tuple[str, ...] = (),
               use_static: bool = True, dtype: torch.dtype = torch.float32, ends_only: bool = False) -> ViewSet:
    """The posed takes' frames (and static photos) at the selected grid frames, resampled to width_px; with
    `ends_only`, each view's images are the first and last selected frames only (the linear model reads its
    frames itself, at full resolution: a seed-size record of them at the working width is 0.9-2 GB).

    `poses` is the pose stage's result (views with name, kind, K, R, t, width_px, height_px); n_timesteps None:
    the record (`select_frames`).
    """
    take_poses = [v for v in poses.views if v.kind == "take" and v.name not in holdout]
    if not take_poses:
        raise InputError(capture.paths.poses_json, "no posed takes to train on")
    notes: list[str] = []
    views, grid, bit_depth, frames, alphas = [], None, None, None, set()
    generation = source_generation(capture, source)
    missing = [vp.name for vp in take_poses if not source_path(capture, source, vp.name).exists()]
    if source != "sync" and missing:
        # magnify does the first view only unless told (a view to watch): a model from a few views is no result
        raise InputError(capture.paths.frames(source, missing[0]).parent,
                         f"no {source} frames for {len(missing)} of the {len(take_poses)} posed takes "
                         f"({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}): run `odsplat magnify "
                         "--every-view` first (`odsplat run` does, for this source)")
    for vp in take_poses:
        path = source_path(capture, source, vp.name)
        if vp.name in missing:
            notes.append(f"{vp.name}: no {source} frames, left out")
            continue
        cam = Camera(vp.K, vp.R, vp.t, vp.width_px, vp.height_px, vp.name)
        small = cam.resized(width_px)
        with open_frames(capture, source, vp.name, generation) as ff:
            times = ff.times_s
            if grid is None:
                grid, bit_depth = times, int(ff.attrs["bit_depth"])
                frames = select_frames(grid, n_timesteps, step, start, max_timesteps)
            elif len(times) != len(grid) or not np.allclose(times, grid, atol=1e-9):
                raise InputError(path, "times_s differ from the other takes' (not on one sync grid)")
            if tuple(ff.frame_shape[:2]) != (cam.height_px, cam.width_px):
                raise InputError(path, f"frames are {ff.frame_shape[1]}x{ff.frame_shape[0]} px, the pose says "
                                       f"{cam.width_px}x{cam.height_px}")

            def shrink(frame: np.ndarray, small=small) -> np.ndarray:   # linear: it commutes with sync's filter
                return _resize(frame, small.width_px, small.height_px)

            data = _read_selected(ff, np.unique(frames[[0, -1]]) if ends_only else frames, shrink)
            before = np.flatnonzero(times < 0)
            rest = ff.read_frames(int(before[0]), int(before[-1]) + 1, shrink).astype(np.float64).mean(axis=0) \
                if len(before) else None
            alphas.add(float(ff.attrs.get("alpha", 1.0)))
        full = 2.0 ** bit_depth - 1
        imgs = data / full
        rest_t = None if rest is None else torch.as_tensor(np.clip(rest / full, 0, 1), dtype=dtype)
        views.append(TrainView(small, torch.as_tensor(np.clip(imgs, 0, 1), dtype=dtype), rest=rest_t))
    if not views:
        raise InputError(capture.paths.frames_dir(source), f"no frame files for the posed takes ({'; '.join(notes)})")
    static = []
    if use_static:
        for vp in (v for v in poses.views if v.kind == "static" and v.name not in holdout):
            img = _read_photo(capture.root / f"{vp.name}.png")
            cam = Camera(vp.K, vp.R, vp.t, vp.width_px, vp.height_px, vp.name).resized(width_px)
            static.append(TrainView(cam, torch.as_tensor(_resize(img, cam.width_px, cam.height_px)[None], dtype=dtype),
                                    kind="static"))
    if len(alphas) > 1:
        raise InputError(capture.paths.frames_dir(source),
                         f"the takes were magnified by different factors: {sorted(alphas)}")
    scene = SceneFrame.fit(np.array([v.camera.center for v in views + static]))
    for v in views + static:
        v.camera = v.camera.in_scene(scene)
    log.info("%d views x %d timesteps (%s), %d static photos, %dx%d px", len(views), len(frames), source,
             len(static), views[0].camera.width_px, views[0].camera.height_px)
    return ViewSet(views, static, frames, grid[frames], scene, bit_depth, notes, alphas.pop())


def pose_camera(poses, name: str, width_px: int | None = None) -> Camera:
    """The estimated camera of a take (or static photo) by name."""
    try:
        v = poses.view(name)
    except KeyError:
        known = ", ".join(v.name for v in poses.views)
        raise InputError("--camera", f"no posed view named {name!r} (posed: {known})") from None
    cam = Camera(np.asarray(v.K, float), np.asarray(v.R, float), np.asarray(v.t, float), v.width_px, v.height_px, name)
    return cam.resized(width_px) if width_px else cam


def _read_photo(path: Path) -> np.ndarray:
    """A static photo as float32 (H, W, C) in [0, 1] (16-bit PNGs are full scale; colour returned as RGB)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "cannot read the static photo (expected a PNG written by the capture session)")
    full = float(np.iinfo(img.dtype).max) if img.dtype.kind == "u" else 1.0
    img = img.astype(np.float32) / full
    return img[..., ::-1].copy() if img.ndim == 3 else img


__all__ = ["Camera", "SceneFrame", "open_frames", "TrainView", "ViewSet", "load_views", "pose_camera", "select_frames",
           "source_path"]
