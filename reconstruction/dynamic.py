"""Dynamic 3D Gaussians after Luiten et al. 2023: a t=0 fit with densification, then per-timestep fits of means and
rotations.

Written from the paper's description. Scale, opacity and colour are fitted at t=0 (on the rest frames and, when
there are any, the static photos) and frozen; each later timestep starts from a constant-velocity extrapolation
of the two before it and fits means and rotations under an L1 + D-SSIM image loss plus the rigidity, rotation
and isometry priors over each Gaussian's k nearest neighbours. Training runs in normalised scene coordinates
(`SceneFrame`), so the unit-dependent constants (learning rates, densification sizes) act alike on scenes in
metres or millimetres.
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
    FRACTION,
    ITERATIONS,
    LEARNING_RATE,
    MAX_ITERATIONS,
    NEIGHBOURS,
    SEED,
    WEIGHT,
    Range,
    check_choice,
    check_fields,
    maybe,
)
from odsplat.spine.errors import InputError

from .gaussians import Gaussians
from .losses import Neighbours, image_loss
from .quaternion import quat_normalize, quat_to_matrix
from .raster import BACKENDS, rasterize
from .views import Camera, TrainView

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitSettings:
    """Iteration counts, learning rates and weights of both fits (lengths in scene units: scene radius = 1)."""

    iters_t0: int = 1500                # iterations of the rest fit
    iters_per_step: int = 150           # iterations per timestep (motion "timestep")
    iters_first_step: int | None = None     # the first moving timestep (default 2 x iters_per_step): no velocity yet
    ssim_weight: float = 0.2
    # t = 0: learning rates as in 3DGS, positions decaying exponentially to 1 % over the fit
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacity: float = 0.05
    lr_colors: float = 0.01
    # densification
    densify_from: int = 100
    densify_until_frac: float = 0.6         # of iters_t0
    densify_every: int = 100
    grad_threshold: float = 2e-4            # mean view-space gradient of a mean, in NDC units
    percent_dense: float = 0.01             # clone below, split above this size (x scene radius)
    prune_opacity: float = 0.005
    max_scale: float = 0.1                  # prune Gaussians larger than this (x scene radius)
    opacity_reset_every: int = 0            # 0: never (short fits); 3DGS uses 3000
    min_scale_px: float = 0.5               # no Gaussian thinner than this many training pixels where the nearest
                                            # view sees it (Mip-Splatting's 3D filter, as a floor on the scales)
    max_gaussians: int = 60_000
    # per-timestep fits
    lr_means_dynamic: float = 1.6e-4
    lr_quats_dynamic: float = 1e-3
    rigid_weight: float = 4.0
    rot_weight: float = 4.0
    iso_weight: float = 2.0
    k_neighbours: int = 20
    average_last: float = 0.5              # per timestep: the mean iterate over this last fraction of the iterations
                                           # (0: the last one)
    prior_fraction: float = 0.25            # of the neighbourhoods each iteration evaluates (a random subset;
                                            # bench: 3.2x faster, same PSNR)
    neighbour_width: float = 2.0            # weight width, x the median neighbour distance
    background: float | None = None         # None: learned at t = 0 (one value per channel), then frozen
    backend: str = "auto"
    seed: int = 0                       # random seed of the fits
    progress: bool = True

    def __post_init__(self) -> None:
        # Lengths are in scene radii (the scene is 1 across); max_gaussians: 3DGS scenes hold a few million.
        check_fields(self, {
            "iters_t0": ITERATIONS, "iters_per_step": ITERATIONS, "iters_first_step": maybe(ITERATIONS),
            "ssim_weight": FRACTION, "lr_means": LEARNING_RATE, "lr_means_final": LEARNING_RATE,
            "lr_quats": LEARNING_RATE, "lr_scales": LEARNING_RATE, "lr_opacity": LEARNING_RATE,
            "lr_colors": LEARNING_RATE, "densify_from": ITERATIONS, "densify_until_frac": FRACTION,
            "densify_every": Range(at_least=1, at_most=MAX_ITERATIONS, integer=True),
            "grad_threshold": Range(above=0, at_most=1), "percent_dense": Range(above=0, at_most=1),
            "prune_opacity": FRACTION, "max_scale": Range(above=0, at_most=100), "opacity_reset_every": ITERATIONS,
            "min_scale_px": Range(at_least=0, at_most=10),
            "max_gaussians": Range(at_least=0, at_most=10_000_000, integer=True),
            "lr_means_dynamic": LEARNING_RATE, "lr_quats_dynamic": LEARNING_RATE, "rigid_weight": WEIGHT,
            "rot_weight": WEIGHT, "iso_weight": WEIGHT, "k_neighbours": NEIGHBOURS, "average_last": FRACTION,
            "prior_fraction": Range(above=0, at_most=1), "neighbour_width": Range(above=0, at_most=100),
            "background": maybe(FRACTION), "seed": SEED})
        check_choice("FitSettings.backend", self.backend, BACKENDS)


def render(g: Gaussians, camera: Camera, *, means: torch.Tensor | None = None, quats: torch.Tensor | None = None,
           background: float | torch.Tensor = 0.0, backend: str = "auto", extras: torch.Tensor | None = None):
    """Rasterize Gaussians (optionally with other means/quats, e.g. a later timestep) seen by `camera`."""
    dt = g.means.dtype
    if isinstance(background, torch.Tensor):
        bg = background.to(dt)
    else:
        bg = torch.full((g.n_colors,), float(background), dtype=dt)
    return rasterize(g.means if means is None else means, g.quats if quats is None else quats, g.scales,
                     g.opacities, g.colors, camera.viewmat(dt), camera.K_tensor(dt), camera.width_px,
                     camera.height_px, background=bg, extras=extras, backend=backend)


# ------------------------------------------------------------------------------------------------------ t = 0
_GROUPS = ("means", "quats", "log_scales", "opacity_logits", "color_logits")


class _StaticFit:
    """The t=0 optimisation: Adam over every parameter, with densification that carries Adam's moments."""

    def __init__(self, g: Gaussians, s: FitSettings):
        self.s = s
        self.params = {k: torch.nn.Parameter(v.detach().clone()) for k, v in g.tensors().items()}
        lrs = dict(means=s.lr_means, quats=s.lr_quats, log_scales=s.lr_scales, opacity_logits=s.lr_opacity,
                   color_logits=s.lr_colors)
        groups = [{"params": [self.params[k]], "lr": lrs[k], "name": k} for k in _GROUPS]
        # What lies beyond the scene (past the floor's edge) shows as one level per channel: learned unless given.
        dt = g.means.dtype
        bg = torch.full((g.n_colors,), 0.5 if s.background is None else float(s.background), dtype=dt)
        self.background_logit = torch.nn.Parameter(torch.logit(bg.clamp(1e-4, 1 - 1e-4)))
        if s.background is None:
            groups.append({"params": [self.background_logit], "lr": s.lr_opacity, "name": "background"})
        self.opt = torch.optim.Adam(groups, eps=1e-15)
        self._reset_stats()

    def gaussians(self) -> Gaussians:
        return Gaussians(**self.params)

    @property
    def background(self) -> torch.Tensor:
        return torch.sigmoid(self.background_logit)

    def _reset_stats(self) -> None:
        n = len(self.params["means"])
        self.grad_sum = torch.zeros(n, dtype=torch.float64)
        self.seen = torch.zeros(n, dtype=torch.float64)

    def set_means_lr(self, it: int) -> None:
        s = self.s
        frac = min(1.0, it / max(1, s.iters_t0))
        lr = math.exp((1 - frac) * math.log(s.lr_means) + frac * math.log(s.lr_means_final))
        for group in self.opt.param_groups:
            if group["name"] == "means":
                group["lr"] = lr

    def accumulate(self, means2d: torch.Tensor, radii: torch.Tensor, width_px: int, height_px: int) -> None:
        """View-space gradient of each visible mean, in NDC units (px gradient x half the image size)."""
        if means2d.grad is None:
            return
        g = means2d.grad.detach().double() * torch.tensor([0.5 * width_px, 0.5 * height_px], dtype=torch.float64)
        visible = radii > 0
        self.grad_sum[visible] += g[visible].norm(dim=-1)
        self.seen[visible] += 1

    def densify(self) -> tuple[int, int, int]:
        """Clone small Gaussians with large view-space gradients, split large ones, prune faint and huge ones."""
        s = self.s
        p = {k: v.detach() for k, v in self.params.items()}
        n = len(p["means"])
        grad = self.grad_sum / self.seen.clamp_min(1)
        size = torch.exp(p["log_scales"]).max(dim=-1).values.double()
        hot = grad >= s.grad_threshold
        room = max(0, s.max_gaussians - n)
        clone = torch.nonzero(hot & (size <= s.percent_dense)).ravel()[:room]
        split = torch.nonzero(hot & (size > s.percent_dense)).ravel()[:max(0, room - len(clone))]
        # Split: two samples from the Gaussian, each 1/1.6 its size (3DGS); the original goes.
        scales = torch.exp(p["log_scales"][split])
        rot = quat_to_matrix(p["quats"][split])
        gen = torch.Generator().manual_seed(s.seed + n)
        samples = [p["means"][split] + torch.einsum("nab,nb->na", rot, scales * torch.randn(scales.shape, generator=gen,
                                                                                           dtype=scales.dtype))
                   for _ in range(2)]
        new = {k: torch.cat([v, v[clone], v[split], v[split]]) for k, v in p.items()}
        lo = n + len(clone)
        new["means"][lo:lo + len(split)] = samples[0]
        new["means"][lo + len(split):] = samples[1]
        new["log_scales"][lo:] = new["log_scales"][lo:] - math.log(1.6)
        keep = torch.ones(len(new["means"]), dtype=torch.bool)
        keep[split] = False
        opacity = torch.sigmoid(new["opacity_logits"])
        big = torch.exp(new["log_scales"]).max(dim=-1).values > s.max_scale
        pruned = keep & ((opacity < s.prune_opacity) | big)
        keep &= ~pruned
        fresh = torch.zeros(len(keep), dtype=torch.bool)
        fresh[n:] = True
        self._replace({k: v[keep] for k, v in new.items()}, torch.cat([torch.arange(n), clone, split, split])[keep],
                      fresh[keep])
        return len(clone), len(split), int(pruned.sum())

    def floor_scales(self, cameras: FootprintCameras, px: float) -> None:
        """Raise every scale to `px` pixels of the finest view that sees the Gaussian (its footprint there, depth /
        focal length): what no training image resolves is not made thinner than that, so a render at a finer
        resolution shows no needles (Mip-Splatting's 3D filter, as a floor)."""
        with torch.no_grad():
            floor = torch.log(px * cameras.finest_footprint(self.params["means"].detach()))[:, None]
            self.params["log_scales"].copy_(torch.maximum(self.params["log_scales"], floor))

    def reset_opacity(self) -> None:
        """Cap opacities at 0.01 (3DGS): floaters must earn their opacity back or be pruned."""
        with torch.no_grad():
            cap = torch.logit(torch.tensor(0.01, dtype=self.params["opacity_logits"].dtype))
            self.params["opacity_logits"].clamp_(max=float(cap))
        state = self.opt.state.get(self.params["opacity_logits"])
        if state:
            state["exp_avg"].zero_()
            state["exp_avg_sq"].zero_()

    def _replace(self, data: dict[str, torch.Tensor], source: torch.Tensor, fresh: torch.Tensor) -> None:
        """New parameters; Adam's moments follow their rows (zero for new Gaussians)."""
        for group in self.opt.param_groups:
            name = group["name"]
            if name not in data:
                continue
            old = group["params"][0]
            par = torch.nn.Parameter(data[name].clone())
            state = self.opt.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    moved = state[key][source].clone()
                    moved[fresh] = 0
                    state[key] = moved
                self.opt.state[par] = state
            group["params"][0] = par
            self.params[name] = par
        self._reset_stats()


