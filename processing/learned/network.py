"""The motion-magnification network of Oh et al. 2018 (encoder, manipulator, decoder), at reduced width.

Images enter and leave the network as (N, 3, H, W) float tensors in [-1, 1]; `to_net` / `from_net` convert
from and to the [0, 1] frames (mono or RGB) used everywhere else in odsplat. H and W must be multiples of 4
for the encoder and decoder sizes to line up; `pad_to_multiple` / `crop_to` do that for callers.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from odsplat.spine.errors import InputError


class ResBlock(nn.Module):
    """x + conv(relu(conv(x))), the paper's residual block (no normalisation)."""

    def __init__(self, ch: int, *, bias: bool = True):
        super().__init__()
        self.c1 = nn.Conv2d(ch, ch, 3, padding=1, padding_mode="reflect", bias=bias)
        self.c2 = nn.Conv2d(ch, ch, 3, padding=1, padding_mode="reflect", bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.c2(F.relu(self.c1(x)))


def _conv(cin: int, cout: int, k: int, stride: int = 1, *, bias: bool = True) -> nn.Conv2d:
    # Reflect padding: zero padding makes a dark frame border that the manipulator reads as an edge.
    return nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2, padding_mode="reflect", bias=bias)


class Manipulator(nn.Module):
    """G_m(M_a, M_b, alpha) = M_a + h(alpha * g(M_b - M_a)).

    g and h carry no biases, so identical shapes (M_b = M_a) or alpha = 0 give M_a back exactly, and the
    amplified term alpha * g(.) is linear in alpha.
    """

    def __init__(self, ch: int):
        super().__init__()
        self.g = _conv(ch, ch, 3, bias=False)
        self.h_conv = _conv(ch, ch, 3, bias=False)
        self.h_res = ResBlock(ch, bias=False)

    def g_term(self, shape_a: torch.Tensor, shape_b: torch.Tensor) -> torch.Tensor:
        return F.relu(self.g(shape_b - shape_a))

    def forward(self, shape_a: torch.Tensor, shape_b: torch.Tensor, alpha: torch.Tensor | float) -> torch.Tensor:
        alpha = _alpha_map(alpha, shape_a)
        return shape_a + self.h_res(self.h_conv(alpha * self.g_term(shape_a, shape_b)))


def _alpha_map(alpha: torch.Tensor | float, like: torch.Tensor) -> torch.Tensor:
    """A scalar, or one alpha per batch item, broadcast to (N, 1, 1, 1)."""
    a = torch.as_tensor(alpha, dtype=like.dtype, device=like.device)
    return a.reshape(-1, 1, 1, 1) if a.ndim else a


# The network's sizes by name: ours as shipped (0.11 M parameters), and the paper's (0.87 M: a 32-channel trunk,
# a decoder of 9 residual blocks at 64 channels).
SIZES = {"small": {"channels": 16, "enc_blocks": 3, "dec_blocks": 3},
         "paper": {"channels": 32, "enc_blocks": 3, "dec_blocks": 9}}


def size_config(name: str) -> dict[str, int]:
    """A named size's MagNet arguments (SIZES), or one line saying which names there are."""
    if name not in SIZES:
        raise InputError("size", f"the learned magnifier's size is one of {', '.join(SIZES)}, got {name!r}")
    return dict(SIZES[name])


class MagNet(nn.Module):
    """Oh et al. 2018's network. `channels` is the width of the half-resolution trunk (the paper: 32);
    the first layer has half of it and the decoder twice it (texture + shape concatenated). `MagNet.of_size`
    builds one of SIZES."""

    def __init__(self, channels: int = 16, enc_blocks: int = 3, dec_blocks: int = 3):
        super().__init__()
        c1, c = max(channels // 2, 4), channels
        self.config = {"channels": channels, "enc_blocks": enc_blocks, "dec_blocks": dec_blocks}
        self.enc = nn.Sequential(_conv(3, c1, 7), nn.ReLU(), _conv(c1, c, 3, 2), nn.ReLU(),
                                 *[ResBlock(c) for _ in range(enc_blocks)])
        self.texture = nn.Sequential(_conv(c, c, 3, 2), nn.ReLU(), ResBlock(c), ResBlock(c))
        self.shape = nn.Sequential(_conv(c, c, 3), nn.ReLU(), ResBlock(c), ResBlock(c))
        self.manipulator = Manipulator(c)
        self.dec = nn.Sequential(*[ResBlock(2 * c) for _ in range(dec_blocks)])
        self.dec_up = _conv(2 * c, c1, 3)
        self.out = _conv(c1, 3, 7)

    @classmethod
    def of_size(cls, name: str) -> "MagNet":
        return cls(**size_config(name))

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3, H, W) in [-1, 1] -> texture (N, C, H/4, W/4), shape (N, C, H/2, W/2)."""
        f = self.enc(x)
        return self.texture(f), self.shape(f)

    def manipulate(self, shape_a: torch.Tensor, shape_b: torch.Tensor, alpha: torch.Tensor | float) -> torch.Tensor:
        return self.manipulator(shape_a, shape_b, alpha)

    def decode(self, texture: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        t = F.interpolate(texture, size=shape.shape[-2:], mode="nearest")
        y = self.dec(torch.cat([t, shape], dim=1))
        y = F.relu(self.dec_up(F.interpolate(y, scale_factor=2, mode="nearest")))
        return self.out(y)

    def forward(self, x_a: torch.Tensor, x_b: torch.Tensor, alpha: torch.Tensor | float) -> torch.Tensor:
        """Frame b with its motion relative to frame a magnified alpha times; texture from frame b (as the paper)."""
        _, shape_a = self.encode(x_a)
        texture_b, shape_b = self.encode(x_b)
        return self.decode(texture_b, self.manipulate(shape_a, shape_b, alpha))


def to_net(frames: torch.Tensor) -> torch.Tensor:
    """(T, C, H, W) frames in [0, 1], C 1 or 3 -> (T, 3, H, W) in [-1, 1]; mono is repeated to RGB."""
    if frames.shape[1] == 1:
        frames = frames.expand(-1, 3, -1, -1)
    return frames * 2.0 - 1.0


def from_net(y: torch.Tensor, channels: int) -> torch.Tensor:
    """The network's (T, 3, H, W) in [-1, 1] -> frames in [0, 1] with `channels` (1: the mean of RGB)."""
    y = ((y + 1.0) * 0.5).clamp(0.0, 1.0)
    return y.mean(dim=1, keepdim=True) if channels == 1 else y


def pad_to_multiple(x: torch.Tensor, m: int = 4) -> torch.Tensor:
    """Reflect-pad H and W on the bottom/right up to multiples of m."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % m, (-w) % m
    if ph == 0 and pw == 0:
        return x
    mode = "reflect" if ph < h and pw < w else "replicate"
    return F.pad(x, (0, pw, 0, ph), mode=mode)


def crop_to(x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    return x[..., :h, :w]


def load_magnet(path, map_location: str | torch.device = "cpu") -> MagNet:
    """A MagNet from a weights file: {"config": {...}, "state_dict": {...}} or a bare state_dict (width 16)."""
    obj = torch.load(path, map_location=map_location, weights_only=True)
    if isinstance(obj, dict) and "state_dict" in obj:
        net = MagNet(**{k: int(v) for k, v in obj.get("config", {}).items()})
        net.load_state_dict(obj["state_dict"])
    else:
        net = MagNet()
        net.load_state_dict(obj)
    return net.eval()


__all__ = ["SIZES", "MagNet", "Manipulator", "ResBlock", "crop_to", "from_net", "load_magnet", "pad_to_multiple",
           "size_config", "to_net"]
