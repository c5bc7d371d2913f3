"""Output-only (operational) modal analysis from response time series alone, with no measured force: frequency-domain
decomposition (FDD), covariance-driven stochastic subspace identification (SSI-cov), a stabilisation chart and mode
picking (ema.py's), operational deflection shapes at any line and each channel's white-noise level.

x is (T, C): T samples of C channels (any unit: the spectra are in that unit^2/Hz), sampled at fs_hz; the channel
order is kept throughout. Poles are in rad/s as in ema.py, lambda = -zeta wn + 1j wn sqrt(1 - zeta^2).
Everything is deterministic: the same input gives bitwise the same output.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.signal import butter, find_peaks, get_window, hilbert, sosfiltfilt
from scipy.stats import chi2, kurtosis

from odsplat.spine.errors import InputError

from .ema import (
    PolesAtOrder,
    StabilisationChart,
    mean_phase_rad,
    pole_damping,
    pole_freq_hz,
    select_poles,
    stabilisation,
)

log = logging.getLogger(__name__)

MIN_SAMPLES = 64          # the shortest record accepted
MAX_NPERSEG = 4096        # fdd()'s longest default segment: finer lines only make a long record's spectrum noisier
N_SV = 4                  # singular values kept per line by fdd()
MAX_DAMPING = 0.2         # poles at or above this damping ratio are not physical (dropped by ssi_cov)
MAX_REFS = 12             # ssi_cov's default references: all channels up to this many, else principal components
MAX_ORDER = 60            # identify()'s default largest model order (state dimension: 30 mode pairs)
MIN_LAGS = 20             # ssi_cov's fewest block rows by default
FREQ_TOL = 0.01           # stabilisation: relative frequency change between orders
DAMPING_TOL = 0.1         # relative damping change (SSI's damping wanders more from order to order than LSCF's)
MAC_TOL = 0.02            # 1 - MAC between the shapes of consecutive orders
MIN_STABLE = 0.4          # a mode: stable poles in at least this share of the orders
PEAK_PROMINENCE = 0.5     # an FDD peak: the first singular value stands this many decades above its surroundings
NOISE_LINES = 16          # identify() takes the noise above the highest mode too where it holds this many lines
HARMONIC_KURTOSIS = 2.0   # a mode's band-passed modal coordinate flatter than this is a harmonic (a sine: 1.5)
HARMONIC_TREND = 0.25      # ... and whose envelope's log changes by less than this over the record (a line fitted to
#                           it): a lightly damped mode's free decay is flat too (kurtosis 1.92 for hil_sim's 23.5 Hz
#                           over 0.5 s) but its envelope falls (-0.48); a steady sine's holds (LADISK's 2466 Hz: +0.05)
PEAK_LINES = 2            # a pole stands on an FDD peak within this many lines (or 1 %, whichever is wider)
_CHUNK_BYTES = 64 << 20   # the spectral matrices are decomposed a chunk of lines at a time


# ------------------------------------------------------------------ input checks

def _check_fs(fs_hz: float) -> float:
    try:
        fs = float(fs_hz)
    except (TypeError, ValueError):
        raise InputError("oma.fs_hz", f"expected a positive sample rate in Hz; got {fs_hz!r}") from None
    if not (math.isfinite(fs) and fs > 0):
        raise InputError("oma.fs_hz", f"expected a positive, finite sample rate in Hz; got {fs_hz!r}")
    return fs


def _check_x(x: npt.ArrayLike, fs_hz: float) -> tuple[np.ndarray, float]:
    """x as float (T, C) with each channel's mean removed, and fs_hz as a float."""
    fs = _check_fs(fs_hz)
    a = np.asarray(x)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[1] == 0 or not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise InputError("oma.x", f"expected a real array of shape (samples, channels); got shape {a.shape}, "
                                  f"dtype {a.dtype}")
    if a.shape[0] < MIN_SAMPLES:
        raise InputError("oma.x", f"expected a record of at least {MIN_SAMPLES} samples; got {a.shape[0]}")
    a = a.astype(float)
    if not np.all(np.isfinite(a)):
        bad = np.flatnonzero(~np.all(np.isfinite(a), axis=0))
        raise InputError("oma.x", f"expected finite samples; channels {bad[:10].tolist()} hold NaN or infinity")
    return a - a.mean(axis=0), fs


def _check_band(fs: float, fmin_hz: float | None, fmax_hz: float | None) -> tuple[float, float]:
    lo = 0.0 if fmin_hz is None else float(fmin_hz)
    hi = fs / 2 if fmax_hz is None else float(fmax_hz)
    if not (0 <= lo < hi <= fs / 2):
        raise InputError("oma.fmin_hz, fmax_hz", f"expected 0 <= fmin_hz < fmax_hz <= fs_hz / 2 = {fs / 2:g}; "
                                                 f"got {lo:g} and {hi:g}")
    return lo, hi


