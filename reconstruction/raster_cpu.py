"""The numba back end of `raster.rasterize`: projection (rules 1-4 of `raster`'s module docstring) and
compositing (rules 4-6) in numba kernels, each with a hand-written backward pass behind a
`torch.autograd.Function`.

Projection (`_project_forward`, `_project_backward`; parallel over Gaussians): the torch path's `_project` per
Gaussian in float64, returned in the dtype of the means. Its backward differentiates the same expressions: the
conic through Sigma2 = M M^T + eps2d I, M = J W R_q S, into J (with nothing through the clamp of x/z or y/z where
it binds, and nothing through the 1e-12 floor of the quaternion's norm), the normalised quaternion, the scales
and W; the camera point into the means and viewmat. Culled Gaussians divide by 1, as in torch, so every gradient
stays finite. The viewmat gradient is summed in a fixed number of parts (_PROJECT_PARTS), in a fixed order.

Compositing input is the `table` that `raster.rasterize` builds from the projection: one row per Gaussian
(u, v, n0, n1, n2, opacity, F features), -q/2 = n0 dx^2 + n1 dx dy + n2 dy^2 with dx = x - u, dy = y - v at pixel
centre (x, y).

Binning (`_bin`): the Gaussians with radius > 0 are ordered front to back (a stable radix sort on z: ties keep
index order). Each one's pixel box is its footprint box [u - r, u + r] x [v - r, v + r] cut down to the bounding
box of the ellipse where the per-pixel test can pass (widened by a bound on the test's rounding, so no pixel that
passes is left out), rounded inwards to pixel centres and clipped to the image. The Gaussian is entered in the
list of every tile_px x tile_px tile its box meets, in depth order, so each tile's list is front to back.

Forward (`_forward`, one parallel task per tile, busiest tiles first): the tile walks its list front to back and
visits each Gaussian's box within the tile only. Per pixel the Gaussian contributes iff -q/2 >= floor, floor =
max(ln(1 / (255 o)), -q_max/2) (computed in torch, so it rounds like the torch path), -q/2 evaluated in the
table's dtype in the torch path's order of operations; a = min(alpha_max, o exp(-q/2)); the pixel stops at the
first contributing Gaussian with T (1 - a) < t_min, which is not kept. T and the composited features are
accumulated in float64 and returned in the table's dtype; per pixel the kernel also keeps the float64 T_final and
how many list entries it walked before stopping (the whole list when it did not stop).

Backward (`_backward`, one task per tile): per pixel, from the last walked entry back to the first, T_i is
recovered as T_{i+1} / (1 - a_i) from the float64 T_final, with S the sum of w_j c_j over the kept Gaussians
behind i: dL/dc_i = w_i g, dL/da_i = g . (T_i c_i - S / (1 - a_i)) - g_T T_final / (1 - a_i), then through
a = o exp(s): da/do = exp(s), da/ds = a, ds/du = -(2 n0 dx + n1 dy), ds/dv = -(n1 dx + 2 n2 dy), ds/dn0 = dx^2,
ds/dn1 = dx dy, ds/dn2 = dy^2. Nothing flows through a clamped a (o exp(s) > alpha_max) or through the cutoff
tests. A tile sums over its pixels into one float64 row per (Gaussian, tile) pair that no other tile writes;
`_reduce` adds each Gaussian's rows in a fixed order: no atomics, and the gradients do not depend on the thread
count.

Threads: see `_use_torch_threads`. The kernels compile on first use for each dtype (float32, float64) and are
cached on disk (cache=True). error_model="numpy": a division by zero gives inf or NaN, as in torch, not an
exception.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba import njit, prange
from torch.autograd.function import once_differentiable

from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

_N_GEOM = 6  # table columns before the features: u, v, n0, n1, n2, opacity
_PROJECT_PARTS = 64  # the projection's backward sums the viewmat gradient in this many fixed parts


@njit(cache=True, error_model="numpy")
def _depth_order(depths, radii):
    """Indices of the Gaussians with radius > 0 by increasing depth, ties in index order: an LSD radix sort
    (stable) on the order-preserving integer image of the float64 depth, skipping digits all keys share."""
    n_vis = 0
    for g in range(depths.shape[0]):
        if radii[g] > 0:
            n_vis += 1
    order = np.empty(n_vis, np.int64)
    keys = np.empty(n_vis, np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    z = np.empty(1, np.float64)
    z_bits = z.view(np.uint64)
    k = 0
    for g in range(depths.shape[0]):
        if radii[g] > 0:
            order[k] = g
            z[0] = depths[g] + 0.0  # -0.0 becomes 0.0: the two tie, as in a float comparison
            bits = z_bits[0]
            keys[k] = ~bits if bits & sign else bits | sign
            k += 1
    order_tmp = np.empty_like(order)
    keys_tmp = np.empty_like(keys)
    count = np.empty(257, np.int64)
    for shift in range(0, 64, 8):
        count[:] = 0
        for i in range(n_vis):
            count[((keys[i] >> np.uint64(shift)) & np.uint64(255)) + 1] += 1
        if n_vis == 0 or count.max() == n_vis:
            continue
        for d in range(256):
            count[d + 1] += count[d]
        for i in range(n_vis):
            d = (keys[i] >> np.uint64(shift)) & np.uint64(255)
            j = count[d]
            count[d] = j + 1
            keys_tmp[j] = keys[i]
            order_tmp[j] = order[i]
        keys, keys_tmp = keys_tmp, keys
        order, order_tmp = order_tmp, order
    return order


@njit(cache=True, inline="always", error_model="numpy")
def _half_extents(n0, n1, n2, fl, r, eps):
    """Half-widths (X, Y) of the ellipse -q/2 >= floor - err, err a bound on the rounding of -q/2 in a dtype of unit
    roundoff `eps` for |dx|, |dy| <= r; (r, r) where that ellipse is not bounded (or the numbers are not finite)."""
    a, b, c, f, rr = np.float64(n0), np.float64(n1), np.float64(n2), np.float64(fl), np.float64(r)
    det = 4.0 * a * c - b * b
    f = f - (8.0 * eps * (abs(a) + abs(b) + abs(c)) * rr * rr + 4.0 * eps * abs(f))
    if not (a < 0.0 and c < 0.0 and det > 0.0 and f < 0.0 and det < np.inf and f > -np.inf):
        return rr, rr
    x_half, y_half = np.sqrt(4.0 * f * c / det), np.sqrt(4.0 * f * a / det)
    return x_half * (1.0 + 1e-9) + 1e-9, y_half * (1.0 + 1e-9) + 1e-9


@dataclass
class _Bins:
    """Tile lists: see `_bin`."""

    tile_start: np.ndarray
    tile_gauss: np.ndarray
    box: np.ndarray
    order: np.ndarray
    gauss_start: np.ndarray
    pair_pos: np.ndarray
    tiles: np.ndarray
    n_tx: int


@njit(cache=True, error_model="numpy")
def _box(g, table, floor, radii_f, width, height, eps, box):
    """Writes Gaussian g's pixel box (see `_bin`) to box[g]; returns False when it holds no pixel centre."""
    u, v, r = np.float64(table[g, 0]), np.float64(table[g, 1]), np.float64(radii_f[g])
    x_half, y_half = _half_extents(table[g, 2], table[g, 3], table[g, 4], floor[g], r, eps)
    x0 = max(max(np.ceil(table[g, 0] - radii_f[g]), np.ceil(u - x_half)), 0.0)
    x1 = min(min(np.floor(table[g, 0] + radii_f[g]), np.floor(u + x_half)), width - 1.0)
    y0 = max(max(np.ceil(table[g, 1] - radii_f[g]), np.ceil(v - y_half)), 0.0)
    y1 = min(min(np.floor(table[g, 1] + radii_f[g]), np.floor(v + y_half)), height - 1.0)
    if not (x0 <= x1 and y0 <= y1):
        return False
    box[g, 0], box[g, 1], box[g, 2], box[g, 3] = int(x0), int(x1), int(y0), int(y1)
    return True


