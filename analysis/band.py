"""What the FRFs themselves say about where to fit: the band the hammer excited, and the clear resonance peaks.

The default fit band follows the DAQ: from a few frequency lines up to where the hammer's force spectrum has
fallen `FORCE_DROP_DB` below its low-frequency level (the usual rule for impact testing: above it the force no
longer excites the structure well enough for a trustworthy FRF), and never above 0.4 x the DAQ's sample rate.
The clear peaks check the automatic pole selection: a clear peak with no pole near it, or a strong peak the
band leaves out, is said in the result, never passed over in silence.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import find_peaks

from odsplat.spine.errors import InputError

from .frf import FRFResult

FORCE_DROP_DB = 20.0        # the band ends where the force spectrum is this far below its level at low frequency
MAX_FRACTION_OF_RATE = 0.4  # ... and at most at this fraction of the DAQ's sample rate (anti-aliasing filters)
MIN_LINES = 3               # the band starts this many frequency lines above 0 Hz
PEAK_PROMINENCE_DB = 10.0   # a clear peak stands this far above the valleys either side of it
PEAK_COHERENCE = 0.9        # ... with at least this coherence around it
PEAK_HEIGHT_DB = 20.0       # ... and within this of the band's highest clear peak
CUT_PEAK_DB = 10.0          # a peak outside the band is reported when within this of the band's highest peak
PEAK_FORCE_DB = 40.0        # no peak counts where the force is further down than this (the FRF is noise there)


@dataclass(frozen=True)
class FRFPeak:
    freq_hz: float
    height_db: float        # relative to the highest clear peak in the range searched
    prominence_db: float
    coherence: float


def force_db(frf: FRFResult) -> np.ndarray:
    """The hammer's force spectrum in dB against its low-frequency level (the median over the lowest 1 % of the
    lines, at least 3 lines); 0 everywhere when that level is unknown."""
    f, s = frf.freq_hz, np.asarray(frf.force_spectrum, float)
    low = (f > 0) & (f <= max(0.01 * f[-1], 3 * (f[1] - f[0]) if len(f) > 1 else 0.0))
    if not low.any() or not np.isfinite(s[low]).any() or not np.nanmedian(s[low]) > 0:
        return np.zeros(len(f))
    ratio = np.where(np.isfinite(s), s, 0.0) / float(np.nanmedian(s[low]))
    return 20 * np.log10(np.maximum(ratio, 1e-15))


def force_band_hz(frf: FRFResult, drop_db: float = FORCE_DROP_DB) -> float:
    """The frequency where the hammer's force spectrum first falls drop_db below its low-frequency level, or the
    FRF's last line if it never does."""
    f = frf.freq_hz
    below = np.flatnonzero((f > 0) & (force_db(frf) < -drop_db))
    return float(f[below[0]]) if len(below) else float(f[-1])


def default_band_hz(frf: FRFResult) -> tuple[float, float]:
    """The fit band when none is given: MIN_LINES lines up to the force's band, at most 0.4 x the DAQ rate."""
    df = float(frf.freq_hz[1] - frf.freq_hz[0]) if len(frf.freq_hz) > 1 else 0.0
    fmax = min(force_band_hz(frf), MAX_FRACTION_OF_RATE * frf.sample_rate_hz, float(frf.freq_hz[-1]))
    return MIN_LINES * df, fmax


def _magnitude_db(frf: FRFResult) -> np.ndarray:
    """The FRFs' magnitudes in one curve (dB): each output scaled to unit rms, then their rms, so every output
    counts whatever its level; NaN lines (not excited) count as the floor."""
    h = np.abs(np.asarray(frf.h1)).reshape(len(frf.freq_hz), -1)
    h = np.where(np.isfinite(h), h, 0.0)
    rms = np.sqrt(np.mean(h ** 2, axis=0))
    h = h / np.where(rms > 0, rms, 1.0)
    mag = np.sqrt(np.mean(h ** 2, axis=1))
    return 20 * np.log10(np.maximum(mag, 1e-12 * max(float(mag.max()), 1e-300)))


def frf_peaks(frf: FRFResult, fmin_hz: float, fmax_hz: float, *, prominence_db: float = PEAK_PROMINENCE_DB,
              min_coherence: float = PEAK_COHERENCE, height_db: float | None = PEAK_HEIGHT_DB) -> list[FRFPeak]:
    """The clear resonance peaks of the FRFs in fmin_hz..fmax_hz, highest first: prominent, coherent, where the
    hammer still excites (force within PEAK_FORCE_DB of its level) and (unless height_db is None) within
    height_db of the highest of them. With one hit the coherence is 1 by construction and checks nothing."""
    if not fmax_hz > fmin_hz:
        raise InputError("frf_peaks", f"expected fmin_hz < fmax_hz; got {fmin_hz:g} and {fmax_hz:g}")
    f = frf.freq_hz
    db = _magnitude_db(frf)
    coh = np.asarray(frf.coherence, float).reshape(len(f), -1)
    coh = np.nanmean(np.where(np.isfinite(coh), coh, 0.0), axis=1)
    idx, props = find_peaks(db, prominence=prominence_db)
    excited = force_db(frf) >= -PEAK_FORCE_DB
    rows = []
    for i, prom in zip(idx, props["prominences"]):
        if not fmin_hz <= f[i] <= fmax_hz or not excited[i]:
            continue
        c = float(np.median(coh[max(i - 2, 0):i + 3]))
        if c >= min_coherence:
            rows.append((float(f[i]), float(db[i]), float(prom), c))
    if not rows:
        return []
    top = max(r[1] for r in rows)
    peaks = [FRFPeak(fr, h - top, p, c) for fr, h, p, c in rows]
    if height_db is not None:
        peaks = [p for p in peaks if p.height_db >= -height_db]
    return sorted(peaks, key=lambda p: -p.height_db)


def unmatched_peaks(peaks: list[FRFPeak], freq_hz: np.ndarray, df_hz: float, tol: float = 0.005) -> list[FRFPeak]:
    """The peaks with no mode within tol (relative) or 3 lines of them, whichever is wider."""
    freq_hz = np.asarray(freq_hz, float)
    return [p for p in peaks
            if not len(freq_hz) or np.min(np.abs(freq_hz - p.freq_hz)) > max(tol * p.freq_hz, 3 * df_hz)]
