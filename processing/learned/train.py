"""Trainer of the learned magnifier on procedural synthetic data (`synth.py`), CPU-friendly.

Loss (Oh et al. 2018): L1(output, ground truth) + lambda * (L1(V_a, V_b) + L1(V_b', V_y') + L1(M_b, M_b')),
V texture and M shape representations, b' and y' the colour-perturbed frame b and ground truth.
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from tqdm import tqdm

from odsplat.processing.learned.network import MagNet, from_net, load_magnet, size_config, to_net
from odsplat.processing.learned.synth import SynthConfig, make_batch, make_sample
from odsplat.processing.metrics import estimate_translation, psnr, ssim
from odsplat.spine.atomic import atomic_open
from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

VAL_SEED = 1_000_003  # held-out: training draws from TrainConfig.seed, which must differ


@dataclass
class TrainConfig:
    """What `train` does. `out` receives the weights ({"config", "state_dict"}); the resumable checkpoint
    (model, optimiser, step) goes next to it as `<out>.ckpt`. Training stops at `steps` or after
    `max_minutes` of wall time, whichever comes first."""

    out: Path = Path("magnet.pt")
    size: str | None = None  # a named network size (network.SIZES: small, paper); it sets the three below
    steps: int = 20000
    batch_size: int = 8
    crop: int = 64
    lr: float = 5e-4
    lr_final: float = 5e-5  # cosine decay to this over `steps`
    seed: int = 0
    threads: int = 1
    resume: bool = False
    init: Path | None = None  # start from these weights (a MagNet file of the same size) rather than at random
    channels: int = 16
    enc_blocks: int = 3
    dec_blocks: int = 3
    reg_weight: float = 0.1
    max_minutes: float | None = None
    val_samples: int = 64
    val_every: int = 1000
    checkpoint_every: int = 250
    log_every: int = 100
    progress: bool = True
    device: str = "cpu"  # "cuda" for the long run where a GPU is lent (the data is made on the CPU)
    workers: int = 0  # processes making the batches ahead of the network (0: made in line)
    synth: SynthConfig = field(default_factory=SynthConfig)

    def __post_init__(self) -> None:
        if self.size is not None:
            sized = size_config(self.size)
            self.channels, self.enc_blocks, self.dec_blocks = (sized[k] for k in ("channels", "enc_blocks",
                                                                                  "dec_blocks"))


@dataclass
class TrainReport:
    out: Path
    steps: int
    wall_s: float
    train_loss: float  # mean over the last log_every steps
    val_ssim: float
    val_psnr: float
    val_ssim_frame_b: float  # the "do nothing" baseline: frame b against the ground truth
    val_psnr_frame_b: float
    val_gain: float  # measured / true magnified displacement on pure translations (1 is ideal)
    history: list[dict] = field(default_factory=list)


def losses(net: MagNet, batch: dict[str, torch.Tensor], reg_weight: float) -> tuple[torch.Tensor, dict[str, float]]:
    """The paper's loss on one batch from `make_batch` (frames in [0, 1])."""
    n = batch["frame_a"].shape[0]
    x = to_net(torch.cat([batch[k] for k in ("frame_a", "frame_b", "frame_b_c", "target_c")]))
    texture, shape = net.encode(x)  # one pass over all four frames
    ta, tb, tbc, tyc = texture.split(n)
    sa, sb, sbc, _ = shape.split(n)
    y = net.decode(tb, net.manipulate(sa, sb, batch["alpha"]))
    rec = F.l1_loss(y, to_net(batch["target"]))
    reg = F.l1_loss(ta, tb) + F.l1_loss(tbc, tyc) + F.l1_loss(sb, sbc)
    total = rec + reg_weight * reg
    return total, {"loss": total.item(), "rec": rec.item(), "reg": reg.item()}


