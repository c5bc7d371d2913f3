"""Frame times from image evidence, when no exposure strobe was recorded.

The camera's trigger frame pins counter 0's exposure start to within about a frame. The images pin it
much finer. For small motion every pixel's intensity change is linear in the structure's displacement,
so the frames' changes from the rest image span the same few time signals as the structure's modal
coordinates; the strongest of them (`motion_components`) are found from every textured pixel at once.
The accelerometers, integrated twice, measure displacements of that same structure on the DAQ's clock
(`DisplacementBasis`). Shifting the frame times until the image signals are best explained by the DAQ
displacements (`fit_frame_times`) is a multi-channel cross-correlation, and it also dates the motion
onset against the hammer's.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.integrate import cumulative_trapezoid

from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImageTiming:
    """Counter 0's exposure start (DAQ time) found from the images, and how well it is determined."""

    frame0_start_s: float
    sigma_frames: float        # one standard deviation, from the misfit's curvature
    motion_z: float            # the frames' change beyond noise, in standard deviations of pure noise's
    n_basis: int               # DAQ displacement signals (and a constant) the pixels were fitted with
    onset_counter: int | None  # the first frame whose motion stands clear of the noise
    flags: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


class DisplacementBasis:
    """The accelerometers' displacements, averaged over each exposure, at any exposure start time (DAQ time)."""

    def __init__(self, accel_m_s2: np.ndarray, sample_rate_hz: float, t0_s: float, hit_time_s: float,
                 exposure_s: float):
        a = np.atleast_2d(np.asarray(accel_m_s2, float))
        n = a.shape[1]
        fs = float(sample_rate_hz)
        rest = max(8, int((hit_time_s - t0_s) * fs) - 4)  # samples before the hit: the sensors' offsets
        if rest >= n:
            raise InputError("accelerometers", "the record ends before the hit")
        a = np.array([_fill_nan(x) for x in a])
        a -= a[:, :rest].mean(axis=1, keepdims=True)
        a[:, :rest] = 0.0  # at rest before the hit: integrating noise there only adds drift
        v = cumulative_trapezoid(a, dx=1.0 / fs, axis=1, initial=0.0)
        d = cumulative_trapezoid(v, dx=1.0 / fs, axis=1, initial=0.0)
        self._cum = np.concatenate([np.zeros((d.shape[0], 1)), np.cumsum(d, axis=1)], axis=1) / fs  # integral of d
        # The integral's knots: sample k covers [t_k - dt/2, t_k + dt/2].
        self._t = t0_s + np.arange(n + 1) / fs - 0.5 / fs
        self.exposure_s = float(exposure_s)
        self.n_channels = d.shape[0]

    @classmethod
    def from_take(cls, reader, hit_time_s: float, exposure_s: float) -> DisplacementBasis | None:
        """From a take's accelerometer channels (kind 'acceleration'); None when it has none."""
        accels = reader.channels_of_kind("acceleration")
        if not accels:
            return None
        return cls(np.stack([reader.channel(a) for a in accels]), reader.sample_rate_hz, reader.daq_t0_s,
                   hit_time_s, exposure_s)

    def __call__(self, start_s: np.ndarray) -> np.ndarray:
        """(N, n_channels): mean displacement over [start, start + exposure] for each start time."""
        s = np.asarray(start_s, float)
        lo = np.stack([np.interp(s, self._t, c) for c in self._cum], axis=1)
        hi = np.stack([np.interp(s + self.exposure_s, self._t, c) for c in self._cum], axis=1)
        return (hi - lo) / self.exposure_s


def _fill_nan(x: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(x)
    if bad.any() and (~bad).any():
        x = x.copy()
        x[bad] = np.interp(np.flatnonzero(bad), np.flatnonzero(~bad), x[~bad])
    return np.nan_to_num(x)


def noise_sd(rest_mean: np.ndarray, rest_var: np.ndarray, n_rest: int) -> np.ndarray:
    """Each pixel's temporal noise, from a straight-line fit of variance against brightness over all pixels.

    A handful of rest frames gives each pixel a poor variance of its own; shot plus read noise follows
    variance = read + gain * brightness, which every pixel helps to fit."""
    m = rest_mean.ravel().astype(np.float64)
    v = rest_var.ravel().astype(np.float64)
    edges = np.unique(np.quantile(m, np.linspace(0, 1, 33)))
    which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, max(len(edges) - 2, 0))
    xs, ys = [], []
    for b in range(max(len(edges) - 1, 1)):
        sel = which == b
        if sel.sum() >= 20:
            xs.append(m[sel].mean())
            ys.append(np.median(v[sel]) / _chi2_median_ratio(n_rest - 1))
    if len(xs) >= 2:
        gain, read = np.polyfit(xs, ys, 1)
    else:
        gain, read = 0.0, float(np.median(v))
    var = read + max(gain, 0.0) * rest_mean.astype(np.float64)
    floor = max(float(np.median(v)) * 1e-3, 1e-6)
    return np.sqrt(np.maximum(var, floor))


def _chi2_median_ratio(dof: int) -> float:
    """median(chi2_dof) / dof: a sample variance's median lies below the true variance by this factor."""
    from scipy.stats import chi2
    return float(chi2.median(max(dof, 1)) / max(dof, 1))


@dataclass(frozen=True)
class MotionGram:
    """The frames' changes from rest, in units of each pixel's noise, as their Gram matrix over frames (N, N).

    Pure noise adds `n_pixels` to each diagonal entry; motion adds the rest."""

    gram: np.ndarray
    n_pixels: int


