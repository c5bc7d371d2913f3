"""Linear Eulerian video magnification (Wu et al. 2012) on a Laplacian pyramid, streamed: the baseline the
phase-based method is compared with.

Gain convention (the same as `phase.PhaseMagnifier`): `alpha` is the factor on the motion itself; a
pattern moving by d pixels comes out moving by about alpha * d. The intensity change of each level
(against the reference frame, or temporally band-passed) is multiplied by alpha - 1 and added back, which
to first order in d moves the pattern by alpha * d. Wu et al. call alpha - 1 "alpha".
"""
from __future__ import annotations

import logging

import torch
import torch.nn.functional as F

from odsplat.processing.filters import TemporalFilter
from odsplat.processing.streaming import StreamingMagnifier
from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

_BINOMIAL = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
MIN_LEVEL_SIDE_PX = 4  # the reflect padding of the 5-tap blur needs at least 3


def _blur(x: torch.Tensor) -> torch.Tensor:
    """Separable 5-tap binomial blur of (N, H, W), mirrored at the borders."""
    k = _BINOMIAL.to(x)
    y = F.pad(x[:, None], (2, 2, 0, 0), mode="reflect")
    y = F.conv2d(y, k.view(1, 1, 1, 5))
    y = F.pad(y, (0, 0, 2, 2), mode="reflect")
    return F.conv2d(y, k.view(1, 1, 5, 1))[:, 0]


def _down(x: torch.Tensor) -> torch.Tensor:
    return _blur(x)[:, ::2, ::2]


def _up(x: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    z = torch.zeros((x.shape[0], *shape), dtype=x.dtype, device=x.device)
    z[:, ::2, ::2] = x
    return 4.0 * _blur(z)  # zeros in 3 of 4 samples: restore the mean


def max_levels(height_px: int, width_px: int) -> int:
    """Band-pass levels that fit while the low-pass residual keeps MIN_LEVEL_SIDE_PX on its short side."""
    n, h, w = 0, height_px, width_px
    while min((h + 1) // 2, (w + 1) // 2) >= MIN_LEVEL_SIDE_PX:
        n, h, w = n + 1, (h + 1) // 2, (w + 1) // 2
    return n


def laplacian_pyramid(x: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """(N, H, W) -> `levels` band-pass images, finest first, then the low-pass residual."""
    out = []
    for _ in range(levels):
        low = _down(x)
        out.append(x - _up(low, tuple(x.shape[-2:])))
        x = low
    out.append(x)
    return out


def collapse(pyramid: list[torch.Tensor]) -> torch.Tensor:
    """Inverse of `laplacian_pyramid` (exact up to rounding)."""
    x = pyramid[-1]
    for band in reversed(pyramid[:-1]):
        x = band + _up(x, tuple(band.shape[-2:]))
    return x


def level_wavelength_px(level: int) -> float:
    """Representative spatial wavelength of Laplacian level `level` (0 finest): the geometric centre of its
    pass band. With the 5-tap binomial, levels k and k + 1 cross at half power near 2**(k + 3) px (measured
    7.7, 15.5, 31 px), so level k holds about 2**(k + 2) to 2**(k + 3) px."""
    return 2.0 ** (level + 2.5)


def level_gains(alpha: float, levels: int, cutoff_wavelength_px: float) -> list[float]:
    """Amplification (alpha_k - 1) of each level, the residual last. Wu et al.'s bound, total motion
    alpha * d < lambda / 8, is met at the cut-off wavelength: below it the total gain falls in proportion
    to the wavelength (never below 1, no amplification), so fine texture is not blown up."""
    gains = []
    for k in range(levels + 1):
        if alpha <= 1.0:
            gains.append(alpha - 1.0)  # attenuating never violates the bound
            continue
        total = min(alpha, alpha * level_wavelength_px(k) / cutoff_wavelength_px)
        gains.append(max(total, 1.0) - 1.0)
    return gains


class LinearMagnifier(StreamingMagnifier):
    """Linear Eulerian magnification: output motion ~ alpha x input motion (first order in the motion).

    Y is decomposed into a Laplacian pyramid of `levels` band-pass levels and a low-pass residual
    (`levels` is reduced to what fits the frame). The change of each level against the reference frame is
    band-passed by `temporal` (None: the change itself, "static" mode), multiplied by the level's gain
    (alpha - 1, reduced for levels finer than `cutoff_wavelength_px`, see `level_gains`) and added to the
    frame. I and Q of RGB frames are carried unchanged.
    """

    def __init__(self, alpha: float, temporal: TemporalFilter | None = None, *, levels: int = 4,
                 cutoff_wavelength_px: float = 16.0, reference: str | torch.Tensor = "first",
                 batch_frames: int = 8):
        if levels < 0:
            raise InputError("levels", f"expected a number of pyramid levels >= 0, got {levels}")
        if not cutoff_wavelength_px > 0:
            raise InputError("cutoff_wavelength_px", f"must be positive, got {cutoff_wavelength_px}")
        self.levels_requested = int(levels)
        self.cutoff_wavelength_px = float(cutoff_wavelength_px)
        self.levels = self.levels_requested
        super().__init__(alpha, temporal, reference=reference, batch_frames=batch_frames)

    def _reset_state(self) -> None:
        self._y_ref: torch.Tensor | None = None

    def _setup(self, height_px: int, width_px: int, device: torch.device) -> int:
        self.levels = min(self.levels_requested, max_levels(height_px, width_px))
        if self.levels < self.levels_requested:
            log.info("LinearMagnifier: %d levels fit a %dx%d frame (asked %d)", self.levels, height_px, width_px,
                     self.levels_requested)
        self.gains = level_gains(self.alpha, self.levels, self.cutoff_wavelength_px)
        shapes = [p.shape[-2:] for p in laplacian_pyramid(torch.zeros((1, height_px, width_px)), self.levels)]
        self._shapes = [tuple(s) for s in shapes]
        return sum(h * w for h, w in self._shapes)

    def _init_reference(self, y_ref: torch.Tensor) -> None:
        self._y_ref = y_ref.clone()

    def _analyse(self, y: torch.Tensor) -> tuple[torch.Tensor, None]:
        # The pyramid is linear, so the pyramid of the change is the change of the pyramids; starting from
        # zero change also keeps the filters free of a start-up step.
        pyr = laplacian_pyramid(y - self._y_ref, self.levels)
        return torch.cat([p.reshape(y.shape[0], -1) for p in pyr], dim=1), None

    def _synthesise(self, y: torch.Tensor, features: torch.Tensor, cache: None) -> torch.Tensor:
        pyr, offset = [], 0
        for (h, w), gain in zip(self._shapes, self.gains):
            pyr.append(gain * features[:, offset:offset + h * w].reshape(-1, h, w))
            offset += h * w
        return y + collapse(pyr)


__all__ = ["LinearMagnifier", "collapse", "laplacian_pyramid", "level_gains", "level_wavelength_px", "max_levels"]
