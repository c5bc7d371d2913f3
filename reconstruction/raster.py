"""Differentiable 3D Gaussian splatting rasterizer: a numba path (CPU), a tile-based PyTorch path, a brute-force
reference and an optional gsplat (CUDA) back end behind one `rasterize` call.

Image formation, the same in the numba path, the torch tile path and the reference (they agree to float
rounding):

1. Camera-space mean m_c = R m + t (OpenCV camera: x right, y down, z forward); z = m_c[2]. Gaussians with
   z <= near are culled: radius 0, no contribution, zero (finite) gradients.
2. Sigma2 = J W Sigma W^T J^T + 0.3 I px^2 (EWA local affine approximation; Sigma = R_q S S^T R_q^T from the
   normalised quaternion). In J, x/z and y/z are clamped to the view frustum widened by 30 % of its
   half-width on each side: x/z in [-(cx + 0.5)/fx - 0.3 tx, (W - 0.5 - cx)/fx + 0.3 tx], tx = W / (2 fx)
   (likewise y), which is gsplat's clamp written in our pixel convention, and INRIA's +-1.3 tan(fov/2) when the
   principal point is centred. It only keeps J sane for Gaussians at or beyond the edge of the view.
3. Projected centre u = fx x/z + cx, v = fy y/z + cy; the centre of pixel (i, j) is at (i, j) (OpenCV).
4. At pixel centre p, q = d^T Sigma2^-1 d with d = p - (u, v). The Gaussian contributes iff q <= 9 and
   a = min(0.99, o exp(-q/2)) >= 1/255 (evaluated as the same inequality on -q/2: -q/2 >= ln(1 / (255 o))).
   Tile footprint radius r = ceil(3 sqrt(lambda_max(Sigma2))) px, which holds the q <= 9 ellipse; a Gaussian
   whose box [u - r, u + r] x [v - r, v + r] holds no pixel centre of the image gets radius 0.
5. Front to back in increasing z (ties by index): T_i = prod_{j<i} (1 - a_j) over contributing Gaussians,
   w_i = a_i T_i. Early termination: Gaussian i is kept iff the transmittance after it, T_i (1 - a_i), is
   >= 1e-4. T only falls, so this drops the first Gaussian that would take T below 1e-4 and every one behind it
   (INRIA's `test_T < 0.0001 -> done`). T_final is the transmittance after the last kept Gaussian.
6. image = sum w_i c_i + T_final background; alpha = 1 - T_final; depth = sum w_i z_i (alpha-weighted, not
   divided by alpha: divide by alpha for the expected depth); extras = sum w_i e_i (no background).

Back ends: "numba" (raster_cpu) projects and composites in numba kernels with hand-written backward passes:
rules 1-3 and the radius in float64, the per-pixel test and alpha of rule 4 in the dtype of the inputs, T and
the sums of rules 5-6 in float64, outputs in the dtype of the inputs. Each tile of tile_px^2 pixels walks its
front-to-back list, visiting each Gaussian only over the pixels where rule 4 can hold. It runs on
torch.get_num_threads() threads and its gradients do not depend on the thread count. In float64 it agrees with
the reference to rounding; in float32 it is nearer the float64 result than the torch path, which projects in
float32. "torch" bins Gaussians into tiles by their boxes and evaluates each tile's padded,
depth-sorted list densely; autograd does the backward, and when its saved tensors would pass ~256 MB each chunk of
tiles is recomputed in backward instead (torch.utils.checkpoint). "reference" evaluates every visible Gaussian at
every pixel. "gsplat" (CUDA, float32) follows the same formation but clamps a at 0.999, has no q <= 9 cutoff (it
agrees exactly when o < 0.35, where a >= 1/255 already implies q < 9) and stops at T <= 1e-4; its means2d is
a leaf whose .grad a hook fills with the view-space gradient.
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

from odsplat.spine.errors import InputError

from .quaternion import quat_to_matrix
from .raster_cpu import composite_numba, image_numba, project_numba

log = logging.getLogger(__name__)

BACKENDS = ("auto", "numba", "torch", "reference", "gsplat")
EPS2D_PX2 = 0.3  # dilation of Sigma2: a Gaussian covers at least ~one pixel (anti-aliasing)
Q_MAX = 9.0  # contributes inside its 3-sigma ellipse only
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
FRUSTUM_MARGIN = 0.3  # J's clamp: the frustum widened by this fraction of its half-width per side
_CHUNK_PAIRS = 1 << 18  # (pixel, Gaussian) pairs evaluated at once: a few MB of temporaries per chunk
_SAVED_BUDGET_BYTES = 256 << 20  # beyond this, chunks are recomputed in backward rather than kept
_SAVED_PER_PAIR = 12  # values of the dtype that autograd keeps per pair (measured: ~50 B in float32)


@dataclass
class RasterOutput:
    """One rendered view. `depth` is sum_i w_i z_i, NOT divided by `alpha` (depth / alpha is the expected z)."""

    image: torch.Tensor  # (H, W, C) composite of colors plus background * final transmittance
    alpha: torch.Tensor  # (H, W) 1 - final transmittance
    depth: torch.Tensor  # (H, W) alpha-weighted camera z
    extras: torch.Tensor | None  # (H, W, E) composite of the extras with the same weights, no background
    means2d: torch.Tensor  # (N, 2) projected centres in px; .retain_grad() on it gives the view-space gradient
    radii_px: torch.Tensor  # (N,) int32 footprint radius, 0 for culled Gaussians
    depths: torch.Tensor  # (N,) camera z of each mean


@dataclass
class _Projected:
    means2d: torch.Tensor  # (N, 2)
    conics: torch.Tensor  # (N, 3): (n0, n1, n2) with -q/2 = n0 dx^2 + n1 dx dy + n2 dy^2
    depths: torch.Tensor  # (N,)
    radii: torch.Tensor  # (N,) int32


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """True when gsplat can run here: CUDA first (so a CPU-only torch never imports, let alone compiles, gsplat)."""
    try:
        if not torch.cuda.is_available():
            return False
        import gsplat  # noqa: F401

        return hasattr(gsplat, "rasterization")
    except Exception as exc:  # a broken install or a failed build must read as "not available"
        log.info("gsplat unavailable: %s", exc)
        return False


def _project(means, quats, scales, viewmat, K, width_px: int, height_px: int, near: float) -> _Projected:
    """Rules 1-4 per Gaussian: centre, negated half inverse of Sigma2, camera z and tile radius."""
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    x, y, z = (means @ rot.T + trans).unbind(-1)
    in_front = z > near
    # Culled Gaussians divide by 1 instead: their output is masked, but a NaN or inf in the unused branch of a
    # where() would still turn into NaN gradients.
    zs = torch.where(in_front, z, torch.ones_like(z))
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    xz, yz = x / zs, y / zs
    means2d = torch.stack([fx * xz + cx, fy * yz + cy], -1)
    tan_x, tan_y = 0.5 * width_px / fx, 0.5 * height_px / fy
    xz = xz.clamp(-(cx + 0.5) / fx - FRUSTUM_MARGIN * tan_x, (width_px - 0.5 - cx) / fx + FRUSTUM_MARGIN * tan_x)
    yz = yz.clamp(-(cy + 0.5) / fy - FRUSTUM_MARGIN * tan_y, (height_px - 0.5 - cy) / fy + FRUSTUM_MARGIN * tan_y)
    zero = torch.zeros_like(zs)
    jac = torch.stack([fx / zs, zero, -fx * xz / zs, zero, fy / zs, -fy * yz / zs], -1).reshape(-1, 2, 3)
    # Sigma2 = (J W R_q S)(J W R_q S)^T: the same product without forming the 3D covariance
    m = jac @ rot @ (quat_to_matrix(quats) * scales[:, None, :])
    cov = m @ m.transpose(1, 2)
    a, b, c = cov[:, 0, 0] + EPS2D_PX2, cov[:, 0, 1], cov[:, 1, 1] + EPS2D_PX2
    det = a * c - b * b
    conics = torch.stack([-0.5 * c / det, b / det, -0.5 * a / det], -1)
    with torch.no_grad():
        lam = 0.5 * (a + c) + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
        r = torch.ceil(3.0 * torch.sqrt(lam)).clamp(max=1e7)
        u, v = means2d.unbind(-1)
        on_image = (u + r >= 0) & (u - r <= width_px - 1) & (v + r >= 0) & (v - r <= height_px - 1)
        radii = torch.where(in_front & on_image, r, torch.zeros_like(r)).to(torch.int32)
    return _Projected(means2d, conics, z, radii)


def _composite(xs: torch.Tensor, ys: torch.Tensor, table: torch.Tensor, gidx: torch.Tensor):
    """Rules 4-6 on B pixel grids, columns `xs` (B, X) by rows `ys` (B, Y), over the depth-sorted rows `gidx`
    (B, M) of `table` (u, v, n0, n1, n2, opacity, F features; its last row empty, opacity 0). Returns the
    composited features (B, Y X, F), pixels in row-major order, and T_final (B, Y X)."""
    n_b, n_pix = xs.shape[0], xs.shape[1] * ys.shape[1]
    if gidx.shape[1] == 0:
        return xs.new_zeros(n_b, n_pix, table.shape[1] - 6), xs.new_ones(n_b, n_pix)
    # a leading empty column makes the cumulative product start at T = 1: T before and after are two views of it
    g = table[torch.nn.functional.pad(gidx, (1, 0), value=len(table) - 1)]
    u, v, n0, n1, n2, opac = g[..., :6].unbind(-1)
    dx = xs[:, :, None] - u[:, None, :]  # (B, X, M)
    dy = ys[:, :, None] - v[:, None, :]  # (B, Y, M)
    # -q/2 = n0 dx^2 + n1 dx dy + n2 dy^2: the squares depend on the column or the row alone, so only the cross
    # term and two additions run over every (pixel, Gaussian) pair
    neg_half_q = ((n1[:, None] * dx)[:, None] * dy[:, :, None] + (n0[:, None] * dx * dx)[:, None]
                  + (n2[:, None] * dy * dy)[:, :, None]).reshape(n_b, n_pix, -1)
    with torch.no_grad():
        # a >= 1/255 as the same inequality on -q/2: -q/2 >= ln(1 / (255 o)) (+inf for the padding's o = 0)
        floor = torch.log(ALPHA_MIN / opac).clamp(min=-0.5 * Q_MAX)
        inside = (neg_half_q >= floor[:, None, :]).to(neg_half_q.dtype)
    # Masks multiply rather than where(): where() and clamp()'s backward are ~30x slower than a product on CPU.
    # Outside, exp(0) * 0 is exactly 0, and exp() never meets the far-out values that take its slow path.
    alpha = opac[:, None, :] * torch.exp(neg_half_q * inside) * inside
    if bool(alpha.detach().max() > ALPHA_MAX):
        alpha = alpha.clamp(max=ALPHA_MAX)
    trans = torch.cumprod(1.0 - alpha, -1)
    t_after = trans[..., 1:]
    w = alpha[..., 1:] * trans[..., :-1]
    if bool((t_after[..., -1] < T_MIN).any()):  # T only falls: the last column tells whether any pixel stops
        keep = t_after.detach() >= T_MIN  # a prefix along M
        w = w * keep.to(w.dtype)
        last = (keep.sum(-1, keepdim=True) - 1).clamp(min=0)
        t_final = torch.where(keep[..., :1], t_after.gather(-1, last), torch.ones_like(t_after[..., :1]))[..., 0]
    else:
        t_final = t_after[..., -1].clone()  # a view would keep all of `trans` alive, checkpointed or not
    return w @ g[:, 1:, 6:], t_final


def _run(xs, ys, table, gidx, recompute: bool):
    if recompute:
        return checkpoint(_composite, xs, ys, table, gidx, use_reentrant=False)
    return _composite(xs, ys, table, gidx)


def _recompute(table: torch.Tensor, n_pairs: int) -> bool:
    """Whether autograd's saved tensors would exceed the budget; then each chunk is recomputed in backward."""
    saved = n_pairs * _SAVED_PER_PAIR * table.element_size()
    return torch.is_grad_enabled() and table.requires_grad and saved > _SAVED_BUDGET_BYTES


