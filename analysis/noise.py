"""The video's noise floor in metres, measured where nothing moves, and what it means for each mode: the amplitude
a mode needs at the sensors before its video shape can be told from the noise.

Where nothing moves: the motion the accelerometer modes do not explain (the decay fit's residual, every point and
sensor), the points whose motion they do not explain at all (the static background: a floor, a base), and the
timesteps before the impact (t < 0 on the sync grid), where the structure is at rest.

A mode's floor comes from the same fit: with the poles held fixed, its amplitude at a sensor is a linear function
of the samples, so noise of white-equivalent level sigma at the mode's frequency gives it a standard deviation of
sigma times the design matrix's gain for that mode ((A^T A)^-1). A shape whose rms amplitude over the sensors is
x, read with complex noise of rms n at each sensor, has an expected MAC against the exact shape of x^2/(x^2 + n^2).
The floor is where that is FLOOR_MAC = 0.95: FLOOR_SIGMAS = sqrt(0.95 / 0.05) = 4.36 noise standard deviations.
It is set by the MAC verdict (verdict.MIN_MAC = 0.9), which must not fail on noise alone: at 3 sigma (expected MAC
0.9, the floor until 2026-11-26) noise alone put the MAC of an exact shape under 0.9 in 25 % of draws at 4 sensors
and 30 % at 6 (simulated, 20000 draws each), so a perfect video of a mode just above the floor was judged "not met"
one time in four; at 4.36 sigma, 1 % (0.25 % through the decay fit at the demo's record and poles,
tests/analysis/test_noise.py). Below the floor the MAC says nothing about the video.

The same noise says which mode shapes are real within it (`real_modes`): their part out of their common phase is
the noise's, and projecting it away halves the noise's power in them.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from odsplat.spine.errors import InputError

from .ema import mean_phase_rad, pole_freq_hz
from .ods import DecayFit, decay_design

log = logging.getLogger(__name__)

FLOOR_MAC = 0.95        # the MAC the noise allows a mode at the floor (x^2 / (x^2 + n^2))
FLOOR_SIGMAS = float(np.sqrt(FLOOR_MAC / (1 - FLOOR_MAC)))   # 4.36 noise standard deviations
# A mode whose amplitude the decay fit reads with this many times the gain it would have alone (its poles too close
# for the record: the variance inflation of its columns) is not separated from its neighbour: any error of the motion
# that is not white noise (a gain error that drifts, the rest fit's) is amplified as much, and the floor does not
# cover it. The rigs' separated modes read 1.00-1.33; the mast's pair 1.3 Hz apart in a 0.1 s record, 4.7 (with shapes
# 2-3x too large and MAC 0.36-0.68 at 400 px, docs/fidelity.md).
MAX_SEPARATION_GAIN = 2.0
MIN_PRE_IMPACT = 3      # timesteps before the impact needed to measure the noise there
SMOOTH_BINS = 2         # the residual's spectrum is averaged over this many lines either side


@dataclass(frozen=True)
class NoiseFloor:
    """The video's displacement noise (metres, per timestep and component, white-equivalent) and each mode's
    amplitude against the amplitude it needs to stand above it (metres at the sensors, the decay's start)."""

    sigma_m: float                   # at a surface point: the median over points of point_sigma_m
    point_sigma_m: np.ndarray        # (N,) per surface point: rms of the motion the modes do not explain
    sensor_sigma_m: np.ndarray       # (S,) the same at each sensor point, along its direction
    static_sigma_m: float            # rms motion of the points the modes do not explain at all (NaN: none)
    n_static: int
    pre_impact_sigma_m: float        # rms motion before the impact, every point (NaN: fewer than MIN_PRE_IMPACT)
    n_pre_impact: int                # timesteps before the impact
    spectrum_gain: np.ndarray        # (R,) the noise's spectral level at each mode's frequency over its mean
    mode_amplitude_m: np.ndarray     # (R,) each mode's video amplitude: rms over the sensors of 2|C_r|
    mode_floor_m: np.ndarray         # (R,) FLOOR_SIGMAS x the noise's standard deviation of that amplitude
    static: np.ndarray | None = None  # (N,) bool: the points whose motion the modes do not explain at all
    moving: np.ndarray | None = None  # (N,) bool: the points whose modal amplitudes stand above their noise
    separation_gain: np.ndarray | None = None  # (R,) its fit's gain over its gain alone (separation_gains)
    record_needed_s: np.ndarray | None = None  # (R,) the record that separates it (NaN: this one does; inf: none)
    full_field_mac: np.ndarray | None = None   # (R,) the MAC the noise allows its shape over the whole structure
    component_sigma_m: np.ndarray | None = None  # (N, components): point_sigma_m per axis (the views see some worse)

    @property
    def expected_mac(self) -> np.ndarray:
        """(R,) the MAC the noise alone allows each mode's video shape against the exact one: x^2 / (x^2 + n^2), x
        its amplitude and n its noise (the floor over FLOOR_SIGMAS); FLOOR_MAC at the floor. A measured MAC near it is
        as good as the video's noise lets it be."""
        x2 = self.mode_amplitude_m ** 2
        n2 = (self.mode_floor_m / FLOOR_SIGMAS) ** 2
        return x2 / np.maximum(x2 + n2, 1e-300)

    @property
    def below_at_sensors(self) -> np.ndarray:
        """(R,) bool: modes whose video amplitude at the sensors does not stand above the floor there."""
        return self.mode_amplitude_m < self.mode_floor_m

    @property
    def below(self) -> np.ndarray:
        """(R,) bool: modes below the floor at the sensors, or over the full structure (where the noise allows their
        shape a MAC under FLOOR_MAC: full_field_expected_mac), where that is known."""
        if self.full_field_mac is None:
            return self.below_at_sensors
        return self.below_at_sensors | (self.full_field_mac < FLOOR_MAC)

    @property
    def unseparated(self) -> np.ndarray:
        """(R,) bool: modes above the floor that the record cannot separate from a neighbour (MAX_SEPARATION_GAIN):
        their shapes are not judged either."""
        if self.separation_gain is None:
            return np.zeros(len(self.mode_amplitude_m), bool)
        return ~self.below & (self.separation_gain > MAX_SEPARATION_GAIN)

    def point_floor_m(self, design_gain: np.ndarray) -> np.ndarray:
        """(R, N) the amplitude each mode needs at each surface point, from the fit's per-mode gains."""
        return FLOOR_SIGMAS * np.outer(design_gain, self.point_sigma_m)


def _dof_rms(resid: np.ndarray, n_params: int) -> np.ndarray:
    """Per column, the residual's rms with the fitted parameters' degrees of freedom given back."""
    n = resid.shape[0]
    return np.sqrt(np.sum(resid ** 2, axis=0) / max(n - n_params, 1))


def _smooth(p: np.ndarray) -> np.ndarray:
    k = 2 * SMOOTH_BINS + 1
    return np.convolve(np.pad(p, SMOOTH_BINS, mode="edge"), np.ones(k) / k, mode="valid")


def spectrum_shape(resid: np.ndarray, design: np.ndarray, dt_s: float, freq_hz: np.ndarray) -> np.ndarray:
    """The residual's power spectrum at freq_hz against what white noise of the same variance would leave after the
    fit (Hann window, averaged over the channels and SMOOTH_BINS lines either side): 1 for white noise. The fit
    takes out the noise near the poles (the more, the shorter the record), so the residual's own spectrum would
    read the noise low exactly there; the white reference, (I - P) for the fit's projection P, is depleted alike."""
    n = resid.shape[0]
    if n < 8 or resid.shape[1] == 0:
        return np.ones(len(freq_hz))
    w = np.hanning(n)
    p = _smooth(np.mean(np.abs(np.fft.rfft(resid * w[:, None], axis=0)) ** 2, axis=1))
    keep = np.eye(n) - design @ np.linalg.pinv(design)                          # (I - P)
    white = _smooth(np.sum(np.abs(np.fft.rfft(w[:, None] * keep, axis=0)) ** 2, axis=1))
    var = float(np.mean(np.sum(resid ** 2, axis=0))) / max(float(np.trace(keep)), 1.0)
    if not var > 0:
        return np.ones(len(freq_hz))
    ratio = p / np.maximum(white, 1e-12 * float(white.max())) / var
    return np.interp(freq_hz, np.fft.rfftfreq(n, dt_s), ratio)


def design_gains(times_s: np.ndarray, poles_rad_s: np.ndarray, t_min_s: float, offset: bool = True) -> np.ndarray:
    """(R,) per mode, sqrt(var(a_r) + var(b_r)) / sigma for the decay fit's cosine and sine coefficients under
    white noise of unit level: the standard deviation of the amplitude 2|C_r| that noise alone gives a channel."""
    t = np.asarray(times_s, float)
    A = decay_design(t[t >= t_min_s], poles_rad_s, offset=offset)
    cov = np.linalg.pinv(A.T @ A)
    R = len(np.atleast_1d(poles_rad_s))
    d = np.diag(cov)
    return np.sqrt(np.maximum(d[:R] + d[R:2 * R], 0.0))


def separation_gains(times_s: np.ndarray, poles_rad_s: np.ndarray, t_min_s: float) -> np.ndarray:
    """(R,) each mode's design gain in the joint fit over its gain fitted alone: 1 for modes the record separates,
    growing as two poles come closer than about 1 / record in frequency (the square root of the variance inflation)."""
    poles = np.atleast_1d(np.asarray(poles_rad_s, complex))
    joint = design_gains(times_s, poles, t_min_s)
    alone = np.array([design_gains(times_s, poles[r:r + 1], t_min_s)[0] for r in range(len(poles))])
    return joint / np.maximum(alone, 1e-300)


def record_needed_s(times_s: np.ndarray, poles_rad_s: np.ndarray, t_min_s: float,
                    max_gain: float = MAX_SEPARATION_GAIN, longest: float = 64.0) -> np.ndarray:
    """(R,) the record (seconds from t_min_s, at the same time step) over which each mode's separation gain falls to
    max_gain: NaN where this record already does; inf where none up to `longest` times it does (the decay ends
    first: one hit cannot separate them)."""
    t = np.asarray(times_s, float)
    poles = np.atleast_1d(np.asarray(poles_rad_s, complex))
    dt = float(np.median(np.diff(t)))
    span = float(t[-1] - t_min_s)
    out = np.full(len(poles), np.nan)
    todo = separation_gains(t, poles, t_min_s) > max_gain
    if not todo.any() or span <= 0:
        return out

    def gains(k: float) -> np.ndarray:
        return separation_gains(np.arange(t_min_s, t_min_s + k * span + dt / 2, dt), poles, t_min_s)

    lo, hi = 1.0, 2.0
    while hi <= longest and (gains(hi)[todo] > max_gain).any():
        lo, hi = hi, 2 * hi
    for _ in range(12):              # to 1/4096 of the step in record length
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if (gains(mid)[todo] > max_gain).any() else (lo, mid)
    g = gains(hi)
    for r in np.flatnonzero(todo):
        out[r] = hi * span if g[r] <= max_gain and hi <= longest else np.inf
    return out


def full_field_expected_mac(amplitudes: np.ndarray, point_sigma_m: np.ndarray, mode_sd: np.ndarray,
                            real: np.ndarray | None = None, kept: np.ndarray | None = None) -> np.ndarray:
    """(R,) the MAC the noise allows each mode's shape over the whole structure (not only at the sensors), against
    the exact shape: amplitudes (R, N, 3) the fit's complex amplitudes C at the structure's points; point_sigma_m
    (N,) or (N, 3) each point's noise (per axis where given: the views see some axes worse); mode_sd (R,) the
    standard deviation of 2|C| per unit noise (design_gains x the noise's spectrum gain); real (R,) modes projected
    on their phase, which keeps half the noise; kept (R, N, 3) or any shape that broadcasts to it, the components
    the shape keeps (the direction floor drops the others as the noise's, and their noise with them: None, all).

    With the shape's energy E over the kept components and the noise's there N: (E - N) / E, the expected MAC of
    shape + noise against the shape, x^2 / (x^2 + n^2) with x^2 = E - N. A mode large at the sensors but small over
    most of the structure reads lower here. What the direction floor drops counts as noise, as it judges: where it
    held true motion (tests/analysis/test_run.py, whose noise does not follow the cameras), the MAC against the
    whole shape is lower by that motion's share. A shape with no energy left on what it keeps allows 0 (before,
    1: no noise there either, which let three modes of the plate whose every axis the direction floor had dropped
    stand above the floor, judged with nothing to judge)."""
    a = np.asarray(amplitudes)
    R = a.shape[0]
    keep = np.ones(a.shape, bool) if kept is None else np.broadcast_to(np.asarray(kept, bool), a.shape)
    share = np.where(np.asarray(real, bool), 0.5, 1.0) if real is not None else np.ones(R)
    sig = np.asarray(point_sigma_m, float)
    sig = sig[:, None] if sig.ndim == 1 else sig
    var = (sig ** 2)[None] * (np.asarray(mode_sd) ** 2 * share)[:, None, None]                          # (R, N, 3)
    energy = np.sum(np.abs(2 * a) ** 2 * keep, axis=(1, 2))
    noise = np.sum(var * keep, axis=(1, 2))
    # a shape with nothing left (the direction floor dropped every component as the noise's) allows nothing: 0
    return np.where(energy > 0, np.clip(1 - noise / np.maximum(energy, 1e-300), 0.0, 1.0), 0.0)


QUADRATURE_SIGNIFICANT = 1.5  # a mode's energy out of phase, over the noise's there, above which it may be complex
MAX_LOST = 0.02               # the share of a mode's shape (above the noise) that one common phase may leave out


@dataclass(frozen=True)
class RealModes:
    """The video's mode shapes as real (normal) modes: each one real vector times a common complex factor, where
    what lies out of that phase is the noise's. A lightly and proportionally damped structure has real modes; the
    decay fit gives every channel a free phase, so half its noise power lies out of phase, and the projection drops
    it. A mode whose part out of phase stands above the noise (a complex mode: non-proportional damping, or a time
    shift between views) keeps its complex shape."""

    phase_rad: np.ndarray         # (R,) each mode's common phase: its shape's principal direction in the complex plane
    mpc: np.ndarray               # (R,) modal phase collinearity of the complex shape: (|sum z^2| / sum |z|^2)^2
    quadrature_ratio: np.ndarray  # (R,) its energy out of phase over what the noise alone puts there (about 1: noise)
    lost: np.ndarray              # (R,) the share of its energy above the noise that lies out of phase
    real: np.ndarray              # (R,) bool: projected onto its phase

    def apply(self, amplitudes: np.ndarray) -> np.ndarray:
        """(R, M) amplitudes with each real mode's on its common phase: e^(i phase) Re(e^(-i phase) C)."""
        a = np.array(amplitudes, complex)
        ph = np.exp(1j * self.phase_rad[self.real])[:, None]
        a[self.real] = ph * np.real(a[self.real] / ph)
        return a


def real_modes(fit: DecayFit, times_s, channels: np.ndarray, channel_sigma_m: np.ndarray,
               spectrum_gain: np.ndarray | None = None) -> RealModes:
    """Which of a decay fit's modes are real within the noise, and their common phases, judged on `channels` (K,)
    (the structure's: the fit's column indices) with their noise per timestep channel_sigma_m (K,) (white-equivalent;
    spectrum_gain (R,) its level at each mode over the mean, as NoiseFloor has it). The noise a channel's 2C gets
    in phase and out of it is sigma^2 times the fit's (A^T A)^-1 for the mode's cosine and sine terms, turned by the
    phase. A mode stays complex where its energy out of phase exceeds QUADRATURE_SIGNIFICANT x the noise's and the
    excess is more than MAX_LOST of its energy above the noise."""
    t = np.asarray(times_s, float).reshape(-1)
    poles = fit.poles_rad_s
    R = len(poles)
    z = 2 * np.asarray(fit.amplitudes, complex)[:, np.asarray(channels)]          # (R, K)
    sig2 = np.asarray(channel_sigma_m, float) ** 2
    gain = np.ones(R) if spectrum_gain is None else np.asarray(spectrum_gain, float)
    A = decay_design(t[t >= fit.t_min_s], poles)
    cov = np.linalg.pinv(A.T @ A)
    phase = mean_phase_rad(z)                                 # as ModalFit.normal_mode_shapes turns its shapes
    c, s, r = np.cos(phase), np.sin(phase), np.arange(R)
    caa, cbb, cab = cov[r, r], cov[R + r, R + r], cov[r, R + r]
    # 2C = a - ib, so e^(-i phase) 2C = (a c - b s) - i (a s + b c): the noise's energy in phase and out of it
    e_in = gain * np.sum(sig2) * (c * c * caa + s * s * cbb - 2 * c * s * cab)
    e_out = gain * np.sum(sig2) * (s * s * caa + c * c * cbb + 2 * c * s * cab)
    w = z * np.exp(-1j * phase)[:, None]
    p_in, p_out = np.sum(w.real ** 2, axis=1), np.sum(w.imag ** 2, axis=1)
    energy = p_in + p_out
    mpc = np.where(energy > 0, (np.abs(np.sum(z ** 2, axis=1)) / np.maximum(energy, 1e-300)) ** 2, 1.0)
    ratio = p_out / np.maximum(e_out, 1e-300)
    signal = energy - e_in - e_out
    lost = np.where(signal > 0, np.maximum(p_out - e_out, 0.0) / np.maximum(signal, 1e-300), 0.0)
    real = ~((ratio > QUADRATURE_SIGNIFICANT) & (lost > MAX_LOST))
    log.info("video mode shapes: MPC %s; out of phase / noise %s; real: %s", np.round(mpc, 3), np.round(ratio, 2),
             real.astype(int))
    return RealModes(phase, mpc, ratio, lost, real)


MOVING_FALSE_ALARM = 1e-3   # the chance that a point of noise alone is taken for a moving one


def moving_points(amplitudes: np.ndarray, gains: np.ndarray, point_sigma_m: np.ndarray, components: int = 3,
                  false_alarm: float = MOVING_FALSE_ALARM) -> np.ndarray:
    """(N,) bool: the points whose fitted modal amplitudes (amplitudes (R, N * components), the decay fit's C)
    stand above what their own noise (point_sigma_m, per unit design gain `gains` (R,)) would give. Under noise
    alone, sum over modes and components of |2C|^2 / (sd^2 / 2) is chi-square with 2 R components degrees of
    freedom; a point moves when it passes that distribution's 1 - false_alarm quantile."""
    from scipy.stats import chi2

    R = amplitudes.shape[0]
    a2 = np.abs(2 * np.asarray(amplitudes)) ** 2                                        # (R, N * c)
    sd2 = (np.asarray(gains, float)[:, None] * np.repeat(np.asarray(point_sigma_m, float), components)[None]) ** 2
    stat = np.sum(2 * a2 / np.maximum(sd2, 1e-300), axis=0).reshape(-1, components).sum(axis=1)
    return stat > chi2.ppf(1 - false_alarm, 2 * R * components)


def noise_floor(times_s, sensors_m, surface_m, fit: DecayFit, *, point_components: int = 3) -> NoiseFloor:
    """The noise floor of the motion a decay fit was made to: sensors_m (T, S) and surface_m (T, N * components),
    the fit's channels in that order (as `video_modes` fits them in one solve)."""
    t = np.asarray(times_s, float).reshape(-1)
    xs = np.asarray(sensors_m, float).reshape(len(t), -1)
    xp = np.asarray(surface_m, float).reshape(len(t), -1)
    S = xs.shape[1]
    if fit.amplitudes.shape[1] != S + xp.shape[1]:
        raise InputError("noise_floor: fit", f"expected a fit of {S + xp.shape[1]} channels (the sensors, then the "
                         f"surface); got {fit.amplitudes.shape[1]}")
    if xp.shape[1] % point_components:
        raise InputError("noise_floor: surface_m", f"expected {point_components} components per point")
    use = t >= fit.t_min_s
    poles = fit.poles_rad_s
    n_params = 2 * len(poles) + 1
    model = fit.synthesize(t[use])
    resid_s = xs[use] - model[:, :S]
    resid_p = xp[use] - model[:, S:]
    sensor_sigma = _dof_rms(resid_s, n_params)
    comp = _dof_rms(resid_p, n_params).reshape(-1, point_components)
    point_sigma = np.sqrt(np.mean(comp ** 2, axis=1))
    # the static background: points whose motion the modes do not explain beyond chance (adjusted r2 <= 0)
    n = int(use.sum())
    ss_res = np.sum(resid_p ** 2, axis=0).reshape(-1, point_components).sum(axis=1)
    dev = xp[use] - xp[use].mean(axis=0)
    ss_tot = np.sum(dev ** 2, axis=0).reshape(-1, point_components).sum(axis=1)
    r2_adj = 1 - (ss_res / np.maximum(ss_tot, 1e-300)) * (n - 1) / max(n - n_params, 1)
    static = r2_adj <= 0
    raw = np.sqrt(np.sum(dev ** 2, axis=0).reshape(-1, point_components).sum(axis=1)
                  / (point_components * max(n - 1, 1)))
    static_sigma = float(np.median(raw[static])) if static.any() else float("nan")
    pre = t < 0
    pre_sigma = float("nan")
    if pre.sum() >= MIN_PRE_IMPACT:
        d = xp[pre] - xp[pre].mean(axis=0)
        pre_sigma = float(np.median(np.sqrt(np.sum(d ** 2, axis=0).reshape(-1, point_components).sum(axis=1)
                                            / (point_components * (pre.sum() - 1)))))
    # each mode's floor at the sensors: the noise's level at its frequency through the fit's gain for it
    dt = float(np.median(np.diff(t)))
    design = decay_design(t[use], poles)
    gain = spectrum_shape(resid_p if resid_p.shape[1] else resid_s, design, dt, pole_freq_hz(poles))
    sd = design_gains(t, poles, fit.t_min_s) * np.sqrt(gain)                       # (R,) per unit sigma
    floor = FLOOR_SIGMAS * sd * float(np.sqrt(np.mean(sensor_sigma ** 2)))
    amplitude = np.sqrt(np.mean(np.abs(2 * fit.amplitudes[:, :S]) ** 2, axis=1))
    out = NoiseFloor(float(np.median(point_sigma)) if len(point_sigma) else float(np.median(sensor_sigma)),
                     point_sigma, sensor_sigma, static_sigma, int(static.sum()), pre_sigma, int(pre.sum()),
                     gain, amplitude, floor, static,
                     moving_points(fit.amplitudes[:, S:], design_gains(t, poles, fit.t_min_s), point_sigma,
                                   point_components),
                     separation_gains(t, poles, fit.t_min_s), record_needed_s(t, poles, fit.t_min_s),
                     component_sigma_m=comp)
    log.info("video noise floor: %.3g um per point (static points %.3g um, %d; before the impact %.3g um), "
             "%.3g um at the sensors; modes below it: %s", 1e6 * out.sigma_m, 1e6 * static_sigma, out.n_static,
             1e6 * pre_sigma, 1e6 * float(np.median(sensor_sigma)),
             ", ".join(f"{f:.1f} Hz" for f in pole_freq_hz(poles)[out.below]) or "none")
    if out.unseparated.any():
        log.info("modes the record cannot separate: %s", ", ".join(
            f"{f:.1f} Hz (gain x{g:.1f})" for f, g in zip(pole_freq_hz(poles)[out.unseparated],
                                                            out.separation_gain[out.unseparated])))
    return out