@njit(cache=True, parallel=True, error_model="numpy")
def _boxes(order, table, floor, radii_f, width, height, tile_px, eps, box, tile_box):
    """Pixel boxes of the Gaussians in `order` and, by rank, the tiles they meet (tx0, tx1, ty0, ty1; an empty
    range when the box holds no pixel centre)."""
    for k in prange(order.shape[0]):
        g = order[k]
        if _box(g, table, floor, radii_f, width, height, eps, box):
            tile_box[k, 0], tile_box[k, 1] = box[g, 0] // tile_px, box[g, 1] // tile_px
            tile_box[k, 2], tile_box[k, 3] = box[g, 2] // tile_px, box[g, 3] // tile_px
        else:
            tile_box[k, 0], tile_box[k, 1], tile_box[k, 2], tile_box[k, 3] = 0, -1, 0, -1


@njit(cache=True, error_model="numpy")
def _fill(order, tile_box, width, height, tile_px):
    """The tile lists from the tile ranges, each in the order of `order` (see `_bin`)."""
    n_tx = (width + tile_px - 1) // tile_px
    n_tiles = n_tx * ((height + tile_px - 1) // tile_px)
    n_vis = order.shape[0]
    per_tile = np.zeros(n_tiles, np.int64)
    gauss_start = np.zeros(n_vis + 1, np.int64)
    for k in range(n_vis):
        n_pairs = 0
        for ty in range(tile_box[k, 2], tile_box[k, 3] + 1):
            for tx in range(tile_box[k, 0], tile_box[k, 1] + 1):
                per_tile[ty * n_tx + tx] += 1
                n_pairs += 1
        gauss_start[k + 1] = gauss_start[k] + n_pairs
    tile_start = np.zeros(n_tiles + 1, np.int64)
    for t in range(n_tiles):
        tile_start[t + 1] = tile_start[t] + per_tile[t]
    cursor = tile_start[:-1].copy()
    tile_gauss = np.empty(tile_start[n_tiles], np.int32)
    pair_pos = np.empty(tile_start[n_tiles], np.int64)
    for k in range(n_vis):
        g = order[k]
        j = gauss_start[k]
        for ty in range(tile_box[k, 2], tile_box[k, 3] + 1):
            for tx in range(tile_box[k, 0], tile_box[k, 1] + 1):
                t = ty * n_tx + tx
                tile_gauss[cursor[t]] = g
                pair_pos[j] = cursor[t]
                cursor[t] += 1
                j += 1
    tiles = np.argsort(-per_tile)  # any order of equal counts: tiles are independent
    return tile_start, tile_gauss, gauss_start, pair_pos, tiles


def _bin(table: np.ndarray, floor: np.ndarray, radii_f: np.ndarray, radii: np.ndarray, depths: np.ndarray,
         width: int, height: int, tile_px: int, eps: float) -> _Bins:
    """Front-to-back tile lists of the visible Gaussians (radius > 0).

    A Gaussian's pixel box is its footprint box [u - r, u + r] x [v - r, v + r] cut down to the bounding box of
    the ellipse where it can pass the per-pixel test (`_half_extents`), both rounded inwards to pixel centres and
    clipped to the image; a Gaussian whose box holds no pixel centre is in no list. Tile t's list is
    tile_gauss[tile_start[t]:tile_start[t + 1]]; the list positions of the Gaussian of rank k (in `order`, front
    to back) are pair_pos[gauss_start[k]:gauss_start[k + 1]]; `tiles` lists the tiles busiest first.
    """
    order = _depth_order(depths, radii)
    box = np.zeros((table.shape[0], 4), np.int32)
    tile_box = np.empty((len(order), 4), np.int32)
    _boxes(order, table, floor, radii_f, width, height, tile_px, eps, box, tile_box)
    tile_start, tile_gauss, gauss_start, pair_pos, tiles = _fill(order, tile_box, width, height, tile_px)
    return _Bins(tile_start, tile_gauss, box, order, gauss_start, pair_pos, tiles, -(-width // tile_px))


@njit(cache=True, inline="always", error_model="numpy")
def _neg_half_q(n0, n1, n2, dx, dy):
    # the torch path's order of operations, so both round alike
    return n1 * dx * dy + n0 * dx * dx + n2 * dy * dy


@njit(cache=True, error_model="numpy")
def _forward_tile(t, tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height, alpha_max,
                  t_min, feats, t_final, t_final64, n_walked):
    """`_forward` for tile t: writes its pixels of feats, t_final, t_final64 and n_walked."""
    n_feat = table.shape[1] - _N_GEOM
    px0, py0 = (t % n_tx) * tile_px, (t // n_tx) * tile_px
    tw, th = min(tile_px, width - px0), min(tile_px, height - py0)
    start, n_list = tile_start[t], tile_start[t + 1] - tile_start[t]
    trans = np.ones(tw * th)
    acc = np.zeros((tw * th, n_feat))
    walked = np.full(tw * th, n_list, np.int64)  # n_list: not stopped
    color = np.empty(n_feat)
    n_active = tw * th
    for kk in range(n_list):
        if n_active == 0:
            break
        g = tile_gauss[start + kk]
        u, v, n0, n1, n2, opac = table[g, 0], table[g, 1], table[g, 2], table[g, 3], table[g, 4], table[g, 5]
        fl = floor[g]
        for f in range(n_feat):
            color[f] = table[g, _N_GEOM + f]
        x_lo, x_hi = max(box[g, 0], px0), min(box[g, 1], px0 + tw - 1)
        for py in range(max(box[g, 2], py0), min(box[g, 3], py0 + th - 1) + 1):
            dy = coords[py] - v
            row = (py - py0) * tw - px0
            for px in range(x_lo, x_hi + 1):
                p = row + px
                if walked[p] != n_list:
                    continue
                dx = coords[px] - u
                s = _neg_half_q(n0, n1, n2, dx, dy)
                if not s >= fl:
                    continue
                a = np.float64(opac * np.exp(s))
                if a > alpha_max:
                    a = alpha_max
                after = trans[p] * (1.0 - a)
                if after < t_min:
                    walked[p] = kk
                    n_active -= 1
                    continue
                w = a * trans[p]
                for f in range(n_feat):
                    acc[p, f] += w * color[f]
                trans[p] = after
    for j in range(th):
        for i in range(tw):
            p = j * tw + i
            for f in range(n_feat):
                feats[py0 + j, px0 + i, f] = acc[p, f]
            t_final[py0 + j, px0 + i] = trans[p]
            t_final64[py0 + j, px0 + i] = trans[p]
            n_walked[py0 + j, px0 + i] = walked[p]


@njit(cache=True, parallel=True, error_model="numpy")
def _forward(tiles, tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height, alpha_max,
             t_min, feats, t_final, t_final64, n_walked):
    for i in prange(tiles.shape[0]):
        _forward_tile(tiles[i], tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height,
                      alpha_max, t_min, feats, t_final, t_final64, n_walked)


@njit(cache=True, error_model="numpy")
def _backward_tile(t, tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height, alpha_max,
                   t_final64, n_walked, grad_feats, grad_t, pair_grad):
    """`_backward` for tile t: writes the pair_grad rows of its list (zero for the entries no pixel walked)."""
    n_cols = table.shape[1]
    n_feat = n_cols - _N_GEOM
    px0, py0 = (t % n_tx) * tile_px, (t // n_tx) * tile_px
    tw, th = min(tile_px, width - px0), min(tile_px, height - py0)
    start, stop = tile_start[t], tile_start[t + 1]
    trans = np.empty(tw * th)
    g_tt = np.empty(tw * th)  # g_T T_final
    g_s = np.zeros(tw * th)  # g . S, S the sum of w_j c_j over the kept Gaussians behind
    g_f = np.empty((tw * th, n_feat))
    walked = np.empty(tw * th, np.int64)
    n_max = 0
    for j in range(th):
        for i in range(tw):
            p = j * tw + i
            trans[p] = t_final64[py0 + j, px0 + i]
            g_tt[p] = np.float64(grad_t[py0 + j, px0 + i]) * trans[p]
            for f in range(n_feat):
                g_f[p, f] = grad_feats[py0 + j, px0 + i, f]
            walked[p] = n_walked[py0 + j, px0 + i]
            n_max = max(n_max, walked[p])
    for k in range(start + n_max, stop):
        pair_grad[k, :] = 0.0
    acc = np.empty(n_cols)
    color = np.empty(n_feat)
    for kk in range(n_max - 1, -1, -1):
        g = tile_gauss[start + kk]
        u, v, n0, n1, n2, opac = table[g, 0], table[g, 1], table[g, 2], table[g, 3], table[g, 4], table[g, 5]
        fl = floor[g]
        n0_64, n1_64, n2_64 = np.float64(n0), np.float64(n1), np.float64(n2)
        for f in range(n_feat):
            color[f] = table[g, _N_GEOM + f]
        x_lo, x_hi = max(box[g, 0], px0), min(box[g, 1], px0 + tw - 1)
        acc[:] = 0.0
        m_x = m_y = m_xx = m_xy = m_yy = d_o = 0.0  # sums of dL/ds times dx, dy, dx^2, dx dy, dy^2; dL/do
        for py in range(max(box[g, 2], py0), min(box[g, 3], py0 + th - 1) + 1):
            dy = coords[py] - v
            dy64 = np.float64(dy)
            row = (py - py0) * tw - px0
            for px in range(x_lo, x_hi + 1):
                p = row + px
                if kk >= walked[p]:
                    continue
                dx = coords[px] - u
                s = _neg_half_q(n0, n1, n2, dx, dy)
                if not s >= fl:
                    continue
                e = np.exp(s)
                a = np.float64(opac * e)
                clamped = a > alpha_max
                if clamped:
                    a = alpha_max
                inv = 1.0 / (1.0 - a)
                t_i = trans[p] * inv
                trans[p] = t_i
                w = a * t_i
                dot_c = 0.0
                for f in range(n_feat):
                    acc[_N_GEOM + f] += w * g_f[p, f]
                    dot_c += g_f[p, f] * color[f]
                d_a = t_i * dot_c - (g_s[p] + g_tt[p]) * inv
                g_s[p] += w * dot_c
                if clamped:
                    continue
                d_o += d_a * np.float64(e)
                d_sx = d_a * a * np.float64(dx)
                d_sy = d_a * a * dy64
                m_x += d_sx
                m_y += d_sy
                m_xx += d_sx * np.float64(dx)
                m_xy += d_sx * dy64
                m_yy += d_sy * dy64
        acc[0] = -(2.0 * n0_64 * m_x + n1_64 * m_y)
        acc[1] = -(n1_64 * m_x + 2.0 * n2_64 * m_y)
        acc[2], acc[3], acc[4], acc[5] = m_xx, m_xy, m_yy, d_o
        pair_grad[start + kk, :] = acc


@njit(cache=True, parallel=True, error_model="numpy")
def _backward(tiles, tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height, alpha_max,
              t_final64, n_walked, grad_feats, grad_t, pair_grad):
    for i in prange(tiles.shape[0]):
        _backward_tile(tiles[i], tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height,
                       alpha_max, t_final64, n_walked, grad_feats, grad_t, pair_grad)


@njit(cache=True, parallel=True, error_model="numpy")
def _reduce(order, gauss_start, pair_pos, pair_grad, grad_table):
    """grad_table[g] = the sum of Gaussian g's pair_grad rows, always in the same order (tile by tile); the rows
    of the Gaussians in no list are left as they are."""
    n_cols = pair_grad.shape[1]
    for k in prange(order.shape[0]):
        g = order[k]
        for c in range(n_cols):
            total = 0.0
            for j in range(gauss_start[k], gauss_start[k + 1]):
                total += pair_grad[pair_pos[j], c]
            grad_table[g, c] = total


@njit(cache=True, error_model="numpy")
def _rotation(qw, qx, qy, qz):
    """Rotation matrix (row-major, 9 values) of the quaternion (w, x, y, z) divided by max(|q|, 1e-12), that
    quaternion, and the divisor."""
    norm = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    div = max(norm, 1e-12)
    w, x, y, z = qw / div, qx / div, qy / div, qz / div
    rot = (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
           2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
           2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
    return rot, w, x, y, z, norm, div


@njit(cache=True, error_model="numpy")
def _project_one(i, means, quats, scales, view, cam, clip, near, eps2d, b_mat, m_mat):
    """Rules 1-3 for Gaussian i in float64: camera point, clamped x/z and y/z, J's entries, B = W R_q S and
    M = J B (written to the scratch arrays b_mat (3, 3) and m_mat (2, 3)), the dilated Sigma2 entries (a, b, c)
    and what the backward pass needs of them."""
    fx, fy = cam[0], cam[1]
    m0, m1, m2 = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
    x = view[0, 0] * m0 + view[0, 1] * m1 + view[0, 2] * m2 + view[0, 3]
    y = view[1, 0] * m0 + view[1, 1] * m1 + view[1, 2] * m2 + view[1, 3]
    z = view[2, 0] * m0 + view[2, 1] * m1 + view[2, 2] * m2 + view[2, 3]
    front = z > near
    zs = z if front else 1.0  # culled Gaussians divide by 1: finite values and gradients
    xz, yz = x / zs, y / zs
    xc, yc = min(max(xz, clip[0]), clip[1]), min(max(yz, clip[2]), clip[3])
    j00, j02, j11, j12 = fx / zs, -fx * xc / zs, fy / zs, -fy * yc / zs
    rot, qw, qx, qy, qz, norm, div = _rotation(np.float64(quats[i, 0]), np.float64(quats[i, 1]),
                                               np.float64(quats[i, 2]), np.float64(quats[i, 3]))
    sc = (np.float64(scales[i, 0]), np.float64(scales[i, 1]), np.float64(scales[i, 2]))
    for r in range(3):
        for k in range(3):
            b_mat[r, k] = (view[r, 0] * rot[k] + view[r, 1] * rot[3 + k] + view[r, 2] * rot[6 + k]) * sc[k]
    for k in range(3):
        m_mat[0, k] = j00 * b_mat[0, k] + j02 * b_mat[2, k]
        m_mat[1, k] = j11 * b_mat[1, k] + j12 * b_mat[2, k]
    a = m_mat[0, 0] * m_mat[0, 0] + m_mat[0, 1] * m_mat[0, 1] + m_mat[0, 2] * m_mat[0, 2] + eps2d
    b = m_mat[0, 0] * m_mat[1, 0] + m_mat[0, 1] * m_mat[1, 1] + m_mat[0, 2] * m_mat[1, 2]
    c = m_mat[1, 0] * m_mat[1, 0] + m_mat[1, 1] * m_mat[1, 1] + m_mat[1, 2] * m_mat[1, 2] + eps2d
    return (m0, m1, m2, x, y, z, front, zs, xz, yz, xc, yc, j00, j02, j11, j12, rot, qw, qx, qy, qz, norm, div, sc,
            a, b, c)


@njit(cache=True, error_model="numpy")
def _project_forward_part(part, n_parts, means, quats, scales, view, cam, clip, width, height, near, eps2d, means2d,
                          conics, depths, radii):
    """Part `part` of n_parts equal ranges of Gaussians: centre, conic, camera z and footprint radius (rule 4)."""
    n = means.shape[0]
    b_mat, m_mat = np.empty((3, 3)), np.empty((2, 3))
    for i in range(part * n // n_parts, (part + 1) * n // n_parts):
        (m0, m1, m2, x, y, z, front, zs, xz, yz, xc, yc, j00, j02, j11, j12, rot, qw, qx, qy, qz, norm, div, sc,
         a, b, c) = _project_one(i, means, quats, scales, view, cam, clip, near, eps2d, b_mat, m_mat)
        u, v = cam[0] * xz + cam[2], cam[1] * yz + cam[3]
        det = a * c - b * b
        means2d[i, 0], means2d[i, 1] = u, v
        conics[i, 0], conics[i, 1], conics[i, 2] = -0.5 * c / det, b / det, -0.5 * a / det
        depths[i] = z
        lam = 0.5 * (a + c) + np.sqrt((0.5 * (a - c)) ** 2 + b * b)
        r = np.ceil(3.0 * np.sqrt(lam))
        r = min(r, 1e7) if r == r else r
        on_image = u + r >= 0 and u - r <= width - 1 and v + r >= 0 and v - r <= height - 1  # False for NaN
        radii[i] = int(r) if front and on_image else 0


@njit(cache=True, parallel=True, error_model="numpy")
def _project_forward(means, quats, scales, view, cam, clip, width, height, near, eps2d, means2d, conics, depths,
                     radii):
    n_parts = min(_PROJECT_PARTS, means.shape[0])
    for part in prange(n_parts):
        _project_forward_part(part, n_parts, means, quats, scales, view, cam, clip, width, height, near, eps2d,
                              means2d, conics, depths, radii)


@njit(cache=True, error_model="numpy")
def _project_backward_part(part, means, quats, scales, view, cam, clip, near, eps2d, g_means2d, g_conics, g_depths,
                           g_means, g_quats, g_scales, g_view_parts):
    """Part `part` of the Gaussians: their gradients, and this part's sum of the viewmat gradient."""
    n = means.shape[0]
    n_parts = g_view_parts.shape[0]
    g_view = np.zeros(12)  # d/d view[:3, :3] row-major, then d/d view[:3, 3]
    b_mat, m_mat = np.empty((3, 3)), np.empty((2, 3))
    g_m = np.empty((2, 3))
    g_b = np.empty((3, 3))
    g_rq = np.empty(9)
    for i in range(part * n // n_parts, (part + 1) * n // n_parts):
        (m0, m1, m2, x, y, z, front, zs, xz, yz, xc, yc, j00, j02, j11, j12, rot, qw, qx, qy, qz, norm, div, sc,
         a, b, c) = _project_one(i, means, quats, scales, view, cam, clip, near, eps2d, b_mat, m_mat)
        # conic = (-c / 2, b, -a / 2) / det
        det = a * c - b * b
        g0, g1, g2 = np.float64(g_conics[i, 0]), np.float64(g_conics[i, 1]), np.float64(g_conics[i, 2])
        det2 = det * det
        g_a = g0 * 0.5 * c * c / det2 - g1 * b * c / det2 + g2 * (-0.5 / det + 0.5 * a * c / det2)
        g_bb = -g0 * c * b / det2 + g1 * (1.0 / det + 2.0 * b * b / det2) - g2 * a * b / det2
        g_c = g0 * (-0.5 / det + 0.5 * a * c / det2) - g1 * a * b / det2 + g2 * 0.5 * a * a / det2
        # a = M0 . M0 + eps, b = M0 . M1, c = M1 . M1 + eps
        for k in range(3):
            g_m[0, k] = 2.0 * g_a * m_mat[0, k] + g_bb * m_mat[1, k]
            g_m[1, k] = g_bb * m_mat[0, k] + 2.0 * g_c * m_mat[1, k]
        # M = J B: J's entries, and B
        g_j00 = g_m[0, 0] * b_mat[0, 0] + g_m[0, 1] * b_mat[0, 1] + g_m[0, 2] * b_mat[0, 2]
        g_j02 = g_m[0, 0] * b_mat[2, 0] + g_m[0, 1] * b_mat[2, 1] + g_m[0, 2] * b_mat[2, 2]
        g_j11 = g_m[1, 0] * b_mat[1, 0] + g_m[1, 1] * b_mat[1, 1] + g_m[1, 2] * b_mat[1, 2]
        g_j12 = g_m[1, 0] * b_mat[2, 0] + g_m[1, 1] * b_mat[2, 1] + g_m[1, 2] * b_mat[2, 2]
        for k in range(3):
            g_b[0, k] = j00 * g_m[0, k]
            g_b[1, k] = j11 * g_m[1, k]
            g_b[2, k] = j02 * g_m[0, k] + j12 * g_m[1, k]
        # B[r, k] = (W R_q)[r, k] s_k
        for k in range(3):
            g_sk = 0.0
            for l in range(3):
                wr = view[0, l] * g_b[0, k] + view[1, l] * g_b[1, k] + view[2, l] * g_b[2, k]  # (W^T gB)[l, k]
                g_sk += wr * rot[3 * l + k]
                g_rq[3 * l + k] = wr * sc[k]
                for r in range(3):
                    g_view[3 * r + l] += g_b[r, k] * rot[3 * l + k] * sc[k]
            g_scales[i, k] = g_sk
        # R_q of the normalised quaternion, then the normalisation (none through the 1e-12 floor)
        gw = 2.0 * (-qz * g_rq[1] + qy * g_rq[2] + qz * g_rq[3] - qx * g_rq[5] - qy * g_rq[6] + qx * g_rq[7])
        gx = 2.0 * (qy * g_rq[1] + qz * g_rq[2] + qy * g_rq[3] - 2.0 * qx * g_rq[4] - qw * g_rq[5]
                    + qz * g_rq[6] + qw * g_rq[7] - 2.0 * qx * g_rq[8])
        gy = 2.0 * (-2.0 * qy * g_rq[0] + qx * g_rq[1] + qw * g_rq[2] + qx * g_rq[3] + qz * g_rq[5]
                    - qw * g_rq[6] + qz * g_rq[7] - 2.0 * qy * g_rq[8])
        gz = 2.0 * (-2.0 * qz * g_rq[0] - qw * g_rq[1] + qx * g_rq[2] + qw * g_rq[3] - 2.0 * qz * g_rq[4]
                    + qy * g_rq[5] + qx * g_rq[6] + qy * g_rq[7])
        if norm >= 1e-12:
            dot = qw * gw + qx * gx + qy * gy + qz * gz
            gw, gx, gy, gz = gw - qw * dot, gx - qx * dot, gy - qy * dot, gz - qz * dot
        g_quats[i, 0], g_quats[i, 1], g_quats[i, 2], g_quats[i, 3] = gw / div, gx / div, gy / div, gz / div
        # J = [[fx / zs, 0, -fx xc / zs], [0, fy / zs, -fy yc / zs]], u = fx x / zs + cx, v = fy y / zs + cy
        fx, fy = cam[0], cam[1]
        g_zs = (-g_j00 * fx + g_j02 * fx * xc - g_j11 * fy + g_j12 * fy * yc) / (zs * zs)
        g_xz = fx * np.float64(g_means2d[i, 0])
        g_yz = fy * np.float64(g_means2d[i, 1])
        if clip[0] <= xz <= clip[1]:
            g_xz -= g_j02 * fx / zs
        if clip[2] <= yz <= clip[3]:
            g_yz -= g_j12 * fy / zs
        g_zs -= (g_xz * x + g_yz * y) / (zs * zs)
        g_p = (g_xz / zs, g_yz / zs, np.float64(g_depths[i]) + (g_zs if front else 0.0))
        # camera point p = W m + t
        for r in range(3):
            g_view[9 + r] += g_p[r]
            g_view[3 * r] += g_p[r] * m0
            g_view[3 * r + 1] += g_p[r] * m1
            g_view[3 * r + 2] += g_p[r] * m2
        for l in range(3):
            g_means[i, l] = view[0, l] * g_p[0] + view[1, l] * g_p[1] + view[2, l] * g_p[2]
    g_view_parts[part, :] = g_view


@njit(cache=True, parallel=True, error_model="numpy")
def _project_backward(means, quats, scales, view, cam, clip, near, eps2d, g_means2d, g_conics, g_depths, g_means,
                      g_quats, g_scales, g_view_parts):
    for part in prange(g_view_parts.shape[0]):
        _project_backward_part(part, means, quats, scales, view, cam, clip, near, eps2d, g_means2d, g_conics,
                               g_depths, g_means, g_quats, g_scales, g_view_parts)


@njit(cache=True, error_model="numpy")
def _image_tile(t, tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height, alpha_max,
                t_min, image, t_final):
    """`_forward_tile` without what the backward pass needs (T in float64, the walked counts): the same per-pixel
    test, alpha, order and stop; writes tile t's pixels of image and t_final."""
    n_feat = table.shape[1] - _N_GEOM
    px0, py0 = (t % n_tx) * tile_px, (t // n_tx) * tile_px
    tw, th = min(tile_px, width - px0), min(tile_px, height - py0)
    start, n_list = tile_start[t], tile_start[t + 1] - tile_start[t]
    trans = np.ones(tw * th)
    acc = np.zeros((tw * th, n_feat))
    n_active = tw * th
    for kk in range(n_list):
        if n_active == 0:
            break
        g = tile_gauss[start + kk]
        u, v, n0, n1, n2, opac = table[g, 0], table[g, 1], table[g, 2], table[g, 3], table[g, 4], table[g, 5]
        fl = floor[g]
        x_lo, x_hi = max(box[g, 0], px0), min(box[g, 1], px0 + tw - 1)
        for py in range(max(box[g, 2], py0), min(box[g, 3], py0 + th - 1) + 1):
            dy = coords[py] - v
            row = (py - py0) * tw - px0
            for px in range(x_lo, x_hi + 1):
                p = row + px
                tp = trans[p]
                if tp < 0.0:  # stopped
                    continue
                dx = coords[px] - u
                s = _neg_half_q(n0, n1, n2, dx, dy)
                if not s >= fl:
                    continue
                a = np.float64(opac * np.exp(s))
                if a > alpha_max:
                    a = alpha_max
                after = tp * (1.0 - a)
                if after < t_min:
                    trans[p] = -tp - 1.0  # stopped; T kept as -(T + 1)
                    n_active -= 1
                    continue
                w = a * tp
                for f in range(n_feat):
                    acc[p, f] += w * table[g, _N_GEOM + f]
                trans[p] = after
    for j in range(th):
        for i in range(tw):
            p = j * tw + i
            for f in range(n_feat):
                image[py0 + j, px0 + i, f] = acc[p, f]
            tp = trans[p]
            t_final[py0 + j, px0 + i] = tp if tp >= 0.0 else -tp - 1.0


@njit(cache=True, parallel=True, error_model="numpy")
def _image(tiles, tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height, alpha_max, t_min,
           image, t_final):
    for i in prange(tiles.shape[0]):
        _image_tile(tiles[i], tile_start, tile_gauss, box, table, floor, coords, tile_px, n_tx, width, height,
                    alpha_max, t_min, image, t_final)


def image_numba(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray, colors: np.ndarray,
                viewmat: np.ndarray, K: np.ndarray, width_px: int, height_px: int, *, near: float, tile_px: int,
                eps2d: float, frustum_margin: float, alpha_min: float, alpha_max: float, q_max: float,
                t_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Forward only, for viewing: the image (H, W, C) and T_final (H, W) of `raster`'s rules over numpy arrays
    (float32 or float64, the dtype of means), with no autograd and nothing kept for a backward pass. The same
    kernels as `project_numba` and `composite_numba` up to the compositing, whose kernel drops the backward's
    bookkeeping; equal to them to rounding."""
    dtype = means.dtype
    n = means.shape[0]
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    tan_x, tan_y = 0.5 * width_px / fx, 0.5 * height_px / fy
    clip = np.array([-(cx + 0.5) / fx - frustum_margin * tan_x, (width_px - 0.5 - cx) / fx + frustum_margin * tan_x,
                     -(cy + 0.5) / fy - frustum_margin * tan_y, (height_px - 0.5 - cy) / fy + frustum_margin * tan_y])
    means2d, conics = np.empty((n, 2), dtype), np.empty((n, 3), dtype)
    depths, radii = np.empty(n, dtype), np.empty(n, np.int32)
    _use_torch_threads()
    _project_forward(np.ascontiguousarray(means), np.ascontiguousarray(quats), np.ascontiguousarray(scales),
                     np.ascontiguousarray(viewmat, np.float64), np.array([fx, fy, cx, cy]), clip, width_px, height_px,
                     float(near), float(eps2d), means2d, conics, depths, radii)
    table = np.empty((n, _N_GEOM + colors.shape[1]), dtype)
    table[:, :2], table[:, 2:5], table[:, 5], table[:, _N_GEOM:] = means2d, conics, opacities, colors
    # in torch, as composite_numba computes it, so that both round alike at the cutoff
    floor = torch.log(alpha_min / torch.from_numpy(table[:, 5].copy())).clamp(min=-0.5 * q_max).numpy()
    bins = _bin(table, floor, radii.astype(dtype), radii, depths, width_px, height_px, tile_px,
                float(np.finfo(dtype).eps) / 2)
    coords = np.arange(max(width_px, height_px), dtype=dtype)
    image = np.empty((height_px, width_px, colors.shape[1]), dtype)
    t_final = np.empty((height_px, width_px), dtype)
    with numba.parallel_chunksize(1):
        _image(bins.tiles, bins.tile_start, bins.tile_gauss, bins.box, table, floor, coords, tile_px, bins.n_tx,
               width_px, height_px, alpha_max, t_min, image, t_final)
    return image, t_final


def _use_torch_threads() -> None:
    """Run the kernels on torch.get_num_threads() threads (at most numba.config.NUMBA_NUM_THREADS).

    numba's omp threading layer (its default where TBB is not installed) binds to the OpenMP runtime that torch has
    already loaded, so both share one pool of threads instead of spinning against each other (on two cores, the
    workqueue layer or a pool of Python threads made two threads barely faster than one). Starting numba's pool
    sets that runtime's thread count to NUMBA_NUM_THREADS, which is why torch's count is read first and put back."""
    want = torch.get_num_threads()
    numba.get_num_threads()  # starts numba's pool once
    if torch.get_num_threads() != want:
        torch.set_num_threads(want)
    numba.set_num_threads(max(1, min(want, numba.config.NUMBA_NUM_THREADS)))


class _Composite(torch.autograd.Function):
    """feats (H, W, F), t_final (H, W) of `table` (N, 6 + F); the other arguments are constants."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, floor: np.ndarray, bins: _Bins, width_px: int, height_px: int,
                tile_px: int, alpha_max: float, t_min: float):
        tab = table.detach().numpy()
        dtype = tab.dtype
        coords = np.arange(max(width_px, height_px), dtype=dtype)
        feats = np.empty((height_px, width_px, tab.shape[1] - _N_GEOM), dtype)
        t_final = np.empty((height_px, width_px), dtype)
        t_final64 = np.empty((height_px, width_px))
        n_walked = np.empty((height_px, width_px), np.int64)
        _use_torch_threads()
        with numba.parallel_chunksize(1):  # tiles one at a time, busiest first
            _forward(bins.tiles, bins.tile_start, bins.tile_gauss, bins.box, tab, floor, coords, tile_px, bins.n_tx,
                     width_px, height_px, alpha_max, t_min, feats, t_final, t_final64, n_walked)
        ctx.save_for_backward(table)
        ctx.consts = (floor, bins, coords, width_px, height_px, tile_px, alpha_max, t_final64, n_walked)
        return torch.from_numpy(feats), torch.from_numpy(t_final)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_feats: torch.Tensor, grad_t: torch.Tensor):
        (table,) = ctx.saved_tensors
        floor, bins, coords, width_px, height_px, tile_px, alpha_max, t_final64, n_walked = ctx.consts
        tab = table.detach().numpy()
        pair_grad = np.empty((len(bins.tile_gauss), tab.shape[1]))
        grad_table = np.zeros(tab.shape)
        _use_torch_threads()
        with numba.parallel_chunksize(1):
            _backward(bins.tiles, bins.tile_start, bins.tile_gauss, bins.box, tab, floor, coords, tile_px,
                      bins.n_tx, width_px, height_px, alpha_max, t_final64, n_walked,
                      grad_feats.detach().to(table.dtype).contiguous().numpy(),
                      grad_t.detach().to(table.dtype).contiguous().numpy(), pair_grad)
        with numba.parallel_chunksize(256):
            _reduce(bins.order, bins.gauss_start, bins.pair_pos, pair_grad, grad_table)
        return torch.from_numpy(grad_table).to(table.dtype), None, None, None, None, None, None, None


class _Project(torch.autograd.Function):
    """means2d (N, 2), conics (N, 3), depths (N,) and radii (N,) int32 (no gradient) of means, quats, scales and
    viewmat; the other arguments are constants."""

    @staticmethod
    def forward(ctx, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmat: torch.Tensor,
                cam: np.ndarray, clip: np.ndarray, width_px: int, height_px: int, near: float, eps2d: float):
        n, dtype = means.shape[0], means.detach().numpy().dtype
        means2d, conics = np.empty((n, 2), dtype), np.empty((n, 3), dtype)
        depths, radii = np.empty(n, dtype), np.empty(n, np.int32)
        _use_torch_threads()
        _project_forward(*_Project._arrays(means, quats, scales, viewmat), cam, clip, width_px, height_px, near, eps2d,
                         means2d, conics, depths, radii)
        out_radii = torch.from_numpy(radii)
        ctx.mark_non_differentiable(out_radii)
        ctx.save_for_backward(means, quats, scales, viewmat)
        ctx.consts = (cam, clip, near, eps2d)
        return torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths), out_radii

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d: torch.Tensor, g_conics: torch.Tensor, g_depths: torch.Tensor, _g_radii):
        means, quats, scales, viewmat = ctx.saved_tensors
        cam, clip, near, eps2d = ctx.consts
        n = means.shape[0]
        g_means, g_quats, g_scales = np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3))
        g_view_parts = np.empty((max(1, min(_PROJECT_PARTS, n)), 12))
        _use_torch_threads()
        _project_backward(*_Project._arrays(means, quats, scales, viewmat), cam, clip, near, eps2d,
                          *(g.detach().contiguous().numpy() for g in (g_means2d, g_conics, g_depths)),
                          g_means, g_quats, g_scales, g_view_parts)
        g_view = np.zeros((4, 4))
        if n:
            parts = g_view_parts.sum(0)
            g_view[:3, :3], g_view[:3, 3] = parts[:9].reshape(3, 3), parts[9:]
        dt = means.dtype
        return (torch.from_numpy(g_means).to(dt), torch.from_numpy(g_quats).to(dt),
                torch.from_numpy(g_scales).to(dt), torch.from_numpy(g_view).to(dt), None, None, None, None, None,
                None)

    @staticmethod
    def _arrays(means, quats, scales, viewmat) -> tuple[np.ndarray, ...]:
        """The kernels' views of the inputs: contiguous, viewmat in float64."""
        return (means.detach().contiguous().numpy(), quats.detach().contiguous().numpy(),
                scales.detach().contiguous().numpy(), viewmat.detach().double().contiguous().numpy())


def project_numba(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmat: torch.Tensor,
                  K: torch.Tensor, width_px: int, height_px: int, near: float, *, eps2d: float,
                  frustum_margin: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rules 1-4 of `raster` per Gaussian, in float64 and returned in the dtype of `means`: projected centres
    (N, 2), conics (N, 3) (n0, n1, n2) with -q/2 = n0 dx^2 + n1 dx dy + n2 dy^2, camera z (N,) and footprint
    radii (N,) int32 (0: culled or off the image), differentiable in means, quats, scales and viewmat (not K).
    eps2d is the px^2 dilation of Sigma2, frustum_margin the widening of J's clamp as a fraction of the half-width."""
    if means.device.type != "cpu" or means.dtype not in (torch.float32, torch.float64):
        raise InputError("means", f"the numba back end needs float32 or float64 CPU tensors, got {means.dtype} on "
                                  f"{means.device}")
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    tan_x, tan_y = 0.5 * width_px / fx, 0.5 * height_px / fy
    clip = np.array([-(cx + 0.5) / fx - frustum_margin * tan_x, (width_px - 0.5 - cx) / fx + frustum_margin * tan_x,
                     -(cy + 0.5) / fy - frustum_margin * tan_y, (height_px - 0.5 - cy) / fy + frustum_margin * tan_y])
    return _Project.apply(means, quats, scales, viewmat, np.array([fx, fy, cx, cy]), clip, width_px, height_px,
                          float(near), float(eps2d))


def composite_numba(table: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, width_px: int, height_px: int,
                    tile_px: int, *, alpha_min: float, alpha_max: float, q_max: float,
                    t_min: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite the rows of `table` (N, 6 + F; float32 or float64, CPU) into features (H, W, F) and T_final
    (H, W), both differentiable in `table`. radii (N,) int footprint radii (0: not drawn) and depths (N,) camera z
    (the depth order) are read without gradient. The cutoffs are those of `raster`'s rules: a >= alpha_min and
    q <= q_max to contribute, a clamped at alpha_max, stop when T would fall below t_min."""
    if table.device.type != "cpu":
        raise InputError("means", f"the numba back end needs CPU tensors, got {table.device}")
    if table.dtype not in (torch.float32, torch.float64):
        raise InputError("means", f"the numba back end needs float32 or float64, got {table.dtype}")
    if table.dim() != 2 or table.shape[1] <= _N_GEOM:
        raise InputError("table", f"expected shape (N, > {_N_GEOM}), got {tuple(table.shape)}")
    if radii.shape != table.shape[:1] or depths.shape != table.shape[:1]:
        raise InputError("radii", f"expected radii and depths of shape ({table.shape[0]},), got "
                                  f"{tuple(radii.shape)} and {tuple(depths.shape)}")
    table = table.contiguous()
    with torch.no_grad():
        floor = torch.log(alpha_min / table[:, 5]).clamp(min=-0.5 * q_max).contiguous().numpy()
        tab = table.detach().numpy()
        radii_f = radii.to(table.dtype).contiguous().numpy()
        _use_torch_threads()
        bins = _bin(tab, floor, radii_f, radii.to(torch.int32).contiguous().numpy(),
                    depths.detach().contiguous().numpy(), width_px, height_px, tile_px,
                    float(np.finfo(tab.dtype).eps) / 2)
    log.debug("%d Gaussians in %d tile pairs", len(bins.order), len(bins.tile_gauss))
    return _Composite.apply(table, floor, bins, width_px, height_px, tile_px, alpha_max, t_min)
