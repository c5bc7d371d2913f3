"""What every magnification method shares: the streaming interface and colour handling.

Frames travel as float32 tensors (T, C, H, W) with values in [0, 1] (C = 1 mono, 3 RGB). A magnifier
is pushed chunks of frames and returns the magnified frames that are complete so far; `flush()` returns
the rest at the end. Methods with a delay (zero-phase FIR filters) return fewer frames than pushed at
first; over the whole stream the output has exactly as many frames as the input, in order.
"""
from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
import torch

from odsplat.spine.checks import MAGNIFICATION, check_number
from odsplat.spine.errors import InputError

# NTSC YIQ: luminance first. Phase and linear methods magnify Y and carry I, Q along.
LUMA = np.array([0.299, 0.587, 0.114], np.float32)   # Y of YIQ, what the methods magnify
_RGB2YIQ = torch.tensor([LUMA.tolist(), [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
_YIQ2RGB = torch.linalg.inv(_RGB2YIQ)


def luma(frames: np.ndarray) -> np.ndarray:
    """Frames (T, H, W) as they are, or (T, H, W, 3) as their Y."""
    return frames if frames.ndim == 3 else frames @ LUMA


def rgb_to_yiq(x: torch.Tensor) -> torch.Tensor:
    """(T, 3, H, W) -> (T, 3, H, W)."""
    return torch.einsum("ij,tjhw->tihw", _RGB2YIQ.to(x), x)


def yiq_to_rgb(x: torch.Tensor) -> torch.Tensor:
    return torch.einsum("ij,tjhw->tihw", _YIQ2RGB.to(x), x)


def check_alpha(alpha: float) -> float:
    """The magnification as a float, refused outside MAGNIFICATION (the settings' range, odsplat.spine.checks)."""
    check_number("alpha", alpha, MAGNIFICATION)
    return float(alpha)


def check_frames(frames: torch.Tensor, shape: tuple[int, ...] | None, *, source: str = "frames") -> tuple[int, ...]:
    """Frames must be (T, C, H, W) with C 1 or 3, and every chunk of one stream the same (C, H, W)."""
    if frames.ndim != 4 or frames.shape[1] not in (1, 3):
        raise InputError(source, f"expected frames shaped (T, C, H, W) with C 1 or 3, got {tuple(frames.shape)}")
    if shape is not None and tuple(frames.shape[1:]) != shape:
        raise InputError(source, f"frames of mixed shape: {tuple(frames.shape[1:])} after {shape}")
    return tuple(frames.shape[1:])


class Magnifier(ABC):
    """A streaming motion magnifier. Subclasses implement `push` and `flush`."""

    alpha: float
    delay_frames: int = 0

    @abstractmethod
    def push(self, frames: torch.Tensor) -> torch.Tensor:
        """Feed (T, C, H, W) frames in [0, 1]; returns the magnified frames complete so far (T_out, C, H, W)."""

    @abstractmethod
    def flush(self) -> torch.Tensor:
        """The frames still held back at the end of the stream."""


__all__ = ["Magnifier", "check_alpha", "check_frames", "rgb_to_yiq", "yiq_to_rgb"]
