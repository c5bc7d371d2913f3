"""Experimental modal analysis: LSCF poles, stabilisation chart, pole selection and LSFD modal constants.

Poles are in rad/s, lambda = -zeta*wn + 1j*wn*sqrt(1 - zeta^2); residues are always displacement residues.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from odsplat.spine.errors import InputError

from .frf import correct_poles

log = logging.getLogger(__name__)

FRF_KINDS = {"receptance": 0, "mobility": 1, "accelerance": 2}
STATUSES = ("stable", "damping", "freq", "new")  # best first


def pole_freq_hz(poles_rad_s) -> np.ndarray:
    """Undamped natural frequency |lambda| / 2 pi of each pole."""
    return np.abs(np.asarray(poles_rad_s)) / (2 * np.pi)


def pole_damping(poles_rad_s) -> np.ndarray:
    """Damping ratio -Re(lambda) / |lambda| of each pole."""
    p = np.asarray(poles_rad_s)
    return -p.real / np.abs(p)


def pole_from_freq_damping(freq_hz, damping) -> np.ndarray:
    wn = 2 * np.pi * np.asarray(freq_hz, float)
    zeta = np.asarray(damping, float)
    return -zeta * wn + 1j * wn * np.sqrt(1 - zeta**2)


# ------------------------------------------------------------------ input checks

def _check_frf(freq_hz, frf) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """(F,) frequencies and the FRFs as (F, n_out, n_in), with the caller's trailing shape."""
    f = np.asarray(freq_hz, float)
    if f.ndim != 1 or f.size < 2:
        raise InputError("freq_hz", f"expected a 1-D array of at least 2 frequency lines; got shape {f.shape}")
    if not np.all(np.isfinite(f)) or np.any(np.diff(f) <= 0) or f[0] < 0:
        raise InputError("freq_hz", "expected finite, non-negative, strictly increasing frequencies")
    h = np.asarray(frf)
    if h.ndim not in (1, 2, 3) or h.shape[0] != f.size or 0 in h.shape:
        raise InputError("frf", f"expected shape (F,), (F, n_out) or (F, n_out, n_in) with F = {f.size}; "
                                f"got {h.shape}")
    if not np.all(np.isfinite(h)):
        raise InputError("frf", "holds NaN or infinite values")
    trailing = h.shape[1:]
    return f, h.astype(complex).reshape(f.size, *(trailing + (1,) * (3 - h.ndim))), trailing


def _band(f: np.ndarray, fmin_hz, fmax_hz) -> tuple[np.ndarray, tuple[float, float]]:
    lo = float(f[0]) if fmin_hz is None else float(fmin_hz)
    hi = float(f[-1]) if fmax_hz is None else float(fmax_hz)
    if not lo < hi:
        raise InputError("fmin_hz, fmax_hz", f"expected fmin_hz < fmax_hz; got {lo} and {hi}")
    mask = (f >= lo) & (f <= hi)
    if mask.sum() < 2:
        raise InputError("fmin_hz, fmax_hz", f"the band {lo:g}-{hi:g} Hz holds {mask.sum()} frequency lines "
                                             f"(data spans {f[0]:g}-{f[-1]:g} Hz); expected at least 2")
    return mask, (lo, hi)


def _check_kind(frf_kind: str) -> int:
    if frf_kind not in FRF_KINDS:
        raise InputError("frf_kind", f"expected one of {', '.join(FRF_KINDS)}; got {frf_kind!r}")
    return FRF_KINDS[frf_kind]


# ------------------------------------------------------------------ LSCF

@dataclass(frozen=True)
class PolesAtOrder:
    """The physical poles of one model order, sorted by frequency.

    `participation` holds the modal participation vector of each pole, (n_poles, n_in), for
    multiple-reference fits; it is None with one reference, where it would be a trivial scalar.
    """

    order: int
    poles_rad_s: np.ndarray
    participation: np.ndarray | None = None

    @property
    def freq_hz(self) -> np.ndarray:
        return pole_freq_hz(self.poles_rad_s)

    @property
    def damping(self) -> np.ndarray:
        return pole_damping(self.poles_rad_s)


