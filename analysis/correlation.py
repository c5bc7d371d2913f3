"""Correlation of two sets of shapes at the same degrees of freedom: MAC, AutoMAC, CoMAC, modal scale factor,
pairing."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from odsplat.spine.errors import InputError


def _shapes(a, name: str) -> np.ndarray:
    """(n_shapes, n_dof) complex; a single shape (n_dof,) becomes (1, n_dof)."""
    a = np.asarray(a)
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] == 0:
        raise InputError(name, f"expected shapes as (n_shapes, n_dof); got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(name, "shapes hold NaN or infinite values")
    return a.astype(complex)


def _pair_check(a: np.ndarray, b: np.ndarray, names: tuple[str, str]) -> None:
    if a.shape[1] != b.shape[1]:
        raise InputError(f"{names[0]}, {names[1]}",
                         f"shapes must have the same degrees of freedom; got {a.shape[1]} and {b.shape[1]}")


def mac(a, b) -> np.ndarray:
    """Modal assurance criterion |a_i^H b_j|^2 / (a_i^H a_i b_j^H b_j), (n_a, n_b), for complex or real shapes."""
    a, b = _shapes(a, "mac: a"), _shapes(b, "mac: b")
    _pair_check(a, b, ("mac: a", "mac: b"))
    num = np.abs(np.conj(a) @ b.T) ** 2
    den = np.outer(np.sum(np.abs(a) ** 2, axis=1), np.sum(np.abs(b) ** 2, axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def auto_mac(shapes) -> np.ndarray:
    """The MAC of a set of shapes with itself, (n, n): how alike each two of them are at their degrees of freedom.
    shapes: (n, ...) per shape, flattened: (n, S) at sensors, or (n, N, 3) on a surface (complex or real)."""
    a = np.asarray(shapes)
    if a.ndim < 1 or a.shape[0] == 0:
        raise InputError("auto_mac: shapes", f"expected at least one shape; got shape {a.shape}")
    a = a.reshape(a.shape[0], -1)
    return mac(a, a)


def modal_scale_factor(a, b) -> np.ndarray:
    """Per pair of rows, the complex factor s minimising |a_i - s b_i|: s = b_i^H a_i / b_i^H b_i, (n,)."""
    a, b = _shapes(a, "modal_scale_factor: a"), _shapes(b, "modal_scale_factor: b")
    _pair_check(a, b, ("modal_scale_factor: a", "modal_scale_factor: b"))
    if a.shape[0] != b.shape[0]:
        raise InputError("modal_scale_factor", f"expected paired shapes; got {a.shape[0]} and {b.shape[0]}")
    den = np.sum(np.abs(b) ** 2, axis=1)
    return np.sum(np.conj(b) * a, axis=1) / np.where(den > 0, den, 1.0)


def comac(a, b) -> np.ndarray:
    """Coordinate MAC per degree of freedom over paired shapes (rows of a and b in pairs), (n_dof,).

    Each b_i is first scaled onto a_i by its modal scale factor, so that a coordinate is judged by how well it
    agrees in shape, not by the two sets' normalisation."""
    a, b = _shapes(a, "comac: a"), _shapes(b, "comac: b")
    b = b * modal_scale_factor(a, b)[:, None]
    num = np.abs(np.sum(np.conj(a) * b, axis=0)) ** 2
    den = np.sum(np.abs(a) ** 2, axis=0) * np.sum(np.abs(b) ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


@dataclass(frozen=True)
class Correlation:
    """Two shape sets compared: the MAC matrix and the pairs found in it."""

    mac: np.ndarray              # (n_a, n_b)
    pairs: tuple[tuple[int, int], ...]   # (i in a, j in b), best one-to-one by MAC
    pair_mac: np.ndarray         # (n_pairs,)
    scale_factor: np.ndarray     # (n_pairs,) complex: a_i ~ s b_j
    comac: np.ndarray            # (n_dof,) over the pairs
    freq_a_hz: np.ndarray | None = None   # (n_pairs,) when frequencies were given
    freq_b_hz: np.ndarray | None = None

    @property
    def freq_diff_rel(self) -> np.ndarray | None:
        """(f_b - f_a) / f_a per pair."""
        if self.freq_a_hz is None or self.freq_b_hz is None:
            return None
        return (self.freq_b_hz - self.freq_a_hz) / self.freq_a_hz


def correlate(a, b, *, freq_a_hz=None, freq_b_hz=None, min_mac: float = 0.0, paired: bool = False) -> Correlation:
    """Pair the shapes of b with those of a one-to-one by maximum total MAC (Hungarian assignment), keeping pairs
    with MAC >= min_mac, and report MAC, modal scale factors, CoMAC over the pairs and frequency differences.

    paired=True: row i of b already belongs to row i of a (as the video's residues fitted with the accelerometers'
    poles do), so they are paired as given. Pairing by MAC would swap two modes whose shapes look alike at a few
    sensors (on the rig, 262 and 371 Hz at the four accelerometers)."""
    a, b = _shapes(a, "correlate: a"), _shapes(b, "correlate: b")
    m = mac(a, b)
    fa = None if freq_a_hz is None else np.asarray(freq_a_hz, float)
    fb = None if freq_b_hz is None else np.asarray(freq_b_hz, float)
    for f, s, name in ((fa, a, "freq_a_hz"), (fb, b, "freq_b_hz")):
        if f is not None and f.shape != (s.shape[0],):
            raise InputError(f"correlate: {name}", f"expected one frequency per shape ({s.shape[0]}); got {f.shape}")
    if paired:
        if a.shape[0] != b.shape[0]:
            raise InputError("correlate: b", f"paired shapes need as many rows as a ({a.shape[0]}); got {b.shape[0]}")
        rows = cols = np.arange(a.shape[0])
    else:
        rows, cols = linear_sum_assignment(-m)
    keep = [(int(i), int(j)) for i, j in zip(rows, cols) if m[i, j] >= min_mac]
    keep.sort()
    ia = np.array([i for i, _ in keep], int)
    jb = np.array([j for _, j in keep], int)
    sf = modal_scale_factor(a[ia], b[jb]) if keep else np.zeros(0, complex)
    cm = comac(a[ia], b[jb]) if keep else np.zeros(a.shape[1])
    return Correlation(mac=m, pairs=tuple(keep), pair_mac=m[ia, jb], scale_factor=sf, comac=cm,
                       freq_a_hz=None if fa is None else fa[ia], freq_b_hz=None if fb is None else fb[jb])