def default_nperseg(n_samples: int) -> int:
    """Welch segment length by default: the largest power of two up to a quarter of the record (7 segments at 50 %
    overlap) and MAX_NPERSEG, at least 16 and at most the record."""
    n = 2 ** int(math.floor(math.log2(max(n_samples // 4, 1))))
    return int(min(n_samples, max(16, min(n, MAX_NPERSEG))))


def _check_nperseg(nperseg: int | None, n_samples: int) -> int:
    n = default_nperseg(n_samples) if nperseg is None else nperseg
    if not isinstance(n, (int, np.integer)) or not 8 <= n <= n_samples:
        raise InputError("oma.nperseg", f"expected an integer segment length in 8..{n_samples} (the record); "
                                        f"got {nperseg!r}")
    return int(n)


# ------------------------------------------------------------------ spectra and FDD

def _segment_spectra(x: np.ndarray, fs: float, nperseg: int, fmax_hz: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Frequencies (F,) and the Hann-windowed DFTs of the half-overlapping segments, (F, C, S), each segment's mean
    removed, scaled so that sum_s X X^H is the one-sided cross-spectral density (scipy.signal.csd's, averaged)."""
    seg = np.lib.stride_tricks.sliding_window_view(x, nperseg, axis=0)[:: nperseg // 2]   # (S, C, nperseg), a view
    win = get_window("hann", nperseg)
    f = np.fft.rfftfreq(nperseg, 1 / fs)
    n_f = f.size if fmax_hz is None else int(np.searchsorted(f, fmax_hz, side="right"))
    spec = np.fft.rfft((seg - seg.mean(axis=2, keepdims=True)) * win, axis=2)[..., :n_f]   # (S, C, F)
    scale = np.full(n_f, 2.0 / (fs * np.sum(win**2) * seg.shape[0]))
    scale[0] /= 2
    if nperseg % 2 == 0 and n_f == nperseg // 2 + 1:
        scale[-1] /= 2
    return f[:n_f], (spec * np.sqrt(scale)).transpose(2, 1, 0)


def _first_singular(y: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """For y (F, C, S): the k largest singular values of y y^H per line, (F, k) (zero-padded), and the first singular
    vector (F, C), unit norm, turned so that its largest component is real and positive."""
    n_f, c, s = y.shape
    vals = np.zeros((n_f, k))
    vecs = np.zeros((n_f, c), complex)
    per_line = 16 * c * max(c if s > c else s, 1) * 3
    chunk = max(1, _CHUNK_BYTES // per_line)
    for a in range(0, n_f, chunk):
        b = min(n_f, a + chunk)
        if s <= c:          # fewer segments than channels: the SVD of the segments' DFTs is that of their CSD
            u, sv, _ = np.linalg.svd(y[a:b], full_matrices=False)
            ev = sv**2
        else:
            g = y[a:b] @ y[a:b].conj().transpose(0, 2, 1)
            ev, u = np.linalg.eigh(g)
            ev, u = np.maximum(ev[:, ::-1], 0.0), u[:, :, ::-1]
        m = min(k, ev.shape[1])
        vals[a:b, :m] = ev[:, :m]
        vecs[a:b] = u[:, :, 0]
    lines, k_top = np.arange(n_f), np.argmax(np.abs(vecs), axis=1)
    big = np.abs(vecs[lines, k_top])
    vecs *= np.where(big > 0, np.conj(vecs[lines, k_top]) / np.where(big > 0, big, 1.0), 1.0)[:, None]
    vecs[lines, k_top] = big                 # exactly real
    return vals, vecs


@dataclass(frozen=True)
class FDDResult:
    """Frequency-domain decomposition: the SVD of the output cross-spectral density matrix G(f) at each line.

    freqs_hz (F,); singular_values (F, k), largest first, in the channels' unit^2/Hz (k = min(4, C, segments));
    first_vectors (F, C) complex, the first singular vector of each line, unit norm, its largest component real
    and positive; nperseg: the Welch segment length (Hann, 50 % overlap), n_segments of them averaged.
    """

    freqs_hz: np.ndarray
    singular_values: np.ndarray
    first_vectors: np.ndarray
    nperseg: int
    n_segments: int
    fs_hz: float

    @property
    def df_hz(self) -> float:
        return self.fs_hz / self.nperseg

    def line(self, freq_hz: float) -> int:
        """Index of the line nearest freq_hz."""
        return int(np.argmin(np.abs(self.freqs_hz - float(freq_hz))))

    def peaks_hz(self, fmin_hz: float | None = None, fmax_hz: float | None = None, *,
                 prominence: float = PEAK_PROMINENCE) -> np.ndarray:
        """Frequencies of the first singular value's peaks in the band that stand `prominence` decades above their
        surroundings (scipy.signal.find_peaks' prominence, on log10), 3-point parabolic refinement on log10."""
        f, s1 = self.freqs_hz, self.singular_values[:, 0]
        lo = f[0] if fmin_hz is None else fmin_hz
        hi = f[-1] if fmax_hz is None else fmax_hz
        with np.errstate(divide="ignore"):
            y = np.log10(np.where(s1 > 0, s1, np.nan))
        y = np.where(np.isfinite(y), y, np.nanmin(y) if np.isfinite(y).any() else 0.0)
        idx, _ = find_peaks(y, prominence=prominence)
        idx = idx[(f[idx] >= lo) & (f[idx] <= hi)]
        a, b, c = y[idx - 1], y[idx], y[idx + 1]
        den = a - 2 * b + c
        shift = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
        return f[idx] + np.clip(shift, -0.5, 0.5) * self.df_hz


def fdd(x: npt.ArrayLike, fs_hz: float, *, nperseg: int | None = None, fmax_hz: float | None = None) -> FDDResult:
    """Frequency-domain decomposition of the outputs x (T, C).

    G(f) = sum over segments of X X^H (Welch: Hann window, 50 % overlap, each segment's mean removed; scaled as
    scipy.signal.csd's one-sided density), then its singular values and first singular vector per line, up to
    fmax_hz (default: Nyquist). The segments are transformed once; with fewer segments than channels the SVD of
    the (C, S) segment spectra gives G's without forming it. nperseg defaults to `default_nperseg`.
    """
    x, fs = _check_x(x, fs_hz)
    n = _check_nperseg(nperseg, x.shape[0])
    if fmax_hz is not None and not 0 < float(fmax_hz) <= fs / 2:
        raise InputError("oma.fmax_hz", f"expected 0 < fmax_hz <= fs_hz / 2 = {fs / 2:g}; got {fmax_hz!r}")
    return _fdd(*_segment_spectra(x, fs, n, fmax_hz), n, fs)


def _fdd(f: np.ndarray, y: np.ndarray, nperseg: int, fs: float) -> FDDResult:
    t0 = time.perf_counter()
    vals, vecs = _first_singular(y, min(N_SV, y.shape[1], y.shape[2]))
    log.debug("fdd: %d lines x %d channels x %d segments in %.3f s", f.size, y.shape[1], y.shape[2],
              time.perf_counter() - t0)
    return FDDResult(f, vals, vecs, nperseg, y.shape[2], fs)


def ods_at(x: npt.ArrayLike, fs_hz: float, freq_hz: float, *, nperseg: int | None = None) -> np.ndarray:
    """Operational deflection shape (C,) complex at the line nearest freq_hz: the first singular vector of the
    cross-spectral density matrix there (`fdd`), scaled by the square root of its singular value, so that each
    component is that channel's amplitude spectral density along the dominant shape (unit/sqrt(Hz)); its largest
    component real and positive (an ODS has no absolute phase without a reference)."""
    return ods_lines(x, fs_hz, [freq_hz], nperseg=nperseg)[0]


def ods_lines(x: npt.ArrayLike, fs_hz: float, freqs_hz: Sequence[float], *, nperseg: int | None = None) -> np.ndarray:
    """`ods_at` at each of freqs_hz (L, C), from one FDD of x."""
    x, fs = _check_x(x, fs_hz)
    f0 = np.asarray(freqs_hz, float).reshape(-1)
    if f0.size == 0 or not np.all((f0 >= 0) & (f0 <= fs / 2)):
        raise InputError("oma.freq_hz", f"expected frequencies in 0..{fs / 2:g} Hz (Nyquist); got "
                                        f"{', '.join(f'{v:g}' for v in f0) or 'none'}")
    n = _check_nperseg(nperseg, x.shape[0])
    res = fdd(x, fs, nperseg=n, fmax_hz=min(fs / 2, float(f0.max()) + fs / n))
    k = [res.line(f) for f in f0]
    return res.first_vectors[k] * np.sqrt(res.singular_values[k, 0])[:, None]


def noise_psd(x: npt.ArrayLike, fs_hz: float, *, nperseg: int | None = None, fmin_hz: float | None = None,
              fmax_hz: float | None = None, exclude_hz: Sequence[float] = (), exclude_rel: float = 0.05) -> np.ndarray:
    """Each channel's white-noise level (C,) in unit^2/Hz: the median of its Welch PSD (as `fdd`'s) over the lines
    in fmin_hz..fmax_hz (default: all but 0 Hz) that lie more than max(exclude_rel f0, 3 lines) from every
    exclude_hz (the modes), divided by the median of the estimate's chi-square distribution (Welch's equivalent
    degrees of freedom for Hann at 50 % overlap), so white noise gives its level.

    Where the structure's response between the modes exceeds the noise (a lightly damped mode's skirt, broadband
    excitation), that is what is measured: take the band above the highest mode for the noise alone.
    """
    x, fs = _check_x(x, fs_hz)
    n = _check_nperseg(nperseg, x.shape[0])
    lo, hi = _check_band(fs, fmin_hz, fmax_hz)
    return _noise(*_segment_spectra(x, fs, n, hi), n, fs, lo, hi, exclude_hz, exclude_rel)


def _noise_lines(f: np.ndarray, df: float, lo: float, hi: float, exclude_hz: Sequence[float] | np.ndarray,
                 exclude_rel: float) -> np.ndarray:
    """The lines in lo..hi (not 0 Hz) more than max(exclude_rel f0, 3 lines) from every exclude_hz."""
    keep = (f >= lo) & (f <= hi) & (f > 0)
    for f0 in np.atleast_1d(np.asarray(exclude_hz, float)):
        keep &= np.abs(f - f0) > max(exclude_rel * f0, 3 * df)
    return keep


def _noise(f: np.ndarray, y: np.ndarray, n: int, fs: float, lo: float, hi: float,
           exclude_hz: Sequence[float] | np.ndarray, exclude_rel: float) -> np.ndarray:
    psd = np.sum(np.abs(y) ** 2, axis=2)       # (F, C)
    keep = _noise_lines(f, fs / n, lo, hi, exclude_hz, exclude_rel)
    if keep.sum() < 3:
        raise InputError("oma.noise_psd", f"expected at least 3 lines in {lo:g}-{hi:g} Hz away from the modes; "
                                          f"{keep.sum()} are left at {fs / n:.3g} Hz lines")
    s, win, step = y.shape[2], get_window("hann", n), n // 2
    c = (win[: n - step] @ win[step:]) ** 2 / (win @ win) ** 2     # 1/9: neighbouring segments' correlation
    dof = 2 * s / (1 + 2 * c * (1 - 1 / s))                          # Welch (1967)
    return np.median(psd[keep], axis=0) / (chi2.median(dof) / dof)


# ------------------------------------------------------------------ SSI-cov

def _references(x: np.ndarray, ref_channels: Sequence[int] | None) -> tuple[np.ndarray, str]:
    """The reference signals (T, r) and what they are. None: every channel up to MAX_REFS, else the MAX_REFS
    leading principal components of x (virtual references, each a fixed combination of channels)."""
    c = x.shape[1]
    if ref_channels is None:
        if c <= MAX_REFS:
            return x, "all channels"
        _, v = np.linalg.eigh(x.T @ x)
        v = v[:, ::-1][:, :MAX_REFS]
        return x @ v, f"{MAX_REFS} principal components"
    refs = np.atleast_1d(np.asarray(ref_channels))
    if (refs.ndim != 1 or refs.size == 0 or not np.issubdtype(refs.dtype, np.integer) or refs.min() < 0
            or refs.max() >= c or np.unique(refs).size != refs.size):
        raise InputError("oma.ref_channels", f"expected distinct channel indices in 0..{c - 1}; got {ref_channels!r}")
    return x[:, refs], f"channels {refs.tolist()}"


def _toeplitz(x: np.ndarray, z: np.ndarray, p: int) -> np.ndarray:
    """The block Toeplitz matrix (p C, p r) of output-reference covariances, block (i, j) = R_{p + i - j}.

    Every lag k = 1..2p-1 sums the same N = T - 2p + 1 reference samples, R_k = sum_{u < N} y_{u+k} z_u^T / N:
    R_k = C A^k G with one G, so the matrix factors exactly as observability times controllability for a free
    decay too (a lag-dependent window would bias its damping), and is unbiased for a stationary response.
    """
    n = x.shape[0] - 2 * p + 1
    zt = z[:n].T
    lags = np.stack([zt @ x[k:k + n] for k in range(2 * p)]) / n       # (2p, r, C): R_k^T
    i, j = np.meshgrid(np.arange(p), np.arange(p), indexing="ij")
    blocks = lags[p + i - j]                                            # (p, p, r, C)
    return blocks.transpose(0, 3, 1, 2).reshape(p * x.shape[1], p * z.shape[1])


def default_n_lags(fs_hz: float, max_order: int, n_refs: int, fmin_hz: float) -> int:
    """ssi_cov's block rows by default: enough for max_order states (p r > max_order), MIN_LAGS at least, and half a
    period of the band's lowest frequency (p > fs / (2 fmin_hz)) where that is above 0, at most 200."""
    p = max(MIN_LAGS, -(-max_order // n_refs) + 1)
    if fmin_hz > 0:
        p = max(p, min(200, math.ceil(fs_hz / (2 * fmin_hz))))
    return int(p)


def ssi_cov(x: npt.ArrayLike, fs_hz: float, *, max_order: int, n_lags: int | None = None, fmin_hz: float | None = None,
            fmax_hz: float | None = None, ref_channels: Sequence[int] | None = None) -> list[PolesAtOrder]:
    """Poles of every even model order 2..max_order by covariance-driven stochastic subspace identification.

    The block Toeplitz matrix of the output covariances against the references (`_toeplitz`, n_lags block rows,
    default `default_n_lags`) is decomposed by SVD; per order n (the state dimension: n / 2 mode pairs) the
    observability matrix is its first n left singular vectors (times sqrt of the values, which changes neither
    poles nor shapes), A from its shift (least squares, one QR for all orders) and C its first block row. The
    poles are log(eig A) fs_hz; kept: upper half plane (one of each conjugate pair), stable, damping in
    (0, MAX_DAMPING), |lambda| / 2 pi in fmin_hz..fmax_hz (default 0..Nyquist). Each PolesAtOrder carries the
    mode shapes C psi of its poles, (n_poles, C), unit norm, in `participation`, so that `stabilisation` checks
    their MAC from order to order, SSI's usual criterion.
    """
    x, fs = _check_x(x, fs_hz)
    return _ssi(x, fs, max_order, n_lags, _check_band(fs, fmin_hz, fmax_hz), ref_channels)[0]


def _ssi(x: np.ndarray, fs: float, max_order: int, n_lags: int | None, band: tuple[float, float],
         ref_channels: Sequence[int] | None) -> tuple[list[PolesAtOrder], int, str]:
    """ssi_cov on checked input; also returns the block rows and the references used."""
    if not isinstance(max_order, (int, np.integer)) or max_order < 2:
        raise InputError("oma.max_order", f"expected an integer of at least 2; got {max_order!r}")
    z, refs = _references(x, ref_channels)
    c, r = x.shape[1], z.shape[1]
    p = default_n_lags(fs, int(max_order), r, band[0]) if n_lags is None else n_lags
    if not isinstance(p, (int, np.integer)) or p < 2 or p * min(c, r) <= max_order or (p - 1) * c < max_order:
        raise InputError("oma.n_lags", f"expected an integer with n_lags * min(channels, references) > max_order "
                                       f"= {max_order}; got {n_lags!r} with {c} channels and {r} references")
    if x.shape[0] < 8 * p:
        raise InputError("oma.x", f"expected at least 8 n_lags = {8 * p} samples for {p} block rows; "
                                  f"got {x.shape[0]}")
    t0 = time.perf_counter()
    u, s, _ = np.linalg.svd(_toeplitz(x, z, int(p)), full_matrices=False)
    n_max = int(max_order) - int(max_order) % 2
    if s[n_max - 1] <= s[0] * 1e-13:
        log.warning("ssi_cov: the covariances have rank %d < max_order %d; the highest orders fit noise only",
                    int(np.sum(s > s[0] * 1e-13)), n_max)
    o = u[:, :n_max]
    q, rr = np.linalg.qr(o[:-c])
    m = q.T @ o[c:]
    out = [_ssi_poles(rr[:n, :n], m[:n, :n], o[:c, :n], n, fs, *band) for n in range(2, n_max + 1, 2)]
    log.debug("ssi_cov: %d block rows, %s as references, orders 2..%d in %.3f s", p, refs, n_max,
              time.perf_counter() - t0)
    return out, int(p), refs


def _ssi_poles(r: np.ndarray, m: np.ndarray, c_mat: np.ndarray, n: int, fs: float, lo: float,
               hi: float) -> PolesAtOrder:
    try:
        a = np.linalg.solve(r, m)           # R^-1 Q^T O_down: the least-squares shift of the leading n columns
    except np.linalg.LinAlgError:
        a = np.linalg.lstsq(r, m, rcond=None)[0]
    mu, psi = np.linalg.eig(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.log(mu.astype(complex)) * fs
    fn, zeta = pole_freq_hz(lam), pole_damping(lam)
    keep = (np.isfinite(lam) & (mu.imag > 0) & (np.abs(mu) < 1) & (zeta > 0) & (zeta < MAX_DAMPING)
            & (fn >= lo) & (fn <= hi))
    order = np.argsort(fn[keep])
    shapes = (c_mat @ psi[:, keep]).T[order]
    shapes /= np.maximum(np.linalg.norm(shapes, axis=1, keepdims=True), np.finfo(float).tiny)
    return PolesAtOrder(n, lam[keep][order], shapes)


# ------------------------------------------------------------------ identification

@dataclass(frozen=True)
class OMAMode:
    """One identified mode.

    freq_hz: undamped natural frequency |lambda| / 2 pi; damping: ratio; pole_rad_s: lambda; shape (C,) complex,
    the SSI shapes of the mode's stable poles averaged (`normalise_shape`: turned by its mean phase, largest
    component of magnitude 1 with a positive real part); mpc: modal phase collinearity |sum phi^2|^2 /
    (sum |phi|^2)^2, 1 for a real (normal) mode; peak_psd: the FDD's first singular value at the mode (the
    largest within one line), unit^2/Hz; snr: peak_psd over the noise along the shape, sum |phi_c|^2 noise_c /
    sum |phi_c|^2 (OMAResult.noise_psd); n_stable: the model orders with a stable pole at the mode; kurtosis: that
    of the mode's coordinate (x band-passed around the mode, projected on the shape's real part): about 3 for a
    randomly excited mode, more for a free decay, 1.5 for a steady sine (a harmonic, not a mode: Brincker et al.
    2007); envelope_trend: the change of that coordinate's log envelope (Hilbert) over the middle 80 % of the record,
    from a line fitted to it: 0 for a steady sine or a stationary random response, -zeta omega T for a free decay;
    `harmonic`: below HARMONIC_KURTOSIS, and |envelope_trend| below HARMONIC_TREND.
    """

    freq_hz: float
    damping: float
    pole_rad_s: complex
    shape: np.ndarray
    mpc: float
    peak_psd: float
    snr: float
    n_stable: int
    kurtosis: float
    envelope_trend: float = 0.0

    @property
    def harmonic(self) -> bool:
        return self.kurtosis < HARMONIC_KURTOSIS and abs(self.envelope_trend) < HARMONIC_TREND


@dataclass(frozen=True)
class OMAResult:
    """Output-only identification: the modes (by frequency), the SSI stabilisation chart, the FDD, and each
    channel's white-noise level noise_psd (C,) in unit^2/Hz (`_identify_noise`). harmonics: what the automatic
    selection found and left out as steady sines (OMAMode.harmonic). band_hz: the band analysed; n_lags and
    references: the SSI's block rows and references."""

    modes: tuple[OMAMode, ...]
    chart: StabilisationChart
    fdd: FDDResult
    noise_psd: np.ndarray
    band_hz: tuple[float, float]
    n_lags: int
    references: str
    harmonics: tuple[OMAMode, ...] = ()

    @property
    def freq_hz(self) -> np.ndarray:
        return np.array([m.freq_hz for m in self.modes], float)

    @property
    def damping(self) -> np.ndarray:
        return np.array([m.damping for m in self.modes], float)

    @property
    def shapes(self) -> np.ndarray:
        """(n_modes, C) complex."""
        return np.array([m.shape for m in self.modes], complex).reshape(len(self.modes), self.noise_psd.size)

    @property
    def mpc(self) -> np.ndarray:
        return np.array([m.mpc for m in self.modes], float)


def mpc(shapes: npt.ArrayLike) -> np.ndarray:
    """Modal phase collinearity of each complex shape (n, C): |sum phi^2|^2 / (sum |phi|^2)^2, the squared ratio of
    the two principal axes' difference to their sum in the complex plane; 1 for a shape whose components share
    one phase (or its opposite), 0 for a circular spread."""
    psi = np.atleast_2d(np.asarray(shapes, complex))
    den = np.sum(np.abs(psi) ** 2, axis=1) ** 2
    return np.abs(np.sum(psi**2, axis=1)) ** 2 / np.where(den > 0, den, 1.0)


def normalise_shape(phi: npt.ArrayLike) -> np.ndarray:
    """phi (C,) turned by its mean phase (`ema.mean_phase_rad`: real-most) and scaled so that its largest component
    has magnitude 1 and a positive real part (its imaginary part is what the shape has out of that phase)."""
    phi = np.asarray(phi, complex)
    phi = phi * np.exp(-1j * mean_phase_rad(phi[None])[0])
    top = phi[int(np.argmax(np.abs(phi)))]
    return phi / (abs(top) * (-1.0 if top.real < 0 else 1.0)) if top != 0 else phi


def _mode_shape(chart: StabilisationChart, freq_hz: float, tol: float) -> tuple[np.ndarray, int]:
    """The mean shape (C,) of the chart's poles within tol (relative) of freq_hz that have the best status there,
    each turned onto the shape of the highest order among them, and the number of orders they come from."""
    order, poles, status = chart.flat()
    shapes = np.concatenate([lv.participation for lv in chart.levels])
    fn = pole_freq_hz(poles)
    near = np.abs(fn - freq_hz) <= tol * freq_hz
    if not near.any():
        near = np.abs(fn - freq_hz) == np.min(np.abs(fn - freq_hz))
    rank = np.array([("stable", "damping", "freq", "new").index(s) for s in status])
    near &= rank == rank[near].min()
    idx = np.flatnonzero(near)
    ref = shapes[idx[np.argmax(order[idx])]]
    turn = shapes[idx] @ ref.conj()
    aligned = shapes[idx] * np.exp(-1j * np.angle(turn))[:, None]
    return aligned.mean(axis=0), int(np.unique(order[idx]).size)


def _on_peaks(poles: np.ndarray, peaks_hz: np.ndarray, df_hz: float) -> np.ndarray:
    """Which poles lie within max(PEAK_LINES lines, 1 %, 2 zeta f: the width of their own peak, over which the
    noise of the spectrum moves its top) of an FDD peak."""
    fn, zeta = pole_freq_hz(poles), pole_damping(poles)
    if peaks_hz.size == 0:
        return np.zeros(fn.size, bool)
    dist = np.min(np.abs(fn[:, None] - peaks_hz[None, :]), axis=1)
    return dist <= np.maximum(np.maximum(PEAK_LINES * df_hz, 0.01 * fn), 2 * zeta * fn)


def identify(x: npt.ArrayLike, fs_hz: float, *, fmin_hz: float | None = None, fmax_hz: float | None = None,
             max_order: int | None = None, n_modes: int | None = None,
             approx_freq_hz: Sequence[float] | None = None, nperseg: int | None = None, n_lags: int | None = None,
             ref_channels: Sequence[int] | None = None) -> OMAResult:
    """Modes of the outputs x (T, C) alone: FDD, SSI-cov up to max_order (default MAX_ORDER), ema's stabilisation
    (FREQ_TOL, DAMPING_TOL, MAC_TOL on the shapes) and pole selection, in fmin_hz..fmax_hz (default 0..Nyquist).

    Automatic (approx_freq_hz None): ema's `select_poles` clusters of stable poles (in at least MIN_STABLE of the
    orders, damping below MAX_DAMPING) that stand on a peak of the FDD's first singular value (PEAK_PROMINENCE
    decades, `_on_peaks`) and are not steady sines (OMAMode.harmonic: those go to OMAResult.harmonics); n_modes
    keeps the strongest of them (peak_psd). Manual: the best pole within 5 % of each approx_freq_hz
    (`select_poles`), in that order, kept whether or not the FDD peaks there and even if harmonic.
    Shapes, MPC, peak PSD, SNR and kurtosis per mode: see OMAMode; the noise: `_identify_noise`.
    """
    x, fs = _check_x(x, fs_hz)
    lo, hi = _check_band(fs, fmin_hz, fmax_hz)
    max_order = MAX_ORDER if max_order is None else max_order
    if n_modes is not None and (not isinstance(n_modes, (int, np.integer)) or n_modes < 1):
        raise InputError("oma.n_modes", f"expected a positive integer; got {n_modes!r}")
    n = _check_nperseg(nperseg, x.shape[0])
    f, y = _segment_spectra(x, fs, n, None)
    in_band = int(np.searchsorted(f, hi, side="right"))
    spectrum = _fdd(f[:in_band], y[:in_band], n, fs)
    levels, p, refs = _ssi(x, fs, max_order, n_lags, (lo, hi), ref_channels)
    chart = stabilisation(levels, freq_tol=FREQ_TOL, damping_tol=DAMPING_TOL, mac_tol=MAC_TOL)
    peaks = spectrum.peaks_hz(lo, hi)
    if approx_freq_hz is not None:
        poles = select_poles(chart, approx_freq_hz=approx_freq_hz)
    else:
        poles = select_poles(chart, min_stable=MIN_STABLE, max_damping=MAX_DAMPING)
        on = _on_peaks(poles, peaks, spectrum.df_hz)
        if np.any(~on):
            log.info("identify: stable poles at %s Hz stand on no FDD peak; left out",
                     np.round(pole_freq_hz(poles[~on]), 2).tolist())
        poles = poles[on]
    noise = _identify_noise(f, y, n, fs, (lo, hi), np.concatenate([pole_freq_hz(poles), peaks]))
    modes = [_mode(chart, pole, spectrum, noise, x) for pole in poles]
    harmonics = [m for m in modes if m.harmonic] if approx_freq_hz is None else []
    if harmonics:
        log.info("identify: %s Hz look like steady sines (kurtosis %s), not modes; left out",
                 [round(m.freq_hz, 2) for m in harmonics], [round(m.kurtosis, 2) for m in harmonics])
        modes = [m for m in modes if not m.harmonic]
    if n_modes is not None and len(modes) > n_modes:
        modes = sorted(sorted(modes, key=lambda m: -m.peak_psd)[:n_modes], key=lambda m: m.freq_hz)
    log.info("identify: %d modes at %s Hz in %g-%g Hz", len(modes), [round(m.freq_hz, 2) for m in modes], lo, hi)
    return OMAResult(tuple(modes), chart, spectrum, noise, (lo, hi), p, refs, tuple(harmonics))


def _identify_noise(f: np.ndarray, y: np.ndarray, n: int, fs: float, band: tuple[float, float],
                    exclude_hz: np.ndarray) -> np.ndarray:
    """Per channel, the smaller of two `noise_psd` levels, each an upper bound of the noise (the structure's
    response adds to it): over the band away from the modes and the FDD's peaks, and from 1.5 times the highest of
    them to 0.9 Nyquist (where a displacement's response has fallen away), each where it holds NOISE_LINES lines;
    over the whole spectrum away from them where neither does."""
    top = 1.5 * max(float(np.max(exclude_hz, initial=0.0)), band[0])
    regions = [r for r in (band, (top, 0.9 * fs / 2))
               if np.count_nonzero(_noise_lines(f, fs / n, *r, exclude_hz, 0.05)) >= NOISE_LINES]
    return np.min([_noise(f, y, n, fs, *r, exclude_hz, 0.05) for r in regions or [(0.0, fs / 2)]], axis=0)


def modal_kurtosis(x: npt.ArrayLike, fs_hz: float, freq_hz: float, shape: npt.ArrayLike,
                   half_width_hz: float) -> float:
    """Kurtosis (3 for a Gaussian) of x (T, C) projected on the real part of shape (C,) and band-passed to
    freq_hz +- half_width_hz (4th-order Butterworth, both ways): a steady sine gives 1.5, random response 3, a
    decay more."""
    x, fs = _check_x(x, fs_hz)
    return _kurtosis(x, fs, freq_hz, np.asarray(shape, complex).real, half_width_hz)


def _coordinate(x: np.ndarray, fs: float, freq_hz: float, phi: np.ndarray, half_width_hz: float) -> np.ndarray:
    """x (T, C) projected on phi (C,), band-passed to freq_hz +- half_width_hz (4th order Butterworth, both ways)."""
    lo = max(freq_hz - half_width_hz, 0.5 * freq_hz)
    hi = min(freq_hz + half_width_hz, 0.5 * (freq_hz + fs / 2))
    return sosfiltfilt(butter(4, [lo, hi], "bandpass", fs=fs, output="sos"), x @ phi)   # projecting first: one series


def _kurtosis(x: np.ndarray, fs: float, freq_hz: float, phi: np.ndarray, half_width_hz: float) -> float:
    return float(kurtosis(_coordinate(x, fs, freq_hz, phi, half_width_hz), fisher=False))


def _envelope_trend(q: np.ndarray) -> float:
    """The change of log |hilbert(q)| over the middle 80 % of q (the filter's ends left out), from a line fitted."""
    env = np.abs(hilbert(q))
    n = len(env)
    mid = env[n // 10: n - n // 10] if n >= 20 else env
    if len(mid) < 4 or not np.all(mid > 0):
        return 0.0
    k = np.arange(len(mid), dtype=float)
    slope = np.polyfit(k, np.log(mid), 1)[0]
    return float(slope * (len(mid) - 1))


def _mode(chart: StabilisationChart, pole: complex, spectrum: FDDResult, noise: np.ndarray,
          x: np.ndarray) -> OMAMode:
    fn, zeta = float(pole_freq_hz(pole)), float(pole_damping(pole))
    phi, n_stable = _mode_shape(chart, fn, 0.005)
    shape = normalise_shape(phi)
    k = spectrum.line(fn)
    peak = float(np.max(spectrum.singular_values[max(k - 1, 0):k + 2, 0]))
    q = _coordinate(x, spectrum.fs_hz, fn, shape.real, max(3 * zeta * fn, PEAK_LINES * spectrum.df_hz))
    return OMAMode(freq_hz=fn, damping=zeta, pole_rad_s=complex(pole), shape=shape, mpc=float(mpc(phi)[0]),
                   peak_psd=peak, snr=shape_snr(peak, phi, noise), n_stable=n_stable,
                   kurtosis=float(kurtosis(q, fisher=False)), envelope_trend=_envelope_trend(q))


def shape_snr(peak_psd: float, shape: np.ndarray, noise_psd: np.ndarray) -> float:
    """A shape's peak over the noise along it: peak_psd / (sum |phi_c|^2 noise_c / sum |phi_c|^2) (OMAMode.snr);
    inf where there is no noise."""
    w = np.abs(np.asarray(shape)) ** 2
    floor = float(np.sum(w * noise_psd) / np.sum(w))
    return peak_psd / floor if floor > 0 else math.inf
