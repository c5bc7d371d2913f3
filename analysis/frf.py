"""Frequency response functions from impact-hammer tests: per-hit checks, force and exponential windows,
and H1/H2/coherence averaged over hits, with the damping the exponential window adds taken back out."""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from odsplat.spine.checks import DURATION_S, FORCE_N, FREQUENCY_HZ, Range, check_fields, maybe
from odsplat.spine.errors import InputError
from odsplat.spine.impulse import ImpactDetector, ImpactSettings

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------- windows

def force_window(n_samples: int, sample_rate_hz: float, onset_index: float, width_s: float,
                 taper_s: float | None = None, lead_s: float | None = None) -> np.ndarray:
    """The force (transient) window: 1 from `lead_s` before the onset to `width_s` after it, then a
    half-cosine taper of `taper_s` down to 0, and 0 elsewhere. It removes the noise the force channel
    records once the pulse is over. Defaults: taper and lead of half the width each."""
    _check_positive("force_window: sample_rate_hz", sample_rate_hz)
    width_s = _check_positive("force_window: width_s", width_s)
    taper_s = _check_positive("force_window: taper_s", 0.5 * width_s if taper_s is None else taper_s, True)
    lead_s = _check_positive("force_window: lead_s", 0.5 * width_s if lead_s is None else lead_s, True)
    s = (np.arange(int(n_samples)) - float(onset_index)) / sample_rate_hz
    w = ((s >= -lead_s) & (s <= width_s)).astype(float)
    if taper_s > 0:
        in_taper = (s > width_s) & (s < width_s + taper_s)
        w[in_taper] = 0.5 * (1.0 + np.cos(np.pi * (s[in_taper] - width_s) / taper_s))
    return w


def exponential_window(n_samples: int, sample_rate_hz: float, start_index: int = 0,
                       end_value: float = 0.01) -> tuple[np.ndarray, float]:
    """w = 1 up to `start_index`, then exp(-(t - t_start) / tau_s), with tau_s such that the last sample is
    `end_value`. Returns (window, tau_s). The window adds 1/tau_s to every pole's decay rate: see correct_poles."""
    _check_positive("exponential_window: sample_rate_hz", sample_rate_hz)
    if not 0.0 < end_value < 1.0:
        raise InputError("exponential_window: end_value", f"expected 0 < end_value < 1; got {end_value}")
    if not 0 <= start_index < n_samples - 1:
        raise InputError("exponential_window: start_index",
                         f"expected 0 <= start_index < n_samples - 1 = {n_samples - 1}; got {start_index}")
    tau_s = (n_samples - 1 - start_index) / sample_rate_hz / np.log(1.0 / end_value)
    return _exp_window(n_samples, sample_rate_hz, start_index, tau_s), float(tau_s)


def _exp_window(n_samples: int, sample_rate_hz: float, start_index: int, tau_s: float) -> np.ndarray:
    t = (np.arange(n_samples) - start_index) / sample_rate_hz
    return np.exp(-np.clip(t, 0.0, None) / tau_s)


def correct_poles(poles_rad_s: ArrayLike, tau_s: float) -> np.ndarray:
    """Poles of the unwindowed structure from poles fitted to exponentially windowed data.

    Convention: lambda = -zeta*wn + i*wn*sqrt(1 - zeta^2) (decaying modes have Re < 0). The window
    multiplies every free decay exp(lambda t) by exp(-t / tau_s), so the fitted poles are lambda - 1/tau_s;
    this returns poles + 1/tau_s (real part less negative; imaginary part, the damped frequency, unchanged)."""
    _check_positive("correct_poles: tau_s", tau_s)
    return np.asarray(poles_rad_s, complex) + 1.0 / tau_s


