"""A modal motion model for the dynamic Gaussians: one small set of temporal functions shared by every Gaussian.

Each Gaussian i moves by a displacement and a small rotation (rotation vector) that are sums of K temporal
basis functions b_k(t) shared by all Gaussians:

    u_i(t) = sum_k Phi_ik b_k(t),        theta_i(t) = sum_k Psi_ik b_k(t)

Phi_ik and Psi_ik (3-vectors) are Gaussian i's shape vectors; b_k is learned at the trained timesteps (a
low-rank model of the motion; its first timestep, the rest state, is fixed at zero) and linear in between.
The rest Gaussians (from `fit_static`) stay frozen. Every iteration renders one (view, timestep) pair, so every
frame of every view constrains the same few shape vectors, instead of a fit per timestep.

The fit is amplitude-free, so the same settings fit the raw motion (a fraction of a pixel) and motion
magnified in 2D. Two choices make it so:
- The image term compares the rendered change from rest with the observed change from rest,
  (R_t - R_0) - (I_t - I_rest), in the mean square (I_rest: the mean of the take's frames before the impact).
  The rest model's own rendering error cancels (to first order), which matters when the motion is smaller
  than that error.
- The shape vectors are learned in units of a motion scale estimated from the images, and both the image term
  and the neighbour priors are normalised by that scale: doubling the motion doubles the solution.

The priors are the linearised rigidity and rotation priors of Luiten et al. 2023 over each Gaussian's k nearest
neighbours at rest: neighbours move as a rigid body with i, (u_j - u_i) = theta_i x (x_j - x_i), and turn alike,
theta_j = theta_i, both in the weighted mean square at the sampled timestep.

Magnification in 3D scales the displacement and the rotation vector of every Gaussian by alpha (see
`DynamicScene.render`): any factor, without retraining.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from odsplat.spine.checks import (
    BLUR_PX,
    CHUNK_FRAMES,
    ITERATIONS,
    LEARNING_RATE,
    NEIGHBOURS,
    SEED,
    WEIGHT,
    Range,
    check_choice,
    check_fields,
)
from odsplat.spine.errors import InputError

from .dynamic import Trajectory, render
from .gaussians import Gaussians
from .losses import Neighbours
from .quaternion import quat_from_rotvec, quat_multiply, quat_normalize
from .raster import BACKENDS
from .views import TrainView

log = logging.getLogger(__name__)

LOSSES = ("difference", "image")


@dataclass(frozen=True)
class ModalSettings:
    """The joint fit of the modal model (dimensionless: lengths are in units of the estimated motion scale)."""

    n_components: int = 4                # K temporal basis functions
    iters: int = 2000                   # iterations of the modal fit
    lr: float = 0.1                      # Adam, on the shape vectors (motion-scale units) and on the basis
    lr_final_frac: float = 0.05          # exponential decay to this fraction of lr over the fit
    loss: str = "difference"             # "difference": (R_t - R_0) vs (I_t - I_rest); "image": R_t vs I_t
    blur_px: float = 0.0                 # Gaussian blur (sd, px) of both sides of the image term: less noise
    batch: int = 1                       # (view, timestep) pairs per step
    rigid_weight: float = 10.0
    rot_weight: float = 0.1
    k_neighbours: int = 10
    neighbour_width: float = 2.0         # weight width, x the median neighbour distance
    backend: str = "auto"
    seed: int = 0                       # random seed of the fit
    progress: bool = True

    def __post_init__(self) -> None:
        # n_components: a handful of modes in any record; batch: (view, timestep) pairs rendered per step.
        check_fields(self, {"n_components": Range(at_least=1, at_most=256, integer=True), "iters": ITERATIONS,
                            "lr": LEARNING_RATE, "lr_final_frac": Range(above=0, at_most=1), "blur_px": BLUR_PX,
                            "batch": CHUNK_FRAMES, "rigid_weight": WEIGHT, "rot_weight": WEIGHT,
                            "k_neighbours": NEIGHBOURS, "neighbour_width": Range(above=0, at_most=100), "seed": SEED})
        check_choice("ModalSettings.loss", self.loss, LOSSES)
        check_choice("ModalSettings.backend", self.backend, BACKENDS)


@dataclass
class ModalMotion:
    """A fitted modal model, scene coordinates: basis (T, K), shape vectors (N, K, 3) in scene units and rad."""

    basis: torch.Tensor
    shapes: torch.Tensor
    rot_shapes: torch.Tensor
    scale: float                          # the motion scale the fit was normalised by (scene units)
    losses: list[dict] = field(default_factory=list)

    def trajectory(self, g0: Gaussians) -> Trajectory:
        """Means and unit quaternions at every trained timestep (timestep 0 is g0 at rest)."""
        q0 = quat_normalize(g0.quats.detach())
        means = g0.means.detach()[None] + torch.einsum("nkc,tk->tnc", self.shapes, self.basis)
        rot = torch.einsum("nkc,tk->tnc", self.rot_shapes, self.basis)
        return Trajectory(means, quat_normalize(quat_multiply(quat_from_rotvec(rot), q0[None])), list(self.losses))

    def principal(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The same motion in orthogonal components, strongest first: basis (T, K) with unit rms, displacement and
        rotation shapes (N, K, 3) in scene units, and each component's share of the motion's energy (K,).

        The model's basis and shapes are defined up to an invertible K x K mixing; this SVD of the (T, 3N)
        displacement field fixes it (signs: the basis's largest excursion is positive)."""
        b = self.basis.detach().double().numpy()
        phi = self.shapes.detach().double().numpy()
        psi = self.rot_shapes.detach().double().numpy()
        n, k, _ = phi.shape
        field_ = b @ phi.transpose(1, 0, 2).reshape(k, 3 * n)             # (T, 3N)
        u, s, vt = np.linalg.svd(field_, full_matrices=False)
        u, s, vt = u[:, :k], s[:k], vt[:k]
        t = len(b)
        basis = u * math.sqrt(t)                                           # unit rms over the timesteps
        sign = np.sign(basis[np.abs(basis).argmax(axis=0), np.arange(k)])
        sign[sign == 0] = 1
        basis *= sign
        shapes = (vt * (s / math.sqrt(t) * sign)[:, None]).reshape(k, n, 3).transpose(1, 0, 2)
        # the rotations follow the same change of basis: b = basis @ mix, so b Psi = basis (mix Psi)
        mix, *_ = np.linalg.lstsq(basis, b, rcond=None)                    # (K, K)
        rot = np.einsum("jk,nkc->njc", mix, psi)
        energy = s ** 2 / max(float((s ** 2).sum()), 1e-300)
        return basis, shapes, rot, energy


