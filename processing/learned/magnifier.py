"""The learned motion magnifier (Oh et al. 2018) behind the streaming `Magnifier` interface.

Modes (the paper's section 4): "static" magnifies every frame's motion relative to the first frame;
"dynamic" magnifies the motion between consecutive frames and accumulates the magnified increments in
the shape representation; with a `temporal` filter, the shape representation is band-passed over time and
only the band's motion is magnified (the paper's temporal mode).
"""
from __future__ import annotations

import logging
from collections import deque
from pathlib import Path

import torch

from odsplat.processing.base import Magnifier, check_alpha, check_frames
from odsplat.processing.filters import TemporalFilter
from odsplat.processing.learned.network import MagNet, crop_to, from_net, load_magnet, pad_to_multiple, to_net
from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "magnet_small.pt"
MODES = ("static", "dynamic")


class LearnedMagnifier(Magnifier):
    """Streams frames (T, C, H, W) in [0, 1] through MagNet; state is one frame's representations (static,
    dynamic) or the filter's delay line of them (temporal). `batch` frames go through the network at once."""

    def __init__(self, alpha: float, temporal: TemporalFilter | None = None, *, mode: str = "static",
                 weights: str | Path | None = None, device: str | torch.device = "cpu", batch: int = 4):
        self.alpha = check_alpha(alpha)
        if mode not in MODES:
            raise InputError("mode", f"expected one of {MODES}, got {mode!r}")
        if temporal is not None and mode != "static":
            raise InputError("mode", "a temporal filter replaces the reference frame; use it with the default mode")
        self.mode = mode
        self.temporal = temporal
        if temporal is not None:
            temporal.reset()  # its state belongs to this stream
        self.delay_frames = temporal.delay_frames if temporal is not None else 0
        path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
        if not path.is_file():
            raise InputError(path, "learned-magnifier weights not found")
        try:
            self.net: MagNet = load_magnet(path, map_location=device).to(device)
        except (RuntimeError, KeyError, TypeError, ValueError) as e:
            raise InputError(path, f"not a MagNet weights file ({e})") from e
        self.device = torch.device(device)
        log.debug("learned magnifier: %s, %s mode, alpha %g, weights %s", self.net.config,
                  "temporal" if temporal is not None else mode, self.alpha, path)
        self.batch = max(1, int(batch))
        self._shape: tuple[int, ...] | None = None
        self._pushed = 0
        self._ref: torch.Tensor | None = None  # static: first shape; dynamic: previous shape; temporal: first shape
        self._acc: torch.Tensor | None = None  # dynamic: the accumulated, magnified shape
        self._fifo: deque[tuple[torch.Tensor, torch.Tensor]] = deque()  # temporal: (texture, shape) of the last D
        self._last_dev: torch.Tensor | None = None  # temporal: the last shape - first shape, held to flush

    @torch.inference_mode()
    def push(self, frames: torch.Tensor) -> torch.Tensor:
        self._shape = check_frames(frames, self._shape)
        c, h, w = self._shape
        outs = []
        for i in range(0, frames.shape[0], self.batch):
            x = pad_to_multiple(to_net(frames[i:i + self.batch].to(self.device, torch.float32)))
            texture, shape = self.net.encode(x)
            y = self._magnify(texture, shape)
            if y is not None:
                outs.append(crop_to(from_net(y, c), h, w).cpu())
        self._pushed += frames.shape[0]
        return torch.cat(outs) if outs else torch.zeros((0, c, h, w), dtype=torch.float32)

    def _magnify(self, texture: torch.Tensor, shape: torch.Tensor) -> torch.Tensor | None:
        net, alpha = self.net, self.alpha
        if self._ref is None:
            self._ref = shape[:1].clone()
            self._acc = shape[:1].clone()
        if self.temporal is not None:
            return self._temporal(texture, shape)
        if self.mode == "static":
            return net.decode(texture, net.manipulate(self._ref.expand_as(shape), shape, alpha))
        # Dynamic: S_t = S_{t-1} + [G_m(M_{t-1}, M_t, alpha) - M_{t-1}], S_0 = M_0.
        prev = torch.cat([self._ref, shape[:-1]])
        increments = net.manipulate(prev, shape, alpha) - prev
        acc = self._acc + torch.cumsum(increments, dim=0)
        self._ref, self._acc = shape[-1:].clone(), acc[-1:].clone()
        return net.decode(texture, acc)

    def _temporal(self, texture: torch.Tensor, shape: torch.Tensor) -> torch.Tensor | None:
        # Filtering M_t - M_0 rather than M_t: the band-pass removes the constant anyway, and a signal that
        # starts at zero has no start-up transient from the filter's zero initial state.
        dev = shape - self._ref
        self._last_dev = dev[-1:].clone()
        band = self.temporal(dev)  # band[k] belongs to the frame delay_frames before dev[k]
        for t, m in zip(texture, shape):
            self._fifo.append((t, m))
        n_out = max(0, len(self._fifo) - self.delay_frames)
        if n_out == 0:
            return None
        band = band[band.shape[0] - n_out:]
        pairs = [self._fifo.popleft() for _ in range(n_out)]
        tex = torch.stack([p[0] for p in pairs])
        m = torch.stack([p[1] for p in pairs])
        # Shape a = M_t - band, shape b = M_t: the band's motion comes out alpha times larger, the rest as is.
        return self.net.decode(tex, self.net.manipulate(m - band, m, self.alpha))

    @torch.inference_mode()
    def flush(self) -> torch.Tensor:
        if self._shape is None:
            raise InputError("frames", "no frames were pushed")
        need = self.temporal.min_frames if self.temporal is not None else 1
        if self._pushed < need:
            raise InputError("frames", f"the temporal filter needs at least {need} frames, got {self._pushed}")
        c, h, w = self._shape
        if self.temporal is None or not self._fifo:
            return torch.zeros((0, c, h, w), dtype=torch.float32)
        # The last frames' filtered values: feed the held last value through the delay line.
        band = self.temporal(self._last_dev.expand(self.delay_frames, *self._last_dev.shape[1:]).clone())
        n = len(self._fifo)
        band = band[band.shape[0] - n:]
        outs = []
        for i in range(0, n, self.batch):
            pairs = [self._fifo.popleft() for _ in range(min(self.batch, len(self._fifo)))]
            tex = torch.stack([p[0] for p in pairs])
            m = torch.stack([p[1] for p in pairs])
            bb = band[i:i + len(pairs)]
            y = self.net.decode(tex, self.net.manipulate(m - bb, m, self.alpha))
            outs.append(crop_to(from_net(y, c), h, w).cpu())
        return torch.cat(outs)


__all__ = ["DEFAULT_WEIGHTS", "LearnedMagnifier", "MODES"]