def correct_damping(freq_hz: ArrayLike, damping: ArrayLike, tau_s: float) -> np.ndarray:
    """Damping ratios of the unwindowed structure from (natural frequency, damping ratio) measured on
    exponentially windowed data: zeta_true ~= zeta - 1/(tau_s wn) for light damping (exact through the
    poles, see correct_poles). A negative result means the window, not the structure, set the decay."""
    f = np.asarray(freq_hz, float)
    z = np.asarray(damping, float)
    if np.any(f <= 0) or not np.all(np.isfinite(f)):
        raise InputError("correct_damping: freq_hz", "expected finite natural frequencies > 0")
    if np.any(np.abs(z) >= 1) or not np.all(np.isfinite(z)):
        raise InputError("correct_damping: damping", "expected damping ratios between -1 and 1")
    wn = 2 * np.pi * f
    lam = correct_poles(-z * wn + 1j * wn * np.sqrt(1 - z**2), tau_s)
    out = -lam.real / np.abs(lam)
    if np.any(out < 0):
        log.warning("correct_damping: %d damping ratio(s) < 0 after the window correction; the window's "
                    "decay dominated (use a longer record or a larger exponential end value)", int(np.sum(out < 0)))
    return out


# ------------------------------------------------------------------------------------------ hit checks

@dataclass(frozen=True)
class HitCheck:
    """The quality of one hammer hit. Indices are samples of the record checked (fractional)."""

    accepted: bool
    reasons: tuple[str, ...]     # why it was rejected; empty when accepted
    peak_n: float                # above the baseline
    onset_index: float           # where the first impact's force starts to rise
    end_index: float             # where the last impact's force has returned to the baseline
    pulse_width_s: float         # of the first impact
    n_impacts: int
    baseline_n: float            # force offset: the pretrigger's median (the record's if that is short)


def check_frf_hit(force: ArrayLike, sample_rate_hz: float, *, overload_n: float | None = None,
                  full_scale_n: float | None = None, impacts: ImpactSettings | None = None,
                  reject_double_hits: bool = True, responses: ArrayLike | None = None,
                  response_full_scale: float | None = None, output_names: Sequence[str] | None = None) -> HitCheck:
    """Check one hit (force record (n_samples,), optional responses (n_outputs, n_samples)).

    The impacts, their onsets and the baseline are every stage's (`odsplat.spine.impulse.ImpactDetector` with
    `impacts`, default `ImpactSettings()`): more than one impact is a double hit, none a record with no pulse
    above the noise. Rejected also: a peak over `overload_n`, force samples at or over `full_scale_n` (clipped)
    and response samples at or over `response_full_scale` (in the response's unit)."""
    f = _as_finite(force, "check_frf_hit: force", ndim=1)
    _check_positive("check_frf_hit: sample_rate_hz", sample_rate_hz)
    reasons: list[str] = []
    if full_scale_n is not None and (n_clip := int(np.sum(np.abs(f) >= full_scale_n))):
        reasons.append(f"clipped: {n_clip} samples at full scale ({full_scale_n:g} N)")
    if responses is not None and response_full_scale is not None:
        x = _as_finite(responses, "check_frf_hit: responses", ndim=2)
        for k, row in enumerate(x):
            if n_over := int(np.sum(np.abs(row) >= response_full_scale)):
                name = output_names[k] if output_names is not None else f"output {k}"
                reasons.append(f"response overload: {name} has {n_over} samples at or over {response_full_scale:g}")

    found = ImpactDetector(impacts or ImpactSettings()).detect(f, sample_rate_hz, source="check_frf_hit: force")
    peak = found.peak_n
    if not found.n:
        reasons.append(f"no impact: peak {peak:.3g} N is within the noise (sigma {found.noise_n:.3g} N, "
                       f"floor {found.floor_n:.3g} N)")
        return HitCheck(False, tuple(reasons), peak, np.nan, np.nan, np.nan, 0, found.baseline_n)
    onsets = [p.onset_sample for p in found.pulses]
    main = found.main
    for k, height in enumerate(found.heights_n if reject_double_hits else ()):
        if k != main:
            dt_ms = (onsets[k] - onsets[main]) / sample_rate_hz * 1e3
            reasons.append(f"double hit at {dt_ms:+.1f} ms ({100 * height / peak:.0f} % of the peak)")
    if overload_n is not None and peak > overload_n:
        reasons.append(f"overload: peak {peak:.0f} N > {overload_n:g} N")
    return HitCheck(not reasons, tuple(reasons), peak, onsets[0], found.end_indices[-1],
                    float(found.end_indices[0] - onsets[0]) / sample_rate_hz, found.n, found.baseline_n)


