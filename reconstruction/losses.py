"""Training losses: L1 + D-SSIM on images, and the neighbour priors of Luiten et al. 2023 (rigidity, rotation,
isometry).

The priors are written from the paper's equations. Neighbours are the k nearest Gaussians at t=0, weighted by an
isotropic Gaussian of their distance; its width is a multiple of the median neighbour distance, so the weights
mean the same in metres, millimetres or normalised units.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from odsplat.spine.similarity import ssim_map

from .quaternion import quat_conjugate, quat_multiply, quat_normalize, quat_to_matrix


# ----------------------------------------------------------------------------------------------------- images
def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images with zero padding at the border, as the 3DGS loss has it; differentiable."""
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"ssim: expected two (H, W, C) images of one shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    return ssim_map(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], pad=True).mean()


def image_loss(render: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM), the 3DGS photometric loss Luiten et al. keep."""
    l1 = (render - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(render, target))


# -------------------------------------------------------------------------------------------------- neighbours
@dataclass
class Neighbours:
    """The k nearest neighbours of each Gaussian at t=0 and their weights."""

    index: torch.Tensor    # (N, k) long
    weight: torch.Tensor   # (N, k)
    rest_dist: torch.Tensor  # (N, k) distances at t=0
    anchor: torch.Tensor | None = None  # (n,) the Gaussians i whose neighbourhoods are evaluated; None: all

    def sample(self, fraction: float, generator: torch.Generator | None = None) -> Neighbours:
        """The same priors on a random `fraction` of the neighbourhoods: an unbiased estimate of each weighted mean
        at `fraction` of the cost (the priors' gathers dominate a per-timestep iteration at 50k Gaussians)."""
        if fraction >= 1.0:
            return self
        n = self.index.shape[0]
        pick = torch.randperm(n, generator=generator)[:max(1, int(round(fraction * n)))].to(self.index.device)
        return Neighbours(self.index[pick], self.weight[pick], self.rest_dist[pick], pick)

    def _anchor(self, x: torch.Tensor) -> torch.Tensor:
        return x if self.anchor is None else x[self.anchor]

    @classmethod
    def build(cls, means0: torch.Tensor, k: int = 20, width: float = 2.0) -> Neighbours:
        """Neighbours of means0 (N, 3). Weights exp(-d^2 / (2 (width * median d)^2)): unit-free by construction."""
        pts = means0.detach().cpu().double().numpy()
        k = int(min(k, len(pts) - 1))
        if k < 1:
            raise ValueError(f"need at least 2 Gaussians for neighbour losses, got {len(pts)}")
        dist, idx = cKDTree(pts).query(pts, k=k + 1)
        dist, idx = dist[:, 1:], idx[:, 1:]
        length = width * max(float(np.median(dist)), 1e-12)
        weight = np.exp(-dist ** 2 / (2 * length ** 2))
        as_t = lambda a, dt: torch.as_tensor(a, dtype=dt, device=means0.device)  # noqa: E731
        return cls(as_t(idx, torch.long), as_t(weight, means0.dtype), as_t(dist, means0.dtype))

    def _mean(self, per_pair: torch.Tensor) -> torch.Tensor:
        return (self.weight * per_pair).sum() / self.weight.sum().clamp_min(1e-12)

    def rigidity(self, means_prev: torch.Tensor, quats_prev: torch.Tensor, means: torch.Tensor,
                 quats: torch.Tensor) -> torch.Tensor:
        """|| (mu_j,t-1 - mu_i,t-1) - R_i,t-1 R_i,t^-1 (mu_j,t - mu_i,t) ||: neighbours move with i as a rigid body."""
        a = self._anchor
        rel = quat_to_matrix(a(quats_prev)) @ quat_to_matrix(a(quats)).transpose(-1, -2)  # (N, 3, 3)
        off_prev = means_prev[self.index] - a(means_prev)[:, None]
        off = means[self.index] - a(means)[:, None]
        pred = torch.einsum("nab,nkb->nka", rel, off)
        return self._mean((off_prev - pred).norm(dim=-1))

    def rotation(self, quats_prev: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
        """|| q_j,t q_j,t-1^-1 - q_i,t q_i,t-1^-1 ||: neighbours turn alike."""
        delta = quat_multiply(quat_normalize(quats), quat_conjugate(quat_normalize(quats_prev)))
        return self._mean((delta[self.index] - self._anchor(delta)[:, None]).norm(dim=-1))

    def priors(self, means_prev: torch.Tensor, quats_prev: torch.Tensor, means: torch.Tensor,
               quats: torch.Tensor, backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(rigidity, rotation, isometry) in one pass: the values of the three methods, with their gradients.

        backend "numba" (CPU float tensors; `priors_cpu`: the pair gathers and scatters in kernels, about 10x the
        torch path at 50k Gaussians), "torch" (the three methods), or "auto" (numba where it applies)."""
        if backend == "auto":
            backend = "numba" if (means.device.type == "cpu" and means.dtype in (torch.float32, torch.float64)
                                  and quats.dtype == means.dtype) else "torch"
        if backend == "torch":
            return (self.rigidity(means_prev, quats_prev, means, quats), self.rotation(quats_prev, quats),
                    self.isometry(means))
        if backend != "numba":
            raise ValueError(f"priors: expected backend auto, numba or torch, got {backend!r}")
        from .priors_cpu import pair_priors_numba

        anchor = self.anchor if self.anchor is not None else torch.arange(self.index.shape[0], device=means.device)
        # index_select, not [anchor]: its backward is index_add, where advanced indexing's is a slow index_put.
        rel = (quat_to_matrix(quats_prev.index_select(0, anchor))
               @ quat_to_matrix(quats.index_select(0, anchor)).transpose(-1, -2))
        delta = quat_multiply(quat_normalize(quats), quat_conjugate(quat_normalize(quats_prev)))
        terms = pair_priors_numba(means, rel, delta, means_prev, anchor, self.index, self.weight, self.rest_dist)
        return terms[0], terms[1], terms[2]

    def isometry(self, means: torch.Tensor) -> torch.Tensor:
        """| ||mu_j,0 - mu_i,0|| - ||mu_j,t - mu_i,t|| |: distances to neighbours kept over the whole sequence."""
        dist = (means[self.index] - self._anchor(means)[:, None]).norm(dim=-1)
        return self._mean((dist - self.rest_dist).abs())


__all__ = ["Neighbours", "image_loss", "ssim"]
