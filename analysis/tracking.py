"""Single-view point tracking: the 2D image displacement of chosen points against the first frame, by Lucas-Kanade
or local phase, and the first-order image motion of 3D displacements, so the 3D ODS can be checked view by view."""
from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import correlate1d, spline_filter1d
from tqdm import tqdm

from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

METHODS = ("gradient", "lk", "phase")
DEFAULT_METHOD = "gradient"  # the most accurate at 0.01-1 px on the simulated rig (see docs)
_PAD = 8          # prefilter rows beyond the spline taps: the boundary error of the B-spline prefilter decays as 0.27^n
_BLOCK = 32       # points iterated together: big enough to vectorise, small enough to stay in cache
_LK_LEVELS = 2    # OpenCV pyramid levels: only the starting guess comes from them, the answer from level 0


@dataclass(frozen=True, eq=False)
class Tracks:
    """Image displacement of points in one view, relative to the first (reference) frame."""

    points_px: np.ndarray        # (P, 2) (x, y) positions in the reference frame, as given
    displacement_px: np.ndarray  # (T, P, 2) (x, y); frame 0 is zero; NaN for untrackable points or lost frames
    quality: np.ndarray          # (P,) rms intensity gradient along the weakest direction over the window, per px,
    #                              as a fraction of the reference frame's intensity range (0.5-99.5 percentile)
    method: str

    @property
    def n_frames(self) -> int:
        return self.displacement_px.shape[0]