def _atomic_save(obj, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as f:
        torch.save(obj, f)


def weights_payload(net: MagNet) -> dict:
    return {"config": dict(net.config),
            "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}}


@torch.no_grad()
def validate(net: MagNet, cfg: SynthConfig, n: int) -> dict[str, float]:
    """SSIM/PSNR against the ground truth on `n` held-out samples, and the gain on pure translations."""
    net.eval()
    dev = next(net.parameters()).device
    b = make_batch(VAL_SEED, 0, n, cfg)
    out = []
    for i in range(0, n, 16):
        pred = net(*(to_net(b[k][i:i + 16].to(dev)) for k in ("frame_a", "frame_b")), b["alpha"][i:i + 16].to(dev))
        out.append(from_net(pred, 3).cpu())
    y = torch.cat(out)
    res = {"ssim": ssim(y, b["target"]), "psnr": psnr(y, b["target"]),
           "ssim_frame_b": ssim(b["frame_b"], b["target"]), "psnr_frame_b": psnr(b["frame_b"], b["target"])}
    # Gain: one moving textured plane, no noise; measured magnified shift over the true one.
    tcfg = SynthConfig(size=max(cfg.size, 64), objects=(0, 0), p_background_moves=1.0, p_noise=0.0,
                       alpha_range=(10.0, 10.0), min_magnified_px=2.0, max_magnified_px=4.0)
    gains = []
    for i in range(8):
        s = make_sample((VAL_SEED, 10_000 + i), tcfg)
        yy = from_net(net(to_net(s.frame_a[None].to(dev)), to_net(s.frame_b[None].to(dev)), s.alpha), 3)[0].cpu()
        dx, dy = estimate_translation(s.frame_a, yy)
        tx, ty = (s.alpha * c for c in s.background_displacement)
        gains.append((dx * tx + dy * ty) / (tx * tx + ty * ty))
    res["gain"] = float(sorted(gains)[len(gains) // 2])
    net.train()
    return res


class _Batches(torch.utils.data.Dataset):
    """Batch k of a run: a deterministic function of (seed, k), the same in whichever process makes it."""

    def __init__(self, seed: int, batch_size: int, synth: SynthConfig, steps: int):
        self.seed, self.batch_size, self.synth, self.steps = seed, batch_size, synth, steps

    def __len__(self) -> int:
        return self.steps

    def __getitem__(self, k: int) -> dict[str, torch.Tensor]:
        return make_batch(self.seed, k * self.batch_size, self.batch_size, self.synth)


def _batches(cfg: TrainConfig, synth: SynthConfig, first: int):
    """Batches `first`..`cfg.steps - 1` in order; made by `cfg.workers` fresh processes ahead of the network."""
    data = _Batches(cfg.seed, cfg.batch_size, synth, cfg.steps)
    if cfg.workers < 1:
        return (data[k] for k in range(first, cfg.steps))
    return torch.utils.data.DataLoader(data, batch_size=None, sampler=range(first, cfg.steps),
                                       num_workers=cfg.workers, multiprocessing_context="spawn", prefetch_factor=4,
                                       pin_memory=cfg.device.startswith("cuda"))


def log_path(out: Path) -> Path:
    """The training log beside the weights: `magnet.pt` -> `magnet.log.json`."""
    return out.with_name(out.stem + ".log.json")


def _write_log(cfg: TrainConfig, net: MagNet, step: int, wall_s: float, history: list[dict], out: Path) -> None:
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}
    doc = {"network": dict(net.config), "parameters": sum(p.numel() for p in net.parameters()), "steps": step,
           "wall_s": round(wall_s, 1), "torch": torch.__version__, "settings": settings, "validation": history}
    with atomic_open(log_path(out), "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")


def train(cfg: TrainConfig) -> TrainReport:
    """Train (or resume) a MagNet; writes `cfg.out` atomically at every checkpoint and at the end, with its
    resumable checkpoint (`<out>.ckpt`) and its log (`log_path`: the settings and every validation)."""
    if cfg.crop % 4 or cfg.crop < 16:
        raise InputError("crop", f"the crop must be a multiple of 4 and at least 16, got {cfg.crop}")
    if cfg.seed == VAL_SEED:
        raise InputError("seed", f"{VAL_SEED} is the validation set's seed; pick another")
    if cfg.steps < 1 or cfg.batch_size < 1:
        raise InputError("steps", "steps and batch size must be positive")
    torch.set_num_threads(max(1, cfg.threads))
    torch.manual_seed(cfg.seed)
    out = Path(cfg.out)
    ckpt_path = out.with_name(out.name + ".ckpt")
    synth = SynthConfig(**{**asdict(cfg.synth), "size": cfg.crop})

    try:
        device = torch.device(cfg.device)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as exc:
        raise InputError("device", f"{cfg.device!r} cannot be used here ({' '.join(str(exc).split())[:120]})") from None
    net = MagNet(cfg.channels, cfg.enc_blocks, cfg.dec_blocks).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    step, elapsed_before, history = 0, 0.0, []
    if cfg.resume:
        if not ckpt_path.exists():
            raise InputError(ckpt_path, "no checkpoint to resume from")
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        if ck["config"] != net.config:
            raise InputError(ckpt_path, f"checkpoint network {ck['config']} differs from the requested {net.config}")
        net.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        step, elapsed_before = int(ck["step"]), float(ck["wall_s"])
        history = list(ck.get("history", []))
        log.info("resumed from %s at step %d", ckpt_path, step)
    elif cfg.init is not None:
        try:
            start = load_magnet(cfg.init)
        except (OSError, RuntimeError, KeyError, TypeError, ValueError) as exc:
            raise InputError(cfg.init, f"not a MagNet weights file ({' '.join(str(exc).split())[:120]})") from None
        if start.config != net.config:
            raise InputError(cfg.init, f"a network {start.config}, not the requested {net.config}")
        net.load_state_dict(start.state_dict())
        log.info("starting from the weights %s", cfg.init)

    def lr_at(k: int) -> float:
        return cfg.lr_final + 0.5 * (cfg.lr - cfg.lr_final) * (1 + math.cos(math.pi * min(k / cfg.steps, 1.0)))

    def checkpoint() -> None:
        wall = elapsed_before + time.monotonic() - t0
        _atomic_save({**weights_payload(net), "optimizer": opt.state_dict(), "step": step, "wall_s": wall,
                      "history": history}, ckpt_path)
        _atomic_save(weights_payload(net), out)
        _write_log(cfg, net, step, wall, history, out)

    t0 = time.monotonic()
    recent: list[float] = []
    net.train()
    bar = tqdm(total=cfg.steps, initial=step, disable=not cfg.progress, desc="train-mm", unit="step")
    for batch in _batches(cfg, synth, step):
        if cfg.max_minutes is not None and elapsed_before + time.monotonic() - t0 > 60 * cfg.max_minutes:
            log.info("time limit of %.1f min reached at step %d", cfg.max_minutes, step)
            break
        for g in opt.param_groups:
            g["lr"] = lr_at(step)
        batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
        loss, parts = losses(net, batch, cfg.reg_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        recent = (recent + [parts["rec"]])[-cfg.log_every:]
        bar.update(1)
        bar.set_postfix(loss=f"{parts['loss']:.4f}")
        if step % cfg.log_every == 0:
            log.info("step %d loss %.4f rec %.4f reg %.4f lr %.2e (%.0f s)", step, parts["loss"], parts["rec"],
                     parts["reg"], lr_at(step), elapsed_before + time.monotonic() - t0)
        if step % cfg.val_every == 0:
            v = validate(net, synth, cfg.val_samples)
            history.append({"step": step, "train_rec": sum(recent) / len(recent), **v})
            log.info("validation at step %d: SSIM %.4f PSNR %.2f dB (frame b: %.4f, %.2f dB) gain %.2f", step,
                     v["ssim"], v["psnr"], v["ssim_frame_b"], v["psnr_frame_b"], v["gain"])
        if step % cfg.checkpoint_every == 0:
            checkpoint()
    bar.close()
    v = validate(net, synth, cfg.val_samples)
    if not history or history[-1]["step"] != step:
        history.append({"step": step, "train_rec": sum(recent) / max(len(recent), 1), **v})
    checkpoint()
    wall = elapsed_before + time.monotonic() - t0
    log.info("done: %d steps in %.0f s; validation SSIM %.4f PSNR %.2f dB gain %.2f; weights %s", step, wall,
             v["ssim"], v["psnr"], v["gain"], out)
    return TrainReport(out, step, wall, sum(recent) / max(len(recent), 1), v["ssim"], v["psnr"],
                       v["ssim_frame_b"], v["psnr_frame_b"], v["gain"], history)


__all__ = ["TrainConfig", "TrainReport", "log_path", "losses", "train", "validate"]
