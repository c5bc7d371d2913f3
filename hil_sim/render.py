"""Software renderer of the simulated rig: textured triangles seen through a pinhole camera, anti-aliased so that
sub-pixel motion changes pixel values smoothly, and the sensor model that turns radiance into camera frames.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
from numba import njit, prange

from odsplat.spine.errors import InputError
from odsplat.spine.geometry import look_at

log = logging.getLogger(__name__)

TILE_PX = 16  # screen tiles binned and rasterised independently, one prange iteration each
_LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)  # linear Rec. 709 / sRGB primaries

# Columns of the per-triangle setup table handed to the numba kernels (one float64 row per screen triangle).
# Edge i (opposite vertex i): E_i(x, y) = DX_i (y - YA_i) - DY_i (x - XA_i), > 0 inside. (XA, YA) is the edge's
# lexicographically smaller end and (DX, DY) the signed direction, so the two faces sharing an edge evaluate exactly
# negated values (no cracks, no double hits) and E is exactly 0 on both end vertices (a sample on a vertex is
# claimed by exactly one face of the fan, through the tie rule).
_XA, _YA, _DX, _DY = 0, 3, 6, 9
_TL = 12                         # 1.0 where a sample with E_i exactly 0 belongs to this face (top-left rule)
_X0, _Y0 = 15, 16                # origin of the attribute planes (vertex 0), for precision
_IZ, _UZ, _VZ = 17, 20, 23       # planes (value at origin, d/dx, d/dy) of 1/z, u/z, v/z: affine in screen space
_SHADE = 26
_XMIN, _XMAX, _YMIN, _YMAX = 27, 28, 29, 30
_NCOL = 31
_SNAP = 2.0**24                  # screen coordinates snapped to 2^-24 px: vertices on samples hit them exactly


def _array(source: str, value, shape: tuple[int | None, ...], dtype) -> np.ndarray:
    arr = np.array(value, dtype=dtype, copy=True)
    if arr.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, arr.shape)):
        want = "(" + ", ".join("N" if n is None else str(n) for n in shape) + ")"
        raise InputError(source, f"expected an array of shape {want}, got {arr.shape}")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise InputError(source, "contains NaN or inf")
    arr.setflags(write=False)
    return arr


class Projection(NamedTuple):
    """Image positions and camera-z depths of world points; unpacks as `px, depth_m = camera.project(points)`."""

    px: np.ndarray       # (N, 2) float64 (x = column, y = row); NaN where depth_m <= 0 (behind the camera)
    depth_m: np.ndarray  # (N,) float64 camera-z depth


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """Distortion-free pinhole camera, OpenCV/COLMAP convention: camera x right, y down, z forward,
    X_cam = R X_world + t.

    Image coordinates are OpenCV's: pixel (column 0, row 0) is centred at (0, 0) and covers [-0.5, 0.5]^2, so the
    image spans [-0.5, width_px - 0.5] x [-0.5, height_px - 0.5]. K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] in px.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width_px: int
    height_px: int

    def __post_init__(self) -> None:
        K = _array("PinholeCamera.K", self.K, (3, 3), np.float64)
        R = _array("PinholeCamera.R", self.R, (3, 3), np.float64)
        t = _array("PinholeCamera.t", self.t, (3,), np.float64)
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError("PinholeCamera.K",
                             f"expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InputError("PinholeCamera.R", "expected a rotation matrix (orthonormal, det +1)")
        if int(self.width_px) < 1 or int(self.height_px) < 1:
            raise InputError("PinholeCamera", f"image size must be >= 1 px, got {self.width_px}x{self.height_px}")
        for name, value in (("K", K), ("R", R), ("t", t), ("width_px", int(self.width_px)),
                            ("height_px", int(self.height_px))):
            object.__setattr__(self, name, value)

    @classmethod
    def look_at(cls, eye_m, target_m, up=(0.0, 0.0, 1.0), *, fov_deg: float | None = None, fx_px: float | None = None,
                width_px: int, height_px: int) -> PinholeCamera:
        """Camera at eye_m looking at target_m, `up` pointing up in the image; square pixels, principal point at the
        image centre ((W-1)/2, (H-1)/2). Give exactly one of fov_deg (horizontal, across width_px) or fx_px."""
        if (fov_deg is None) == (fx_px is None):
            raise InputError("PinholeCamera.look_at", "give exactly one of fov_deg or fx_px")
        if fx_px is None:
            if not 0 < fov_deg < 180:
                raise InputError("PinholeCamera.look_at", f"fov_deg must be in (0, 180), got {fov_deg}")
            fx_px = 0.5 * width_px / math.tan(math.radians(fov_deg) / 2)
        R, t = look_at(eye_m, target_m, up)
        K = np.array([[fx_px, 0, (width_px - 1) / 2], [0, fx_px, (height_px - 1) / 2], [0, 0, 1]], dtype=np.float64)
        return cls(K=K, R=R, t=t, width_px=width_px, height_px=height_px)

    def project(self, points_m) -> Projection:
        """Project (N, 3) world points to (N, 2) image coordinates and (N,) camera-z depths."""
        pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        cam = pts @ self.R.T + self.t
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = cam @ self.K.T
            px = uvw[:, :2] / z[:, None]
        px[z <= 0] = np.nan
        return Projection(px, z)

    @property
    def center_m(self) -> np.ndarray:
        """Optical centre in world coordinates."""
        return -self.R.T @ self.t


@dataclass(frozen=True, eq=False)
class TexturedMesh:
    """Triangle mesh with per-vertex texel coordinates into one atlas.

    faces are counter-clockwise seen from outside (outward normal (v1-v0) x (v2-v0)); that matters for
    `lambert_shade` and for `render(..., cull_backfaces=True)`. uv_px are texel coordinates (x = column, y = row)
    with texel centres at integers, like pixels; vertices shared by faces must carry one uv for all of them.
    """

    vertices_m: np.ndarray   # (V, 3) float64 world positions (already deformed)
    faces: np.ndarray        # (F, 3) int32 vertex indices
    uv_px: np.ndarray        # (V, 2) float32
    object_id: np.ndarray    # (F,) int16, >= 1 (0 means background in RenderResult.object_id)
    shade: np.ndarray | None = None  # (F,) float32 brightness factor, e.g. from lambert_shade; None means 1

    def __post_init__(self) -> None:
        v = _array("TexturedMesh.vertices_m", self.vertices_m, (None, 3), np.float64)
        f = _array("TexturedMesh.faces", self.faces, (None, 3), np.int32)
        uv = _array("TexturedMesh.uv_px", self.uv_px, (len(v), 2), np.float32)
        oid = _array("TexturedMesh.object_id", self.object_id, (len(f),), np.int16)
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise InputError("TexturedMesh.faces",
                             f"vertex indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        if oid.size and oid.min() < 1:
            raise InputError("TexturedMesh.object_id", "ids must be >= 1 (0 is the background)")
        shade = None if self.shade is None else _array("TexturedMesh.shade", self.shade, (len(f),), np.float32)
        for name, value in (("vertices_m", v), ("faces", f), ("uv_px", uv), ("object_id", oid), ("shade", shade)):
            object.__setattr__(self, name, value)


@dataclass
class RenderResult:
    """One rendered frame; all (H, W) maps are in the camera's pixel grid."""

    image: np.ndarray     # (H, W) or (H, W, 3) float32 linear radiance: atlas units x shade, background where empty
    depth_m: np.ndarray   # (H, W) float32 camera-z depth at pixel centres, inf where empty
    object_id: np.ndarray  # (H, W) int16 at pixel centres, 0 = background
    coverage: np.ndarray  # (H, W) float32 fraction of sub-samples covered (anti-aliased foreground mask)


def lambert_shade(vertices_m, faces, light_dir, ambient: float = 0.3) -> np.ndarray:
    """Per-face brightness ambient + (1 - ambient) max(0, -n . l) from the (deformed) geometry, n and l unit vectors.

    light_dir is the direction the light travels, from the light into the scene (need not be unit length):
    (0, 0, -1) is a light straight overhead. n is the outward normal of counter-clockwise faces, so faces turned
    away from the light get `ambient`.
    """
    v = np.asarray(vertices_m, dtype=np.float64)
    f = np.asarray(faces)
    light = np.asarray(light_dir, dtype=np.float64)
    if np.linalg.norm(light) == 0:
        raise InputError("lambert_shade.light_dir", "must not be zero")
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    cos = -(n @ (light / np.linalg.norm(light))) / np.where(norm > 0, norm, 1.0)
    return (ambient + (1.0 - ambient) * np.clip(cos, 0.0, None)).astype(np.float32)


# --------------------------------------------------------------------------------------------- rasteriser

def _atlas_hwc(atlas) -> np.ndarray:
    a = np.ascontiguousarray(atlas, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3) or a.shape[0] < 1 or a.shape[1] < 1:
        raise InputError("render.atlas", f"expected (Ht, Wt) mono or (Ht, Wt, 3) RGB, got shape {np.shape(atlas)}")
    return a


def _background(background, nc: int) -> np.ndarray:
    bg = np.asarray(background, dtype=np.float64)
    if bg.ndim == 0:
        return np.full(nc, float(bg))
    if bg.shape != (nc,):
        raise InputError("render.background", f"expected a number or {nc} channel values, got shape {bg.shape}")
    return np.ascontiguousarray(bg)


def _clip_near(P: np.ndarray, UV: np.ndarray, near_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clip camera-space triangles (F,3,3) against z = near_m: 1 vertex in front -> 1 triangle, 2 -> 2 triangles.

    Returns the clipped triangles, their uv and, per output triangle, the index of the input face.
    """
    front = P[:, :, 2] >= near_m
    if front.all():
        return P, UV, np.arange(len(P))
    n_front = front.sum(axis=1)
    keep = np.flatnonzero(n_front == 3)
    outs_P, outs_UV, outs_idx = [P[keep]], [UV[keep]], [keep]

    def cut(Pa, UVa, Pb, UVb):
        # Always from the front vertex to the behind one, so neighbours sharing the edge get bit-identical points.
        s = ((near_m - Pa[:, 2]) / (Pb[:, 2] - Pa[:, 2]))[:, None]
        Pc = Pa + s * (Pb - Pa)
        Pc[:, 2] = near_m
        return Pc, UVa + s * (UVb - UVa)

    for count in (1, 2):
        idx = np.flatnonzero(n_front == count)
        if not idx.size:
            continue
        # Rotate each triangle cyclically (keeps its orientation) so vertex 0 is the lone front / lone behind one.
        lone = np.argmax(front[idx] if count == 1 else ~front[idx], axis=1)
        order = (lone[:, None] + np.arange(3)) % 3
        p = P[idx[:, None], order]
        uv = UV[idx[:, None], order]
        if count == 1:  # front vertex 0 kept, the edges to 1 and 2 cut
            c1, t1 = cut(p[:, 0], uv[:, 0], p[:, 1], uv[:, 1])
            c2, t2 = cut(p[:, 0], uv[:, 0], p[:, 2], uv[:, 2])
            outs_P.append(np.stack([p[:, 0], c1, c2], axis=1))
            outs_UV.append(np.stack([uv[:, 0], t1, t2], axis=1))
            outs_idx.append(idx)
        else:  # vertex 0 behind: the quad 1, 2, cut(2->0), cut(1->0) as two triangles
            c2, t2 = cut(p[:, 2], uv[:, 2], p[:, 0], uv[:, 0])
            c1, t1 = cut(p[:, 1], uv[:, 1], p[:, 0], uv[:, 0])
            outs_P += [np.stack([p[:, 1], p[:, 2], c2], axis=1), np.stack([p[:, 1], c2, c1], axis=1)]
            outs_UV += [np.stack([uv[:, 1], uv[:, 2], t2], axis=1), np.stack([uv[:, 1], t2, t1], axis=1)]
            outs_idx += [idx, idx]
    return np.concatenate(outs_P), np.concatenate(outs_UV), np.concatenate(outs_idx)


@njit(cache=True)
def _setup_rows(P, UV, K, width, height, cull) -> tuple[np.ndarray, np.ndarray]:
    """Project and set up camera-space triangles (T,3,3) with uv (T,3,2): the rasteriser's table and, per row,
    the index of its input triangle. Degenerate, off-screen and (if cull) back-facing ones are dropped."""
    tri = np.empty((P.shape[0], _NCOL))
    src = np.empty(P.shape[0], dtype=np.int64)
    x, y, iz, u, v = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    n = 0
    for k in range(P.shape[0]):
        for m in range(3):
            iz[m] = 1.0 / P[k, m, 2]
            x[m] = np.floor(((K[0, 0] * P[k, m, 0] + K[0, 1] * P[k, m, 1]) * iz[m] + K[0, 2]) * _SNAP + 0.5) / _SNAP
            y[m] = np.floor((K[1, 1] * P[k, m, 1] * iz[m] + K[1, 2]) * _SNAP + 0.5) / _SNAP
            u[m], v[m] = UV[k, m, 0] * iz[m], UV[k, m, 1] * iz[m]
        area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
        # Counter-clockwise-from-outside faces come out with area < 0 in (x right, y down) image coordinates.
        if not abs(area) > 1e-12 or not abs(area) < np.inf or (cull and area > 0):
            continue
        xmin, xmax = min(x[0], x[1], x[2]), max(x[0], x[1], x[2])
        ymin, ymax = min(y[0], y[1], y[2]), max(y[0], y[1], y[2])
        if xmax < -0.5 or xmin > width - 0.5 or ymax < -0.5 or ymin > height - 0.5:
            continue
        if area < 0:  # make it positive, so that inside means all three edge functions > 0
            for a in (x, y, iz, u, v):
                a[1], a[2] = a[2], a[1]
            area = -area
        for e in range(3):  # edge e is opposite vertex e, running i -> j
            i, j = (e + 1) % 3, (e + 2) % 3
            sign = 1.0
            if x[j] < x[i] or (x[j] == x[i] and y[j] < y[i]):
                i, j, sign = j, i, -1.0
            dx, dy = sign * (x[j] - x[i]), sign * (y[j] - y[i])
            tri[n, _XA + e], tri[n, _YA + e], tri[n, _DX + e], tri[n, _DY + e] = x[i], y[i], dx, dy
            # On a tie the sample counts as if moved by (+eps, +eps^2): one consistent choice for every face.
            tri[n, _TL + e] = 1.0 if -dy > 0 or (dy == 0 and dx > 0) else 0.0
        dx1, dy1, dx2, dy2 = x[1] - x[0], y[1] - y[0], x[2] - x[0], y[2] - y[0]
        for col, f in ((_IZ, iz), (_UZ, u), (_VZ, v)):  # planes through vertex 0: value, d/dx, d/dy
            df1, df2 = f[1] - f[0], f[2] - f[0]
            tri[n, col] = f[0]
            tri[n, col + 1] = (df1 * dy2 - df2 * dy1) / area
            tri[n, col + 2] = (df2 * dx1 - df1 * dx2) / area
        tri[n, _X0], tri[n, _Y0] = x[0], y[0]
        tri[n, _XMIN], tri[n, _XMAX] = max(xmin, -0.5), min(xmax, width - 0.5)
        tri[n, _YMIN], tri[n, _YMAX] = max(ymin, -0.5), min(ymax, height - 0.5)
        src[n] = k
        n += 1
    return tri[:n], src[:n]


def _setup_triangles(mesh: TexturedMesh, camera: PinholeCamera, near_m: float, cull_backfaces: bool
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Clip, project, cull and set up every triangle for rasterisation.

    Returns the (T, _NCOL) float64 table and the (T,) int16 object ids of the triangles that may be visible.
    """
    P = (mesh.vertices_m @ camera.R.T + camera.t)[mesh.faces]  # (F, 3, 3) camera space
    UV = mesh.uv_px.astype(np.float64)[mesh.faces]
    P, UV, face = _clip_near(P, UV, near_m)
    tri, src = _setup_rows(P, UV, camera.K, camera.width_px, camera.height_px, cull_backfaces)
    face = face[src]
    tri[:, _SHADE] = 1.0 if mesh.shade is None else mesh.shade[face]
    return tri, np.ascontiguousarray(mesh.object_id[face])


@njit(cache=True)
def _bin_tiles(tri: np.ndarray, width: int, height: int, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists of the triangles whose bounding box touches each screen tile, in triangle order."""
    ntx = (width + tile - 1) // tile
    nty = (height + tile - 1) // tile
    span = np.empty((tri.shape[0], 4), dtype=np.int64)  # tile columns and rows touched, inclusive
    start = np.zeros(ntx * nty + 1, dtype=np.int64)
    for k in range(tri.shape[0]):
        # Bounding boxes are clipped to [-0.5, size - 0.5], so the shifted coordinates are >= 0 and int() floors.
        span[k, 0] = int((tri[k, _XMIN] + 0.5) / tile)
        span[k, 1] = min(ntx - 1, int((tri[k, _XMAX] + 0.5) / tile))
        span[k, 2] = int((tri[k, _YMIN] + 0.5) / tile)
        span[k, 3] = min(nty - 1, int((tri[k, _YMAX] + 0.5) / tile))
        for ty in range(span[k, 2], span[k, 3] + 1):
            for tx in range(span[k, 0], span[k, 1] + 1):
                start[ty * ntx + tx + 1] += 1
    for i in range(ntx * nty):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    tris = np.empty(start[-1], dtype=np.int32)
    for k in range(tri.shape[0]):
        for ty in range(span[k, 2], span[k, 3] + 1):
            for tx in range(span[k, 0], span[k, 1] + 1):
                tris[fill[ty * ntx + tx]] = k
                fill[ty * ntx + tx] += 1
    return start, tris


@njit(cache=True)
def _sample_xy(g0: int, n: int, s: int) -> np.ndarray:
    """Positions in px of samples g0 .. g0+n-1 of a grid with s samples per pixel: (g + 0.5) / s - 0.5.

    Always computed by this one expression, so every face sees bit-identical sample positions."""
    out = np.empty(n)
    for g in range(n):
        out[g] = (g0 + g + 0.5) / s - 0.5
    return out


@njit(cache=True)
def _raster_grid(tri, tris, s, gx0, gy0, zb, tb) -> None:
    """Z-buffer the triangles `tris` into a block of the global sample grid (s x s samples per pixel), whose top-left
    sample is (gx0, gy0); sample (i, j) sits at ((i + 0.5) / s - 0.5, (j + 0.5) / s - 0.5) px. zb holds 1/z
    (0 = empty)."""
    gh, gw = zb.shape
    xs, ys = _sample_xy(gx0, gw, s), _sample_xy(gy0, gh, s)
    for n in range(tris.size):
        k = tris[n]
        i0 = max(gx0, int(math.ceil((tri[k, _XMIN] + 0.5) * s - 0.5)))
        i1 = min(gx0 + gw - 1, int(math.floor((tri[k, _XMAX] + 0.5) * s - 0.5)))
        j0 = max(gy0, int(math.ceil((tri[k, _YMIN] + 0.5) * s - 0.5)))
        j1 = min(gy0 + gh - 1, int(math.floor((tri[k, _YMAX] + 0.5) * s - 0.5)))
        if i0 > i1 or j0 > j1:
            continue
        xa0, xa1, xa2 = tri[k, _XA], tri[k, _XA + 1], tri[k, _XA + 2]
        ya0, ya1, ya2 = tri[k, _YA], tri[k, _YA + 1], tri[k, _YA + 2]
        dx0, dx1, dx2 = tri[k, _DX], tri[k, _DX + 1], tri[k, _DX + 2]
        dy0, dy1, dy2 = tri[k, _DY], tri[k, _DY + 1], tri[k, _DY + 2]
        t0, t1, t2 = tri[k, _TL] > 0, tri[k, _TL + 1] > 0, tri[k, _TL + 2] > 0
        x0, y0 = tri[k, _X0], tri[k, _Y0]
        iz0, izx, izy = tri[k, _IZ], tri[k, _IZ + 1], tri[k, _IZ + 2]
        for j in range(j0, j1 + 1):
            y = ys[j - gy0]
            r0, r1, r2 = dx0 * (y - ya0), dx1 * (y - ya1), dx2 * (y - ya2)
            izr = iz0 + izy * (y - y0)
            # The row's span from the edge crossings, a sample wider each side: the exact test below decides.
            lo, hi = i0 - 0.5, i1 + 0.5
            for r, dy, xa in ((r0, dy0, xa0), (r1, dy1, xa1), (r2, dy2, xa2)):
                if dy > 0:
                    hi = min(hi, (xa + r / dy + 0.5) * s + 0.5)
                elif dy < 0:
                    lo = max(lo, (xa + r / dy + 0.5) * s - 1.5)
                elif r < 0:
                    hi = lo - 1.0
            if not lo <= hi:
                continue
            for i in range(max(i0, int(math.ceil(lo))), min(i1, int(math.floor(hi))) + 1):
                x = xs[i - gx0]
                e0 = r0 - dy0 * (x - xa0)
                if e0 < 0 or (e0 == 0 and not t0):
                    continue
                e1 = r1 - dy1 * (x - xa1)
                if e1 < 0 or (e1 == 0 and not t1):
                    continue
                e2 = r2 - dy2 * (x - xa2)
                if e2 < 0 or (e2 == 0 and not t2):
                    continue
                iz = izr + izx * (x - x0)
                if iz > zb[j - gy0, i - gx0]:  # strictly nearer: on exact ties the earlier face wins
                    zb[j - gy0, i - gx0] = iz
                    tb[j - gy0, i - gx0] = k


@njit(cache=True)
def _sample_add(atlas, u, v, w, acc) -> None:
    """acc += w * atlas bilinearly sampled at texel coordinates (u, v), clamped to the edge texels."""
    ht, wt, nc = atlas.shape
    u = min(max(u, -1.0), wt + 0.0) if u == u else 0.0  # also tames NaN before the int conversion
    v = min(max(v, -1.0), ht + 0.0) if v == v else 0.0
    fu, fv = math.floor(u), math.floor(v)
    ax, ay = u - fu, v - fv
    xa, ya = int(fu), int(fv)
    xb, yb = min(max(xa + 1, 0), wt - 1), min(max(ya + 1, 0), ht - 1)
    xa, ya = min(max(xa, 0), wt - 1), min(max(ya, 0), ht - 1)
    for c in range(nc):
        top = atlas[ya, xa, c] + ax * (atlas[ya, xb, c] - atlas[ya, xa, c])
        bot = atlas[yb, xa, c] + ax * (atlas[yb, xb, c] - atlas[yb, xa, c])
        acc[c] += w * (top + ay * (bot - top))


@njit(cache=True)
def _render_tile(t, tri, oid, start, tris, atlas, bg, s, tile, image, coverage, depth, ids) -> None:
    height, width, nc = image.shape
    ntx = (width + tile - 1) // tile
    px0, py0 = (t % ntx) * tile, (t // ntx) * tile
    tw, th = min(tile, width - px0), min(tile, height - py0)
    mine = tris[start[t]:start[t + 1]]
    zb = np.zeros((th * s, tw * s))
    tb = np.full((th * s, tw * s), -1, dtype=np.int32)
    _raster_grid(tri, mine, s, px0 * s, py0 * s, zb, tb)

    inv_n = 1.0 / (s * s)
    acc = np.empty(nc)
    xs, ys = _sample_xy(px0 * s, tw * s, s), _sample_xy(py0 * s, th * s, s)
    for j in range(th):
        for i in range(tw):
            acc[:] = 0.0
            hits = 0
            for sj in range(j * s, j * s + s):
                y = ys[sj]
                for si in range(i * s, i * s + s):
                    k = tb[sj, si]
                    if k < 0:
                        for c in range(nc):
                            acc[c] += bg[c]
                        continue
                    hits += 1
                    # Deferred shading: only the visible face of each sample is textured, perspective-correctly.
                    dx = xs[si] - tri[k, _X0]
                    dy = y - tri[k, _Y0]
                    z = 1.0 / zb[sj, si]
                    u = (tri[k, _UZ] + tri[k, _UZ + 1] * dx + tri[k, _UZ + 2] * dy) * z
                    v = (tri[k, _VZ] + tri[k, _VZ + 1] * dx + tri[k, _VZ + 2] * dy) * z
                    _sample_add(atlas, u, v, tri[k, _SHADE], acc)
            for c in range(nc):
                image[py0 + j, px0 + i, c] = acc[c] * inv_n
            coverage[py0 + j, px0 + i] = hits * inv_n

    if s % 2 == 1:  # the middle sample of each pixel sits on its centre
        zc, tc = zb[s // 2::s, s // 2::s], tb[s // 2::s, s // 2::s]
    else:
        zc = np.zeros((th, tw))
        tc = np.full((th, tw), -1, dtype=np.int32)
        _raster_grid(tri, mine, 1, px0, py0, zc, tc)
    for j in range(th):
        for i in range(tw):
            k = tc[j, i]
            depth[py0 + j, px0 + i] = 1.0 / zc[j, i] if k >= 0 else np.inf
            ids[py0 + j, px0 + i] = oid[k] if k >= 0 else 0


@njit(parallel=True, cache=True)
def _render_tiles(tri, oid, start, tris, atlas, bg, s, tile, image, coverage, depth, ids) -> None:
    # Each tile owns its sample buffers and a disjoint block of the outputs: no races, no locks.
    for t in prange(start.size - 1):
        _render_tile(t, tri, oid, start, tris, atlas, bg, s, tile, image, coverage, depth, ids)


def render(mesh: TexturedMesh, camera: PinholeCamera, atlas: np.ndarray, *, supersample: int = 3,
           background: float | np.ndarray = 0.0, near_m: float = 1e-3, cull_backfaces: bool = False) -> RenderResult:
    """Rasterise `mesh` through `camera` with supersample x supersample samples per pixel (box filter).

    The atlas (float32 (Ht, Wt) mono or (Ht, Wt, 3) RGB) is sampled bilinearly with perspective-correct uv, so the
    image changes smoothly with sub-pixel motion inside faces; edges are anti-aliased by sample coverage. Samples
    are at ((i + 0.5) / s - 0.5, (j + 0.5) / s - 0.5) px around each pixel centre; uncovered ones take `background`
    (a number or one value per channel). Faces crossing the near plane z = near_m are clipped to it; on exact depth
    ties the earlier face wins. Depth and object id are taken at pixel centres (an extra pass for even supersample).
    """
    if int(supersample) < 1:
        raise InputError("render.supersample", f"must be >= 1, got {supersample}")
    if not near_m > 0:
        raise InputError("render.near_m", f"must be > 0, got {near_m}")
    tex = _atlas_hwc(atlas)
    nc = tex.shape[2]
    bg = _background(background, nc)
    tri, oid = _setup_triangles(mesh, camera, float(near_m), bool(cull_backfaces))
    H, W = camera.height_px, camera.width_px
    start, tris = _bin_tiles(tri, W, H, TILE_PX)
    log.debug("render %dx%d, %d faces -> %d screen triangles, %d tile entries", W, H, len(mesh.faces), len(tri),
              len(tris))
    image = np.empty((H, W, nc), dtype=np.float32)
    coverage = np.empty((H, W), dtype=np.float32)
    depth = np.empty((H, W), dtype=np.float32)
    ids = np.empty((H, W), dtype=np.int16)
    # Tiles differ widely in cost (the structure is in the middle); hand them out one at a time.
    with numba.parallel_chunksize(1):
        _render_tiles(tri, oid, start, tris, tex, bg, int(supersample), TILE_PX,
                      image, coverage, depth, ids)
    return RenderResult(image[:, :, 0] if nc == 1 else image, depth, ids, coverage)


# ------------------------------------------------------------------------------------------- reference

def _bilinear_np(atlas: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    ht, wt, _ = atlas.shape
    fu, fv = np.floor(u), np.floor(v)
    ax, ay = (u - fu)[:, None], (v - fv)[:, None]
    xa, ya = np.clip(fu.astype(np.int64), 0, wt - 1), np.clip(fv.astype(np.int64), 0, ht - 1)
    xb, yb = np.clip(fu.astype(np.int64) + 1, 0, wt - 1), np.clip(fv.astype(np.int64) + 1, 0, ht - 1)
    return ((1 - ay) * ((1 - ax) * atlas[ya, xa] + ax * atlas[ya, xb])
            + ay * ((1 - ax) * atlas[yb, xa] + ax * atlas[yb, xb]))


def _raycast(P: np.ndarray, UV: np.ndarray, Kinv: np.ndarray, width: int, height: int, step: int,
             bbox: np.ndarray, near_m: float, cull_backfaces: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit along the ray of every sample of a (height*step, width*step) grid: depth, face (-1: none), uv."""
    gw, gh = width * step, height * step
    xs, ys = (np.arange(gw) + 0.5) / step - 0.5, (np.arange(gh) + 0.5) / step - 0.5
    depth = np.full(gw * gh, np.inf)
    face = np.full(gw * gh, -1, dtype=np.int64)
    uv = np.zeros((gw * gh, 2))
    for f in range(len(P)):
        if np.isfinite(bbox[f]).all():  # only the samples of the bounding box, found from the grid
            i0, i1 = np.clip(np.ceil((bbox[f, :2] + 0.5) * step - 0.5), 0, gw - 1).astype(int)
            j0, j1 = np.clip(np.ceil((bbox[f, 2:] + 0.5) * step - 0.5), 0, gh - 1).astype(int)
            sel = (np.arange(j0, j1 + 1)[:, None] * gw + np.arange(i0, i1 + 1)).ravel()
        else:
            sel = np.arange(gw * gh)
        pix = np.stack([xs[sel % gw], ys[sel // gw], np.ones(sel.size)], axis=1)
        d = pix @ Kinv.T  # ray directions with z = 1, so the ray parameter is the camera-z depth
        e1, e2, tvec = P[f, 1] - P[f, 0], P[f, 2] - P[f, 0], -P[f, 0]  # Moller-Trumbore, ray origin at 0
        pvec = np.cross(d, e2)
        det = pvec @ e1  # = -d . (e1 x e2): > 0 for front faces
        qvec = np.cross(tvec, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (pvec @ tvec) / det
            b = (d @ qvec) / det
            z = (e2 @ qvec) / det
        hit = (det != 0) & (a >= 0) & (b >= 0) & (a + b <= 1) & (z >= near_m) & (z < depth[sel])
        if cull_backfaces:
            hit &= det > 0
        idx = sel[hit]
        depth[idx], face[idx] = z[hit], f
        uv[idx] = (1 - a[hit] - b[hit])[:, None] * UV[f, 0] + a[hit, None] * UV[f, 1] + b[hit, None] * UV[f, 2]
    return depth, face, uv


def render_reference(mesh: TexturedMesh, camera: PinholeCamera, atlas: np.ndarray, *, supersample: int = 3,
                     background: float | np.ndarray = 0.0, near_m: float = 1e-3, cull_backfaces: bool = False
                     ) -> RenderResult:
    """Brute-force numpy ray caster with the same sampling as `render`: the reference it is tested against.

    One Moller-Trumbore pass per face over the samples of its (1 px padded) bounding box, all samples for faces
    crossing the near plane. Slow (about 0.1 ms per face); meant for tests and as the benchmark baseline.
    """
    s = int(supersample)
    tex = _atlas_hwc(atlas)
    nc = tex.shape[2]
    bg = _background(background, nc)
    H, W = camera.height_px, camera.width_px
    P = (mesh.vertices_m @ camera.R.T + camera.t)[mesh.faces]
    UV = mesh.uv_px.astype(np.float64)[mesh.faces]
    px, z = camera.project(mesh.vertices_m)
    fpx = px[mesh.faces]
    bbox = np.stack([fpx[:, :, 0].min(1) - 1, fpx[:, :, 0].max(1) + 1,
                     fpx[:, :, 1].min(1) - 1, fpx[:, :, 1].max(1) + 1], 1)
    bbox[(z[mesh.faces] < near_m).any(1)] = np.nan  # crossing the near plane: test every sample
    Kinv = np.linalg.inv(camera.K)
    shade = np.ones(len(P)) if mesh.shade is None else mesh.shade.astype(np.float64)
    _, face, uv = _raycast(P, UV, Kinv, W, H, s, bbox, near_m, cull_backfaces)
    hit = face >= 0
    samples = np.broadcast_to(bg, (face.size, nc)).copy()
    samples[hit] = _bilinear_np(tex, uv[hit, 0], uv[hit, 1]) * shade[face[hit], None]
    image = samples.reshape(H, s, W, s, nc).mean(axis=(1, 3))
    coverage = hit.reshape(H, s, W, s).mean(axis=(1, 3))
    depth_c, face_c, _ = _raycast(P, UV, Kinv, W, H, 1, bbox, near_m, cull_backfaces)
    ids = np.where(face_c >= 0, mesh.object_id[np.maximum(face_c, 0)], 0).reshape(H, W)
    return RenderResult((image[:, :, 0] if nc == 1 else image).astype(np.float32),
                        depth_c.reshape(H, W).astype(np.float32), ids.astype(np.int16), coverage.astype(np.float32))


# ------------------------------------------------------------------------------------------- sensor

def to_mono(rgb: np.ndarray) -> np.ndarray:
    """Luminance of linear RGB radiance (Rec. 709 weights), float32 (H, W); a mono image is returned as float32."""
    a = np.asarray(rgb, dtype=np.float32)
    if a.ndim == 2:
        return a
    if a.ndim != 3 or a.shape[2] != 3:
        raise InputError("to_mono.rgb", f"expected (H, W, 3), got shape {a.shape}")
    return a @ _LUMA_709


def expose(radiance: np.ndarray, *, bit_depth: int = 12, full_well_e: float = 20_000.0, read_noise_e: float = 5.0,
           shot_noise: bool = True, gain_dn_per_e: float | None = None, black_level_dn: float = 0.0,
           rng: np.random.Generator | None = None, rgb: bool = False) -> np.ndarray:
    """Sensor model: radiance 1.0 fills the well (full_well_e electrons); Poisson shot noise, saturation at the full
    well, Gaussian read noise, gain (default: full well -> top code), black level, rounding and clipping.

    Returns uint8 for bit_depth <= 8, else uint16 holding bit_depth-bit codes. shot_noise=False with read_noise_e=0
    is plain deterministic quantisation. rgb=False turns (H, W, 3) radiance into mono first (`to_mono`); rgb=True
    keeps three channels (no Bayer mosaic). rng None draws fresh entropy.
    """
    if not 1 <= int(bit_depth) <= 16:
        raise InputError("expose.bit_depth", f"must be in 1..16, got {bit_depth}")
    if not full_well_e > 0 or read_noise_e < 0:
        raise InputError("expose", f"need full_well_e > 0 and read_noise_e >= 0, got {full_well_e}, {read_noise_e}")
    a = np.asarray(radiance, dtype=np.float64)
    if rgb and (a.ndim != 3 or a.shape[2] != 3):
        raise InputError("expose.radiance", f"rgb=True needs (H, W, 3) radiance, got shape {a.shape}")
    if not rgb and a.ndim == 3:
        a = to_mono(a).astype(np.float64)
    top = 2 ** int(bit_depth) - 1
    gain = top / full_well_e if gain_dn_per_e is None else float(gain_dn_per_e)
    electrons = np.clip(np.nan_to_num(a, nan=0.0), 0.0, None) * full_well_e
    if shot_noise or read_noise_e > 0:
        rng = np.random.default_rng() if rng is None else rng
    if shot_noise:
        electrons = rng.poisson(np.minimum(electrons, 1e15)).astype(np.float64)  # poisson overflows beyond ~1e18
    electrons = np.minimum(electrons, full_well_e)
    if read_noise_e > 0:
        electrons = electrons + rng.normal(0.0, read_noise_e, electrons.shape)
    dn = np.clip(np.rint(electrons * gain + black_level_dn), 0, top)
    return dn.astype(np.uint8 if bit_depth <= 8 else np.uint16)