def track_points(frames, points_px, *, method: str = DEFAULT_METHOD, window_px: int = 15, min_quality: float = 0.01,
                 wavelength_px: float = 6.0, max_iterations: int = 20, tolerance_px: float = 1e-4,
                 progress: bool = False) -> Tracks:
    """Track `points_px` (P, 2) (x, y) through `frames`, each frame against the first one (no drift).

    frames: a (T, H, W) array, an iterable of (H, W) arrays (streamed, one frame in memory at a time) or a
    `VideoSource` (read in chunks); mono, any real dtype. method: "gradient" (template Lucas-Kanade on a cubic
    B-spline of each frame, with gain and offset of the intensity solved for), "lk" (OpenCV's pyramidal LK on
    frames scaled to 8 bits) or "phase" (local phase of a Gabor quadrature pair along x and y with `wavelength_px`,
    amplitude weighted). window_px: the side of the square window (odd). Points whose `quality` is below
    `min_quality`, or that lie within window_px // 2 + 2 px of the border, get NaN tracks and a logged warning
    naming them. Each frame starts from the previous frame's answer and iterates until the step is below
    `tolerance_px`; a point whose answer moves a half window from there is lost in that frame (NaN). The phase
    filter reaches 1.25 wavelengths beyond the window: keep that much texture that moves with the point around it.
    """
    if method not in METHODS:
        raise InputError("track_points.method", f"expected one of {', '.join(METHODS)}, got {method!r}")
    if int(window_px) != window_px or window_px < 3 or window_px % 2 == 0:
        raise InputError("track_points.window_px", f"expected an odd integer >= 3, got {window_px}")
    if int(max_iterations) < 1 or not tolerance_px > 0:
        raise InputError("track_points",
                         f"need max_iterations >= 1 and tolerance_px > 0, got {max_iterations}, {tolerance_px}")
    if not wavelength_px >= 3:
        raise InputError("track_points.wavelength_px",
                         f"expected >= 3 px (below that the filter aliases), got {wavelength_px}")
    pts = np.array(points_px, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.all(np.isfinite(pts)):
        raise InputError("track_points.points_px",
                         f"expected finite (P, 2) (x, y) pixel positions, got shape {pts.shape}")
    hw = int(window_px) // 2
    it = _frames(frames)
    try:
        ref = next(it)
    except StopIteration:
        raise InputError("track_points.frames", "expected at least one frame, got none") from None
    H, W = ref.shape
    outside = np.flatnonzero((pts[:, 0] < -0.5) | (pts[:, 0] > W - 0.5) | (pts[:, 1] < -0.5) | (pts[:, 1] > H - 0.5))
    if outside.size:
        raise InputError("track_points.points_px", f"points {outside.tolist()} lie outside the {W}x{H} image")
    base = np.rint(pts).astype(np.int64)
    quality = np.zeros(len(pts))
    inside = np.all((base >= hw + 2) & (base < np.array([W, H]) - hw - 2), axis=1)  # window and its spline taps
    quality[inside] = _quality(ref, base[inside], hw)
    ok = inside & (quality >= min_quality)
    if not inside.all():
        log.warning("track_points: points %s lie within %d px of the image border; their tracks are NaN",
                    np.flatnonzero(~inside).tolist(), hw + 2)
    if not ok[inside].all():
        log.warning("track_points: points %s have too little texture (quality < %g); their tracks are NaN",
                    np.flatnonzero(inside & ~ok).tolist(), min_quality)
    out = [np.zeros((len(pts), 2))]
    out[0][~ok] = np.nan
    if ok.any():
        iters = (max_iterations, tolerance_px)
        tracker = (_OpenCVLK(ref, pts[ok], window_px, *iters) if method == "lk" else
                   _PhaseLK(ref, base[ok], hw, wavelength_px, *iters) if method == "phase" else
                   _GradientLK(ref, base[ok], hw, *iters))
        guess = np.zeros((int(ok.sum()), 2))
        total = getattr(frames, "n_frames", None) or (len(frames) if hasattr(frames, "__len__") else None)
        for frame in tqdm(it, total=None if total is None else total - 1, desc=f"track ({method})", unit="frame",
                          disable=not progress):
            d = np.full((len(pts), 2), np.nan)
            d[ok] = tracker(frame, guess)
            found = np.isfinite(d[ok]).all(axis=1)
            guess[found] = d[ok][found]
            out.append(d)
    else:
        out.extend(np.full((len(pts), 2), np.nan) for _ in it)
    displacement = np.stack(out)
    lost = np.flatnonzero(ok & np.isnan(displacement).any(axis=(0, 2)))
    if lost.size:
        log.warning("track_points: points %s were lost in some frames (NaN there)", lost.tolist())
    return Tracks(pts, displacement, quality, method)


def good_points(frame, mask=None, *, max_points: int = 50, min_distance_px: float = 10.0, window_px: int = 15,
                quality_level: float = 0.05) -> np.ndarray:
    """Shi-Tomasi points (P, 2) (x, y), strongest first: local maxima of the structure tensor's smaller eigenvalue
    over a window_px block, at least `quality_level` times the strongest, `min_distance_px` apart, inside the
    optional boolean mask (H, W) and far enough from the border for a `window_px` window."""
    img = np.asarray(frame)
    if img.ndim != 2 or img.size == 0:
        raise InputError("good_points.frame", f"expected a mono (H, W) image, got shape {img.shape}")
    keep = np.ones(img.shape, bool) if mask is None else np.asarray(mask)
    if keep.shape != img.shape:
        raise InputError("good_points.mask",
                         f"expected a boolean mask of the frame's shape {img.shape}, got {keep.shape}")
    keep = keep.astype(bool).copy()
    b = int(window_px) // 2 + 2  # as track_points needs
    keep[:b], keep[-b:], keep[:, :b], keep[:, -b:] = False, False, False, False
    if not keep.any() or max_points < 1:
        return np.zeros((0, 2))
    corners = cv2.goodFeaturesToTrack(img.astype(np.float32), int(max_points), float(quality_level),
                                      float(min_distance_px), mask=keep.astype(np.uint8), blockSize=int(window_px) | 1)
    if corners is None:
        log.warning("good_points: no textured points found inside the mask")
        return np.zeros((0, 2))
    return corners.reshape(-1, 2).astype(np.float64)


def _border(shape: tuple[int, int], window_px: int) -> np.ndarray:
    """(H, W) bool: the pixels far enough from the border for a window_px window (as track_points needs)."""
    keep = np.zeros(shape, bool)
    b = int(window_px) // 2 + 2
    keep[b:-b, b:-b] = True
    return keep


def grid_points(frame, *, spacing_px: float, window_px: int = 15, quality_level: float = 0.005,
                max_points: int | None = None) -> np.ndarray:
    """A regular grid (P, 2) (x, y) every spacing_px over the frame, kept where a window_px window has texture
    enough to track (the structure tensor's smaller eigenvalue at least `quality_level` times the frame's largest);
    the spacing grows until at most max_points remain. Row by row, from the top left."""
    img = np.asarray(frame, np.float32)
    if img.ndim != 2 or img.size == 0:
        raise InputError("grid_points.frame", f"expected a mono (H, W) image, got shape {img.shape}")
    texture = cv2.cornerMinEigenVal(img, int(window_px) | 1)
    ok = (texture >= quality_level * float(texture.max())) & _border(img.shape, window_px) if texture.max() > 0 \
        else np.zeros(img.shape, bool)
    step = float(spacing_px)
    while True:
        ys, xs = np.arange(0.0, img.shape[0], step), np.arange(0.0, img.shape[1], step)
        gx, gy = np.meshgrid(xs, ys)
        p = np.stack([gx.ravel(), gy.ravel()], axis=1)
        p = p[ok[p[:, 1].astype(int), p[:, 0].astype(int)]]
        if max_points is None or len(p) <= max_points:
            return p
        step *= np.sqrt(len(p) / max_points) * 1.01


def edge_points(frame, *, spacing_px: float, window_px: int = 15, max_points: int = 300) -> np.ndarray:
    """Points (P, 2) (x, y) on the frame's edges (Canny, thresholds from the gradient's median), strongest gradient
    first, at least spacing_px apart: where a structure's outline moves across the image, the motion across the
    edge is measured best (along it, the window sees the aperture problem)."""
    img = np.asarray(frame, np.float32)
    if img.ndim != 2 or img.size == 0:
        raise InputError("edge_points.frame", f"expected a mono (H, W) image, got shape {img.shape}")
    lo, hi = float(img.min()), float(img.max())
    u8 = np.zeros(img.shape, np.uint8) if hi <= lo else ((img - lo) * (255.0 / (hi - lo))).astype(np.uint8)
    grad = np.hypot(cv2.Sobel(u8, cv2.CV_32F, 1, 0), cv2.Sobel(u8, cv2.CV_32F, 0, 1))
    med = float(np.median(grad[grad > 0])) if (grad > 0).any() else 0.0
    edges = (cv2.Canny(u8, 0.5 * med, 1.5 * med, L2gradient=True) > 0) & _border(img.shape, window_px)
    ys, xs = np.nonzero(edges)
    order = np.argsort(-grad[ys, xs], kind="stable")
    taken = np.zeros(img.shape, bool)
    r = max(int(np.ceil(spacing_px)), 1)
    out = []
    for y, x in zip(ys[order], xs[order]):
        if taken[y, x]:
            continue
        out.append((float(x), float(y)))
        taken[max(y - r + 1, 0):y + r, max(x - r + 1, 0):x + r] = True
        if len(out) == max_points:
            break
    return np.asarray(out, float).reshape(-1, 2)


def project_displacement(displacement_m, points_m, K, R, t) -> np.ndarray:
    """First-order image displacement (T, P, 2) (x, y) in px of world displacements (T, P, 3) at world points (P, 3),
    seen by a pinhole K with the world-to-camera pose x_cam = R X + t (OpenCV: x right, y down, z forward)."""
    d = np.asarray(displacement_m, dtype=np.float64)
    X = np.asarray(points_m, dtype=np.float64)
    K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError("project_displacement.points_m", f"expected (P, 3) world points, got shape {X.shape}")
    if d.ndim != 3 or d.shape[1:] != X.shape:
        raise InputError("project_displacement.displacement_m", f"expected (T, {len(X)}, 3), got shape {d.shape}")
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise InputError("project_displacement",
                         f"expected K (3, 3), R (3, 3), t (3,), got {K.shape}, {R.shape}, {t.shape}")
    c = X @ R.T + t
    z = c[:, 2]
    if np.any(z <= 0):
        raise InputError("project_displacement.points_m",
                         f"points {np.flatnonzero(z <= 0).tolist()} lie behind the camera")
    # d(K c / c_z) / dc: the pinhole's Jacobian at each point, then chained with R.
    J = np.zeros((len(X), 2, 3))
    J[:, 0, 0] = K[0, 0] / z
    J[:, 0, 1] = K[0, 1] / z
    J[:, 0, 2] = -(K[0, 0] * c[:, 0] + K[0, 1] * c[:, 1]) / z**2
    J[:, 1, 1] = K[1, 1] / z
    J[:, 1, 2] = -K[1, 1] * c[:, 1] / z**2
    return np.einsum("pij,jk,tpk->tpi", J, R, d)


# ------------------------------------------------------------------------------------------- frames and texture

def _frames(frames) -> Iterator[np.ndarray]:
    """Mono frames one by one, all of the first one's shape."""
    if hasattr(frames, "iter_chunks"):
        source: Iterable = (f for chunk in frames.iter_chunks() for f in chunk)
    elif isinstance(frames, np.ndarray) and frames.ndim != 3:
        raise InputError("track_points.frames", f"expected a (T, H, W) array, got shape {frames.shape}")
    else:
        source = frames
    shape = None
    for i, f in enumerate(source):
        f = np.asarray(f)
        if f.ndim != 2 or f.size == 0 or f.dtype.kind not in "uif":
            raise InputError("track_points.frames", f"frame {i}: expected a mono (H, W) image of real numbers, "
                                                    f"got shape {f.shape} ({f.dtype})")
        if shape is None:
            shape = f.shape
        elif f.shape != shape:
            raise InputError("track_points.frames", f"frame {i} has shape {f.shape}, frame 0 has {shape}")
        yield f


def _patches(frame: np.ndarray, centres: np.ndarray, h: int) -> np.ndarray:
    """(P, 2h+1, 2h+1) float64 pixels around integer (x, y) centres; the frame's edge is repeated beyond it."""
    H, W = frame.shape
    r = np.arange(-h, h + 1)
    rows = np.clip(centres[:, 1, None] + r, 0, H - 1)
    cols = np.clip(centres[:, 0, None] + r, 0, W - 1)
    return frame[rows[:, :, None], cols[:, None, :]].astype(np.float64)


def _quality(ref: np.ndarray, base: np.ndarray, hw: int) -> np.ndarray:
    """sqrt of the smaller eigenvalue of the window-mean structure tensor, over the frame's intensity range."""
    p = _patches(ref, base, hw + 1)
    gx = 0.5 * (p[:, 1:-1, 2:] - p[:, 1:-1, :-2])
    gy = 0.5 * (p[:, 2:, 1:-1] - p[:, :-2, 1:-1])
    a, b, c = (gx * gx).mean((1, 2)), (gx * gy).mean((1, 2)), (gy * gy).mean((1, 2))
    lam_min = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    lo, hi = np.percentile(ref, (0.5, 99.5))
    return np.sqrt(np.clip(lam_min, 0, None)) / (hi - lo) if hi > lo else np.zeros(len(base))


# ------------------------------------------------------------------------------------------- cubic B-spline sampling

def _coefficients(patches: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients of each patch (P, S, S), prefiltered along its two image axes only."""
    return spline_filter1d(spline_filter1d(patches, 3, axis=1, mode="mirror"), 3, axis=2, mode="mirror")


def _sample(coef: np.ndarray, frac: np.ndarray, n: int) -> np.ndarray:
    """The spline of coef (P, S, S), centred at index S // 2, on the grid -n..n shifted by frac (P, 2) in [0, 1)."""
    t = frac[:, :, None]
    w = np.concatenate([(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3], axis=2) / 6
    c = coef.shape[1] // 2
    rows = sum(w[:, 1, m, None, None] * coef[:, c - n - 1 + m:c + n + m, :] for m in range(4))
    return sum(w[:, 0, m, None, None] * rows[:, :, c - n - 1 + m:c + n + m] for m in range(4))


def _gabor_pair(wavelength_px: float) -> tuple[np.ndarray, np.ndarray]:
    """1D kernels of a DC-free Gabor filter: the Gaussian envelope and its complex carrier (sigma = wavelength / 2)."""
    sigma = 0.5 * wavelength_px
    m = np.arange(-int(np.ceil(2.5 * sigma)), int(np.ceil(2.5 * sigma)) + 1)
    g = np.exp(-0.5 * (m / sigma) ** 2)
    carrier = np.exp(2j * np.pi * m / wavelength_px)
    gc = g * (carrier - (g * carrier).sum() / g.sum())  # exactly zero response to a constant
    return g / g.sum(), gc / g.sum()


def _gabor_responses(a: np.ndarray, g: np.ndarray, gc: np.ndarray) -> np.ndarray:
    """(P, 2, Y - 2r, X - 2r) complex responses of patches (P, Y, X) to the Gabor filters along x (carrier gc along
    x, envelope g along y) and along y, only where the kernels (2r + 1 taps) fit."""
    r = len(g) // 2
    along_x = [correlate1d(a, k, axis=2) for k in (gc.real, gc.imag, g)]
    fx = correlate1d(along_x[0], g, axis=1) + 1j * correlate1d(along_x[1], g, axis=1)
    fy = correlate1d(along_x[2], gc.real, axis=1) + 1j * correlate1d(along_x[2], gc.imag, axis=1)
    return np.stack([fx, fy], axis=1)[:, :, r:-r, r:-r]


# ------------------------------------------------------------------------------------------- trackers

class _TemplateLK(ABC):
    """Inverse-additive Lucas-Kanade on a window of the reference: the Gauss-Newton matrix is fixed, and each step
    resamples the current frame (cubic B-spline) on the window placed at the current estimate."""

    n: int                 # half-side of the resampled grid
    pinv: np.ndarray       # (P, k, k) inverse of the Gauss-Newton matrix

    def __init__(self, base: np.ndarray, hw: int, max_iterations: int, tolerance_px: float):
        self.base, self.hw, self.max_iterations, self.tolerance_px = base, hw, max_iterations, tolerance_px

    def _resample(self, frame: np.ndarray, pos: np.ndarray) -> np.ndarray:
        corner = np.floor(pos).astype(np.int64)
        return _sample(_coefficients(_patches(frame, corner, self.n + 2 + _PAD)), pos - corner, self.n)

    @abstractmethod
    def _step(self, frame: np.ndarray, pos: np.ndarray, sl: slice) -> np.ndarray:
        """The correction (p, 2) to subtract from the windows of points sl placed at pos (p, 2)."""

    def __call__(self, frame: np.ndarray, guess: np.ndarray) -> np.ndarray:
        d = guess.copy()
        for start in range(0, len(d), _BLOCK):
            sl = slice(start, start + _BLOCK)
            for _ in range(self.max_iterations):
                step = self._step(frame, self.base[sl] + d[sl], sl)
                d[sl] -= step
                if np.all(np.abs(step) < self.tolerance_px):
                    break
        d[~np.all(np.abs(d - guess) < self.hw, axis=1)] = np.nan  # ran away from its window: lost
        return d


class _GradientLK(_TemplateLK):
    """Matches intensities, d = (G^T G)^-1 G^T (I_t - I_ref) iterated, with the intensity's gain and offset solved
    for as well (lamp flicker); G is the reference's gradient, the derivative of its own B-spline."""

    def __init__(self, ref: np.ndarray, base: np.ndarray, hw: int, max_iterations: int, tolerance_px: float):
        super().__init__(base, hw, max_iterations, tolerance_px)
        self.n = n = hw
        coef = _coefficients(_patches(ref, base, hw + 1 + _PAD))
        c = coef.shape[1] // 2
        gx = 0.5 * (coef[:, c - n:c + n + 1, c - n + 1:c + n + 2] - coef[:, c - n:c + n + 1, c - n - 1:c + n])
        gy = 0.5 * (coef[:, c - n + 1:c + n + 2, c - n:c + n + 1] - coef[:, c - n - 1:c + n, c - n:c + n + 1])
        self.template = _patches(ref, base, hw).reshape(len(base), -1)
        self.X = np.stack([gx.reshape(len(base), -1), gy.reshape(len(base), -1), self.template,
                           np.ones_like(self.template)], axis=2)  # (P, N, 4): d/dx, d/dy, gain, offset
        self.pinv = np.linalg.pinv(np.einsum("pni,pnj->pij", self.X, self.X))

    def _step(self, frame: np.ndarray, pos: np.ndarray, sl: slice) -> np.ndarray:
        e = self._resample(frame, pos).reshape(len(pos), -1) - self.template[sl]
        return np.einsum("pij,pnj,pn->pi", self.pinv[sl, :2], self.X[sl], e)


class _PhaseLK(_TemplateLK):
    """Matches the local phase of a Gabor quadrature pair along x and along y: at each pixel of the window,
    grad(phase_ref) . step = phase_t - phase_ref (wrapped), solved by least squares with |response_ref|^2 weights."""

    def __init__(self, ref: np.ndarray, base: np.ndarray, hw: int, wavelength_px: float, max_iterations: int,
                 tolerance_px: float):
        super().__init__(base, hw, max_iterations, tolerance_px)
        self.g, self.gc = _gabor_pair(wavelength_px)
        self.n = hw + len(self.g) // 2
        R = _gabor_responses(_patches(ref, base, self.n + 1), self.g, self.gc)  # 1 px more each side for gradients
        self.R0 = R[..., 1:-1, 1:-1]
        dR = np.stack([R[..., 1:-1, 2:] - R[..., 1:-1, :-2], R[..., 2:, 1:-1] - R[..., :-2, 1:-1]], axis=-1) / 2
        w = np.abs(self.R0) ** 2
        # grad(phase) = Im(conj(R) grad R) / |R|^2; times the weight |R|^2 it stays finite where R vanishes.
        self.wgrad = np.imag(np.conj(self.R0)[..., None] * dR)                      # (P, 2 filters, Y, X, 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            grad = np.nan_to_num(self.wgrad / w[..., None])
        self.pinv = np.linalg.pinv(np.einsum("pkyxi,pkyxj->pij", self.wgrad, grad))

    def _step(self, frame: np.ndarray, pos: np.ndarray, sl: slice) -> np.ndarray:
        dphi = np.angle(_gabor_responses(self._resample(frame, pos), self.g, self.gc) * np.conj(self.R0[sl]))
        return np.einsum("pij,pkyxj,pkyx->pi", self.pinv[sl], self.wgrad[sl], dphi)


class _OpenCVLK:
    """cv2.calcOpticalFlowPyrLK from the reference frame to each frame, started from the previous answer."""

    def __init__(self, ref: np.ndarray, pts: np.ndarray, window_px: int, max_iterations: int, tolerance_px: float):
        lo, hi = (0.0, 255.0) if ref.dtype == np.uint8 else (float(ref.min()), float(ref.max()))
        self.scale = 255.0 / (hi - lo) if hi > lo else 1.0
        self.lo = lo
        self.p0 = pts.astype(np.float32).reshape(-1, 1, 2)
        self.win = (int(window_px), int(window_px))
        self.ref = self._u8(ref)
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(max_iterations), float(tolerance_px) ** 2)

    def _u8(self, frame: np.ndarray) -> np.ndarray:
        if frame.dtype == np.uint8:
            return frame
        return np.clip(np.rint((frame.astype(np.float64) - self.lo) * self.scale), 0, 255).astype(np.uint8)

    def __call__(self, frame: np.ndarray, guess: np.ndarray) -> np.ndarray:
        start = (self.p0 + guess.astype(np.float32).reshape(-1, 1, 2)).copy()
        p1, status, _ = cv2.calcOpticalFlowPyrLK(self.ref, self._u8(frame), self.p0, start, winSize=self.win,
                                                 maxLevel=_LK_LEVELS, criteria=self.criteria,
                                                 flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        d = (p1 - self.p0).reshape(-1, 2).astype(np.float64)
        d[status.ravel() == 0] = np.nan
        return d