def lscf(freq_hz, frf, *, max_order: int, fmin_hz: float | None = None, fmax_hz: float | None = None,
         orders: Sequence[int] | None = None) -> list[PolesAtOrder]:
    """Poles of every model order by the (poly-reference) least-squares complex-frequency-domain estimator.

    The common-denominator right matrix-fraction model H_o(w) = N_o(z) D(z)^-1 in z = exp(i w dt), with
    dt = 1 / (2 fmax_hz) so that the band maps onto the upper half of the unit circle, is linearised,
    the numerator coefficients are eliminated (reduced normal equations, Guillaume et al. / Peeters et al.
    PolyMAX), and the highest denominator coefficient is fixed to the identity. frf is (F, n_out) or
    (F, n_out, n_in), any kind; each output is scaled to unit RMS in the band so that all weigh alike.
    Order n gives n * n_in poles; only those with Re < 0, Im > 0 and |lambda| / 2 pi in the band are kept.
    Orders default to 2..max_order.
    """
    f, h, _ = _check_frf(freq_hz, frf)
    mask, (lo, hi) = _band(f, fmin_hz, fmax_hz)
    if not isinstance(max_order, (int, np.integer)) or max_order < 2:
        raise InputError("max_order", f"expected an integer of at least 2; got {max_order!r}")
    orders = list(range(2, max_order + 1)) if orders is None else sorted({int(o) for o in orders})
    if not orders or orders[0] < 1 or orders[-1] > max_order:
        raise InputError("orders", f"expected model orders in 1..max_order={max_order}; got {orders}")
    if 2 * mask.sum() <= max_order:
        raise InputError("max_order", f"order {max_order} needs more than {max_order // 2} lines in the band; "
                                      f"it holds {mask.sum()}")
    t0 = time.perf_counter()
    hb = h[mask]
    rms = np.sqrt(np.mean(np.abs(hb) ** 2, axis=(0, 2)))
    if np.any(rms == 0):
        raise InputError("frf", f"outputs {np.flatnonzero(rms == 0).tolist()} are zero in the band")
    hb = hb / rms[None, :, None]
    dt = 1.0 / (2.0 * hi)
    R, S, T = _lscf_normal_matrices(2 * np.pi * f[mask] * dt, hb, max_order)
    n_in = h.shape[2]
    out = [_lscf_poles(_lscf_denominator(M, n, n_in), n, n_in, dt, lo, hi)
           for n, M in _lscf_reduced(R, S, T, orders, n_in)]
    log.debug("lscf: %d orders up to %d on %d lines x %d FRFs in %.3f s", len(orders), orders[-1],
              hb.shape[0], hb.shape[1] * n_in, time.perf_counter() - t0)
    return out


def _lscf_normal_matrices(theta: np.ndarray, h: np.ndarray, n: int):
    """R (n+1, n+1), S (n_out, n+1, (n+1) m) and sum_o T_o ((n+1) m, (n+1) m) of the order-n problem.

    Every entry depends on k - j only (the basis is z^j), so all three are Toeplitz-like gathers of
    sums over the lines of z^d times 1, H or H^H H; lower orders are their leading blocks.
    """
    d = np.arange(-n, n + 1)
    v = np.exp(1j * np.outer(theta, d))  # (F, 2n+1)
    n_out, m = h.shape[1], h.shape[2]
    r = v.sum(axis=0)
    s = (v.T @ h.reshape(h.shape[0], -1)).reshape(-1, n_out, m)
    p = np.einsum("foi,fol->fil", h.conj(), h)
    t = (v.T @ p.reshape(h.shape[0], -1)).reshape(-1, m, m)
    idx = d[n:][None, :] - d[n:][:, None] + n  # [j, k] -> k - j + n
    R = r[idx].real
    S = -s[idx].real.transpose(2, 0, 1, 3).reshape(n_out, n + 1, (n + 1) * m)
    T = t[idx].real.transpose(0, 2, 1, 3).reshape((n + 1) * m, (n + 1) * m)
    return R, S, T