def motion_scale(views: list[TrainView], g0: Gaussians, blur_px: float = 0.0) -> float:
    """A rough rms displacement of the scene in scene units, from the images alone.

    Per view, the change from rest I_t - I_rest against the rest image's gradient gives the rms shift in px of a
    uniformly moving image (sqrt(2 sum dI^2 / sum |grad I|^2): a random direction sees half the gradient's
    energy); px -> scene units at the median depth of the Gaussians. The median over views. Sensor noise
    inflates it (blur_px, the fit's blur, takes some out); it only sets the units the fit works in, so a factor
    of two either way does no harm."""
    means = g0.means.detach().double()
    out = []
    for v in views:
        imgs = _blur(v.images.double(), blur_px)
        if len(imgs) < 2:
            continue
        rest = _blur(v.rest_image.double(), blur_px)
        d2 = float(((imgs[1:] - rest) ** 2).sum()) / (len(imgs) - 1)
        gy, gx = torch.gradient(rest, dim=(0, 1))
        g2 = float((gx ** 2 + gy ** 2).sum())
        if g2 <= 0:
            continue
        cam = v.camera
        z = (means @ torch.tensor(np.asarray(cam.R, float)).T + torch.tensor(np.asarray(cam.t, float)))[:, 2]
        depth = float(z[z > 0].median()) if bool((z > 0).any()) else 1.0
        out.append(math.sqrt(2.0 * d2 / g2) * depth / float(cam.K[0][0]))
    if not out:
        raise InputError("views", "the modal fit needs views with at least two timesteps")
    return max(float(np.median(out)), 1e-12)


def _blur(images: torch.Tensor, sd_px: float) -> torch.Tensor:
    """Separable Gaussian blur (sd in px, radius 3 sd, zero padding) of (..., H, W, C) images."""
    if sd_px <= 0:
        return images
    r = max(1, int(math.ceil(3 * sd_px)))
    x = torch.arange(-r, r + 1, dtype=images.dtype)
    k = torch.exp(-0.5 * (x / sd_px) ** 2)
    k = k / k.sum()
    shape = images.shape
    h, w, c = shape[-3:]
    x = images.reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, 1, h, w)
    x = torch.nn.functional.conv2d(x, k.view(1, 1, -1, 1), padding=(r, 0))
    x = torch.nn.functional.conv2d(x, k.view(1, 1, 1, -1), padding=(0, r))
    return x.reshape(-1, c, h, w).permute(0, 2, 3, 1).reshape(shape)


def _initial_basis(n_t: int, k: int, dtype: torch.dtype) -> torch.Tensor:
    """Smooth, nearly orthogonal functions that are zero at rest: sin(pi (2k+1) j / (2 (T-1))), j = 1..T-1."""
    j = torch.arange(1, n_t, dtype=torch.float64)[:, None]
    kk = torch.arange(k, dtype=torch.float64)[None]
    return torch.sin(math.pi * (2 * kk + 1) * j / (2 * max(1, n_t - 1))).to(dtype)


