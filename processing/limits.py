"""How far a method can magnify the motion a take holds: the measured motion against each method's bound, and
the largest alpha that fits it (docs/processing.md, "Motion limits").

Bounds, in our gain convention (output motion = alpha x input motion d; the papers' 1 + alpha is our alpha):
- linear Eulerian (Wu et al. 2012, Eq. 15): alpha_k d < lambda_k / 8 at every Laplacian level k, alpha_k the
  level's total gain after the wavelength cut-off (`eulerian.level_gains`);
- phase-based (Wadhwa et al. 2013, Sec. 4, octave-bandwidth complex steerable pyramid): alpha d < lambda_s / 4
  at every band s, lambda_s its peak wavelength: 2**(s + 2) px (4 px at the finest band; 2 px with
  `top_band`). In phase: the magnified phase change alpha dphi stays under pi / 2.
The learned method and the phase method's `warp` synthesis resample frames (Lagrangian) and have no such bound.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .eulerian import level_gains, level_wavelength_px

log = logging.getLogger(__name__)

MOTION_PERCENTILE = 99.0      # of the textured pixels' motion, in the frame where it is largest
TEXTURE_QUANTILE = 0.75       # pixels whose gradient is in the reference's top quarter carry measurable motion
SAMPLE_FRAMES = 16            # frames (evenly spread over the take) whose motion against the first is measured


def motion_px(reference: np.ndarray, frames: list[np.ndarray]) -> float:
    """The take's motion in pixels: dense optical flow (Farneback, OpenCV) from the 8-bit reference frame to each
    8-bit frame, its MOTION_PERCENTILE over the reference's textured pixels, the largest over the frames. The
    flow finds sub-pixel and many-pixel motion alike; on still frames with the simulated rig's noise it reads
    0.05-0.07 px, its floor."""
    ref = np.ascontiguousarray(reference)
    gx, gy = cv2.Sobel(ref, cv2.CV_32F, 1, 0), cv2.Sobel(ref, cv2.CV_32F, 0, 1)
    grad = np.hypot(gx, gy)
    textured = grad >= np.quantile(grad, TEXTURE_QUANTILE)
    if not textured.any():
        return 0.0
    most = 0.0
    for frame in frames:
        flow = cv2.calcOpticalFlowFarneback(ref, np.ascontiguousarray(frame), None, 0.5, 5, 15, 3, 5, 1.1, 0)
        most = max(most, float(np.percentile(np.hypot(flow[..., 0], flow[..., 1])[textured], MOTION_PERCENTILE)))
    return most


def sample_indices(n_frames: int, n: int = SAMPLE_FRAMES) -> np.ndarray:
    """The frames whose motion is measured: n spread evenly over the take, the first one excluded."""
    return np.unique(np.linspace(1, max(1, n_frames - 1), min(n, max(1, n_frames - 1))).round().astype(int))


@dataclass(frozen=True)
class MotionLimit:
    """A take's measured motion against its method's bound at one alpha (recorded in magnify.json)."""

    method: str
    alpha: float
    motion_px: float                 # measured: the input's motion against its first frame
    limit_px: float | None           # the largest magnified motion alpha x d the binding level takes; None: no bound
    level_wavelength_px: float | None  # that level's wavelength
    bound: str                       # the bound's formula, in words
    fits_alpha: float | None         # the largest alpha that keeps within every level's bound (None: any)
    passes: bool                     # alpha x motion passes the bound (the output smears where it does)
    band_hz: list[float] | None = None

    def line(self, take: str) -> str:
        """One line for the engineer: what passes the limit and what alpha would fit."""
        if self.limit_px is None:
            return f"{take}: {self.bound}"
        head = (f"{take}: alpha {self.alpha:g} x {self.motion_px:.3g} px of motion "
                f"= {self.alpha * self.motion_px:.3g} px")
        where = (f"the {self.method} method's limit ({self.limit_px:.3g} px, {self.bound} at its finest "
                 f"level used, {self.level_wavelength_px:.3g} px)")
        if not self.passes:
            return f"{head} keeps within {where}"
        fit = self.fits_alpha
        advice = (f"alpha <= {_floor2(fit):g} fits" if fit >= 1.0 else
                  f"only alpha <= {_floor2(fit):.2g} fits: the motion itself is past the limit (magnify a temporal "
                  f"band without the large motion, or crop to what moves less)")
        scope = " (the motion is the whole motion, an upper bound of the band's)" if self.band_hz else ""
        return f"{head} passes {where}{scope}; {advice}"


def _floor2(x: float) -> float:
    """Down to two significant digits: a suggested alpha must not pass the limit by rounding."""
    if x <= 0:
        return 0.0
    step = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.floor(x / step) * step


def phase_bands_px(top_band: bool = False, n_bands: int = 8) -> list[float]:
    """Peak wavelengths of the complex steerable pyramid's bands, finest first (`pyramid.py`: band s peaks at
    r = 2**-(s+1) of Nyquist, one octave finer with `top_band`)."""
    first = 2.0 if top_band else 4.0
    return [first * 2.0 ** s for s in range(n_bands)]


def check_limit(method: str, alpha: float, motion: float, options: dict, band_hz: list[float] | None = None
                ) -> MotionLimit:
    """The bound of `method` with its options, for a take whose motion is `motion` px."""
    if method == "learned" or (method == "phase" and options.get("warp")):
        what = "the learned method" if method == "learned" else "the phase method's warp synthesis"
        return MotionLimit(method, alpha, motion, None, None, f"{what} resamples frames: no motion bound is checked",
                           None, False, band_hz)
    if method == "phase":
        lam = phase_bands_px(bool(options.get("top_band", False)))[0]
        limit = lam / 4.0
        fits = limit / motion if motion > 0 else None
        return MotionLimit(method, alpha, motion, limit, lam, "alpha x motion < lambda/4", fits,
                           alpha > 1.0 and alpha * motion > limit, band_hz)

    levels = int(options.get("levels", 4))
    cutoff = float(options.get("cutoff_wavelength_px", 16.0))

    def worst(a: float) -> tuple[float, float, float]:
        """(magnified motion over its limit at the binding level, that limit in alpha x d, its wavelength)."""
        out = (0.0, math.inf, math.nan)
        for k, g in enumerate(level_gains(a, levels, cutoff)):
            if g <= 0:
                continue
            lam = level_wavelength_px(k)
            limit = lam / 8.0 * a / (1.0 + g)   # (1 + g) d < lam / 8, written as a limit on alpha x d
            ratio = a * motion / limit
            if ratio > out[0]:
                out = (ratio, limit, lam)
        return out

    ratio, limit, lam = worst(alpha)
    if not math.isfinite(limit):   # nothing magnified
        limit, lam = cutoff / 8.0, cutoff
    if worst(1.0 + 1e-6)[0] > 1.0:   # the motion alone passes a level's bound
        fits = alpha / ratio
    else:   # the ratio grows with alpha: bisect for where it reaches 1
        lo, hi = 1.0, max(alpha, 1e4)   # 1e4: "any alpha"
        for _ in range(60):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if worst(mid)[0] <= 1.0 else (lo, mid)
        fits = lo
    return MotionLimit(method, alpha, motion, limit, lam, "(1 + gain) x motion < lambda/8", fits, ratio > 1.0,
                       band_hz)


__all__ = ["MotionLimit", "check_limit", "motion_px", "phase_bands_px", "sample_indices"]
