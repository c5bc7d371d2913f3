"""The motion of every timestep in one linear solve on the raw frames: the rest Gaussians give the geometry, the
frames give the motion, and a coarse graph of nodes carries it.

For motion far below a pixel, a view's intensity change at pixel p is linear in the 3D displacement u of the surface
point X_p seen there (the brightness-constancy, or optical-flow, constraint in 3D):

    I_t(p) - I_rest(p) = -grad I(p) . J_p u(X_p),

with J_p (2x3) the derivative of the camera's projection at X_p. X_p is the rest Gaussians' rendered depth at p
(pixels they cover at least `min_alpha`; near a depth edge only where the other side, within the filters' reach,
has no more texture than the surfaces have: elsewhere there an edge's motion is not the surface's);
grad I is taken on the mean of the take's frames with Farid and Simoncelli's matched prefilter and derivative
(a central difference reads fine texture 15-20 % low, and so the motion that much high), and both sides pass the
same prefilter and blur.

The displacement field is an embedded deformation (Sumner et al. 2007) on nodes spread over the opaque Gaussians,
u(X) = sum_j w_j(X) (u_j + theta_j x (X - x_j)), with Gaussian weights over the k nearest nodes. That is 6 unknowns
per node and timestep, constrained by every pixel of every view; the linearised rigidity prior of Luiten et al.
2023 on the node graph, u_k - u_j - theta_j x (x_k - x_j) = 0 and theta_k = theta_j, regularises it. Each view's
rows are weighted by its noise, so the prior's weight (`smoothing`, relative to the data term) is dimensionless.

The normal matrix is the same at every timestep: it is built and factorised once, and every timestep is one
back-substitution. The temporal components of the solution that stand above the noise floor are kept as the
basis of a modal model (`ModalMotion`): the rest is each timestep's own noise. The frames are the raw ones
(`source="sync"`): the model's displacement is the physical motion, magnified in 3D at render time (`odsplat
render --alpha`).

The nodes' motion with every temporal component kept (`NodeMotion`) is the measurement itself. A mode whose motion
is spread below the noise floor over the components (on the rig, 371 Hz at 16 um) is dropped from the basis but
not from this; a fit with known poles (the analysis) recovers it there, since that fit is itself the filter.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass

import cv2
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from scipy.ndimage import maximum_filter
from scipy.spatial import cKDTree
from tqdm import tqdm

from odsplat.spine.checks import (
    BLUR_PX,
    CHUNK_FRAMES,
    FRACTION,
    LENGTH_M,
    NEIGHBOURS,
    WEIGHT,
    WORKERS,
    Range,
    check_fields,
    maybe,
)
from odsplat.spine.errors import InputError
from odsplat.spine.pool import process_pool
from odsplat.spine.store import Capture

from .dynamic import render
from .gaussians import Gaussians
from .modal import ModalMotion
from .views import Camera, SceneFrame, ViewSet, open_frames, pose_camera, source_generation, source_path

log = logging.getLogger(__name__)

# Farid & Simoncelli (2004), 7 taps: a prefilter and the derivative of the signal it interpolates.
PREFILTER = np.array([0.004711, 0.069321, 0.245410, 0.361117, 0.245410, 0.069321, 0.004711])
DERIVATIVE = np.array([0.018708, 0.125376, 0.193091, 0.0, -0.193091, -0.125376, -0.018708])
EDGE_MARGIN_PX = 3   # the filters' reach: a pixel this close to a depth edge sees the other side ...
EDGE_TEXTURE = 1.0   # ... and is left out where the other side's gradient energy there passes the surfaces' median
NODE_PX = 5          # default node spacing, in pixels of the views' median footprint on the Gaussians


@dataclass(frozen=True)
class LinearSettings:
    node_spacing_m: float | None = None   # None: 5 px of the views' footprint (at least scene radius / 100), widened
    #                                       until at most max_nodes nodes
    max_nodes: int = 4000
    smoothing: float = 64.0               # prior weight, relative to the data term's mean diagonal (docs: sweep)
    blur_px: float = 0.0                  # Gaussian blur (sd) of both sides after the prefilter (0: none; on the demo
    #                                       1 px read the tip 1.16x and the floor 3.5 um, none 1.10x and 2.3 um)
    min_alpha: float = 0.5                # pixels the rest Gaussians cover at least this much
    min_opacity: float = 0.5              # Gaussians that place nodes
    gradient_quantile: float = 0.3        # skip covered pixels with less gradient energy than this quantile
    k_interp: int = 6                     # nodes per point
    k_graph: int = 8                      # neighbours per node in the prior
    rank_factor: float = 4.0              # keep temporal components this far above the noise floor (energy)
    max_components: int = 24
    chunk_frames: int = 64                # frames read at a time
    workers: int | None = None            # processes reading the views' frames at once; None: one per core (at
    #                                       most what `[run] memory_gb` holds); the same result whatever the count
    progress: bool = True

    def __post_init__(self) -> None:
        # max_nodes: six unknowns each in one sparse solve; max_components: at most one per timestep.
        check_fields(self, {"node_spacing_m": maybe(LENGTH_M),
                            "max_nodes": Range(at_least=1, at_most=100_000, integer=True), "smoothing": WEIGHT,
                            "blur_px": BLUR_PX, "min_alpha": FRACTION, "min_opacity": FRACTION,
                            "gradient_quantile": Range(at_least=0, below=1), "k_interp": NEIGHBOURS,
                            "k_graph": NEIGHBOURS, "rank_factor": Range(above=0, at_most=1e6),
                            "max_components": Range(at_least=1, at_most=1024, integer=True),
                            "chunk_frames": CHUNK_FRAMES, "workers": maybe(WORKERS)})


def _filter(image: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """Separable convolution (not correlation) with kx along x and ky along y, mirrored borders."""
    return cv2.sepFilter2D(image, cv2.CV_64F, kx[::-1].copy(), ky[::-1].copy(), borderType=cv2.BORDER_REFLECT)


def _skew(v: np.ndarray) -> np.ndarray:
    """(n, 3, 3) matrices [v]x with [v]x w = v x w."""
    z = np.zeros((len(v), 3, 3))
    z[:, 0, 1], z[:, 0, 2], z[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    z[:, 1, 0], z[:, 2, 0], z[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return z


@dataclass
class NodeGraph:
    """Nodes (M, 3, world metres) at the centroids of the occupied cells of a grid of `spacing_m`."""

    nodes_m: np.ndarray
    spacing_m: float
    k_interp: int

    @classmethod
    def over(cls, points_m: np.ndarray, spacing_m: float, k_interp: int) -> NodeGraph:
        cell = np.floor(np.asarray(points_m, float) / spacing_m).astype(np.int64)
        _, inv = np.unique(cell, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        nodes = np.zeros((inv.max() + 1, 3))
        np.add.at(nodes, inv, points_m)
        return cls(nodes / np.bincount(inv)[:, None], float(spacing_m), min(k_interp, inv.max() + 1))

    def __post_init__(self) -> None:
        self._tree = cKDTree(self.nodes_m)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes_m)

    def weights(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nodes (n, k) and their Gaussian weights (n, k), summing to 1, for points (n, 3)."""
        d, j = self._tree.query(points_m, k=self.k_interp)
        d, j = d.reshape(len(points_m), -1), j.reshape(len(points_m), -1)
        w = np.exp(-0.5 * (d / self.spacing_m) ** 2) + 1e-12
        return j, w / w.sum(axis=1, keepdims=True)

    def rows(self, points_m: np.ndarray, a: np.ndarray) -> sp.csr_matrix:
        """(n, 6M) sparse rows a_i . u(X_i), u the embedded deformation; unknowns (u_j, theta_j) per node."""
        j, w = self.weights(points_m)
        r = points_m[:, None, :] - self.nodes_m[j]                  # (n, k, 3)
        cu = w[..., None] * a[:, None, :]                           # a . u_j
        ct = w[..., None] * np.cross(r, a[:, None, :])              # a . (theta_j x r) = theta_j . (r x a)
        cols = np.concatenate([6 * j[..., None] + np.arange(3), 6 * j[..., None] + 3 + np.arange(3)], axis=-1)
        n = len(points_m)
        return sp.csr_matrix((np.concatenate([cu, ct], -1).ravel(), (np.repeat(np.arange(n), j.shape[1] * 6),
                                                                     cols.ravel())), shape=(n, 6 * self.n_nodes))

    def prior(self, k_graph: int) -> sp.csr_matrix:
        """Rows of the linearised rigidity and rotation priors over each node's k_graph nearest nodes, in metres
        (the rotation rows times the spacing)."""
        k = min(k_graph + 1, self.n_nodes)
        d, nb = self._tree.query(self.nodes_m, k=k)
        i = np.repeat(np.arange(self.n_nodes), k - 1)
        j, d = nb[:, 1:].ravel(), d[:, 1:].ravel()
        w = np.exp(-0.5 * (d / (2 * self.spacing_m)) ** 2)
        S = _skew(self.nodes_m[j] - self.nodes_m[i])
        e = np.arange(len(i))
        rows, cols, vals = [], [], []
        for c in range(3):
            rid = 3 * e + c                                  # u_j - u_i + [x_j - x_i]x theta_i = 0
            rows += [rid, rid] + [rid] * 3
            cols += [6 * j + c, 6 * i + c] + [6 * i + 3 + c2 for c2 in range(3)]
            vals += [w, -w] + [w * S[:, c, c2] for c2 in range(3)]
            rid = 3 * (len(e) + e) + c                       # (theta_j - theta_i) x spacing = 0
            rows += [rid, rid]
            cols += [6 * j + 3 + c, 6 * i + 3 + c]
            vals += [w * self.spacing_m, -w * self.spacing_m]
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(6 * len(e), 6 * self.n_nodes))

    def displacement(self, points_m: np.ndarray, solution: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (T, n, 3) and rotation vectors (T, n, 3) at points from node unknowns (6M, T)."""
        j, w = self.weights(points_m)
        x = solution.reshape(self.n_nodes, 6, -1)
        u, th = x[:, :3][j], x[:, 3:][j]                                  # (n, k, 3, T)
        r = (points_m[:, None, :] - self.nodes_m[j])[..., None]           # (n, k, 3, 1)
        turn = np.cross(th, r, axisa=2, axisb=2, axisc=2)
        disp = np.einsum("nk,nkct->tnc", w, u + turn)
        return disp, np.einsum("nk,nkct->tnc", w, th)


@dataclass(frozen=True)
class NodeMotion:
    """The solve's motion at the nodes, every temporal component kept (unfiltered), world frame, metres."""

    points_m: np.ndarray          # (M, 3) the nodes at rest
    displacement_m: np.ndarray    # (T, M, 3) at the model's timesteps


@dataclass
class ViewRows:
    """What one view contributed: the pixels used and its frames' noise (its rows were weighted by 1 / noise)."""

    name: str
    n_pixels: int
    noise: float             # rms of the prefiltered, blurred frame noise, in full-scale units


def median_footprint_m(points_m: np.ndarray, cameras: list[Camera]) -> float:
    """The views' median pixel footprint on the points (each view's median depth over its focal length, in metres
    per pixel at full resolution); NaN when no point is in front of any view."""
    footprints = []
    for cam in cameras:
        z = points_m @ np.asarray(cam.R, float)[2] + float(np.asarray(cam.t, float)[2])
        footprints.append(np.median(z[z > 0]) / float(cam.K[0, 0]) if np.any(z > 0) else np.nan)
    return float(np.nanmedian(footprints)) if np.isfinite(footprints).any() else float("nan")


def node_spacing(points_m: np.ndarray, cameras: list[Camera], scene: SceneFrame, s: LinearSettings,
                 widen: bool = True) -> float:
    """The node spacing: as set, else NODE_PX of the views' median pixel footprint on the Gaussians (so that every
    node has pixels enough to pin it) and at least the scene radius / 100, widened (unless told not to) until at
    most max_nodes nodes."""
    if s.node_spacing_m is not None:
        return s.node_spacing_m
    footprint = median_footprint_m(points_m, cameras)
    spacing = max(scene.radius / 100, NODE_PX * footprint if np.isfinite(footprint) else 0)
    while widen and len(np.unique(np.floor(points_m / spacing).astype(np.int64), axis=0)) > s.max_nodes:
        spacing *= 1.25
    return spacing


def _projection_rows(camera: Camera, u_px: np.ndarray, v_px: np.ndarray, z_m: np.ndarray, gx: np.ndarray,
                     gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points at pixels (u, v) of camera-z depth z, and a = -grad I . d(pixel)/d(X) (n, 3), world frame."""
    K, R, t = np.asarray(camera.K, float), np.asarray(camera.R, float), np.asarray(camera.t, float)
    xc = (np.stack([u_px, v_px, np.ones_like(u_px)], 1).astype(float) @ np.linalg.inv(K).T) * z_m[:, None]
    X = (xc - t) @ R                                                    # R^T (x_cam - t)
    fx, skew, fy = K[0, 0], K[0, 1], K[1, 1]
    du = np.stack([fx / z_m, skew / z_m, -(fx * xc[:, 0] + skew * xc[:, 1]) / z_m**2], 1)
    dv = np.stack([np.zeros_like(z_m), fy / z_m, -fy * xc[:, 1] / z_m**2], 1)
    a_cam = -(gx[:, None] * du + gy[:, None] * dv)
    return X, a_cam @ R                                                 # R^T a_cam


def fit_linear(capture: Capture, poses, vs: ViewSet, g0: Gaussians, background: torch.Tensor,
               s: LinearSettings) -> tuple[ModalMotion, dict, NodeMotion]:
    """The motion of g0 (scene coordinates) at vs's timesteps from the raw synced frames of vs's views, as a modal
    model (the temporal components above the noise, basis, and each Gaussian's shape vectors); its figures; and
    the nodes' unfiltered motion."""
    t_start = time.perf_counter()
    scene = vs.scene
    means_m = scene.to_world(g0.means.detach().double().numpy())
    opaque = g0.opacities.detach().numpy().reshape(-1) >= s.min_opacity
    if opaque.sum() < 4:
        raise InputError("linear motion", f"only {opaque.sum()} Gaussians at least {s.min_opacity} opaque to place "
                                          "nodes on; the rest fit failed")
    cameras = [pose_camera(poses, v.name) for v in vs.views]          # full resolution, world frame
    spacing = node_spacing(means_m[opaque], cameras, scene, s)
    graph = NodeGraph.over(means_m[opaque], spacing, s.k_interp)
    log.info("linear motion: %d nodes %.1f mm apart over %d opaque Gaussians", graph.n_nodes, spacing * 1e3,
             opaque.sum())
    frames = np.asarray(vs.frame_index)
    n_unknown = 6 * graph.n_nodes
    ata = sp.csr_matrix((n_unknown, n_unknown))
    rhs = np.zeros((n_unknown, len(frames)))
    bg = background.to(g0.means.dtype)
    views: list[ViewRows] = []
    grid = Grid(frames, np.asarray(vs.times_s, float), scene)
    tasks = [(str(capture.root), str(capture.paths.root), source_generation(capture, "sync"), v.name, cam, grid, g0,
              bg, graph, spacing, s) for v, cam in zip(vs.views, cameras)]
    # Each view's rows in a process of its own (pool.map keeps the views' order: the sums, and so the result, are
    # those of one process).
    workers = max(1, min(s.workers or os.cpu_count() or 1, len(tasks)))
    if multiprocessing.current_process().daemon:   # a batch's Dask worker: it may start no processes
        workers = 1
    with process_pool(workers, fresh=True) if workers > 1 else nullcontext(None) as pool:   # torch has run here
        done = pool.map(_view_rows_task, *zip(*tasks)) if pool is not None else (_view_rows_task(*t) for t in tasks)
        for rows in tqdm(done, total=len(tasks), desc="linear motion", unit="view", disable=not s.progress):
            if rows is None:
                continue
            A, row, d_rhs = rows
            ata = ata + (A.T @ A).tocsr()
            rhs += d_rhs
            views.append(row)
    if not views:
        raise InputError(capture.paths.aligned_dir, "no view has pixels the rest Gaussians cover with texture")
    prior = graph.prior(s.k_graph)
    ptp = (prior.T @ prior).tocsr()
    diag_a, diag_p = ata.diagonal()[0::6].mean(), ptp.diagonal()[0::6].mean()
    lam = s.smoothing * diag_a / max(diag_p, 1e-300)
    normal = (ata + lam * ptp + sp.identity(n_unknown) * 1e-9 * ata.diagonal().mean()).tocsc()
    solution = spla.splu(normal).solve(rhs)                            # (6M, T)
    basis, eig = _temporal_basis(rhs, solution, np.asarray(vs.times_s) < 0, s)
    shapes_m, rot_shapes = graph.displacement(means_m, solution @ basis)  # (K, N, 3) each
    measured = NodeMotion(graph.nodes_m.copy(), np.concatenate(
        [graph.displacement(graph.nodes_m, solution[:, a:a + s.chunk_frames])[0]
         for a in range(0, solution.shape[1], s.chunk_frames)]).astype(np.float32))
    modal = ModalMotion(torch.as_tensor(basis, dtype=g0.means.dtype),
                        torch.as_tensor(shapes_m.transpose(1, 0, 2) / scene.radius, dtype=g0.means.dtype),
                        torch.as_tensor(rot_shapes.transpose(1, 0, 2), dtype=g0.means.dtype),
                        float(np.sqrt((shapes_m**2).sum(axis=(0, 2)).mean() / len(basis))) / scene.radius)
    seconds = time.perf_counter() - t_start
    stats = dict(settings=asdict(s), node_spacing_m=spacing, n_nodes=graph.n_nodes, prior_weight=float(lam),
                 n_components=int(basis.shape[1]), component_snr=[float(e) for e in eig[:basis.shape[1] + 4]],
                 views=[asdict(r) for r in views], n_pixels=int(sum(r.n_pixels for r in views)), seconds=seconds)
    log.info("linear motion: %d views, %d pixels, %d timesteps, %d temporal components, in %.1f s", len(views),
             stats["n_pixels"], len(frames), basis.shape[1], seconds)
    return modal, stats, measured


@dataclass(frozen=True)
class Grid:
    """What a view's rows need of the training views: the grid frames, their times and the scene frame."""

    frame_index: np.ndarray
    times_s: np.ndarray
    scene: SceneFrame


def _view_rows_task(capture_root: str, derived_root: str, generation: str | None, name: str, cam, grid: Grid,
                    g0: Gaussians, bg: torch.Tensor, graph: NodeGraph, spacing: float, s: LinearSettings):
    """`_view_rows` in a pool's process (or this one), the capture opened again."""
    if multiprocessing.parent_process() is not None:     # a pool's process: its share of the cores
        torch.set_num_threads(1)
    return _view_rows(Capture.open(capture_root, derived=derived_root), generation, name, cam, grid, g0, bg, graph,
                      spacing, s)


def _view_rows(capture: Capture, generation: str | None, name: str, cam, grid: Grid, g0: Gaussians,
               bg: torch.Tensor, graph: NodeGraph, spacing: float, s: LinearSettings):
    """One view's rows of the normal equations: its usable pixels' brightness-constancy rows `A` (noise-weighted),
    the view's figures, and its share of the right-hand side, A^T d / noise at every timestep; None when too few
    pixels are usable."""
    blur = (lambda im: cv2.GaussianBlur(im, (0, 0), s.blur_px)) if s.blur_px > 0 else (lambda im: im)
    smooth = lambda im: blur(_filter(im, PREFILTER, PREFILTER))  # noqa: E731
    frames = np.asarray(grid.frame_index)
    path = source_path(capture, "sync", name)
    with open_frames(capture, "sync", name, generation) as ff:
        times = ff.times_s
        if frames.max() >= len(times) or not np.allclose(times[frames], grid.times_s, atol=1e-9):
            raise InputError(path, "times_s differ from the training grid's")
        full = 2.0 ** int(ff.attrs["bit_depth"]) - 1

        def read(a, b, box=(slice(None), slice(None)), ff=ff, full=full):
            """Frames a..b as grey levels in [0, 1] (colour: the mean of the channels), within `box` (two slices)."""
            whole = box == (slice(None), slice(None))
            x = np.asarray(ff.read_frames(a, b, spatial=None if whole else lambda f: f[box]), np.float64)
            return x.reshape(*x.shape[:3], -1).mean(axis=-1) / full

        before = times < 0
        if not before.any():
            raise InputError(path, "no frame before the impact to take the rest image from")
        h, w = (int(n) for n in ff.frame_shape[:2])
        if (h, w) != (cam.height_px, cam.width_px):
            raise InputError(path, f"frames are {w}x{h} px, the pose says {cam.width_px}x{cam.height_px}")
        # One pass over every frame: the rest image (the mean of those before the impact), the mean of all (the
        # appearance at rest with the noise of one frame / sqrt(T)) and a few frame-to-frame differences.
        total, rest, diffs, prev = np.zeros((h, w)), np.zeros((h, w)), [], None
        for a in range(0, len(times), s.chunk_frames):
            b = min(a + s.chunk_frames, len(times))
            chunk = read(a, b)
            total += chunk.sum(axis=0)
            rest += chunk[before[a:b]].sum(axis=0)
            for f in chunk:
                if prev is not None and len(diffs) < 16:
                    diffs.append(smooth(f - prev))
                prev = f
        rest /= before.sum()
        mean_img = total / len(times)
        gx = blur(_filter(mean_img, DERIVATIVE, PREFILTER))
        gy = blur(_filter(mean_img, PREFILTER, DERIVATIVE))
        with torch.no_grad():
            out = render(g0, cam.in_scene(grid.scene), background=bg)
        alpha = out.alpha.double().numpy()
        z = out.depth.double().numpy() / np.maximum(alpha, 1e-9) * grid.scene.radius
        use = alpha >= s.min_alpha
        # Away from depth edges (a step of more than 1.5 node spacings between neighbouring pixels, or the
        # uncovered background) by the filters' reach: there the image moves with one side only.
        zf = np.where(use, z, 0.0)
        step = np.maximum(np.abs(np.diff(zf, axis=0, append=zf[-1:])),
                          np.abs(np.diff(zf, axis=1, append=zf[:, -1:])))
        energy = gx**2 + gy**2
        near_edge = maximum_filter(step, size=2 * EDGE_MARGIN_PX + 1) >= 1.5 * spacing
        keep = ~near_edge
        inner = use & keep
        if inner.any():            # near an edge only where the other side has no more texture than the surfaces
            keep |= _other_surface_energy(z, use, energy, 1.5 * spacing) <= EDGE_TEXTURE * np.median(energy[inner])
        use &= keep
        if use.any():
            use &= energy > np.quantile(energy[use], s.gradient_quantile)
        vv, uu = np.nonzero(use)
        if len(vv) < 16:
            log.warning("%s: %d usable pixels; left out of the linear motion", name, len(vv))
            return None
        # Noise of one frame after the filters, from frame-to-frame differences (the motion is far smaller).
        noise = float(1.4826 * np.median(np.abs(np.stack(diffs)[:, vv, uu])) / np.sqrt(2)) if diffs else 1.0
        X, a = _projection_rows(cam, uu, vv, z[vv, uu], gx[vv, uu], gy[vv, uu])
        A = graph.rows(X, a / noise)
        rhs = np.zeros((A.shape[1], len(frames)))
        # The timesteps' frames within the used pixels' box, widened by the filters' reach (so that the filtered
        # values there are those of the whole frame), a chunk at a time (a frame at a time recomputed the time
        # filter's 32 raw frames for each, and copied them).
        reach = len(PREFILTER) // 2 + (int(np.ceil(4 * s.blur_px)) if s.blur_px > 0 else 0) + 1
        r0, c0 = max(int(vv.min()) - reach, 0), max(int(uu.min()) - reach, 0)
        box = (slice(r0, min(int(vv.max()) + reach + 1, h)), slice(c0, min(int(uu.max()) + reach + 1, w)))
        rest_box, vb, ub = rest[box], vv - r0, uu - c0
        for a0 in range(0, len(frames), s.chunk_frames):
            idx = frames[a0:a0 + s.chunk_frames]
            d = np.stack([smooth(f - rest_box)[vb, ub] for f in _frames_at(read, idx, box)], axis=1)
            rhs[:, a0:a0 + len(idx)] += A.T @ (d / noise)
    return A, ViewRows(name, int(len(vv)), noise), rhs


def _frames_at(read, idx: np.ndarray, box) -> np.ndarray:
    """Grid frames idx (ascending) through read(a, b, box): as one span where they lie close (the usual step of 1),
    else one at a time."""
    a, b = int(idx[0]), int(idx[-1]) + 1
    if b - a <= 4 * len(idx):
        return read(a, b, box)[idx - a]
    return np.concatenate([read(int(k), int(k) + 1, box) for k in idx])


def _other_surface_energy(z: np.ndarray, covered: np.ndarray, energy: np.ndarray, step_m: float) -> np.ndarray:
    """At each pixel, the largest gradient energy within the filters' reach (EDGE_MARGIN_PX) on another surface
    (uncovered, or more than step_m nearer or farther): that surface's texture, or the edge's own contrast seen from
    its side. Where it is strong, the pixel's filtered change mixes in a motion that is not its surface's; where it
    is weak (a plain background behind a thin member), the pixel is as good as any: a column 8-14 px wide keeps its
    edges' pixels, which a fixed 3 px margin took (docs/reconstruction.md)."""
    h, w = z.shape
    m = EDGE_MARGIN_PX
    zz = np.pad(np.where(covered, z, np.inf), m, constant_values=np.inf)
    zc = zz[m:m + h, m:m + w]                       # the pixel's own depth (inf: uncovered)
    ee = np.pad(energy, m)
    out = np.zeros((h, w))
    for dy in range(-m, m + 1):
        for dx in range(-m, m + 1):
            zo = zz[m + dy:m + dy + h, m + dx:m + dx + w]
            with np.errstate(invalid="ignore"):
                other = ~(np.abs(zo - zc) <= step_m)
            np.maximum(out, np.where(other, ee[m + dy:m + dy + h, m + dx:m + dx + w], 0.0), out=out)
    return out


def _temporal_basis(rhs: np.ndarray, solution: np.ndarray, at_rest: np.ndarray, s: LinearSettings
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The temporal components of the solution that stand above the noise: basis (T, K), orthonormal, zero at the
    timesteps before the impact; and every component's energy over the noise floor (T,), strongest first.

    The rows are noise-weighted, so rhs' N^-1 rhs is the Gram matrix of the noise-whitened data over time: each
    timestep's independent noise adds about the same to every eigenvalue (the median one estimates it), and the
    motion concentrates in a few components well above it."""
    gram = rhs.T @ solution
    gram = 0.5 * (gram + gram.T)
    vals, vecs = np.linalg.eigh(gram)
    vals, vecs = vals[::-1], vecs[:, ::-1]
    snr = vals / max(float(np.median(vals)), 1e-300)
    k = int(np.clip(np.sum(snr > s.rank_factor), 1, s.max_components))
    basis = vecs[:, :k].copy()
    basis[at_rest] = 0.0               # before the impact the structure is at rest: the rest state exactly
    return basis, snr


__all__ = ["LinearSettings", "NodeGraph", "NodeMotion", "fit_linear"]