class FootprintCameras:
    """The training cameras batched, for the size of a pixel where each point is seen best."""

    def __init__(self, cameras: list[Camera], dtype: torch.dtype):
        views = torch.stack([cam.viewmat(dtype) for cam in cameras])
        self.R, self.t = views[:, :3, :3], views[:, None, :3, 3]                          # (V, 3, 3), (V, 1, 3)
        K = torch.stack([cam.K_tensor(dtype) for cam in cameras])
        self.f, self.c = K[:, None, [0, 1], [0, 1]], K[:, None, [0, 1], [2, 2]]          # (V, 1, 2)
        self.size = torch.tensor([[cam.width_px, cam.height_px] for cam in cameras], dtype=dtype)[:, None]

    def finest_footprint(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) the smallest depth / focal length over the cameras that see each point (in front, inside the
        image); 0 for a point no camera sees (no image says anything of its size)."""
        pc = torch.einsum("vab,nb->vna", self.R, means) + self.t
        z = pc[..., 2]
        uv = self.f * pc[..., :2] / z.clamp_min(1e-9)[..., None] + self.c
        seen = (z > 1e-3) & ((uv >= 0) & (uv < self.size)).all(-1)
        footprint = torch.where(seen, z / self.f[..., 0], torch.full_like(z, math.inf)).min(dim=0).values
        return torch.where(torch.isfinite(footprint), footprint, torch.zeros_like(footprint))


def fit_static(g: Gaussians, views: list[tuple[Camera, torch.Tensor]], s: FitSettings) -> tuple[Gaussians, dict]:
    """Fit every parameter to images of the structure at rest: [(camera, (H, W, C) image)], a random view per step."""
    if not views:
        raise InputError("views", "the t=0 fit needs at least one posed image")
    fit = _StaticFit(g, s)
    footprints = FootprintCameras([cam for cam, _ in views], g.means.dtype)
    rng = np.random.default_rng(s.seed)
    until = int(s.densify_until_frac * s.iters_t0)
    losses, t0 = [], time.perf_counter()
    bar = tqdm(range(s.iters_t0), desc="gaussians t=0", unit="it", disable=not s.progress, leave=False)
    for it in bar:
        fit.set_means_lr(it)
        cam, target = views[rng.integers(len(views))]
        out = render(fit.gaussians(), cam, background=fit.background, backend=s.backend)
        out.means2d.retain_grad()
        loss = image_loss(out.image, target, s.ssim_weight)
        fit.opt.zero_grad(set_to_none=True)
        loss.backward()
        fit.accumulate(out.means2d, out.radii_px, cam.width_px, cam.height_px)
        fit.opt.step()
        losses.append(loss.item())
        if s.densify_from <= it < until and (it + 1) % s.densify_every == 0:
            c, sp, pr = fit.densify()
            log.debug("iteration %d: cloned %d, split %d, pruned %d -> %d", it + 1, c, sp, pr, len(fit.params["means"]))
        if s.opacity_reset_every and (it + 1) % s.opacity_reset_every == 0 and it + 1 < until:
            fit.reset_opacity()
        if s.min_scale_px:
            fit.floor_scales(footprints, s.min_scale_px)
        if it % 50 == 0:
            bar.set_postfix(loss=f"{np.mean(losses[-50:]):.4f}", n=len(fit.params["means"]))
    bar.close()
    out_g = fit.gaussians().detached()
    stats = dict(background=fit.background.detach().tolist(), iterations=s.iters_t0,
                 seconds=time.perf_counter() - t0, n_gaussians=len(out_g),
                 loss_first=float(np.mean(losses[:20])) if losses else None,
                 loss_last=float(np.mean(losses[-20:])) if losses else None)
    return out_g, stats


# ------------------------------------------------------------------------------------------ per timestep
@dataclass
class Trajectory:
    """Means (T, N, 3) and unit quaternions (T, N, 4) per timestep, scene coordinates; t = 0 is the rest fit."""

    means: torch.Tensor
    quats: torch.Tensor
    losses: list[dict] = field(default_factory=list)


def fit_dynamic(g0: Gaussians, views: list[TrainView], s: FitSettings,
                background: float | torch.Tensor) -> Trajectory:
    """Per-timestep fits of means and rotations to each view's frame at that timestep (views' images (T, H, W, C)).

    Timestep 0 is g0 itself (the rest fit). Scale, opacity, colour and the background (`fit_static`'s
    stats["background"]) stay the rest fit's.
    """
    n_t = int(views[0].images.shape[0])
    if any(int(v.images.shape[0]) != n_t for v in views):
        raise InputError("views", "every view needs the same number of timesteps")
    frozen = g0.detached()
    nb = Neighbours.build(frozen.means, s.k_neighbours, s.neighbour_width)
    means = [frozen.means.clone()]
    quats = [quat_normalize(frozen.quats).clone()]
    rng = np.random.default_rng(s.seed + 1)
    gen = torch.Generator().manual_seed(s.seed + 2)
    records = []
    bar = tqdm(range(1, n_t), desc="gaussians per timestep", unit="step", disable=not s.progress, leave=False)
    for t in bar:
        start = time.perf_counter()
        if t >= 2:  # constant velocity from the two timesteps before
            m_init = 2 * means[-1] - means[-2]
            q_init = quat_normalize(2 * quats[-1] - quats[-2])
        else:
            m_init, q_init = means[-1], quats[-1]
        m = torch.nn.Parameter(m_init.clone())
        q = torch.nn.Parameter(q_init.clone())
        opt = torch.optim.Adam([{"params": [m], "lr": s.lr_means_dynamic}, {"params": [q], "lr": s.lr_quats_dynamic}],
                               eps=1e-15)
        iters = s.iters_per_step if t >= 2 else (s.iters_first_step or 2 * s.iters_per_step)
        img_losses, prior_losses = [], []
        n_avg = int(round(s.average_last * iters))
        m_sum, q_sum = torch.zeros_like(m_init), torch.zeros_like(q_init)
        for it in range(iters):
            v = views[rng.integers(len(views))]
            out = render(frozen, v.camera, means=m, quats=q, background=background, backend=s.backend)
            l_img = image_loss(out.image, v.images[t], s.ssim_weight)
            sub = nb.sample(s.prior_fraction, gen)
            l_rig, l_rot, l_iso = sub.priors(means[-1], quats[-1], m, q)
            l_prior = s.rigid_weight * l_rig + s.rot_weight * l_rot + s.iso_weight * l_iso
            loss = l_img + l_prior
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            img_losses.append(l_img.item())
            prior_losses.append(l_prior.item())
            if it >= iters - n_avg:
                m_sum += m.detach()
                q_sum += quat_normalize(q.detach())
        if n_avg:
            means.append(m_sum / n_avg)
            quats.append(quat_normalize(q_sum))
        else:
            means.append(m.detach().clone())
            quats.append(quat_normalize(q.detach()).clone())
        k = max(1, iters // 5)
        records.append(dict(timestep=t, iterations=iters, seconds=time.perf_counter() - start,
                            image_loss=float(np.mean(img_losses[-k:])), prior_loss=float(np.mean(prior_losses[-k:]))))
        bar.set_postfix(loss=f"{records[-1]['image_loss']:.4f}")
    bar.close()
    return Trajectory(torch.stack(means), torch.stack(quats), records)


__all__ = ["FitSettings", "Trajectory", "fit_dynamic", "fit_static", "render"]
