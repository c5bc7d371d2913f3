"""Hammer pulses in a force record: how many there are, where each starts (to a fraction of a sample), whether
the hammer hit twice. The one rule of every stage, `ImpactDetector` with its `ImpactSettings`.

The acquisition stage's hit QC (impacts and their times), sync (the onset every take is locked to) and the analysis
(the FRF's hit check, `split_hits`' segments, each hit's windows) all count impacts, find double hits and take each
onset here. An impact hammer's pulse is close to a half sine, F(t) = A sin(pi (t - t0) / tau) for
t0 <= t <= t0 + tau; fitting that shape to the samples around the peak (`fit_pulse`) gives the onset t0 far finer
than a sample, and the fit's residual says how well the shape held.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.signal import find_peaks

from odsplat.spine.checks import MAX_FORCE_N, Range, check_fields
from odsplat.spine.errors import InputError

REBOUND_FRACTION = 0.05
"""The default `ImpactSettings.rebound_fraction`: a second pulse that stands 5 % of the largest peak above the dip
before it is an impact, so a rebound (a double hit). Every stage's default is this one constant: hit QC, sync, the
FRF's hit check and split_hits (an `ImpactSettings()` reads it when it is made)."""

# The extent of a pulse: the samples above this fraction of the largest peak and this many noise sigmas. The
# pretrigger (baseline and noise) ends _PRE_GUARD samples before the first of them (the rise may begin below the
# level); an impact's end is walked on from its last one down to _END_SIGMAS noise sigmas.
_EXTENT_FRACTION = 0.05
_EXTENT_SIGMAS = 5.0
_END_SIGMAS = 3.0
_PRE_GUARD = 2


def _rebound_fraction() -> float:
    return REBOUND_FRACTION  # read when settings are made: the one constant moves every stage's default


@dataclass(frozen=True)
class ImpactSettings:
    """What counts as an impact in a force record, for every stage. A pulse is an impact when it passes all three
    thresholds below; more than one impact is a double hit. Forces are over the record's baseline.

    rebound_fraction: a pulse must stand this fraction (dimensionless, between 0 and 1) of the record's largest
        peak above the baseline and above the dip between it and the larger pulse beside it (its prominence).
        Default: REBOUND_FRACTION.
    noise_sigmas: ... and this many noise sigmas (dimensionless; sigma, in N, is the scaled MAD of the pretrigger),
        so that noise, on a record with no hit or on a weak one, is never an impact. 0: no noise floor.
    min_peak_n: ... and its peak must reach this force (N). 0: no floor.
    """

    rebound_fraction: float = field(default_factory=_rebound_fraction)
    noise_sigmas: float = 10.0
    min_peak_n: float = 0.0

    def __post_init__(self) -> None:
        check_fields(self, {"rebound_fraction": Range(above=0, below=1),
                            "noise_sigmas": Range(at_least=0, at_most=1000),
                            "min_peak_n": Range(at_least=0, at_most=MAX_FORCE_N)})


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


# ---------------------------------------------------------------------------------------------- impacts

@dataclass(frozen=True)
class Impacts:
    """The impacts in one force record, in time order. Indices are samples of the record (onsets fractional);
    forces are over its baseline (N)."""

    pulses: tuple[PulseFit, ...]     # each impact's half sine (`fit_pulse`): onset, peak, duration, impulse
    peak_indices: tuple[int, ...]    # each impact's largest sample
    heights_n: tuple[float, ...]     # ... and the force there
    end_indices: tuple[float, ...]   # where each impact's force is back at the baseline
    baseline_n: float                # the force's offset: the pretrigger's median (the record's where that is short)
    noise_n: float                   # the force's noise, one sigma (the scaled MAD)
    peak_n: float                    # the record's largest force
    floor_n: float                   # the least peak that is a hit: min_peak_n or noise_sigmas sigmas, the larger

    @property
    def n(self) -> int:
        return len(self.pulses)

    @property
    def double_hit(self) -> bool:
        """More than one impact: the hammer hit twice (a rebound), and no single onset stands for the take."""
        return len(self.pulses) > 1

    @property
    def main(self) -> int:
        """Which impact is the largest (the record must hold one)."""
        return int(np.argmax(self.heights_n))


