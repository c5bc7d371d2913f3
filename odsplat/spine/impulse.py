"""Hammer pulses in a force record: how many there are, and where each starts, to a fraction of a sample.

The one definition of the impact onset, used by every stage: the acquisition stage's hit QC (impacts and
their times), sync (the onset every take is locked to) and the analysis (each hit's windows and segments) all
take it from `fit_pulse`. An impact hammer's pulse is close to a half sine, F(t) = A sin(pi (t - t0) / tau) for
t0 <= t <= t0 + tau; fitting that shape to the samples around the peak gives the onset t0 far finer
than a sample, and the fit's residual says how well the shape held.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import find_peaks

from odsplat.spine.errors import InputError


def find_impacts(force_n: np.ndarray, *, fraction: float = 0.05, min_peak_n: float = 0.0) -> np.ndarray:
    """Sample indices of the impacts in a force record: peaks that stand out by `fraction` of the largest.

    Two half-sine pulses that do not overlap leave a dip to zero between them, so even a rebound right
    after the first pulse (1 ms apart for 1 ms pulses) stands out by its full height.
    """
    f = np.nan_to_num(np.asarray(force_n, float), nan=0.0)
    peak = f.max(initial=0.0)
    if peak <= min_peak_n:
        return np.array([], int)
    idx, _ = find_peaks(np.concatenate([[0.0], f, [0.0]]), height=max(min_peak_n, fraction * peak),
                        prominence=fraction * peak)
    return idx - 1


@dataclass(frozen=True)
class PulseFit:
    """One hammer pulse. Times are in samples of the record given (fractional) and in seconds from its sample 0."""

    onset_sample: float      # where the force starts to rise
    onset_s: float
    peak_n: float
    duration_s: float
    impulse_n_s: float       # the integral of the force over the pulse
    residual: float          # rms misfit of the half sine, relative to the peak (0: a perfect half sine)
    method: str              # "half_sine" or "threshold" (when the fit failed)


def half_sine(t: np.ndarray, onset: float, peak: float, duration: float) -> np.ndarray:
    s = np.asarray(t, float) - onset
    return np.where((s >= 0) & (s <= duration), peak * np.sin(np.pi * np.clip(s, 0.0, duration) / duration), 0.0)


def fit_pulse(force_n: np.ndarray, sample_rate_hz: float, *, peak_index: int | None = None,
              source: str = "force") -> PulseFit:
    """Fit a half sine to the pulse around `peak_index` (default: the largest sample).

    The window spans the pulse and one pulse length of quiet either side; other pulses outside it do not
    matter. Falls back to the threshold crossing at 10 % of the peak, moved back to the onset along the
    half sine, when the fit does not converge (method "threshold").
    """
    f = np.nan_to_num(np.asarray(force_n, float), nan=0.0)
    if f.ndim != 1 or f.size < 4:
        raise InputError(source, f"expected a 1-D force record of at least 4 samples, got shape {f.shape}")
    if sample_rate_hz <= 0:
        raise InputError(source, f"sample rate must be positive, got {sample_rate_hz}")
    i_peak = int(np.argmax(f)) if peak_index is None else int(peak_index)
    peak = float(f[i_peak])
    if peak <= 0:
        raise InputError(source, "no positive force pulse to fit")
    # The pulse's extent: where the force falls below 5 % of the peak on either side.
    lo = i_peak
    while lo > 0 and f[lo - 1] > 0.05 * peak:
        lo -= 1
    hi = i_peak
    while hi < f.size - 1 and f[hi + 1] > 0.05 * peak:
        hi += 1
    width = hi - lo + 1
    a, b = max(0, lo - width - 2), min(f.size, hi + width + 3)
    t = np.arange(a, b, dtype=float)
    y = f[a:b]
    half = y >= 0.5 * peak
    w_half = max(float(np.count_nonzero(half)), 1.0)
    tau0 = 1.5 * w_half  # a half sine is above half its peak for 2/3 of its length
    x0 = np.array([i_peak - tau0 / 2, peak, tau0])
    thresh = _threshold_onset(f, i_peak, 0.1 * peak, tau0)

    def resid(x: np.ndarray) -> np.ndarray:
        return (half_sine(t, *x) - y) / peak

    try:
        sol = least_squares(resid, x0, x_scale=np.array([1.0, peak, tau0]), method="lm")
        onset, amp, tau = (float(v) for v in sol.x)
        ok = sol.success and tau > 0.5 and amp > 0 and abs(onset - thresh) < max(2.0, 0.5 * tau0)
    except (ValueError, np.linalg.LinAlgError):
        ok = False
    if ok:
        res = float(np.sqrt(np.mean(resid(sol.x) ** 2)))
        method = "half_sine"
    else:
        onset, amp, tau = thresh, peak, tau0
        res = float(np.sqrt(np.mean(resid(np.array([onset, amp, tau])) ** 2)))
        method = "threshold"
    impulse = float(np.trapezoid(f[max(0, lo - 1):hi + 2])) / sample_rate_hz
    return PulseFit(onset, onset / sample_rate_hz, amp, tau / sample_rate_hz, impulse, res, method)


def impact_onsets(force_n: np.ndarray, sample_rate_hz: float, *, fraction: float = 0.05,
                  min_peak_n: float = 0.0) -> list[PulseFit]:
    """Every impact in a force record (`find_impacts`), each fitted (`fit_pulse`): its onset, peak and impulse."""
    f = np.nan_to_num(np.asarray(force_n, float), nan=0.0)
    return [fit_pulse(f, sample_rate_hz, peak_index=int(i)) for i in find_impacts(f, fraction=fraction,
                                                                                   min_peak_n=min_peak_n)]


def _threshold_onset(f: np.ndarray, i_peak: int, level: float, tau: float) -> float:
    """The rising crossing of `level` before the peak (interpolated), moved back along a half sine of length tau."""
    i = i_peak
    while i > 0 and f[i - 1] >= level:
        i -= 1
    if i == 0:
        return 0.0
    frac = (level - f[i - 1]) / (f[i] - f[i - 1])
    crossing = i - 1 + frac
    return crossing - tau / np.pi * np.arcsin(min(1.0, level / f[i_peak]))


__all__ = ["PulseFit", "find_impacts", "fit_pulse", "half_sine", "impact_onsets"]