def _lscf_reduced(R, S, T, orders: list[int], m: int):
    """Yield (n, M_n) with M_n = T_n - sum_o S_o^T R_n^-1 S_o, the reduced normal matrix of order n.

    R_n is the leading block of R, so its Cholesky factor is the leading block of R's, and L_n^-1 S_o
    is made of the leading rows of L^-1 S_o: one factorisation serves every order, and the sum grows
    by one row of G = L^-1 S per order.
    """
    n_max, n_out, K = R.shape[0] - 1, S.shape[0], S.shape[2]
    Sflat = S.transpose(1, 0, 2).reshape(n_max + 1, -1)  # (j, o K)
    try:
        L = np.linalg.cholesky(R)
    except np.linalg.LinAlgError:
        log.warning("lscf: the band is too narrow for order %d to be well conditioned; slow path", n_max)
        for n in orders:
            k = (n + 1) * m
            Sn = S[:, : n + 1, :k].transpose(1, 0, 2).reshape(n + 1, -1)
            X = np.linalg.lstsq(R[: n + 1, : n + 1], Sn, rcond=None)[0]
            yield n, T[:k, :k] - Sn.reshape(-1, k).T @ X.reshape(-1, k)
        return
    G = solve_triangular(L, Sflat, lower=True).reshape(n_max + 1, n_out, K)
    Q = np.zeros((K, K))
    done = 0  # rows of G summed into Q
    for n in orders:
        for j in range(done, n + 1):
            Q += G[j].T @ G[j]
        done = n + 1
        k = (n + 1) * m
        yield n, T[:k, :k] - Q[:k, :k]


def _lscf_denominator(M: np.ndarray, n: int, m: int) -> np.ndarray:
    """Denominator coefficients alpha_0..alpha_{n-1} as (n m, m), with alpha_n = I."""
    a, b = M[: n * m, : n * m], M[: n * m, n * m:]
    try:
        return -np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        return -np.linalg.lstsq(a, b, rcond=None)[0]


def _lscf_poles(alpha: np.ndarray, n: int, m: int, dt: float, lo: float, hi: float) -> PolesAtOrder:
    # Companion matrix of D(z)^T: its eigenvectors start with the left null vectors of D, which are
    # the participation vectors of H = N D^-1.
    c = np.zeros((n * m, n * m))
    c[:-m, m:] = np.eye((n - 1) * m)
    c[-m:, :] = -alpha.reshape(n, m, m).transpose(2, 0, 1).reshape(m, n * m)  # [-alpha_0^T ... -alpha_{n-1}^T]
    if m == 1:
        z, vec = np.linalg.eigvals(c.T), None  # upper Hessenberg: LAPACK needs no reduction, 2-3x faster
    else:
        z, vec = np.linalg.eig(c)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.log(z.astype(complex)) / dt
    fn = np.abs(lam) / (2 * np.pi)
    keep = np.isfinite(lam) & (lam.real < 0) & (lam.imag > 0) & (fn >= lo) & (fn <= hi)
    order = np.argsort(fn[keep])
    part = None if vec is None else vec[:m, keep].T[order]
    return PolesAtOrder(n, lam[keep][order], part)


# ------------------------------------------------------------------ stabilisation and selection