def motion_gram(blocks: Iterable[np.ndarray], n_frames: int, rest_image: np.ndarray, rest_sd: np.ndarray, *,
                max_memory_bytes: float = 256e6) -> MotionGram:
    """Stream the frames once; keep the pixels that change most per pixel of motion (as many as memory allows)."""
    ref = rest_image.astype(np.float32)
    sd = rest_sd.astype(np.float32)
    gray = ref if ref.ndim == 2 else ref.mean(axis=2)
    sd_gray = sd if sd.ndim == 2 else sd.mean(axis=2)
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3) / 8
    weight = np.hypot(gx, gy) / sd_gray  # intensity change per pixel of motion, in noise units
    n_ch = 1 if ref.ndim == 2 else ref.shape[2]
    n_keep = int(min(weight.size, max(1000, max_memory_bytes // (4 * n_ch * max(n_frames, 1)))))
    order = np.argsort(weight.ravel())[::-1][:n_keep]
    flat_ref = ref.reshape(weight.size, -1)[order]
    flat_sd = sd.reshape(weight.size, -1)[order]
    D = np.empty((n_frames, flat_ref.size), np.float32)
    k = 0
    for block in blocks:
        b = block.reshape(block.shape[0], weight.size, -1)[:, order].astype(np.float32)
        D[k:k + len(b)] = ((b - flat_ref) / flat_sd).reshape(len(b), -1)
        k += len(b)
    if k != n_frames:
        raise InputError("frames", f"expected {n_frames} frames, read {k}")
    gram = D.astype(np.float64) @ D.T.astype(np.float64)
    return MotionGram(gram, int(flat_ref.size))


def fit_frame_times(motion: MotionGram, counters: np.ndarray, period_s: float, basis: DisplacementBasis,
                    prior_start_s: float, *, search_frames: float = 1.5, step_frames: float = 0.02,
                    rest: np.ndarray | None = None, hit_time_s: float | None = None) -> ImageTiming:
    """Counter 0's exposure start: the shift within +-search_frames of `prior_start_s` at which the DAQ
    displacements explain the image motion best.

    Every pixel's change is fitted by its own mix of the DAQ displacements (and a constant); the misfit
    summed over pixels is trace(G) - trace(Q' G Q), Q an orthonormal basis of those time signals, so
    only the Gram matrix G is needed."""
    G = motion.gram
    counters = np.asarray(counters, float)
    ones = np.ones((len(counters), 1))

    def captured(shift: float) -> float:
        B = np.hstack([basis(prior_start_s + (counters + shift) * period_s), ones])
        Q, _ = np.linalg.qr(B)
        return float(np.einsum("ij,jk,ik->", Q.T, G, Q.T))

    shifts = np.arange(-search_frames, search_frames + 1e-9, step_frames)
    J = -np.array([captured(s) for s in shifts])
    i = int(np.argmin(J))
    flags: list[str] = []
    notes: list[str] = []
    if i in (0, len(J) - 1):
        flags.append("image_fit_at_window_edge")
        notes.append(f"the best shift lies at the edge of the +-{search_frames:g} frame search window")
        best = shifts[i]
    else:
        a, b, c = J[i - 1], J[i], J[i + 1]
        curv = a - 2 * b + c
        best = shifts[i] + (0.5 * step_frames * (a - c) / curv if curv > 0 else 0.0)
    h = 0.1
    j0 = -captured(best)
    curv = (-captured(best - h) - 2 * j0 - captured(best + h)) / h ** 2
    total = float(np.trace(G))
    n, rank = len(counters), basis.n_channels + 1
    s2 = (total + j0) / max(1.0, motion.n_pixels * (n - rank))  # residual variance per pixel and frame
    sigma = float(np.sqrt(2 * s2 / curv)) if curv > 0 else float("inf")
    # Pure noise energy per frame, from the rest frames (their mean is the rest image: they hold 1 - 1/k of it).
    energy = np.diag(G)
    k = int(rest.sum()) if rest is not None else 0
    noise = float(energy[rest].mean() / (1 - 1 / k)) if k >= 2 else motion.n_pixels * s2
    expected = np.full(n, noise * (1 + 1 / k) if k else noise)
    if k:
        expected[rest] = noise * (1 - 1 / k)
    # How clearly the images see motion at all: the energy above noise, in standard deviations of pure noise's.
    motion_z = (total - float(expected.sum())) / float(np.sqrt(np.sum(2.0 * expected ** 2 / motion.n_pixels)))
    onset = _motion_onset(energy, counters, expected)
    start = prior_start_s + best * period_s
    if onset is not None and hit_time_s is not None:
        end_of_onset = start + onset * period_s + basis.exposure_s
        if end_of_onset < hit_time_s - 0.5 * period_s:
            flags.append("motion_before_hit")
            notes.append(f"the images move {(hit_time_s - end_of_onset) / period_s:.2f} frame(s) before the hammer hit")
    return ImageTiming(start, sigma, float(motion_z), rank, onset, tuple(flags), tuple(notes))


def _motion_onset(energy: np.ndarray, counters: np.ndarray, expected: np.ndarray) -> int | None:
    """The counter of the first of three frames in a row whose change stands 6 sigma above pure noise
    (`expected`, per frame: a chi-square with that many degrees of freedom has sd sqrt(2 expected))."""
    above = energy > expected + 6.0 * np.sqrt(2.0 * expected)
    for k in range(len(energy) - 2):
        if above[k] and above[k + 1] and above[k + 2]:
            return int(counters[k])
    return None


__all__ = ["DisplacementBasis", "ImageTiming", "MotionGram", "fit_frame_times", "motion_gram", "noise_sd"]
