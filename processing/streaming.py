"""The push/flush plumbing the Eulerian magnifiers (phase-based, linear) share: per-frame features, the
temporal filter over them, and a FIFO pairing each filtered value with its frame."""
from __future__ import annotations

import logging
from abc import abstractmethod
from collections import deque
from typing import Any

import torch

from odsplat.processing.base import Magnifier, check_alpha, check_frames, rgb_to_yiq, yiq_to_rgb
from odsplat.processing.filters import TemporalFilter
from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

class StreamingMagnifier(Magnifier):
    """Push/flush plumbing shared by the Eulerian magnifiers.

    Each frame's luminance Y is turned into a vector of per-pixel features (phase changes, intensity
    changes) by `_analyse`; the temporal filter runs over those vectors; the filtered vector of frame
    n - D comes out when frame n goes in and is paired with that frame, which waits in a FIFO of D frames,
    to give the magnified Y (`_synthesise`). I and Q of RGB input are carried along unchanged.
    The held state is one frame's features, the filter's own state and the FIFO, whatever the length.
    """

    def __init__(self, alpha: float, temporal: TemporalFilter | None, *, reference: str | torch.Tensor,
                 batch_frames: int):
        self.alpha = check_alpha(alpha)
        self.temporal = temporal if temporal is not None else TemporalFilter()
        if not isinstance(self.temporal, TemporalFilter):
            raise InputError("temporal filter",
                             f"expected a TemporalFilter (make_filter), got {type(temporal).__name__}")
        self.delay_frames = int(self.temporal.delay_frames)
        if isinstance(reference, str):
            if reference != "first":
                raise InputError("reference", f"expected 'first' or a frame tensor (C, H, W), got {reference!r}")
            self._reference = None
        else:
            ref = torch.as_tensor(reference)
            self._reference = ref[None] if ref.ndim == 3 else ref
        if batch_frames < 1:
            raise InputError("batch_frames", f"must be at least 1, got {batch_frames}")
        self.batch_frames = int(batch_frames)
        self._reset()

    def _reset(self) -> None:
        self._shape: tuple[int, ...] | None = None
        self._fifo: deque[torch.Tensor] = deque()
        self._last_features: torch.Tensor | None = None
        self._count = 0
        self._batch = self.batch_frames
        self.temporal.reset()
        self._reset_state()

    @property
    def frames_pushed(self) -> int:
        return self._count

    @property
    def held_frames(self) -> int:
        """Frames waiting for their filtered features: at most the filter's delay."""
        return len(self._fifo)

    # --- what a method provides -------------------------------------------------------------------
    @abstractmethod
    def _reset_state(self) -> None:
        """Forget the per-stream state of the method."""

    @abstractmethod
    def _setup(self, height_px: int, width_px: int, device: torch.device) -> int:
        """Build the decompositions for this frame size; return the number of features per frame."""

    @abstractmethod
    def _init_reference(self, y_ref: torch.Tensor) -> None:
        """(1, H, W) luminance of the reference frame."""

    @abstractmethod
    def _analyse(self, y: torch.Tensor) -> tuple[torch.Tensor, Any]:
        """(n, H, W) consecutive frames -> (n, P) float32 features and a cache reusable by `_synthesise`."""

    @abstractmethod
    def _synthesise(self, y: torch.Tensor, features: torch.Tensor, cache: Any | None) -> torch.Tensor:
        """Frames (k, H, W) and their filtered features (k, P) -> magnified luminance (k, H, W)."""

    # --- streaming --------------------------------------------------------------------------------
    def push(self, frames: torch.Tensor) -> torch.Tensor:
        shape = check_frames(frames, self._shape)
        frames = frames.detach().to(torch.float32)
        if frames.shape[0] == 0:
            return frames
        if self._shape is None:
            self._start(frames, shape)
        outs = [self._push_batch(frames[i:i + self._batch]) for i in range(0, frames.shape[0], self._batch)]
        return torch.cat(outs) if outs else frames[:0]

    def flush(self) -> torch.Tensor:
        """The last D frames, their filter fed with the last frame's features held (the video frozen),
        as the start is fed with the reference. Resets the magnifier for a new stream."""
        if self._shape is None:
            self._reset()
            return torch.empty((0, 1, 0, 0))
        need, got = int(self.temporal.min_frames), self._count
        if got < need:
            kind = self.temporal.kind
            self._reset()
            raise InputError(f"{kind} temporal filter", f"needs at least {need} frames, got {got}; "
                                                         f"widen the band or film longer")
        outs = []
        pending = len(self._fifo)
        # Pad rows for frames before 0 (a stream shorter than the delay) come out first and are dropped.
        skip = self.delay_frames - pending
        if skip > 0:
            self.temporal(self._last_features.expand(skip, -1))
        while pending:
            n = min(self._batch, pending)
            pad = self._last_features.expand(n, -1)
            filtered = self.temporal(pad)
            frames = torch.stack([self._fifo.popleft() for _ in range(n)])
            outs.append(self._finish(frames, filtered, None))
            pending -= n
        shape = self._shape
        self._reset()
        return torch.cat(outs) if outs else torch.empty((0, *shape))

    def _start(self, frames: torch.Tensor, shape: tuple[int, ...]) -> None:
        _, h, w = shape
        n_features = self._setup(h, w, frames.device)
        self._batch = self.batch_frames  # the filters hold one batch's features whatever their length
        if self._reference is not None:
            ref = self._reference.to(frames.device, torch.float32)
            if tuple(ref.shape) != (1, *shape):
                raise InputError("reference", f"expected a frame shaped {shape}, got {tuple(self._reference.shape)}")
            self._init_reference(self._luma(ref))
        else:
            self._init_reference(self._luma(frames[:1]))
        self._shape = shape
        log.debug("%s: %dx%d, %d features/frame, delay %d, batches of %d", type(self).__name__, h, w,
                  n_features, self.delay_frames, self._batch)

    def _push_batch(self, frames: torch.Tensor) -> torch.Tensor:
        n, D = frames.shape[0], self.delay_frames
        features, cache = self._analyse(self._luma(frames))
        self._last_features = features[-1:].clone()
        filtered = self.temporal(features)
        before, self._count = self._count, self._count + n
        # Output row i is the filtered value of frame (before + i - D); rows for frames before 0 are dropped.
        k = max(0, self._count - D) - max(0, before - D)
        self._fifo.extend(f.clone() for f in frames)  # clones: a view would pin the caller's whole chunk
        if k == 0:
            return frames[:0]
        paired = torch.stack([self._fifo.popleft() for _ in range(k)])
        return self._finish(paired, filtered[n - k:], cache if D == 0 else None)

    def _finish(self, frames: torch.Tensor, filtered: torch.Tensor, cache: Any | None) -> torch.Tensor:
        if frames.shape[1] == 1:
            y = self._synthesise(frames[:, 0], filtered, cache)
            return y[:, None].clamp(0.0, 1.0)
        yiq = rgb_to_yiq(frames)
        y = self._synthesise(yiq[:, 0], filtered, cache)
        yiq = torch.cat([y[:, None], yiq[:, 1:]], dim=1)
        return yiq_to_rgb(yiq).clamp(0.0, 1.0)

    @staticmethod
    def _luma(frames: torch.Tensor) -> torch.Tensor:
        return frames[:, 0] if frames.shape[1] == 1 else rgb_to_yiq(frames)[:, 0]


__all__ = ["StreamingMagnifier"]