@dataclass(frozen=True)
class StabilisationChart:
    """The poles of every order with a status per pole, from comparison with the previous order.

    "new": no pole of the previous order within freq_tol; "freq": frequency stable only;
    "damping": frequency and damping stable but the participation vector is not (multiple references);
    "stable": frequency, damping and (where there are vectors) participation vector stable.
    """

    levels: tuple[PolesAtOrder, ...]
    status: tuple[np.ndarray, ...]
    freq_tol: float
    damping_tol: float

    @property
    def orders(self) -> tuple[int, ...]:
        return tuple(lv.order for lv in self.levels)

    def flat(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every pole of the chart as (order, pole_rad_s, status) arrays, for plotting and selection."""
        order = np.concatenate([np.full(lv.poles_rad_s.size, lv.order) for lv in self.levels])
        poles = np.concatenate([lv.poles_rad_s for lv in self.levels])
        return order, poles, np.concatenate(self.status)


def stabilisation(poles_by_order: Sequence[PolesAtOrder], *, freq_tol: float = 0.01, damping_tol: float = 0.05,
                  mac_tol: float = 0.02) -> StabilisationChart:
    """Classify each pole against the nearest (in frequency) pole of the previous order.

    Relative tolerances: |df| / f < freq_tol, |dzeta| / zeta < damping_tol and, where both poles carry
    participation vectors, MAC > 1 - mac_tol.
    """
    levels = tuple(poles_by_order)
    if not levels:
        raise InputError("poles_by_order", "expected the poles of at least one model order")
    for name, tol in (("freq_tol", freq_tol), ("damping_tol", damping_tol), ("mac_tol", mac_tol)):
        if not tol > 0:
            raise InputError(name, f"expected a positive relative tolerance; got {tol}")
    status = []
    prev = None
    for lv in levels:
        st = np.full(lv.poles_rad_s.size, "new", dtype="<U7")
        if prev is not None and prev.poles_rad_s.size and lv.poles_rad_s.size:
            f, z, fp, zp = lv.freq_hz, lv.damping, prev.freq_hz, prev.damping
            near = np.argmin(np.abs(f[:, None] - fp[None, :]), axis=1)
            f_ok = np.abs(f - fp[near]) < freq_tol * f
            d_ok = np.abs(z - zp[near]) < damping_tol * np.abs(z)
            v_ok = np.ones_like(f_ok)
            if lv.participation is not None and prev.participation is not None:
                a, b = lv.participation, prev.participation[near]
                mac = np.abs(np.sum(a.conj() * b, axis=1)) ** 2 / (
                    np.sum(np.abs(a) ** 2, axis=1) * np.sum(np.abs(b) ** 2, axis=1))
                v_ok = mac > 1 - mac_tol
            st[f_ok] = "freq"
            st[f_ok & d_ok] = "damping"
            st[f_ok & d_ok & v_ok] = "stable"
        status.append(st)
        prev = lv
    return StabilisationChart(levels, tuple(status), freq_tol, damping_tol)


def select_poles(chart: StabilisationChart, *, approx_freq_hz: Sequence[float] | None = None,
                 min_stable: float = 0.5, cluster_tol: float = 0.005, max_damping: float = 0.2,
                 search_tol: float = 0.05, peaks_hz: Sequence[float] = (), peak_tol: float = 0.005,
                 peak_min_stable: float = 0.25) -> np.ndarray:
    """Pick one pole per mode from a stabilisation chart; returns poles (rad/s) sorted by frequency.

    Automatic (approx_freq_hz None): the "stable" poles with damping below max_damping are sorted by
    frequency and split into clusters wherever neighbours lie more than cluster_tol (relative) apart;
    a cluster is a mode when it has stable poles in at least min_stable of the chart's orders. Its pole
    has the median frequency and damping of the cluster's poles in the upper half of its orders: the
    noise biases LSCF's damping, less so the more the model is over-specified. Since the fraction counts
    every order of the chart, max_order should be about twice the order where the modes first settle.
    Guided by peaks_hz (the FRFs' clear peaks): a peak with no cluster within peak_tol of it takes the cluster
    nearest to it within peak_tol that is stable in at least peak_min_stable of the orders. A lightly damped
    mode's damping settles late (its frequency long before), so the half-of-the-orders rule alone can miss a
    mode the FRF shows plainly.
    Manual: for each approx_freq_hz (in the order given), among the poles within search_tol (relative)
    of it, those of the best status; of them the nearest in frequency.
    """
    order, poles, status = chart.flat()
    if approx_freq_hz is not None:
        return _select_manual(order, poles, status, np.atleast_1d(np.asarray(approx_freq_hz, float)), search_tol)
    if not 0 < min_stable <= 1:
        raise InputError("min_stable", f"expected a fraction of the orders in (0, 1]; got {min_stable}")
    keep = (status == "stable") & (pole_damping(poles) < max_damping)
    order, poles = order[keep], poles[keep]
    if poles.size == 0:
        return np.zeros(0, complex)
    fn = pole_freq_hz(poles)
    srt = np.argsort(fn)
    order, poles, fn = order[srt], poles[srt], fn[srt]
    cuts = np.flatnonzero(np.diff(fn) > cluster_tol * fn[1:]) + 1
    need = min_stable * len(chart.levels)
    clusters = []                                   # (centre Hz, orders with a stable pole, pole)
    for idx in np.split(np.arange(fn.size), cuts):
        top = idx[order[idx] >= np.median(order[idx])]
        clusters.append((float(np.median(fn[idx])), np.unique(order[idx]).size,
                         pole_from_freq_damping(np.median(fn[top]), np.median(pole_damping(poles[top])))))
    picked = [c for c in clusters if c[1] >= need]
    for f0 in peaks_hz:
        if any(abs(c[0] - f0) <= peak_tol * f0 for c in picked):
            continue
        near = [c for c in clusters if abs(c[0] - f0) <= peak_tol * f0
                and c[1] >= peak_min_stable * len(chart.levels) and c not in picked]
        if near:
            best = min(near, key=lambda c: abs(c[0] - f0))
            picked.append(best)
            log.info("select_poles: the FRF peak at %.1f Hz takes the pole at %.1f Hz (stable in %d orders)", f0,
                     best[0], best[1])
    log.debug("select_poles: %d clusters, %d kept (need stable poles in %.1f orders)", len(clusters),
              len(picked), need)
    picked = np.array([c[2] for c in picked], complex)
    return picked[np.argsort(pole_freq_hz(picked))]


def _select_manual(order, poles, status, approx, search_tol: float) -> np.ndarray:
    if approx.ndim != 1 or not np.all(np.isfinite(approx)) or np.any(approx <= 0):
        raise InputError("approx_freq_hz", f"expected positive frequencies; got {approx}")
    fn = pole_freq_hz(poles)
    rank = np.array([STATUSES.index(s) for s in status], int)
    picked = []
    for f0 in approx:
        near = np.abs(fn - f0) <= search_tol * f0
        if not near.any():
            raise InputError("approx_freq_hz", f"no pole of the chart within {search_tol:.0%} of {f0:g} Hz")
        cand = np.flatnonzero(near & (rank == rank[near].min()))
        picked.append(poles[cand[np.argmin(np.abs(fn[cand] - f0))]])
    return np.array(picked, complex)


# ------------------------------------------------------------------ LSFD

@dataclass(frozen=True)
class LSFDResult:
    """Modal constants of a fixed set of poles, fitted in the FRF kind `frf_kind`.

    Model (receptance; mobility and accelerance are it times (i w)^1 and (i w)^2):
    H = sum_r [A_r / (i w - lambda_r) + conj(A_r) / (i w - conj(lambda_r))] + lower / (i w)^2 + upper.
    residues A_r: (n_modes, *frf trailing shape) complex, m/(N s); residue_std: their standard error from
    the fit residual (real and imaginary parts taken as independent). The lower (1/kg, a mass line) and
    upper (m/N, a stiffness line) residuals are real, zero when fitted without them. fit_error: the
    relative RMS misfit of each FRF in the band.
    """

    poles_rad_s: np.ndarray
    residues: np.ndarray
    residue_std: np.ndarray
    lower_residual: np.ndarray
    upper_residual: np.ndarray
    fit_error: np.ndarray
    frf_kind: str
    band_hz: tuple[float, float]

    def synthesize(self, freq_hz) -> np.ndarray:
        """The fitted FRF (kind frf_kind) at freq_hz: (F, *frf trailing shape)."""
        f = np.asarray(freq_hz, float)
        basis = _lsfd_basis(2 * np.pi * f, self.poles_rad_s, FRF_KINDS[self.frf_kind], True)
        n = self.poles_rad_s.size
        coef = np.concatenate([self.residues.real.reshape(n, -1), self.residues.imag.reshape(n, -1),
                               self.lower_residual.reshape(1, -1), self.upper_residual.reshape(1, -1)])
        return (basis @ coef).reshape(f.size, *self.residues.shape[1:])

    def normal_mode_shapes(self) -> np.ndarray:
        """Real shapes: each complex shape rotated by its mean phase, then the real part.

        The mean phase is half the angle of sum(psi^2): the direction of the least-squares line through
        the shape's points in the complex plane, so components near 0 and 180 degrees both count. Each
        shape's largest component is made positive.
        """
        n = self.residues.shape[0]
        psi = self.residues.reshape(n, -1)
        real = (psi * np.exp(-1j * mean_phase_rad(psi))[:, None]).real
        sign = np.sign(real[np.arange(n), np.argmax(np.abs(real), axis=1)])
        return (real * np.where(sign == 0, 1, sign)[:, None]).reshape(self.residues.shape)


def mean_phase_rad(psi: np.ndarray) -> np.ndarray:
    """(n,) the mean phase of each complex shape psi (n, M): half the angle of sum(psi^2), the direction of the
    least-squares line through its points in the complex plane (components near 0 and 180 degrees both count)."""
    return 0.5 * np.angle(np.sum(np.asarray(psi, complex) ** 2, axis=1))


def _lsfd_basis(w: np.ndarray, poles: np.ndarray, power: int, residuals: bool) -> np.ndarray:
    """(F, 2 n_modes [+ 2]) complex columns of the real unknowns Re A_r, Im A_r [, lower, upper]."""
    iw = 1j * w[:, None]
    a = 1 / (iw - poles[None, :])
    b = 1 / (iw - poles.conj()[None, :])
    cols = [(a + b) * iw**power, 1j * (a - b) * iw**power]
    if residuals:
        with np.errstate(divide="ignore", invalid="ignore"):
            cols += [iw ** (power - 2) if power >= 2 else 1 / iw ** (2 - power), iw**power]
    return np.concatenate(cols, axis=1)


def lsfd(freq_hz, frf, poles_rad_s, *, frf_kind: str, residuals: bool = True, fmin_hz: float | None = None,
         fmax_hz: float | None = None) -> LSFDResult:
    """Least-squares frequency-domain modal constants of given poles, per output (and input).

    One real linear least-squares problem (real and imaginary parts stacked) shared by every FRF in the
    band; the 0 Hz line, where the lower residual is singular, is left out. Residues are displacement
    residues whatever frf_kind is: the model is fitted in the kind of the data (see LSFDResult).
    """
    f, h, trailing = _check_frf(freq_hz, frf)
    power = _check_kind(frf_kind)
    poles = np.atleast_1d(np.asarray(poles_rad_s, complex))
    if poles.ndim != 1 or poles.size == 0 or not np.all(np.isfinite(poles)) or np.any(poles.imag <= 0):
        raise InputError("poles_rad_s", f"expected a 1-D array of poles with positive imaginary part; "
                                        f"got {poles!r}")
    mask, band = _band(f, fmin_hz, fmax_hz)
    mask &= f > 0
    basis = _lsfd_basis(2 * np.pi * f[mask], poles, power, residuals)
    n_f, k = basis.shape
    if 2 * n_f <= k:
        raise InputError("fmin_hz, fmax_hz", f"the band holds {n_f} lines; LSFD needs more than {k // 2}")
    y = h[mask].reshape(n_f, -1)
    A = np.concatenate([basis.real, basis.imag])
    rhs = np.concatenate([y.real, y.imag])
    norm = np.linalg.norm(A, axis=0)
    u, s, vt = np.linalg.svd(A / norm, full_matrices=False)
    s_inv = np.where(s > s[0] * 1e-12, 1 / s, 0.0)
    coef = (vt.T * s_inv) @ (u.T @ rhs) / norm[:, None]
    resid = rhs - A @ coef
    sigma2 = np.sum(resid**2, axis=0) / max(2 * n_f - k, 1)
    var = ((vt.T * s_inv) ** 2).sum(axis=1) / norm**2  # diag((A^T A)^-1)
    n = poles.size
    shape = (n, *trailing)
    zeros = np.zeros(trailing)
    std = np.sqrt((var[:n, None] + var[n:2 * n, None]) * sigma2[None, :])
    fit_error = np.linalg.norm(resid, axis=0) / np.maximum(np.linalg.norm(rhs, axis=0), np.finfo(float).tiny)
    return LSFDResult(
        poles_rad_s=poles,
        residues=(coef[:n] + 1j * coef[n:2 * n]).reshape(shape),
        residue_std=std.reshape(shape),
        lower_residual=coef[2 * n].reshape(trailing) if residuals else zeros,
        upper_residual=coef[2 * n + 1].reshape(trailing) if residuals else zeros,
        fit_error=fit_error.reshape(trailing),
        frf_kind=frf_kind,
        band_hz=band,
    )


# ------------------------------------------------------------------ one call

@dataclass(frozen=True)
class ModalFit:
    """Identified modes sorted by frequency: freq_hz is the undamped natural frequency |lambda| / 2 pi.

    shapes are the complex displacement residues of the first reference, (n_modes, n_out); residues
    keep every reference, as LSFDResult.residues.
    """

    freq_hz: np.ndarray
    damping: np.ndarray
    poles_rad_s: np.ndarray
    shapes: np.ndarray
    residues: np.ndarray
    chart: StabilisationChart
    lsfd: LSFDResult
    frf_kind: str
    band_hz: tuple[float, float]
    output_names: tuple[str, ...] | None = None

    @property
    def n_modes(self) -> int:
        return self.freq_hz.size

    def with_corrected_damping(self, tau_s: float) -> ModalFit:
        """Remove the damping added by an exponential window exp(-t / tau_s) on the measured responses.

        The window moves every pole left by 1 / tau_s; the true pole is lambda + 1 / tau_s, so
        zeta_true ~ zeta_measured - 1 / (tau_s wn). Shapes, residues and the LSFD fit are kept as fitted.
        """
        poles = correct_poles(self.poles_rad_s, tau_s)
        if np.any(poles.real >= 0):
            bad = self.freq_hz[poles.real >= 0]
            raise InputError("tau_s", f"a window of {tau_s:g} s would leave the modes at {bad} Hz undamped; "
                                      "it is shorter than the window the FRFs were computed with")
        return dataclasses.replace(self, poles_rad_s=poles, freq_hz=pole_freq_hz(poles),
                                   damping=pole_damping(poles))


MAX_ORDER = 120   # a low, lightly damped mode settles late (23.5 Hz on the rig with 1 Hz lines: from order ~42)


def default_max_order(n_lines: int) -> int:
    """The LSCF order a band of n_lines carries by default: MAX_ORDER, at most half its lines (lscf needs fewer
    than twice; on a 170 ms record of the rig, 49 lines, orders 24 and 47 select the same four modes)."""
    return max(2, min(MAX_ORDER, int(n_lines) // 2))


def fit_modes(freq_hz, frf, *, frf_kind: str, fmin_hz: float, fmax_hz: float, max_order: int | None = 80,
              approx_freq_hz: Sequence[float] | None = None, output_names: Sequence[str] | None = None,
              min_stable: float = 0.5, freq_tol: float = 0.01, damping_tol: float = 0.05,
              residuals: bool = True, peaks_hz: Sequence[float] = ()) -> ModalFit:
    """LSCF poles up to max_order (None: `default_max_order` of the band's lines, as the analysis asks by default;
    80 here keeps the function's own default as it was), a stabilisation chart, automatic
    (guided by the FRFs' clear peaks_hz; or, with approx_freq_hz, manual) pole selection, and LSFD modal
    constants, all in the band fmin_hz..fmax_hz."""
    f, h, trailing = _check_frf(freq_hz, frf)
    _check_kind(frf_kind)
    if max_order is None:
        max_order = default_max_order(int(_band(f, fmin_hz, fmax_hz)[0].sum()))
        log.info("fit_modes: max_order %d from the band's lines", max_order)
    if output_names is not None:
        output_names = tuple(str(s) for s in output_names)
        n_out = 1 if not trailing else trailing[0]
        if len(output_names) != n_out:
            raise InputError("output_names", f"expected {n_out} names, one per output; got {len(output_names)}")
    chart = stabilisation(lscf(f, frf, max_order=max_order, fmin_hz=fmin_hz, fmax_hz=fmax_hz),
                          freq_tol=freq_tol, damping_tol=damping_tol)
    poles = select_poles(chart, approx_freq_hz=approx_freq_hz, min_stable=min_stable, peaks_hz=peaks_hz)
    if poles.size == 0:
        raise InputError("max_order", f"no mode stable in {min_stable:.0%} of the orders up to {max_order} "
                                      f"in {fmin_hz:g}-{fmax_hz:g} Hz; raise max_order or lower min_stable")
    poles = poles[np.argsort(pole_freq_hz(poles))]
    fit = lsfd(f, frf, poles, frf_kind=frf_kind, residuals=residuals, fmin_hz=fmin_hz, fmax_hz=fmax_hz)
    res = fit.residues
    shapes = res.reshape(res.shape[0], -1) if not trailing else res.reshape(*res.shape[:2], -1)[..., 0]
    log.info("fit_modes: %d modes at %s Hz", poles.size, np.round(pole_freq_hz(poles), 2).tolist())
    return ModalFit(pole_freq_hz(poles), pole_damping(poles), poles, shapes, res, chart, fit, frf_kind,
                    fit.band_hz, output_names)