@dataclass(frozen=True)
class ImpactDetector:
    """The one rule for a force record's impacts (`ImpactSettings`): how many, each one's onset (`fit_pulse`, on
    the force less its baseline) and end, and so whether the hammer hit twice.

    The baseline and noise are the median and MAD of the pretrigger, the samples before the force first rises
    over 5 % of its largest peak (of the whole record where fewer than 4). Two half-sine pulses that do not
    overlap leave a dip to the baseline between them, so even a rebound right after the first pulse (1 ms apart
    for 1 ms pulses) stands out by its full height. Lost samples (NaN) count as the baseline."""

    settings: ImpactSettings = field(default_factory=ImpactSettings)

    def baseline(self, force_n: ArrayLike) -> tuple[float, float]:
        """(baseline, noise sigma) of a force record, in N."""
        f = np.asarray(force_n, float)
        finite = np.isfinite(f)
        if not finite.any():
            return 0.0, 0.0
        med, sigma = _median_mad(f[finite])
        g = np.where(finite, f - med, 0.0)
        first = int(np.argmax(g > max(_EXTENT_FRACTION * float(g.max()), _EXTENT_SIGMAS * sigma)))
        pre = f[:max(first - _PRE_GUARD, 0)]
        pre = pre[np.isfinite(pre)]
        if pre.size < 4:
            return med, sigma
        base, sigma_pre = _median_mad(pre)
        return base, max(sigma, sigma_pre)

    def peak_indices(self, force_n: ArrayLike) -> np.ndarray:
        """The impacts' sample indices (their largest samples), without fitting them."""
        g, _, sigma = self._less_baseline(force_n)
        return self._peaks(g, sigma)[0]

    def detect(self, force_n: ArrayLike, sample_rate_hz: float, *, source: str = "force") -> Impacts:
        """Every impact of a force record (1-D, N), each fitted; `source` names the record in errors."""
        f = np.asarray(force_n, float)
        if f.ndim != 1:
            raise InputError(source, f"expected a 1-D force record, got shape {f.shape}")
        if not sample_rate_hz > 0:
            raise InputError(source, f"sample rate must be positive, got {sample_rate_hz}")
        g, base, sigma = self._less_baseline(f)
        idx, floor = self._peaks(g, sigma)
        peak = float(g.max(initial=0.0))
        pulses = tuple(fit_pulse(g, sample_rate_hz, peak_index=int(i), source=source) for i in idx)
        off = max(_EXTENT_FRACTION * peak, _EXTENT_SIGMAS * sigma)
        ends = []
        for i in idx:
            below = np.flatnonzero(g[i:] < off)
            stop = int(i) + max(int(below[0]), 1) if below.size else g.size
            ends.append(_pulse_end(g, stop - 1, _END_SIGMAS * sigma))
        return Impacts(pulses, tuple(int(i) for i in idx), tuple(float(g[i]) for i in idx), tuple(ends), base, sigma,
                       peak, floor)

    def _less_baseline(self, force_n: ArrayLike) -> tuple[np.ndarray, float, float]:
        f = np.asarray(force_n, float)
        base, sigma = self.baseline(f)
        return np.nan_to_num(f - base, nan=0.0), base, sigma

    def _peaks(self, g: np.ndarray, sigma: float) -> tuple[np.ndarray, float]:
        """(indices of the impacts in g, the force less its baseline; the least peak that is a hit)."""
        s = self.settings
        floor = max(s.min_peak_n, s.noise_sigmas * sigma)
        peak = float(g.max(initial=0.0))
        if peak <= floor or peak <= 0:
            return np.array([], int), floor
        need = max(s.rebound_fraction * peak, s.noise_sigmas * sigma)
        # Zeros either side: a pulse cut by the record's end still has a base to stand out from.
        idx, _ = find_peaks(np.concatenate([[0.0], g, [0.0]]), height=max(need, s.min_peak_n), prominence=need)
        return idx - 1, floor


def find_impacts(force_n: ArrayLike) -> np.ndarray:
    """Sample indices of the impacts in a force record, by the default rule (`ImpactDetector`)."""
    return ImpactDetector(ImpactSettings()).peak_indices(force_n)


def impact_onsets(force_n: ArrayLike, sample_rate_hz: float) -> list[PulseFit]:
    """Every impact in a force record by the default rule (`ImpactDetector`), each fitted (`fit_pulse`): its onset,
    peak and impulse."""
    return list(ImpactDetector(ImpactSettings()).detect(force_n, sample_rate_hz).pulses)


def _pulse_end(g: np.ndarray, i: int, level: float) -> float:
    """From sample i on a pulse's falling flank, walk on while the force keeps falling and stays above `level`,
    then extrapolate the last two samples to zero force."""
    n = g.size
    while i + 1 < n and level < g[i + 1] < g[i]:
        i += 1
    if i < 1 or g[i - 1] <= g[i]:
        return float(i)
    return float(i + np.clip(g[i] / (g[i - 1] - g[i]), 0.0, 1.0))


def _median_mad(a: np.ndarray) -> tuple[float, float]:
    """Median and the MAD scaled to a Gaussian sigma: baseline and noise, blind to a few outliers."""
    med = float(np.median(a))
    return med, 1.4826 * float(np.median(np.abs(a - med)))


__all__ = ["REBOUND_FRACTION", "ImpactDetector", "ImpactSettings", "Impacts", "PulseFit", "find_impacts", "fit_pulse",
           "half_sine", "impact_onsets"]