# -------------------------------------------------------------------------------------------- the FRF

@dataclass(frozen=True)
class FRFSettings:
    """How estimate_frf windows, checks and averages the hits.

    force_window_s: length of the force window after the onset; None: 3 x the longest accepted pulse (first
        impact's onset to last impact's end), at least 2 ms, so the pulse and its filter ringing pass whole.
    exponential_end: value of the response window at the last sample; None: rectangular (no window).
    fmax_hz: keep lines up to this frequency; n_fft: FFT length (>= n_samples, zero padded).
    impacts: what counts as an impact, so a double hit, in each hit's force (`odsplat.spine.impulse.ImpactSettings`,
        every stage's rule; its rebound fraction defaults to `odsplat.spine.impulse.REBOUND_FRACTION`).
    """

    force_window_s: float | None = None
    exponential_end: float | None = 0.01
    fmax_hz: float | None = None
    n_fft: int | None = None
    reject_double_hits: bool = True
    impacts: ImpactSettings = field(default_factory=ImpactSettings)  # what an impact is (odsplat.spine.impulse)
    overload_n: float | None = None
    full_scale_n: float | None = None
    response_full_scale: float | None = None

    def __post_init__(self) -> None:
        # n_fft: 2**24 lines hold 10 minutes at 25.6 kHz; response_full_scale is in the response's unit (a shock
        # accelerometer's 1e5 g is 1e6 m/s^2).
        check_fields(self, {
            "force_window_s": maybe(DURATION_S), "exponential_end": maybe(Range(above=0, below=1)),
            "fmax_hz": maybe(FREQUENCY_HZ), "n_fft": maybe(Range(at_least=1, at_most=2**24, integer=True)),
            "overload_n": maybe(FORCE_N),
            "full_scale_n": maybe(FORCE_N), "response_full_scale": maybe(Range(above=0, at_most=1e7))},
            name="estimate_frf: settings")


@dataclass(frozen=True)
class FRFResult:
    """H1, H2 and coherence of one input to several outputs, averaged over hits; arrays are (F,) or (F, n_out).

    force_spectrum (N/Hz = N s) and response_spectrum (output_unit/Hz) are the rms over hits of |X(f)| / fs,
    the Fourier transform of the windowed signals (a half-sine pulse of peak A and length T reads 2AT/pi at 0 Hz)."""

    freq_hz: np.ndarray
    h1: np.ndarray
    h2: np.ndarray
    coherence: np.ndarray
    force_spectrum: np.ndarray
    response_spectrum: np.ndarray
    input_name: str
    output_names: tuple[str, ...]
    output_unit: str
    sample_rate_hz: float
    n_samples: int
    n_averages: int
    hits: tuple[HitCheck, ...]
    exp_tau_s: float | None
    force_window_s: float
    input_unit: str = "N"

    def h(self, estimator: str = "H1") -> np.ndarray:
        key = estimator.upper()
        if key not in ("H1", "H2"):
            raise InputError("FRFResult.h: estimator", f"expected 'H1' or 'H2'; got {estimator!r}")
        return self.h1 if key == "H1" else self.h2

    def to_receptance(self) -> FRFResult:
        """The FRF with displacement output (m): accelerance / (iw)^2, mobility / (iw); the 0 Hz line is 0."""
        power = {"m/s^2": 2, "m/s": 1, "m": 0}.get(self.output_unit)
        if power is None:
            raise InputError("FRFResult.output_unit",
                             f"expected 'm/s^2', 'm/s' or 'm' to convert to receptance; got {self.output_unit!r}")
        if power == 0:
            return self
        iw = (2j * np.pi * self.freq_hz)[:, None] ** power
        scale = np.divide(1.0, iw, out=np.zeros_like(iw), where=iw != 0)
        return replace(self, h1=self.h1 * scale, h2=self.h2 * scale,
                       response_spectrum=self.response_spectrum * np.abs(scale), output_unit="m")

    def select(self, fmin_hz: float, fmax_hz: float) -> FRFResult:
        """The lines with fmin_hz <= f <= fmax_hz."""
        keep = (self.freq_hz >= fmin_hz) & (self.freq_hz <= fmax_hz)
        if not keep.any():
            raise InputError("FRFResult.select", f"no lines in {fmin_hz:g} to {fmax_hz:g} Hz "
                             f"(the FRF spans {self.freq_hz[0]:g} to {self.freq_hz[-1]:g} Hz)")
        return replace(self, freq_hz=self.freq_hz[keep], h1=self.h1[keep], h2=self.h2[keep],
                       coherence=self.coherence[keep], force_spectrum=self.force_spectrum[keep],
                       response_spectrum=self.response_spectrum[keep])


