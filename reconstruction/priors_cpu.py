"""The neighbour priors' pair sums (`losses.Neighbours.priors`) in numba kernels, with a hand-written backward pass.

Per evaluated neighbourhood a (Gaussian i = anchor[a]) and neighbour j = index[a, k] with weight w:
- rigidity  w |(mp_j - mp_i) - rel_a (m_j - m_i)|, rel_a = R(qp_i) R(q_i)^T given per neighbourhood;
- rotation  w |delta_j - delta_i|, delta = q ⊗ conj(qp) given per Gaussian (both normalised);
- isometry  w | |m_j - m_i| - d0_aj |,
each summed and divided by the sum of the weights. Only the gathers and scatters over the (n, k) pairs are here;
`rel` and `delta` come from torch, whose autograd takes their gradients on to the quaternions. That gather and
its scatter were most of a per-timestep iteration in torch (index_put's accumulate on the CPU is slow).

Forward and backward are parallel over neighbourhoods, accumulate in float64 and return the input dtype. The
backward writes one row per pair and per neighbourhood, then adds them into the Gaussians serially in a fixed
order: no atomics, and the gradients do not depend on the thread count. As in torch, a norm's gradient at 0 is 0.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch.autograd.function import once_differentiable

from .raster_cpu import _use_torch_threads


@njit(cache=True, inline="always", error_model="numpy")
def _offsets(means_prev, means, rel, a, i, j):
    """o = m_j - m_i and the rigidity residual e = (mp_j - mp_i) - rel_a o, in float64."""
    o0 = float(means[j, 0]) - float(means[i, 0])
    o1 = float(means[j, 1]) - float(means[i, 1])
    o2 = float(means[j, 2]) - float(means[i, 2])
    e0 = float(means_prev[j, 0]) - float(means_prev[i, 0]) - (rel[a, 0, 0] * o0 + rel[a, 0, 1] * o1 + rel[a, 0, 2] * o2)
    e1 = float(means_prev[j, 1]) - float(means_prev[i, 1]) - (rel[a, 1, 0] * o0 + rel[a, 1, 1] * o1 + rel[a, 1, 2] * o2)
    e2 = float(means_prev[j, 2]) - float(means_prev[i, 2]) - (rel[a, 2, 0] * o0 + rel[a, 2, 1] * o1 + rel[a, 2, 2] * o2)
    return o0, o1, o2, e0, e1, e2


@njit(cache=True, inline="always", error_model="numpy")
def _delta_gap(delta, i, j):
    """|delta_j - delta_i|."""
    s = 0.0
    for c in range(4):
        d = float(delta[j, c]) - float(delta[i, c])
        s += d * d
    return math.sqrt(s)


@njit(cache=True, parallel=True, error_model="numpy")
def _forward(means_prev, means, rel, delta, anchor, index, weight, rest_dist, parts):
    for a in prange(index.shape[0]):
        i = anchor[a]
        rig = 0.0
        rot = 0.0
        iso = 0.0
        for kk in range(index.shape[1]):
            j = index[a, kk]
            w = float(weight[a, kk])
            o0, o1, o2, e0, e1, e2 = _offsets(means_prev, means, rel, a, i, j)
            rig += w * math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            iso += w * abs(math.sqrt(o0 * o0 + o1 * o1 + o2 * o2) - float(rest_dist[a, kk]))
            rot += w * _delta_gap(delta, i, j)
        parts[a, 0] = rig
        parts[a, 1] = rot
        parts[a, 2] = iso


@njit(cache=True, parallel=True, error_model="numpy")
def _backward_pairs(means_prev, means, rel, delta, anchor, index, weight, rest_dist, g_rig, g_rot, g_iso,
                    pair_m, pair_d, own_m, own_d, g_rel):
    """Per pair: the gradient into m_j (pair_m) and delta_j (pair_d); per neighbourhood: into m_i, delta_i, rel_a."""
    for a in prange(index.shape[0]):
        i = anchor[a]
        for c in range(3):
            own_m[a, c] = 0.0
            for c2 in range(3):
                g_rel[a, c, c2] = 0.0
        for c in range(4):
            own_d[a, c] = 0.0
        for kk in range(index.shape[1]):
            j = index[a, kk]
            w = float(weight[a, kk])
            o0, o1, o2, e0, e1, e2 = _offsets(means_prev, means, rel, a, i, j)
            go0 = 0.0
            go1 = 0.0
            go2 = 0.0
            ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            if ne > 0.0:
                f = w * g_rig / ne  # dL/de = f e; e = ... - rel o: dL/do = -rel^T f e, dL/drel = -f e o^T
                ge0, ge1, ge2 = f * e0, f * e1, f * e2
                go0 -= rel[a, 0, 0] * ge0 + rel[a, 1, 0] * ge1 + rel[a, 2, 0] * ge2
                go1 -= rel[a, 0, 1] * ge0 + rel[a, 1, 1] * ge1 + rel[a, 2, 1] * ge2
                go2 -= rel[a, 0, 2] * ge0 + rel[a, 1, 2] * ge1 + rel[a, 2, 2] * ge2
                g_rel[a, 0, 0] -= ge0 * o0
                g_rel[a, 0, 1] -= ge0 * o1
                g_rel[a, 0, 2] -= ge0 * o2
                g_rel[a, 1, 0] -= ge1 * o0
                g_rel[a, 1, 1] -= ge1 * o1
                g_rel[a, 1, 2] -= ge1 * o2
                g_rel[a, 2, 0] -= ge2 * o0
                g_rel[a, 2, 1] -= ge2 * o1
                g_rel[a, 2, 2] -= ge2 * o2
            r = math.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
            gap = r - float(rest_dist[a, kk])
            if r > 0.0 and gap != 0.0:
                f = w * g_iso * (1.0 if gap > 0.0 else -1.0) / r
                go0 += f * o0
                go1 += f * o1
                go2 += f * o2
            pair_m[a, kk, 0] = go0
            pair_m[a, kk, 1] = go1
            pair_m[a, kk, 2] = go2
            own_m[a, 0] -= go0
            own_m[a, 1] -= go1
            own_m[a, 2] -= go2
            nd = _delta_gap(delta, i, j)
            for c in range(4):
                h = w * g_rot * (float(delta[j, c]) - float(delta[i, c])) / nd if nd > 0.0 else 0.0
                pair_d[a, kk, c] = h
                own_d[a, c] -= h


@njit(cache=True, error_model="numpy")
def _scatter(anchor, index, pair_m, pair_d, own_m, own_d, g_means, g_delta):
    """Add the pair and neighbourhood rows into the Gaussians, in a fixed order."""
    for a in range(index.shape[0]):
        i = anchor[a]
        for kk in range(index.shape[1]):
            j = index[a, kk]
            for c in range(3):
                g_means[j, c] += pair_m[a, kk, c]
            for c in range(4):
                g_delta[j, c] += pair_d[a, kk, c]
        for c in range(3):
            g_means[i, c] += own_m[a, c]
        for c in range(4):
            g_delta[i, c] += own_d[a, c]


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _PairPriors(torch.autograd.Function):
    """(3,) weighted means of the rigidity, rotation and isometry pair terms; differentiable in means, rel, delta."""

    @staticmethod
    def forward(ctx, means: torch.Tensor, rel: torch.Tensor, delta: torch.Tensor, means_prev: torch.Tensor,
                anchor: torch.Tensor, index: torch.Tensor, weight: torch.Tensor, rest_dist: torch.Tensor):
        arrays = (_np(means_prev), _np(means), _np(rel).astype(np.float64), _np(delta), _np(anchor), _np(index),
                  _np(weight), _np(rest_dist))
        parts = np.empty((index.shape[0], 3))
        _use_torch_threads()
        _forward(*arrays, parts)
        w_sum = max(float(weight.double().sum()), 1e-12)
        ctx.arrays, ctx.w_sum = arrays, w_sum
        ctx.dtypes = (means.dtype, rel.dtype, delta.dtype)
        return torch.from_numpy(parts.sum(0) / w_sum).to(means.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):
        means_prev, means, rel, delta, anchor, index, weight, rest_dist = ctx.arrays
        g = grad.double().numpy() / ctx.w_sum
        n, k = index.shape
        pair_m, pair_d = np.empty((n, k, 3)), np.empty((n, k, 4))
        own_m, own_d, g_rel = np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3, 3))
        _use_torch_threads()
        _backward_pairs(means_prev, means, rel, delta, anchor, index, weight, rest_dist, float(g[0]), float(g[1]),
                        float(g[2]), pair_m, pair_d, own_m, own_d, g_rel)
        g_means, g_delta = np.zeros(means.shape), np.zeros(delta.shape)
        _scatter(anchor, index, pair_m, pair_d, own_m, own_d, g_means, g_delta)
        dm, dr, dd = ctx.dtypes
        return (torch.from_numpy(g_means).to(dm), torch.from_numpy(g_rel).to(dr), torch.from_numpy(g_delta).to(dd),
                None, None, None, None, None)


def pair_priors_numba(means: torch.Tensor, rel: torch.Tensor, delta: torch.Tensor, means_prev: torch.Tensor,
                      anchor: torch.Tensor, index: torch.Tensor, weight: torch.Tensor,
                      rest_dist: torch.Tensor) -> torch.Tensor:
    """The three pair terms (rigidity, rotation, isometry) as a (3,) tensor; see the module docstring.

    means, means_prev (N, 3), delta (N, 4), rel (n, 3, 3), anchor (n,) long, index/weight/rest_dist (n, k); CPU."""
    return _PairPriors.apply(means, rel, delta, means_prev.detach(), anchor, index, weight, rest_dist)


__all__ = ["pair_priors_numba"]