def _depth_order(proj: _Projected) -> torch.Tensor:
    """Indices of the Gaussians with radius > 0, front to back (stable: ties keep index order)."""
    visible = proj.radii > 0
    z = torch.where(visible, proj.depths.detach(), torch.full_like(proj.depths, math.inf))
    return torch.argsort(z, stable=True)[: int(visible.sum())]


def _composite_reference(table, proj, width_px: int, height_px: int):
    order = _depth_order(proj)
    coords = [torch.arange(n, device=table.device).to(table)[None] for n in (width_px, height_px)]
    # blocks of whole rows, or of part of one row when a row alone holds more than a chunk of pairs
    cols = min(width_px, max(1, _CHUNK_PAIRS // max(1, len(order))))
    rows = max(1, _CHUNK_PAIRS // (cols * max(1, len(order))))
    recompute = _recompute(table, width_px * height_px * len(order))
    feats, finals = [], []
    for i in range(0, height_px, rows):
        ys = coords[1][:, i:i + rows]
        parts = [_run(coords[0][:, j:j + cols], ys, table, order[None], recompute) for j in range(0, width_px, cols)]
        feats.append(torch.cat([f.reshape(ys.shape[1], -1, f.shape[-1]) for f, _ in parts], 1))
        finals.append(torch.cat([t.reshape(ys.shape[1], -1) for _, t in parts], 1))
    return torch.cat(feats), torch.cat(finals)


def _composite_tiles(table, proj, width_px: int, height_px: int, tile_px: int):
    n_cols, n_tx, n_ty = table.shape[1], -(-width_px // tile_px), -(-height_px // tile_px)
    n_tiles, n_pix, dev = n_tx * n_ty, tile_px * tile_px, table.device
    with torch.no_grad():
        order = _depth_order(proj)
        n_vis = len(order)
        u, v = proj.means2d[order].unbind(-1)
        r = proj.radii[order].to(u.dtype)
        x0, x1 = (torch.ceil(u - r).clamp(0, width_px - 1).long() // tile_px,
                  torch.floor(u + r).clamp(0, width_px - 1).long() // tile_px)
        y0, y1 = (torch.ceil(v - r).clamp(0, height_px - 1).long() // tile_px,
                  torch.floor(v + r).clamp(0, height_px - 1).long() // tile_px)
        nx = x1 - x0 + 1
        count = nx * (y1 - y0 + 1)
        rank = torch.repeat_interleave(torch.arange(n_vis, device=dev), count)  # one row per (Gaussian, tile) pair
        local = torch.arange(len(rank), device=dev) - (torch.cumsum(count, 0) - count)[rank]
        tile = (y0[rank] + local // nx[rank]) * n_tx + x0[rank] + local % nx[rank]
        key = torch.sort(tile * max(n_vis, 1) + rank).values  # by tile, then front to back
        gauss = order[key % max(n_vis, 1)]
        per_tile = torch.bincount(key // max(n_vis, 1), minlength=n_tiles)
        start = torch.cumsum(per_tile, 0) - per_tile
        # chunks of tiles with similar counts: little padding
        by_count = torch.argsort(per_tile, descending=True)
        counts = per_tile[by_count].tolist()
        span = torch.arange(tile_px, device=dev)
    recompute = _recompute(table, n_pix * int(per_tile.sum()))
    log.debug("%d Gaussians in %d tile pairs, recompute in backward: %s", n_vis, len(key), recompute)
    feats, finals, done = [], [], []
    s, n_busy = 0, sum(1 for c in counts if c > 0)
    while s < n_busy:
        m = counts[s]
        e = min(n_busy, s + max(1, _CHUNK_PAIRS // (n_pix * m)))
        t = by_count[s:e]
        j = torch.arange(m, device=dev)
        idx = start[t, None] + j
        gidx = torch.where(j < per_tile[t, None], gauss[idx.clamp(max=len(gauss) - 1)], len(table) - 1)
        xs = ((t % n_tx) * tile_px)[:, None] + span
        ys = ((t // n_tx) * tile_px)[:, None] + span
        f, tf = _run(xs.to(table), ys.to(table), table, gidx, recompute)
        feats.append(f), finals.append(tf), done.append(t)
        s = e
    out = table.new_zeros(n_tiles, n_pix, n_cols - 6)
    t_final = table.new_ones(n_tiles, n_pix)
    if done:
        t = torch.cat(done)
        out, t_final = out.index_copy(0, t, torch.cat(feats)), t_final.index_copy(0, t, torch.cat(finals))

    def untile(x: torch.Tensor) -> torch.Tensor:
        x = x.reshape(n_ty, n_tx, tile_px, tile_px, -1).permute(0, 2, 1, 3, 4)
        return x.reshape(n_ty * tile_px, n_tx * tile_px, -1)[:height_px, :width_px]

    return untile(out), untile(t_final)[..., 0]


def _check(name: str, t, shape: tuple, like: torch.Tensor | None = None) -> None:
    """`shape` holds sizes or (label, size) pairs; a size of None is free."""
    dims = [s if isinstance(s, tuple) else (None, s) for s in shape]
    want = "(" + ", ".join(f"{k}={n}" if k and n is not None else (k or str(n)) for k, n in dims) + ")"
    if not isinstance(t, torch.Tensor):
        raise InputError(name, f"expected a tensor of shape {want}, got {type(t).__name__}")
    if t.dim() != len(dims) or any(n is not None and n != d for (_, n), d in zip(dims, t.shape)):
        raise InputError(name, f"expected shape {want}, got {tuple(t.shape)}")
    if like is not None and (t.dtype != like.dtype or t.device != like.device):
        raise InputError(name, f"expected {like.dtype} on {like.device} like means, got {t.dtype} on {t.device}")


def _validate(means, quats, scales, opacities, colors, viewmat, K, width_px, height_px, background, extras,
              near, tile_px) -> None:
    _check("means", means, (("N", None), 3))
    if not means.is_floating_point():
        raise InputError("means", f"expected a floating-point tensor, got {means.dtype}")
    n = ("N", means.shape[0])
    _check("quats", quats, (n, 4), means)
    _check("scales", scales, (n, 3), means)
    _check("opacities", opacities, (n,), means)
    _check("colors", colors, (n, ("C", None)), means)
    if colors.shape[1] < 1:
        raise InputError("colors", "expected at least one channel, got C=0")
    _check("viewmat", viewmat, (4, 4), means)
    _check("K", K, (3, 3), means)
    if background is not None:
        _check("background", background, (("C", colors.shape[1]),), means)
    if extras is not None:
        _check("extras", extras, (n, ("E", None)), means)
    for name, val in (("width_px", width_px), ("height_px", height_px), ("tile_px", tile_px)):
        if not isinstance(val, int) or val < 1:
            raise InputError(name, f"expected a positive int, got {val!r}")
    if not (isinstance(near, (int, float)) and near >= 0):
        raise InputError("near", f"expected a number >= 0, got {near!r}")


def _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, K, width_px, height_px, background,
                      extras, near, tile_px) -> RasterOutput:
    import gsplat

    n_colors = colors.shape[1]
    feats = colors if extras is None else torch.cat([colors, extras], 1)
    # gsplat puts the centre of pixel (i, j) at (i + 0.5, j + 0.5), ours at (i, j): shift the principal point.
    shift = torch.zeros_like(K)
    shift[0, 2] = shift[1, 2] = 0.5
    bg = None if background is None else torch.cat([background, background.new_zeros(feats.shape[1] - n_colors)])
    render, alphas, meta = gsplat.rasterization(
        means, quats, scales, opacities, feats, viewmat[None], (K + shift)[None], width_px, height_px,
        near_plane=near, eps2d=EPS2D_PX2, packed=False, tile_size=tile_px,
        backgrounds=None if bg is None else bg[None], render_mode="RGB+D", rasterize_mode="classic")
    render = render[0]
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5 gives an (x, y) radius pair
        radii = radii.amax(-1)
    # gsplat's own means2d (C, N, 2) is what its image depends on; ours is a leaf whose .grad a hook fills with
    # that gradient, so .retain_grad() and .grad work as on the torch path (a leaf: no gradient flows back).
    theirs = meta["means2d"]
    means2d = (theirs[0].detach() - 0.5).requires_grad_(theirs.requires_grad)
    if theirs.requires_grad:
        def _pass_grad(grad: torch.Tensor) -> None:
            g = grad[0].detach()
            means2d.grad = g.clone() if means2d.grad is None else means2d.grad + g

        theirs.register_hook(_pass_grad)
    depths = (means @ viewmat[:3, :3].T + viewmat[:3, 3])[:, 2]
    return RasterOutput(render[..., :n_colors], alphas[0, ..., 0], render[..., -1],
                        None if extras is None else render[..., n_colors:-1], means2d, radii.to(torch.int32), depths)


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
              colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width_px: int, height_px: int, *,
              background: torch.Tensor | None = None, extras: torch.Tensor | None = None, near: float = 0.01,
              tile_px: int = 8, backend: str = "auto") -> RasterOutput:
    """Render N Gaussians into one (height_px, width_px) view by the rules of the module docstring.

    means (N, 3) world; quats (N, 4) as (w, x, y, z), normalised here; scales (N, 3) standard deviations;
    opacities (N,) in (0, 1); colors (N, C); viewmat (4, 4) world-to-camera (OpenCV); K (3, 3) in px, centre
    of pixel (0, 0) at (0, 0); background (C,) or None (zeros); extras (N, E) or None, composited like colors
    without background. Gradients reach every tensor but K. backend: "numba" (CPU, float32 or float64; tiles of
    tile_px^2), "torch" (tiles of tile_px^2), "reference" (brute force), "gsplat" (CUDA, float32), "auto" (gsplat
    for float32 CUDA tensors when available, else numba for float32 or float64 CPU tensors, else torch).
    """
    if backend not in BACKENDS:
        raise InputError("backend", f"expected one of {', '.join(BACKENDS)}, got {backend!r}")
    _validate(means, quats, scales, opacities, colors, viewmat, K, width_px, height_px, background, extras, near,
              tile_px)
    if backend == "auto":
        cuda32 = means.is_cuda and means.dtype == torch.float32
        cpu = means.device.type == "cpu" and means.dtype in (torch.float32, torch.float64)
        backend = "gsplat" if cuda32 and gsplat_available() else ("numba" if cpu else "torch")
    if backend == "gsplat":
        if not gsplat_available():
            raise InputError("backend", "gsplat needs CUDA and the gsplat package, which this machine lacks")
        if not means.is_cuda:
            raise InputError("means", f"the gsplat back end needs CUDA tensors, got {means.device}")
        return _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, K, width_px, height_px,
                                 background, extras, near, tile_px)
    if backend == "numba":
        proj = _Projected(*project_numba(means, quats, scales, viewmat, K, width_px, height_px, near,
                                         eps2d=EPS2D_PX2, frustum_margin=FRUSTUM_MARGIN))
    else:
        proj = _project(means, quats, scales, viewmat, K, width_px, height_px, near)
    n_colors = colors.shape[1]
    table = torch.cat([proj.means2d, proj.conics, opacities[:, None], colors, proj.depths[:, None]]
                      + ([extras] if extras is not None else []), 1)
    if backend == "numba":
        feats, t_final = composite_numba(table, proj.radii, proj.depths, width_px, height_px, tile_px,
                                         alpha_min=ALPHA_MIN, alpha_max=ALPHA_MAX, q_max=Q_MAX, t_min=T_MIN)
    else:
        table = torch.cat([table, table.new_zeros(1, table.shape[1])])  # an empty last row (opacity 0): padding
        if backend == "reference":
            feats, t_final = _composite_reference(table, proj, width_px, height_px)
        else:
            feats, t_final = _composite_tiles(table, proj, width_px, height_px, tile_px)
    image = feats[..., :n_colors]
    if background is not None:
        image = image + t_final[..., None] * background
    extras_img = None if extras is None else feats[..., n_colors + 1:]
    return RasterOutput(image, 1.0 - t_final, feats[..., n_colors], extras_img, proj.means2d, proj.radii, proj.depths)


def rasterize_image(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
                    colors: np.ndarray, viewmat: np.ndarray, K: np.ndarray, width_px: int, height_px: int, *,
                    background: np.ndarray | None = None, near: float = 0.01, tile_px: int = 8,
                    backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Forward only, for viewing: the image (H, W, C) and alpha (H, W) of `rasterize`'s rules, numpy in and out
    (float32 or float64), no gradients and nothing kept for a backward pass. backend: "numba" (CPU), "gsplat"
    (CUDA), "auto" (gsplat where it is available, else numba). The arguments are `rasterize`'s as arrays."""
    if backend not in ("auto", "numba", "gsplat"):
        raise InputError("backend", f"expected auto, numba or gsplat, got {backend!r}")
    means = np.asarray(means)
    if means.dtype not in (np.float32, np.float64):
        means = means.astype(np.float32)
    dt = means.dtype
    arrays = [np.asarray(a, dt) for a in (quats, scales, opacities, colors)]
    if backend == "gsplat" or (backend == "auto" and gsplat_available()):
        if not gsplat_available():
            raise InputError("backend", "gsplat needs CUDA and the gsplat package, which this machine lacks")
        cuda = lambda a: torch.as_tensor(np.asarray(a, np.float32), device="cuda")  # noqa: E731
        bg = None if background is None else cuda(background)
        with torch.no_grad():
            out = _rasterize_gsplat(cuda(means), *(cuda(a) for a in arrays), cuda(viewmat), cuda(K), width_px,
                                    height_px, bg, None, near, tile_px)
        return out.image.cpu().numpy().astype(dt), out.alpha.cpu().numpy().astype(dt)
    image, t_final = image_numba(means, *arrays, np.asarray(viewmat, np.float64), np.asarray(K, np.float64),
                                 width_px, height_px, near=near, tile_px=tile_px, eps2d=EPS2D_PX2,
                                 frustum_margin=FRUSTUM_MARGIN, alpha_min=ALPHA_MIN, alpha_max=ALPHA_MAX, q_max=Q_MAX,
                                 t_min=T_MIN)
    if background is not None:
        image += t_final[..., None] * np.asarray(background, dt)
    return image, 1.0 - t_final


def rasterize_reference(means, quats, scales, opacities, colors, viewmat, K, width_px: int, height_px: int, *,
                        background=None, extras=None, near: float = 0.01) -> RasterOutput:
    """Brute force: every Gaussian at every pixel (in chunks of pixels); for tests and small scenes."""
    return rasterize(means, quats, scales, opacities, colors, viewmat, K, width_px, height_px,
                     background=background, extras=extras, near=near, backend="reference")