def estimate_frf(force: ArrayLike, responses: ArrayLike, sample_rate_hz: float,
                 settings: FRFSettings | None = None, *, input_name: str = "force",
                 output_names: Sequence[str] | None = None, output_unit: str = "m/s^2") -> FRFResult:
    """H1 = Gfx/Gff, H2 = Gxx/Gxf and coherence |Gfx|^2/(Gff Gxx), the spectra averaged over accepted hits.

    force: (n_hits, n_samples) or (n_samples,) in N; responses: (n_hits, n_outputs, n_samples),
    (n_outputs, n_samples) or (n_samples,) for a single hit. Each hit is checked (check_frf_hit); rejected hits
    stay out of the averages. Each hit's windows follow its own onset: the force window around its pulse,
    and the exponential window from the onset on (the pretrigger is untouched), applied to the force as well
    as the responses, so the FRF is that of the structure with every pole's decay rate raised by 1/exp_tau_s
    (correct_poles, correct_damping). All hits share one tau, from the latest onset. The force's baseline
    (pretrigger median) is removed first. With one hit the coherence is 1 by construction. `settings`: default
    `FRFSettings()`.
    """
    f, x = _hits_arrays(force, responses)
    n_hits, n_out, n = x.shape
    _check_positive("estimate_frf: sample_rate_hz", sample_rate_hz)
    s = settings or FRFSettings()
    n_fft = n if s.n_fft is None else int(s.n_fft)
    if n_fft < n:
        raise InputError("estimate_frf: settings.n_fft", f"expected >= n_samples = {n}; got {n_fft}")
    if s.exponential_end is not None and not 0 < s.exponential_end < 1:
        raise InputError("estimate_frf: settings.exponential_end", f"expected 0 < end < 1; got {s.exponential_end}")
    if s.fmax_hz is not None and not 0 < s.fmax_hz <= sample_rate_hz / 2:
        raise InputError("estimate_frf: settings.fmax_hz", f"expected 0 < fmax <= {sample_rate_hz / 2:g} Hz "
                         f"(Nyquist); got {s.fmax_hz}")
    names = tuple(output_names) if output_names is not None else tuple(f"output {k}" for k in range(n_out))
    if len(names) != n_out:
        raise InputError("estimate_frf: output_names", f"expected {n_out} names; got {len(names)}")

    checks = tuple(check_frf_hit(f[h], sample_rate_hz, overload_n=s.overload_n, full_scale_n=s.full_scale_n,
                                 impacts=s.impacts, reject_double_hits=s.reject_double_hits, responses=x[h],
                                 response_full_scale=s.response_full_scale, output_names=names)
                   for h in range(n_hits))
    good = [h for h, c in enumerate(checks) if c.accepted]
    for h, c in enumerate(checks):
        if not c.accepted:
            log.warning("estimate_frf: hit %d rejected: %s", h, "; ".join(c.reasons))
    if not good:
        raise InputError("estimate_frf: force", "every hit was rejected: " + "; ".join(
            f"hit {h}: {', '.join(c.reasons)}" for h, c in enumerate(checks)))

    if s.force_window_s is None:
        longest_s = max((checks[h].end_index - checks[h].onset_index) / sample_rate_hz for h in good)
        width_s = max(3.0 * longest_s, 2e-3)  # see FRFSettings
    else:
        width_s = _check_positive("estimate_frf: settings.force_window_s", s.force_window_s)
    tau_s = None
    if s.exponential_end is not None:
        latest = max(int(np.floor(checks[h].onset_index)) for h in good)
        tau_s = exponential_window(n, sample_rate_hz, latest, s.exponential_end)[1]

    spec_f = np.empty((len(good), n_fft // 2 + 1), complex)
    spec_x = np.empty((len(good), n_out, n_fft // 2 + 1), complex)
    for a, h in enumerate(good):
        c = checks[h]
        w_exp = (np.ones(n) if tau_s is None
                 else _exp_window(n, sample_rate_hz, int(np.floor(c.onset_index)), tau_s))
        w_force = force_window(n, sample_rate_hz, c.onset_index, width_s) * w_exp
        spec_f[a] = np.fft.rfft((f[h] - c.baseline_n) * w_force, n_fft)
        spec_x[a] = np.fft.rfft(x[h] * w_exp, n_fft, axis=-1)

    freq = np.fft.rfftfreq(n_fft, 1.0 / sample_rate_hz)
    keep = freq <= (s.fmax_hz if s.fmax_hz is not None else np.inf)
    spec_f, spec_x, freq = spec_f[:, keep], spec_x[:, :, keep], freq[keep]
    g_ff = np.mean(np.abs(spec_f) ** 2, axis=0)[:, None]                       # (F, 1)
    g_xx = np.mean(np.abs(spec_x) ** 2, axis=0).T                             # (F, n_out)
    g_fx = np.mean(np.conj(spec_f)[:, None, :] * spec_x, axis=0).T            # (F, n_out)
    return FRFResult(
        freq_hz=freq, h1=_divide(g_fx, g_ff), h2=_divide(g_xx, np.conj(g_fx)),
        coherence=_divide(np.abs(g_fx) ** 2, g_ff * g_xx).real,
        force_spectrum=np.sqrt(g_ff[:, 0]) / sample_rate_hz, response_spectrum=np.sqrt(g_xx) / sample_rate_hz,
        input_name=input_name, output_names=names, output_unit=output_unit, sample_rate_hz=float(sample_rate_hz),
        n_samples=n, n_averages=len(good), hits=checks, exp_tau_s=tau_s, force_window_s=width_s)


def _divide(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a / b, NaN where b is 0 (a line the force did not excite)."""
    a, b = np.broadcast_arrays(a.astype(complex), b.astype(complex))
    return np.divide(a, b, out=np.full(a.shape, np.nan, complex), where=b != 0)


def _hits_arrays(force: ArrayLike, responses: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Force as (n_hits, n_samples) and responses as (n_hits, n_outputs, n_samples), checked."""
    f = _as_finite(force, "estimate_frf: force")
    x = _as_finite(responses, "estimate_frf: responses")
    f = f[None] if f.ndim == 1 else f
    if f.ndim != 2:
        raise InputError("estimate_frf: force", f"expected shape (n_hits, n_samples) or (n_samples,); got {f.shape}")
    if x.ndim == 1:
        x = x[None, None]
    elif x.ndim == 2:
        if f.shape[0] != 1:
            raise InputError("estimate_frf: responses", f"shape {x.shape} is one hit of (n_outputs, n_samples), "
                             f"but force has {f.shape[0]} hits; pass (n_hits, n_outputs, n_samples)")
        x = x[None]
    if x.ndim != 3:
        raise InputError("estimate_frf: responses", "expected shape (n_hits, n_outputs, n_samples), "
                         f"(n_outputs, n_samples) or (n_samples,); got {x.shape}")
    if x.shape[0] != f.shape[0] or x.shape[2] != f.shape[1]:
        raise InputError("estimate_frf: responses", f"expected ({f.shape[0]}, n_outputs, {f.shape[1]}) to match "
                         f"force {f.shape}; got {x.shape}")
    if f.shape[1] < 16 or x.shape[1] < 1:
        raise InputError("estimate_frf: responses", f"expected one output or more, 16 samples or more; got {x.shape}")
    return f, x


# --------------------------------------------------------------------------- hits in a continuous record

@dataclass(frozen=True)
class HitSegments:
    """Hits cut from one continuous record, ready for estimate_frf."""

    force: np.ndarray          # (n_hits, n_samples), N
    responses: np.ndarray      # (n_hits, n_outputs, n_samples)
    start_index: np.ndarray    # (n_hits,) first sample of each segment in the record
    sample_rate_hz: float
    n_impacts: np.ndarray      # (n_hits,) impacts in each hit (odsplat.spine.impulse): 2 or more, a double hit


def split_hits(force: ArrayLike, responses: ArrayLike, sample_rate_hz: float, pretrigger_s: float,
               length_s: float, min_gap_s: float | None = None, impacts: ImpactSettings | None = None) -> HitSegments:
    """Find every impact in a continuous record (force (n,), responses (n_outputs, n) or (n,)) and cut
    `length_s` from `pretrigger_s` before each hit's onset. The impacts and onsets are every stage's
    (`odsplat.spine.impulse.ImpactDetector` with `impacts`, default `ImpactSettings()`; the largest peak is the
    record's). Impacts within `min_gap_s` (default `length_s`) of the last hit's onset belong to that hit (its
    `n_impacts`), so a double hit stays in one segment for check_frf_hit to find. Hits whose segment would run
    off either end of the record are skipped (and logged)."""
    f = _as_finite(force, "split_hits: force", ndim=1)
    x = _as_finite(responses, "split_hits: responses")
    x = x[None] if x.ndim == 1 else x
    if x.ndim != 2 or x.shape[1] != f.size:
        raise InputError("split_hits: responses", f"expected shape (n_outputs, {f.size}) or ({f.size},); got {x.shape}")
    fs = _check_positive("split_hits: sample_rate_hz", sample_rate_hz)
    n_pre = int(round(_check_positive("split_hits: pretrigger_s", pretrigger_s, allow_zero=True) * fs))
    n_len = int(round(_check_positive("split_hits: length_s", length_s) * fs))
    if n_len <= n_pre:
        raise InputError("split_hits: length_s", f"expected longer than the pretrigger ({pretrigger_s:g} s)")
    gap = n_len if min_gap_s is None else int(round(_check_positive("split_hits: min_gap_s", min_gap_s) * fs))
    found = ImpactDetector(impacts or ImpactSettings()).detect(f, fs, source="split_hits: force")
    if not found.n:
        raise InputError("split_hits: force", f"no impact found (largest force {found.peak_n:.3g} N over the "
                         f"baseline, noise sigma {found.noise_n:.3g} N)")
    hits: list[list[float]] = []   # each hit's impact onsets
    for p in found.pulses:
        if hits and p.onset_sample - hits[-1][0] < gap:
            hits[-1].append(p.onset_sample)
        else:
            hits.append([p.onset_sample])
    starts, counts = [], []
    for hit in hits:
        onset = hit[0]
        start = int(round(onset)) - n_pre
        if start < 0 or start + n_len > f.size:
            log.warning("split_hits: skipped the hit at %.4f s: its segment (%d samples from %d) runs off the "
                        "record of %d samples", onset / fs, n_len, start, f.size)
        else:
            starts.append(start)
            counts.append(len(hit))
    if not starts:
        raise InputError("split_hits: length_s", f"found {len(hits)} hit(s), but none has {pretrigger_s:g} s "
                         f"before and {length_s - pretrigger_s:g} s after its onset inside the record")
    idx = np.asarray(starts)[:, None] + np.arange(n_len)
    return HitSegments(f[idx], np.moveaxis(x[:, idx], 0, 1), np.asarray(starts), fs, np.asarray(counts))


# ------------------------------------------------------------------------------------------- helpers

def _as_finite(a: ArrayLike, source: str, ndim: int | None = None) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(source, f"expected a float array; {exc}") from None
    if ndim is not None and arr.ndim != ndim:
        raise InputError(source, f"expected a {ndim}-D array; got shape {arr.shape}")
    if arr.size == 0:
        raise InputError(source, "expected samples; got an empty array")
    if not np.all(np.isfinite(arr)):
        raise InputError(source, f"{int(np.sum(~np.isfinite(arr)))} non-finite values (NaN or inf)")
    return arr


def _check_positive(source: str, value: float, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = np.nan
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(source, f"expected a finite value {'>= 0' if allow_zero else '> 0'}; got {value}")
    return v
