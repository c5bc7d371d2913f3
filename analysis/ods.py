"""Quantitative 3D operational deflection shapes from the dynamic Gaussians: physical surface motion, sensor
points, and modal amplitudes fitted with known poles (the hybrid approach: accelerometer poles, video shapes).

The reconstruction's `derived/reconstruction/trajectories.npz` holds every Gaussian's displacement as trained,
i.e. multiplied by the magnification of the frames it was trained on (`source_alpha`); `SurfaceMotion` divides
that out, so everything here is in metres of real motion, on the impact-locked timeline (0 = impact onset).
The linear motion model also leaves `measured_motion.npz` in the same keys: its node graph's motion with every
temporal component, where the model keeps only those above the noise floor.

The free response after a short impulse is x(t) = sum_r A_r F(lambda_r) e^(lambda_r t) + c.c., where A_r is
the displacement residue of mode r (the receptance is H(w) = sum_r A_r / (iw - lambda_r) + c.c.) and
F(lambda) = integral f(t) e^(-lambda t) dt the force pulse's Laplace transform at the pole. Fitting the decay
with the poles held fixed and dividing by F(lambda_r) gives video residues in m/N, directly comparable with
the residues LSFD fits to the accelerometer FRFs.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from odsplat.reconstruction import MotionRecord
from odsplat.spine.errors import InputError

from .ema import pole_damping, pole_freq_hz

log = logging.getLogger(__name__)

READ_CHUNK = 2048   # points SurfaceMotion.at_points reads at a time
DECAY_T_MIN_S = 1.5e-3    # the video's decay fit starts after a ~1 ms hammer pulse


@dataclass(frozen=True)
class SurfaceMotion:
    """The physical 3D motion of the reconstruction's opaque Gaussians, world frame, metres."""

    times_s: np.ndarray           # (T,) after the impact onset
    points_m: np.ndarray          # (N, 3) rest positions
    displacement_m: np.ndarray    # (T, N, 3) real motion (the frames' magnification divided out)
    opacity: np.ndarray           # (N,)
    source_alpha: float
    source: str = ""

    @classmethod
    def read(cls, path: str | Path, *, min_opacity: float = 0.5, capture_id: str | None = None) -> SurfaceMotion:
        """From a reconstruction's trajectories.npz (or measured_motion.npz), keeping Gaussians at least
        `min_opacity` opaque (the translucent ones fill gaps and carry little of the image, so their motion is
        weakly observed). Given the capture's id, a file of another capture is refused (`MotionRecord.read`)."""

        m = MotionRecord.read(path, capture_id)
        times, rest, disp, alpha = m.times_s, m.means_rest_m, np.asarray(m.displacement_m, float), m.source_alpha
        opacity = 1.0 / (1.0 + np.exp(-m.opacity_logits))
        keep = opacity >= min_opacity
        if not keep.any():
            raise InputError(path, f"no Gaussian is at least {min_opacity} opaque")
        log.info("%s: %d of %d Gaussians at least %.2f opaque, %d timesteps, source alpha %g", path, keep.sum(),
                 len(rest), min_opacity, len(times), alpha)
        return cls(times, rest[keep], disp[:, keep] / alpha, opacity[keep], alpha, str(path))

    @property
    def n_points(self) -> int:
        return len(self.points_m)

    def nearest(self, points_m, k: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Indices (S, k), inverse-distance weights (S, k) summing to 1, and distances (S, k) in metres of the k
        Gaussians nearest each point."""
        pts = np.asarray(points_m, float).reshape(-1, 3)
        k = int(min(k, self.n_points))
        dist, idx = cKDTree(self.points_m).query(pts, k=k)
        dist, idx = dist.reshape(len(pts), k), idx.reshape(len(pts), k)
        w = 1.0 / np.maximum(dist, 1e-6)
        return idx, w / w.sum(axis=1, keepdims=True), dist

    def at_points(self, points_m, directions=None, *, k: int = 16, outlier_factor: float | None = 2.0
                  ) -> np.ndarray:
        """Displacement at points: (T, S, 3), or (T, S) along unit `directions` (S, 3) such as the accelerometers'
        axes. A local plane (`_local_linear`) through the k nearest Gaussians' motion, less the outliers among them
        (a mean would read a free end low): a Gaussian whose
        trajectory lies further than `outlier_factor` times the median such distance from the median trajectory
        (per timestep and component, over the k) is left out (None: keep all). A per-timestep fit leaves a few
        Gaussians that wander, and one of them in a plain mean can move a sensor's reading by half."""
        pts = np.asarray(points_m, float).reshape(-1, 3)
        dirs = None
        if directions is not None:
            dirs = np.asarray(directions, float).reshape(-1, 3)
            if len(dirs) != len(pts):
                raise InputError("at_points: directions",
                                 f"expected one direction per point ({len(pts)}); got {len(dirs)}")
            dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        if len(pts) > READ_CHUNK:          # bounded memory: T x READ_CHUNK x k x 3 values at a time
            parts = [self.at_points(pts[i:i + READ_CHUNK], None if dirs is None else dirs[i:i + READ_CHUNK], k=k,
                                    outlier_factor=outlier_factor) for i in range(0, len(pts), READ_CHUNK)]
            return np.concatenate(parts, axis=1)
        idx, _, dist = self.nearest(pts, k)
        disp = self.displacement_m[:, idx]                                    # (T, S, k, 3)
        keep = np.ones(idx.shape, bool)
        if outlier_factor is not None and idx.shape[1] > 2:
            med = np.median(disp, axis=2, keepdims=True)
            dev = np.sqrt(((disp - med) ** 2).sum(axis=(0, 3)))               # (S, k)
            keep = dev <= outlier_factor * np.median(dev, axis=1, keepdims=True) * (1 + 1e-9) + 1e-30
        d = self._local_linear(pts, idx, dist, disp, keep)
        return d if dirs is None else np.einsum("tsc,sc->ts", d, dirs)

    def _local_linear(self, pts: np.ndarray, idx: np.ndarray, dist: np.ndarray, disp: np.ndarray, use: np.ndarray
                      ) -> np.ndarray:
        """(T, S, 3) the motion at pts from a weighted least-squares plane through each point's neighbours' motion
        (value and gradient; Gaussian weights of their median distance `dist` (S, k); `use` (S, k) the neighbours
        kept). A mean
        of the neighbours reads a free end's motion low, since they all lie inboard of it: on the demo, the arm
        tip's 371 Hz motion read 0.68-0.98 of the truth, and 0.88-1.03 from the plane."""
        out = np.empty((disp.shape[0], len(pts), 3))
        for s in range(len(pts)):
            r = self.points_m[idx[s]] - pts[s]                                 # (k, 3)
            h = max(float(np.median(dist[s][use[s]])), 1e-12)
            wt = np.exp(-0.5 * (dist[s] / h) ** 2) * use[s]                     # (k,)
            y = disp[:, s].transpose(1, 0, 2).reshape(len(r), -1)             # (k, T*3)
            # The gradient only along the directions the neighbours spread in (on one face: in its plane), so the
            # plane is never extrapolated across a direction it has no data in; too few for a plane: their mean.
            centred = (r - (wt @ r) / wt.sum()) * np.sqrt(wt)[:, None] / h
            _, sv, vt = np.linalg.svd(centred, full_matrices=False)
            axes = vt[sv > 0.1 * max(sv[0], 1e-12)]
            if int(use[s].sum()) < len(axes) + 2:
                out[:, s] = ((wt @ y) / wt.sum()).reshape(disp.shape[0], 3)
                continue
            A = np.column_stack([np.ones(len(r)), r @ axes.T / h]) * np.sqrt(wt)[:, None]
            coef = np.linalg.lstsq(A, y * np.sqrt(wt)[:, None], rcond=None)[0]
            out[:, s] = coef[0].reshape(disp.shape[0], 3)
        return out


def force_transform(force_n, sample_rate_hz: float, t0_s: float, s) -> np.ndarray:
    """F(s) = integral f(t) e^(-s t) dt of a force record whose sample 0 is at t0_s on the impact-locked
    timeline, at the complex values s (rad/s); trapezoidal rule."""
    f = np.asarray(force_n, float).reshape(-1)
    t = t0_s + np.arange(len(f)) / float(sample_rate_hz)
    s = np.atleast_1d(np.asarray(s, complex))
    return np.trapezoid(f[None] * np.exp(-s[:, None] * t[None]), t, axis=1)


@dataclass(frozen=True)
class DecayFit:
    """Free-decay amplitudes of known poles in a set of response channels."""

    poles_rad_s: np.ndarray       # (R,)
    amplitudes: np.ndarray        # (R, M) complex: x_m(t) = sum_r 2 Re(C_rm e^(lambda_r t)) + offset_m
    offset: np.ndarray            # (M,)
    t_min_s: float
    r2: np.ndarray                # (M,) share of each channel's variance the fit explains
    condition: float              # of the (column-normalised) design matrix

    def synthesize(self, times_s) -> np.ndarray:
        """(T, M) the fitted response."""
        e = np.exp(np.outer(np.asarray(times_s, float), self.poles_rad_s))
        return 2 * np.real(e @ self.amplitudes) + self.offset

    def residues(self, force_at_poles) -> np.ndarray:
        """(R, M) displacement residues in m/N: the amplitudes divided by the force's transform at each pole."""
        return self.amplitudes / np.asarray(force_at_poles, complex)[:, None]


def decay_design(times_s, poles_rad_s, *, offset: bool = True) -> np.ndarray:
    """(T, 2R [+1]) the decay fit's columns at times_s: e^(sigma_r t) cos(w_r t), then the sines, then 1."""
    tu = np.asarray(times_s, float).reshape(-1, 1)
    poles = np.atleast_1d(np.asarray(poles_rad_s, complex))
    env = np.exp(tu * poles.real[None])
    cols = [env * np.cos(tu * poles.imag[None]), env * np.sin(tu * poles.imag[None])]
    if offset:
        cols.append(np.ones((len(tu), 1)))
    return np.concatenate(cols, axis=1)


def adjusted_r2(r2, n_samples: int, n_poles: int) -> np.ndarray:
    """A decay fit's share of each channel's motion (r2) less what a fit of that many parameters (2 per pole and an
    offset) explains of pure noise over n_samples: 0 for noise alone, whatever the record's length."""
    p = 2 * n_poles + 1
    return 1 - (1 - np.asarray(r2, float)) * (n_samples - 1) / max(n_samples - p - 1, 1)


def fit_decay(times_s, x, poles_rad_s, *, t_min_s: float = 0.0, offset: bool = True) -> DecayFit:
    """Least-squares amplitudes of damped sinusoids at fixed poles, on samples at t >= t_min_s (after the force
    pulse, so the response is free decay). x: (T,) or (T, M); one solve for every channel."""
    t = np.asarray(times_s, float).reshape(-1)
    x = np.asarray(x, float)
    x2 = x.reshape(len(t), -1) if x.shape[:1] == t.shape else None
    if x2 is None:
        raise InputError("fit_decay: x", f"expected ({len(t)}, ...) samples at the given times; got {x.shape}")
    poles = np.atleast_1d(np.asarray(poles_rad_s, complex))
    if np.any(poles.real >= 0) or np.any(poles.imag <= 0):
        raise InputError("fit_decay: poles_rad_s", "expected stable poles with positive frequency (Re < 0, Im > 0)")
    use = t >= t_min_s
    n_cols = 2 * len(poles) + int(offset)
    if use.sum() < n_cols:
        raise InputError("fit_decay: times_s", f"{use.sum()} samples after t_min_s={t_min_s:g} s for {n_cols} unknowns")
    A = decay_design(t[use], poles, offset=offset)
    norm = np.linalg.norm(A, axis=0)
    coef, *_ = np.linalg.lstsq(A / norm, x2[use], rcond=None)
    coef = coef / norm[:, None]
    sv = np.linalg.svd(A / norm, compute_uv=False)
    R = len(poles)
    # e^(st)(a cos wt + b sin wt) = 2 Re(C e^(lambda t)) with C = (a - i b) / 2
    amps = 0.5 * (coef[:R] - 1j * coef[R:2 * R])
    off = coef[2 * R] if offset else np.zeros(x2.shape[1])
    resid = x2[use] - A @ coef
    var = np.var(x2[use], axis=0)
    r2 = 1.0 - np.mean(resid**2, axis=0) / np.where(var > 0, var, 1.0)
    return DecayFit(poles, amps, off, float(t_min_s), r2, float(sv[0] / max(sv[-1], 1e-300)))


def receptance(residues, poles_rad_s, freq_hz) -> np.ndarray:
    """H(w) = sum_r A_r / (iw - lambda_r) + conj(A_r) / (iw - conj(lambda_r)) at freq_hz: (F, ...) for residues
    (R, ...) — the operational deflection shape per newton at each frequency line."""
    A = np.asarray(residues, complex)
    lam = np.asarray(poles_rad_s, complex).reshape(-1)
    iw = 2j * np.pi * np.atleast_1d(np.asarray(freq_hz, float))
    g = 1.0 / (iw[:, None] - lam[None])                 # (F, R)
    gc = 1.0 / (iw[:, None] - np.conj(lam)[None])
    flat = A.reshape(len(lam), -1)
    return (g @ flat + gc @ np.conj(flat)).reshape((len(iw),) + A.shape[1:])


def principal_components(x: np.ndarray, n: int) -> np.ndarray:
    """(T, n) the time histories of x's (T, M) n strongest principal components, its mean taken out: the same
    motion in few channels, scaled as it is, with the noise of the weak directions left out."""
    y = x - x.mean(axis=0)
    if y.shape[1] <= y.shape[0]:
        u, s, _ = np.linalg.svd(y, full_matrices=False)
        return u[:, :n] * s[:n]
    # Few timesteps, many channels (a reconstruction's points): the left singular vectors are the eigenvectors
    # of the (T, T) Gram matrix, 20-40x faster than the SVD of the wide matrix and equal to rounding.
    w, v = np.linalg.eigh(y @ y.T)
    top = np.argsort(w)[::-1][:n]
    return v[:, top] * np.sqrt(np.clip(w[top], 0.0, None))


def _decay_channels(who: str, times_s, x, t_min_s: float, n_channels: int) -> tuple[np.ndarray, float]:
    """The samples at t >= t_min_s reduced to n_channels principal components, and the sample interval (the
    times must be uniform): what both pole finders start from."""
    t = np.asarray(times_s, float).reshape(-1)
    x = np.asarray(x, float).reshape(len(t), -1)
    dt = np.diff(t)
    if len(dt) == 0 or np.ptp(dt) > 1e-6 * np.mean(dt):
        raise InputError(f"{who}: times_s", "expected uniformly spaced times")
    return principal_components(x[t >= t_min_s], n_channels), float(np.mean(dt))


def _stable_upper(z: np.ndarray, dt: float) -> np.ndarray:
    """Discrete roots z as poles lambda = ln(z) / dt, the stable ones of positive frequency, sorted."""
    lam = np.log(np.asarray(z).astype(complex)) / dt
    return np.sort_complex(lam[(lam.real < 0) & (lam.imag > 0)])


def lsce_poles(times_s, x, order: int, *, t_min_s: float = 0.0, n_channels: int = 8) -> np.ndarray:
    """Poles (rad/s, Re < 0 < Im) of a multi-channel free decay by least-squares complex exponentials: one
    autoregressive polynomial of `order` shared by every channel (Prony, poly-reference form). The channels are
    first reduced to their n_channels principal components, which keeps the solve small and averages the noise."""
    y, dt = _decay_channels("lsce_poles", times_s, x, t_min_s, n_channels)
    T = len(y)
    if T - order < 2 or y.shape[1] * (T - order) < 2 * order:
        raise InputError("lsce_poles: order", f"{T} samples cannot fit an order-{order} model; lower it")
    # y[k + p] = -sum_j a_j y[k + j]
    rows = np.stack([y[j:T - order + j] for j in range(order)], axis=-1)     # (T-p, C, p)
    A = rows.reshape(-1, order)
    b = -y[order:].reshape(-1)
    a, *_ = np.linalg.lstsq(A, b, rcond=None)
    z = np.roots(np.concatenate([[1.0], a[::-1]]))
    return _stable_upper(z, dt)


def pencil_poles(times_s, x, rank: int, *, t_min_s: float = 0.0, n_channels: int = 8) -> np.ndarray:
    """Poles (rad/s, Re < 0 < Im) of a multi-channel free decay by the matrix pencil (Kung's shift invariance):
    the block Hankel matrix of the channels' samples, truncated to its `rank` strongest singular vectors, and the
    eigenvalues of the one-sample shift between their rows. The truncation removes most of the noise before the
    poles are solved for, where LSCE's least-squares prediction fits it: on a short, noisy record LSCE merges
    close low modes (23.5 and 31 Hz at 2000 fps) and biases the rest, the pencil does not. `rank` counts real
    exponentials: two per mode, one per drift, and one for the mean taken out (six modes need 13). The channels
    are first reduced to their n_channels principal components."""
    y, dt = _decay_channels("pencil_poles", times_s, x, t_min_s, n_channels)
    T = len(y)
    L = T // 2                                   # rows: the shifts; half the record is the least noisy choice
    if rank < 1 or L < rank + 1:
        raise InputError("pencil_poles: rank", f"{T} samples cannot fit rank {rank} (at most {max(L - 1, 0)})")
    H = np.stack([y[j:T - L + j] for j in range(L + 1)]).reshape(L + 1, -1)     # row j: samples j .. j+T-L-1
    U = np.linalg.svd(H, full_matrices=False)[0][:, :rank]
    z = np.linalg.eigvals(np.linalg.lstsq(U[:-1], U[1:], rcond=None)[0])
    return _stable_upper(z, dt)


PENCIL_RANKS = (16, 20, 24)   # six modes and the mean need 13; at 12 the low modes come out biased


def default_ranks(n_samples: int) -> tuple[int, ...]:
    """The pencil's ranks for a record of n_samples: PENCIL_RANKS, all lowered alike where the Hankel matrix (half
    the samples as rows) cannot hold the highest (rank + 1 rows); () when it cannot hold rank 2."""
    top = min(PENCIL_RANKS[-1], n_samples // 2 - 1)
    shift = PENCIL_RANKS[-1] - top
    return tuple(r - shift for r in PENCIL_RANKS if r - shift >= 2)


RECORD_RANKS = (24, 32, 40)  # a long record holds more: on the demo's 247 timesteps 16/20/24 find 5 of its 6 modes
#                               in the video, these 6, neither a pole of the noise (docs/analysis.md)
# A weak pole of the video's motion is kept when it explains this share of it beyond the other poles, and this many
# times what a pole of white noise would (`stable_poles`): a video's weak modes stand above its noise long before
# they carry a thousandth of its energy (the demo's 142 Hz: 1e-4 and 6x).
POLE_WEAK_SHARE = 1e-5
POLE_MIN_SIGNIFICANCE = 4.0
# ... unless it lies within this fraction of the frequency of a pole that explains this many times more: the takes
# that make up one motion differ a little (force, timing), which leaves sidebands beside a strong mode that a weak
# pole there would fit (the demo's 242 Hz beside 262 Hz: 160x less, 4.2x the noise).
SIDEBAND_FRACTION = 0.1
SIDEBAND_RATIO = 30.0


def record_ranks(n_samples: int) -> tuple[int, ...]:
    """The pencil's ranks for a record of n_samples: RECORD_RANKS where the Hankel matrix holds them (rank + 1 rows
    of half the samples), else `default_ranks`."""
    return RECORD_RANKS if n_samples // 2 - 1 >= RECORD_RANKS[-1] else default_ranks(n_samples)


POLE_METHODS = {"pencil": pencil_poles, "lsce": lsce_poles}


def stable_poles(times_s, x, orders, fmax_hz: float, min_share: float = 1e-3, method: str = "pencil", *,
                 min_significance: float | None = None, weak_share: float = POLE_WEAK_SHARE
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Poles of a multi-channel free decay: found by `method` (the matrix pencil, or LSCE) at every order (the
    pencil's rank) within 1 % in frequency, damped less than 20 %, and explaining at least `min_share` of the
    motion's energy beyond the other poles (`explained_share`; drops the stable but empty poles a high order
    fits to the noise). With `min_significance`, a weaker pole is kept too where it explains at least weak_share
    and that many times what a pole of white noise would (`pole_evidence`): a weak mode that stands above the
    noise (on the demo's video, 142 Hz at 1e-4 of the energy and 6x the noise's share; the noise's own poles 1x),
    and not within SIDEBAND_FRACTION of a pole explaining SIDEBAND_RATIO times more (a strong mode's sideband).
    Where a mode is missing from the fit (too short a window to separate it) its motion counts as noise, and only
    the share decides. Returns (freq_hz, damping)."""
    if method not in POLE_METHODS:
        raise InputError("stable_poles: method", f"expected one of {sorted(POLE_METHODS)}; got {method!r}")
    find = POLE_METHODS[method]
    sets = []
    for order in orders:
        try:
            lam = find(times_s, x, order)
        except InputError:          # too few timesteps for this order
            continue
        sets.append(lam[(pole_freq_hz(lam) < fmax_hz) & (pole_damping(lam) < 0.2)])
    if not sets:
        return np.zeros(0), np.zeros(0)
    keep = [lam for lam in sets[-1]
            if all(len(o) and np.min(np.abs(np.abs(o) - abs(lam))) < 0.01 * abs(lam) for o in sets[:-1])]
    lam = _one_per_cluster(times_s, x, np.array(sorted(keep, key=abs), complex))
    if len(lam):
        share, significance = pole_evidence(times_s, x, lam)
        ok = share >= min_share
        if min_significance is not None:
            f = pole_freq_hz(lam)
            beside = np.array([np.any((np.abs(f - fr) < SIDEBAND_FRACTION * fr) & (share >= SIDEBAND_RATIO * sr))
                               for fr, sr in zip(f, share)])
            ok |= (share >= weak_share) & (significance >= min_significance) & ~beside
        lam = lam[ok]
    return pole_freq_hz(lam), pole_damping(lam)


def _one_per_cluster(times_s, x, lam: np.ndarray, n_channels: int = 8) -> np.ndarray:
    """The poles (sorted by |lambda|) with each cluster within 1 % of each other reduced to the member whose fit
    with the other poles leaves the least residual. The pencil can split one mode in two at a high rank (the
    demo's 371 Hz as 370.9 and 371.3 Hz), and then each explains nothing beyond its twin: both would be
    dropped."""
    if len(lam) < 2:
        return lam
    groups, start = [], 0
    for i in range(1, len(lam) + 1):
        if i == len(lam) or abs(lam[i]) - abs(lam[i - 1]) >= 0.01 * abs(lam[i - 1]):
            groups.append(list(range(start, i)))
            start = i
    if all(len(g) == 1 for g in groups):
        return lam
    t = np.asarray(times_s, float).reshape(-1)
    y = principal_components(np.asarray(x, float).reshape(len(t), -1), n_channels)
    keep = np.ones(len(lam), bool)
    for g in (g for g in groups if len(g) > 1):
        def rss(member: int, g=g) -> float:
            use = keep.copy()
            use[g] = False
            use[member] = True
            return float(np.sum((y - fit_decay(t, y, lam[use]).synthesize(t)) ** 2))
        best = min(g, key=rss)
        keep[g] = False
        keep[best] = True
    return lam[keep]


def explained_share(times_s, x, poles_rad_s, n_channels: int = 8) -> np.ndarray:
    """(R,) the share of the motion's energy (less its mean, in its n_channels principal components) that each
    pole explains beyond all the others: what a decay fit loses without it. An amplitude would not do: two
    close poles, one of them spurious, can take large amplitudes that cancel."""
    return pole_evidence(times_s, x, poles_rad_s, n_channels)[0]


def pole_evidence(times_s, x, poles_rad_s, n_channels: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Per pole, (share, significance): the energy a decay fit loses without it (in the motion's n_channels
    principal components) as a share of the motion's (`explained_share`), and as a multiple of what a pole
    would explain in white noise of the fit's residual variance (2 unknowns per channel, so about 1 for a pole
    of the noise's, chi-square with 2 x n_channels degrees of freedom over its mean: 4 is 8 standard
    deviations above at 8 channels)."""
    t = np.asarray(times_s, float).reshape(-1)
    y = principal_components(np.asarray(x, float).reshape(len(t), -1), n_channels)
    total = float(np.sum(y ** 2))
    lam = np.asarray(poles_rad_s, complex)

    def residual(keep) -> float:
        return float(np.sum((y - fit_decay(t, y, lam[keep]).synthesize(t)) ** 2)) if keep.any() else total

    every = np.ones(len(lam), bool)
    base = residual(every)
    loss = np.array([residual(every & (np.arange(len(lam)) != r)) - base for r in range(len(lam))])
    n_c = y.shape[1]
    dof = max(y.size - (2 * len(lam) + 1) * n_c, 1)
    noise = 2 * n_c * max(base, 1e-300 * max(total, 1e-300)) / dof
    return loss / max(total, 1e-300), loss / noise