def fit_modal(g0: Gaussians, views: list[TrainView], s: ModalSettings,
              background: float | torch.Tensor) -> ModalMotion:
    """Fit the modal model to every view's frames (images (T, H, W, C), timestep 0 at rest) jointly.

    Scale, opacity, colour, the rest means and rotations and the background stay g0's (the rest fit's)."""
    n_t = int(views[0].images.shape[0])
    if any(int(v.images.shape[0]) != n_t for v in views):
        raise InputError("views", "every view needs the same number of timesteps")
    if n_t < 2:
        raise InputError("timesteps", "the modal fit needs at least 2 timesteps (rest and one more)")
    frozen = g0.detached()
    dt = frozen.means.dtype
    n, k = len(frozen), s.n_components
    scale = motion_scale(views, frozen, s.blur_px)
    nb = Neighbours.build(frozen.means, s.k_neighbours, s.neighbour_width)
    offsets = frozen.means[nb.index] - frozen.means[:, None]                # (N, k, 3) at rest
    wsum = nb.weight.sum().clamp_min(1e-12)
    rot_scale = scale / max(float(nb.rest_dist.median()), 1e-12)            # rad per motion-scale shift
    q0 = quat_normalize(frozen.quats)
    with torch.no_grad():
        rest = [_blur(render(frozen, v.camera, background=background, backend=s.backend).image, s.blur_px)
                for v in views]
        change = [_blur(v.images - v.rest_image, s.blur_px) for v in views]
        targets = change if s.loss == "difference" else [_blur(v.images, s.blur_px) for v in views]
    # the observed change's energy: the image term's unit
    energy = max(float(np.mean([float((c[1:] ** 2).mean()) for c in change])), 1e-20)
    basis_free = torch.nn.Parameter(_initial_basis(n_t, k, dt))
    phi = torch.nn.Parameter(torch.zeros(n, k, 3, dtype=dt))               # x scale
    psi = torch.nn.Parameter(torch.zeros(n, k, 3, dtype=dt))               # x rot_scale
    opt = torch.optim.Adam([basis_free, phi, psi], lr=s.lr, eps=1e-15)
    gamma = s.lr_final_frac ** (1.0 / max(1, s.iters))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    rng = np.random.default_rng(s.seed + 2)
    zero = torch.zeros(1, k, dtype=dt)
    records, img_l, prior_l = [], [], []
    t_start = time.perf_counter()
    bar = tqdm(range(s.iters), desc="modal motion", unit="it", disable=not s.progress, leave=False)
    for it in bar:
        opt.zero_grad(set_to_none=True)
        l_img = 0.0
        for j in range(s.batch):  # gradients of `batch` random (view, timestep) pairs per step
            vi, t = int(rng.integers(len(views))), int(rng.integers(1, n_t))
            v = views[vi]
            b = torch.cat([zero, basis_free])[t]
            u = scale * torch.einsum("nkc,k->nc", phi, b)
            theta = rot_scale * torch.einsum("nkc,k->nc", psi, b)
            quats = quat_multiply(quat_from_rotvec(theta), q0)
            out = render(frozen, v.camera, means=frozen.means + u, quats=quats, background=background,
                         backend=s.backend)
            img = _blur(out.image, s.blur_px)
            if s.loss == "difference":
                img = img - rest[vi]
            li = ((img - targets[vi][t]) ** 2).mean() / energy
            loss = li / s.batch
            l_img += li.item() / s.batch
            if j == s.batch - 1:  # the priors, at the last pair's timestep
                resid = (u[nb.index] - u[:, None]) - torch.cross(theta[:, None].expand_as(offsets), offsets, dim=-1)
                l_rigid = (nb.weight * (resid ** 2).sum(-1)).sum() / wsum / scale ** 2
                l_rot = (nb.weight * ((theta[nb.index] - theta[:, None]) ** 2).sum(-1)).sum() / wsum / rot_scale ** 2
                prior = s.rigid_weight * l_rigid + s.rot_weight * l_rot
                loss = loss + prior
            loss.backward()
        opt.step()
        sched.step()
        img_l.append(l_img)
        prior_l.append(prior.item())
        if (it + 1) % 100 == 0 or it + 1 == s.iters:
            records.append(dict(iteration=it + 1, image_loss=float(np.mean(img_l[-100:])),
                                prior_loss=float(np.mean(prior_l[-100:]))))
            bar.set_postfix(loss=f"{records[-1]['image_loss']:.3f}")
    bar.close()
    log.info("modal fit: %d Gaussians x %d components, %d iterations in %.0f s (motion scale %.3g scene units)",
             n, k, s.iters, time.perf_counter() - t_start, scale)
    with torch.no_grad():
        basis = torch.cat([zero, basis_free.detach()])
        shapes = scale * phi.detach()
        rot_shapes = rot_scale * psi.detach()
    return ModalMotion(basis, shapes, rot_shapes, scale, records)


__all__ = ["LOSSES", "ModalMotion", "ModalSettings", "fit_modal", "motion_scale"]
