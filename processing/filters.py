"""Temporal band-pass filters that stream: push frames (or any per-frame representation) in chunks
along axis 0, get the filtered values out, with the state carried between chunks.

Kinds (`make_filter`):
- `ideal`: the brick-wall band, realised as a linear-phase FIR whose frequency response samples the
  ideal band exactly (frequency-sampling design over `taps` frames); zero phase after its delay;
- `fir`: a Hamming-windowed linear-phase band-pass FIR (`scipy.signal.firwin`); zero phase after its delay;
- `butter`: a Butterworth band-pass (second-order sections), causal, no delay, some phase lag;
- `diff_iir`: the difference of two first-order low-passes (Wadhwa et al. 2013, Oh et al. 2018), causal;
- `none`: identity.

A filter with `delay_frames = D` returns, for the n-th frame pushed, the filtered value of frame n - D
(zeros for the first D). Callers pair the output with the input frame D back.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.signal import butter, firwin

from odsplat.spine.errors import InputError

KINDS = ("ideal", "fir", "butter", "diff_iir", "none")


class TemporalFilter:
    """Base: identity. Subclasses keep their state in tensors shaped like one frame."""

    kind = "none"
    delay_frames = 0
    min_frames = 1

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return x

    def reset(self) -> None:
        pass


class FIRFilter(TemporalFilter):
    """Linear-phase FIR over a history of the last taps-1 frames."""

    def __init__(self, taps: np.ndarray, kind: str):
        self.kind = kind
        self._h = torch.as_tensor(np.asarray(taps, np.float64))
        self.delay_frames = (len(taps) - 1) // 2
        self.min_frames = len(taps)
        self._hist: torch.Tensor | None = None

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        n_taps = len(self._h)
        if self._hist is None:
            self._hist = torch.zeros((n_taps - 1, *x.shape[1:]), dtype=x.dtype, device=x.device)
        buf = torch.cat([self._hist, x], dim=0)
        t = x.shape[0]
        # y[n] = sum_k h[k] x[n - k], with buf[j] = x[j - (taps - 1)]: one shifted slice per tap, so the working
        # memory is one output's worth whatever the length of the filter.
        y = torch.zeros_like(x)
        for k, hk in enumerate(self._h.tolist()):
            if hk:
                y.add_(buf[n_taps - 1 - k:n_taps - 1 - k + t], alpha=hk)
        self._hist = buf[-(n_taps - 1):].clone() if n_taps > 1 else buf[:0]
        return y

    def reset(self) -> None:
        self._hist = None


class SOSFilter(TemporalFilter):
    """Cascaded biquads (direct form II transposed), state per section."""

    kind = "butter"

    def __init__(self, sos: np.ndarray):
        self._sos = np.asarray(sos, np.float64)
        self._z: list[torch.Tensor] | None = None
        self.min_frames = 4 * len(self._sos)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self._z is None:
            self._z = [torch.zeros((2, *x.shape[1:]), dtype=x.dtype, device=x.device) for _ in self._sos]
        y = x
        for s, (b0, b1, b2, _a0, a1, a2) in enumerate(self._sos):
            z = self._z[s]
            out = torch.empty_like(y)
            for n in range(y.shape[0]):
                xn = y[n]
                yn = b0 * xn + z[0]
                z0 = b1 * xn - a1 * yn + z[1]
                z1 = b2 * xn - a2 * yn
                z = torch.stack([z0, z1])
                out[n] = yn
            self._z[s] = z
            y = out
        return y

    def reset(self) -> None:
        self._z = None


class DiffIIRFilter(TemporalFilter):
    """Two first-order low-passes, y = lp(r_high) - lp(r_low): a cheap, causal band-pass."""

    kind = "diff_iir"

    def __init__(self, r_low: float, r_high: float):
        self.r_low, self.r_high = r_low, r_high
        self._lo: torch.Tensor | None = None
        self._hi: torch.Tensor | None = None
        self.min_frames = 2

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.empty_like(x)
        if self._lo is None:
            self._lo, self._hi = x[0].clone(), x[0].clone()
        lo, hi = self._lo, self._hi
        for n in range(x.shape[0]):
            hi = (1 - self.r_high) * hi + self.r_high * x[n]
            lo = (1 - self.r_low) * lo + self.r_low * x[n]
            out[n] = hi - lo
        self._lo, self._hi = lo, hi
        return out

    def reset(self) -> None:
        self._lo = self._hi = None


def check_band(low_hz: float, high_hz: float, fps: float, *, source: str = "--band") -> None:
    if not fps > 0:
        raise InputError(source, f"the frame rate must be positive, got {fps}")
    if not 0 < low_hz < high_hz < fps / 2:
        raise InputError(source, f"expected 0 < low < high < fps/2 = {fps / 2:g} Hz; got {low_hz:g} to {high_hz:g} Hz")


def make_filter(kind: str, fps: float, low_hz: float | None = None, high_hz: float | None = None, *,
                order: int = 2, taps: int | None = None) -> TemporalFilter:
    """A fresh streaming filter. FIR lengths default to three periods of the band's low edge (odd)."""
    if kind not in KINDS:
        raise InputError("temporal filter", f"expected one of {KINDS}, got {kind!r}")
    if kind == "none":
        return TemporalFilter()
    if low_hz is None or high_hz is None:
        raise InputError("--band", f"the {kind} filter needs a band LOW HIGH in Hz")
    check_band(low_hz, high_hz, fps)
    if kind in ("ideal", "fir"):
        n = taps or int(math.ceil(3 * fps / low_hz))
        n += 1 - n % 2  # odd: a whole-frame delay
        if kind == "fir":
            h = firwin(n, [low_hz, high_hz], pass_zero=False, fs=fps)
        else:
            # Frequency sampling: the ideal band at the n DFT frequencies, made real, even and causal.
            f = np.fft.fftfreq(n, 1.0 / fps)
            band = ((np.abs(f) >= low_hz) & (np.abs(f) <= high_hz)).astype(float)
            h = np.fft.fftshift(np.real(np.fft.ifft(band)))
        return FIRFilter(h, kind)
    if kind == "butter":
        return SOSFilter(butter(order, [low_hz, high_hz], btype="bandpass", fs=fps, output="sos"))
    # diff_iir: the first-order low-passes' cut-offs at the band's edges.
    r = [1.0 - math.exp(-2 * math.pi * f / fps) for f in (low_hz, high_hz)]
    return DiffIIRFilter(r[0], r[1])


__all__ = ["KINDS", "TemporalFilter", "check_band", "make_filter"]
