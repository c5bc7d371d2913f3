"""Band-limited fractional delay of short records (the DAQ's impulse fit): a frequency-domain phase shift along
time; and the regular counter run that dropped frames leave gaps in. The frames' own delay and gap filling are
AlignedTake's (aligned.py), computed as they are read.

A record is mirrored before the FFT (x, then x reversed), so its two ends meet without a jump and the
shift does not ring where the record starts at rest and stops mid-vibration.
"""
from __future__ import annotations

import numpy as np


def fractional_shift(x: np.ndarray, shift: float, axis: int = 0) -> np.ndarray:
    """y[n] = x(n + shift) for a band-limited x sampled at n = 0..N-1 (|shift| up to a sample or two)."""
    x = np.asarray(x)
    n = x.shape[axis]
    if n < 2 or shift == 0.0:
        return x.astype(np.result_type(x.dtype, np.float32), copy=True)
    ext = np.concatenate([x, np.flip(x, axis=axis)], axis=axis).astype(np.float64)
    m = 2 * n
    spec = np.fft.rfft(ext, axis=axis)
    k = np.arange(spec.shape[axis])
    phase = np.exp(2j * np.pi * k * shift / m)
    phase[-1] = np.cos(np.pi * shift)  # the Nyquist bin of a real, even-length signal stays real
    shape = [1] * x.ndim
    shape[axis] = -1
    y = np.fft.irfft(spec * phase.reshape(shape), n=m, axis=axis)
    return np.take(y, np.arange(n), axis=axis)


def fill_dropped(counters: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The regular counter run covering `counters`, and where each stored frame sits in it."""
    c = np.asarray(counters, int)
    full = np.arange(c.min(), c.max() + 1)
    return full, c - c.min()


__all__ = ["fill_dropped", "fractional_shift"]
